"""Uploads of small host arrays into Taichi ndarrays that do not make the host wait for the device.

A synchronous host-to-device copy (:func:`sim_core.ti_kernels.device_copy.to_device`, the driver's
``cuMemcpyHtoD_v2``) first waits for every kernel queued on the stream before it: a ``(B,)`` array of per-copy step
sizes or actions uploaded after a factorisation's launch waits for the factorisation (20.8 ms a Newton iteration at
1024 Forming copies on the H100, docs/benchmarks_log.md, session 43, 28res). :class:`AsyncUploads` copies the values
into a page-locked staging slot of its own and queues the driver's ``cuMemcpyHtoDAsync_v2`` on the legacy default
stream, the stream of Taichi's launches and of the synchronous copies (NVIDIA, CUDA Driver API, "API synchronization
behavior": an asynchronous copy from page-locked memory returns at once): the copy runs after the kernels queued before
it and before those launched after it, and the host goes on. A slot is written again only once its last copy has run
(a CUDA event recorded after each copy, queried before the slot's reuse). On the CPU, or where no CUDA context is
current on the calling thread, an upload is :func:`~sim_core.ti_kernels.device_copy.to_device`'s (``memmove`` on
the CPU: the kernels launched before have run), or ``from_numpy``. The bytes on the device are the same.
"""

from __future__ import annotations

import ctypes
import weakref

import numpy as np
from taichi.lang.util import to_numpy_type

from sim_core.ti_backend import current_arch
from sim_core.ti_kernels import device_copy

_CUDA_SUCCESS = 0
_EVENT_DISABLE_TIMING = 2  # CU_EVENT_DISABLE_TIMING


def _declared(lib: ctypes.CDLL) -> ctypes.CDLL:
    """``lib`` (the driver library of :mod:`~sim_core.ti_kernels.device_copy`) with the argument types of the
    asynchronous copy and event entry points set."""
    lib.cuMemcpyHtoDAsync_v2.argtypes = (ctypes.c_uint64, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p)
    lib.cuEventCreate.argtypes = (ctypes.POINTER(ctypes.c_void_p), ctypes.c_uint)
    lib.cuEventRecord.argtypes = (ctypes.c_void_p, ctypes.c_void_p)
    lib.cuEventQuery.argtypes = (ctypes.c_void_p,)
    lib.cuEventSynchronize.argtypes = (ctypes.c_void_p,)
    lib.cuEventDestroy_v2.argtypes = (ctypes.c_void_p,)
    return lib


class AsyncUploads:
    """Uploads of host arrays of at most ``nbytes`` bytes into Taichi ndarrays, queued without the host waiting for
    the device on CUDA (module docstring).

    Args:
        nbytes: the largest upload, bytes.
        slots: staging slots (uploads in flight before the host waits for the oldest one to have run).

    Attributes:
        queued: whether uploads are queued asynchronously here (CUDA with its context current on the thread that made
            this object), else they are synchronous copies.
    """

    def __init__(self, nbytes: int, slots: int = 8) -> None:
        self.nbytes = max(int(nbytes), 8)
        lib = device_copy._driver() if current_arch() == "cuda" else None
        self.queued = lib is not None and device_copy._cuda_ready(lib)
        self._lib = _declared(lib) if self.queued else None
        self._next = 0
        self._staging: list[np.ndarray] = []
        self._events: list[int | None] = []
        if not self.queued:
            return
        words = -(-self.nbytes // 8)
        for _ in range(max(int(slots), 1)):
            buffer = device_copy.pinned_zeros((words,))
            event = ctypes.c_void_p()
            if self._lib.cuEventCreate(ctypes.byref(event), _EVENT_DISABLE_TIMING) != _CUDA_SUCCESS:
                event.value = None
            self._staging.append(buffer.view(np.uint8))
            self._events.append(event.value)
        weakref.finalize(self, _destroy_events, self._lib, list(self._events))

    def upload(self, array, host: np.ndarray) -> None:
        """Copy the C-contiguous ``host`` (``array``'s dtype and element count, at most :attr:`nbytes` bytes) into
        the Taichi ndarray ``array``: queued after the kernels launched before and before those launched after (on
        CUDA the host does not wait), else synchronously.

        Raises:
            ValueError: ``host`` is larger than :attr:`nbytes` or not C-contiguous.
        """
        if host.nbytes > self.nbytes or not host.flags.c_contiguous:
            raise ValueError(f"AsyncUploads: a C-contiguous array of at most {self.nbytes} bytes is needed; got "
                             f"{host.nbytes} bytes")
        lib = self._lib
        if lib is None or not device_copy._cuda_ready(lib) or not self._queue(lib, array, host):
            if not device_copy.to_device(array, host):
                array.from_numpy(host)

    def _queue(self, lib: ctypes.CDLL, array, host: np.ndarray) -> bool:
        """Stage ``host`` in the next slot and queue its copy; False where the slot has no event (nothing queued)."""
        k = self._next
        event = self._events[k]
        if event is None:
            return False
        n = host.nbytes
        if int(np.prod(array.shape)) * np.dtype(to_numpy_type(array.dtype)).itemsize != n:
            raise ValueError(f"AsyncUploads: {n} bytes for an ndarray of shape {tuple(array.shape)} and "
                             f"{array.dtype}")
        self._next = (k + 1) % len(self._staging)
        if lib.cuEventQuery(event) != _CUDA_SUCCESS:  # the slot's last copy has not run yet (a recorded event)
            lib.cuEventSynchronize(event)
        slot = self._staging[k]
        slot[:n] = host.reshape(-1).view(np.uint8)
        if n and lib.cuMemcpyHtoDAsync_v2(device_copy.address(array), slot.ctypes.data, n, None) != _CUDA_SUCCESS:
            return False
        lib.cuEventRecord(event, None)
        return True


def _destroy_events(lib: ctypes.CDLL, events: list) -> None:
    """Destroy the staging slots' events (their results ignored: the context may be gone at exit)."""
    for event in events:
        if event is not None:
            lib.cuEventDestroy_v2(event)
