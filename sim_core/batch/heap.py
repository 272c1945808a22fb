"""The C heap's handling of a lockstep batch's large temporaries.

A lockstep Newton iteration of ``B`` copies makes a few hundred NumPy temporaries of the stacked arrays'
size (``(N, 3)`` float64: 14 MB at ``B = 1024`` Forming copies). glibc's ``malloc`` serves a request above
its mmap threshold (128 kB at first, raised by itself up to 32 MiB as such blocks are freed) with fresh pages
from the kernel and returns them at ``free``, so each such temporary pays a page fault per 4 kB page on first
touch: a fresh ``x - y`` of two ``(580000, 3)`` arrays took 7.6 ms against 3.2 ms into a kept array on the
2-core VM (session 39). :func:`keep_freed_memory` raises the mmap and trim thresholds so that freed blocks stay
in the heap and serve the next temporaries (``mallopt(3)``, ``M_MMAP_THRESHOLD`` and ``M_TRIM_THRESHOLD``):
the process keeps its peak heap instead of returning it to the system.
"""

from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD = -1
"""``mallopt`` parameter: free memory at the heap's top above which ``free`` returns it to the system (bytes)."""
M_MMAP_THRESHOLD = -3
"""``mallopt`` parameter: request size from which ``malloc`` maps fresh pages (bytes; at most 32 MiB on 64-bit)."""
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
"""The largest mmap threshold glibc accepts on 64-bit (``DEFAULT_MMAP_THRESHOLD_MAX``)."""
TRIM_THRESHOLD_BYTES = 1024 * 1024 * 1024
"""Freed heap memory kept before any is returned to the system."""


def keep_freed_memory() -> bool:
    """Set glibc's mmap threshold to :data:`MMAP_THRESHOLD_BYTES` and its trim threshold to
    :data:`TRIM_THRESHOLD_BYTES` for this process (module docstring; idempotent).

    Returns:
        whether both were set: False where the C library has no ``mallopt`` (not glibc) or refuses a value.
    """
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD,
                                                                                   TRIM_THRESHOLD_BYTES))
