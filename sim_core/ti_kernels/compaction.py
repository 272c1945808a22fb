"""The compaction of integer indices where their Taichi copies are (:func:`sim_core.unique.compact_indices` on the
device).

:func:`~sim_core.unique.compact_indices` of a contact set's candidate lists (``(own, local)``: the distinct vertices
that the pairs name, sorted, and every pair's vertices as positions among them; the pair batch's indices,
:class:`~sim_core.energies.contact.pair_lists.BatchLayout`) is a host pass over every candidate's four vertices (7.3
million indices at 1024 stacked Forming copies) whose ``local`` (29 MB) is then sent to the device. On CUDA the lists'
int32 vertices are already there (the candidate geometry's launch reads them), so :func:`compact_on_device` makes the
compaction there in one launch of :func:`_compact_kernel` and copies back only ``own`` (the distinct vertices, a few
hundred thousand) and their count; ``local`` stays in device memory. The steps are those of the host function: a
presence mark per vertex, the marks' running sums, the marked vertices written at their ranks, and
every index replaced by its vertex's rank (the prefix sum by :func:`~sim_core.ti_kernels.scan.running_sums`). Integer
arithmetic only: the results equal the host's exactly, in any
order of the threads.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np

from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import LaunchArrays, copy_back, on_device
from sim_core.ti_kernels.device_copy import new_ndarray
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.scan import SCAN_CHUNK, running_sums

_I32_1, _I32_2 = linalg.I32_1, linalg.I32_2

_COUNT, _BAD = 0, 1  # count: [0] the distinct vertices, [1] 1 if an index lies outside [0, size)


@ti.func
def _index(first: ti.template(), first_count: ti.i32, second: ti.template(), k: ti.i32, c: ti.i32) -> ti.i32:
    """Entry ``c`` of row ``k`` of the rows of ``first`` (its first ``first_count``) followed by those of ``second``."""
    v = 0
    if k < first_count:
        v = first[k, c]
    else:
        v = second[k - first_count, c]
    return v


@fast_kernel
def _compact_kernel(first: _I32_2, first_count: ti.i32, second: _I32_2, second_count: ti.i32, size: ti.i32,
                    position: _I32_1, chunk_total: _I32_1, own: _I32_1, count: _I32_1, local: _I32_2):
    """``own[:count[0]]``: the distinct values of rows ``0 .. first_count - 1`` of ``first`` and ``0 .. second_count
    - 1`` of ``second`` (int32 ``(k, m)``, values in ``[0, size)``), increasing; ``local`` ``(first_count +
    second_count, m)``: each of those indices' position in ``own`` (``first``'s rows, then ``second``'s).
    ``count[1]`` = 1 when an index lies outside ``[0, size)`` (it is then not marked; ``local`` holds -1 there).
    Scratch: ``position`` (at least ``size + 1``: vertex ``v``'s mark at ``v + 1``, then the number of marked vertices
    below ``v`` at ``v``), ``chunk_total`` (at least ``ceil(size / SCAN_CHUNK)``)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for v in range(size + 1):
        position[v] = 0
    ti.loop_config(serialize=True)  # one thread; never the CPU thread pool (a forked worker hangs there)
    for _ in range(1):
        count[_BAD] = 0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(first_count + second_count):
        for c in range(first.shape[1]):
            v = _index(first, first_count, second, k, c)
            if 0 <= v < size:
                position[v + 1] = 1  # (the same value from every thread that marks v)
            else:
                count[_BAD] = 1
    running_sums(position, size, chunk_total, count, _COUNT)  # the ranks; the distinct vertices into count[0]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for v in range(size):
        if position[v + 1] != position[v]:  # marked
            own[position[v]] = v
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(first_count + second_count):
        for c in range(first.shape[1]):
            v = _index(first, first_count, second, k, c)
            rank = -1
            if 0 <= v < size:  # (a statement, not a select: no read of position outside its range)
                rank = position[v]
            local[k, c] = rank


_ARRAYS = LaunchArrays()
"""The kernel's work arrays and the stand-in of an empty part (on CUDA their device copies, kept per thread)."""


def compact_on_device(first: np.ndarray, second: np.ndarray, size: int, device: dict | None = None,
                      names: tuple[str, str] = ("first", "second")) -> tuple[np.ndarray, object]:
    """``compact_indices((first, second), dtype=np.int32, size=size)`` (:func:`sim_core.unique.compact_indices`: the
    same ``own`` and ``local``, exactly), made by one launch of :func:`_compact_kernel` where the index arrays' Taichi
    copies are (module docstring).

    Args:
        first, second: C-contiguous int32 index arrays ``(p, m)`` and ``(q, m)`` (the same ``m``), values in
            ``[0, size)``, never changed in place (on CUDA their device copies are kept in ``device``), or Taichi int32
            ndarrays of that shape (read where they are).
        size: the bound of the indices (a model's vertex count), ``< 2**31``.
        device: the cache of the index arrays' device copies (:func:`~sim_core.ti_kernels.buffers.on_device`; a
            candidate list's, where the geometry's launch keeps them), or None for one of this call's own.
        names: the two arrays' names in ``device``.

    Returns:
        ``(own, local)``: ``own`` int64 ``(u,)``, the sorted distinct values (on the host); ``local`` int32 ``(p + q,
        m)``, each index's position in ``own``: on CUDA a new Taichi ndarray in device memory (nothing copied back),
        elsewhere a NumPy array (a NumPy one, also on CUDA, when ``p + q = 0``).

    Raises:
        ConfigError: the Taichi backend is not initialised.
        ValueError: index arrays that are not C-contiguous int32 of two dimensions and equal widths.
        IndexError: an index outside ``[0, size)``.
    """
    require_backend("compact_on_device")
    for part in (first, second):
        good = part.dtype == np.int32 and part.ndim == 2 and part.flags.c_contiguous \
            if isinstance(part, np.ndarray) else part.dtype == ti.i32 and len(part.shape) == 2
        if not good or part.shape[1] != first.shape[1]:
            raise ValueError(f"compact_on_device: indices must be C-contiguous int32 (k, m) of one m, got "
                             f"{part.dtype} {tuple(part.shape)}")
    p, q, m = first.shape[0], second.shape[0], first.shape[1]
    if not p + q or not m:
        return np.zeros(0, dtype=np.int64), np.zeros((p + q, m), dtype=np.int32)
    size = int(size)
    device = {} if device is None else device
    position, own = _ARRAYS.rows("position", size + 1, (), np.int32), _ARRAYS.rows("own", size, (), np.int32)
    chunk_total = _ARRAYS.rows("chunk_total", -(-size // SCAN_CHUNK), (), np.int32)
    count = _ARRAYS.rows("count", 2, (), np.int32)
    stand_in = _ARRAYS.rows(f"empty_{m}", 1, (m,), np.int32)  # a part without rows (the kernel reads none)
    parts = [part if not isinstance(part, np.ndarray)  # (a Taichi ndarray: where the candidate search gathered it)
             else on_device(device, name, part) if len(part) else on_device(_ARRAYS.device(), f"empty_{m}", stand_in)
             for name, part in zip(names, (first, second))]
    scratch = _ARRAYS.device()
    work = [on_device(scratch, name, host, scratch=True)
            for name, host in (("position", position), ("chunk_total", chunk_total), ("own", own), ("count", count))]
    on_gpu = not isinstance(parts[0], np.ndarray)  # (device copies or given ndarrays: on CUDA only)
    local = new_ndarray(ti.i32, (p + q, m)) if on_gpu else np.empty((p + q, m), dtype=np.int32)
    _compact_kernel(parts[0], p, parts[1], q, size, *work, local)
    copy_back(count, work[3])
    if count[_BAD]:
        raise IndexError(f"compact_on_device: an index outside [0, {size})")
    u = int(count[_COUNT])
    copy_back(own, work[2], u)
    return own[:u].astype(np.int64), local


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the kernel on two small index arrays.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    compact_on_device(np.array([[0, 2]], dtype=np.int32), np.array([[2, 3]], dtype=np.int32), 4)
