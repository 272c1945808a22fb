"""Byte copies between NumPy arrays and Taichi ndarrays by address, and zero fills, without a kernel launch, and
ndarrays allocated without Taichi's record of the Python stack.

A copy through a Taichi kernel (``from_numpy`` / ``to_numpy``, or a planned launch of a copy kernel with a
NumPy argument, :mod:`sim_core.ti_kernels.transfer`) costs on CUDA a launch, a device buffer for the NumPy
array, its copy to the device *and back* (Taichi's CUDA launcher copies every host array of a launch both
ways), a synchronisation and a free: 83-103 us a call on the H200 host (``benchmarks/profile_single.py``'s
launch micro-benchmark, docs/benchmarks_log.md, session 38, 28single). Here the ndarray's address
(``Program.get_ndarray_data_ptr_as_int``: a device pointer on CUDA, a host pointer on the CPU) is copied
to or from directly: on CUDA by the driver's synchronous ``cuMemcpyHtoD_v2`` / ``cuMemcpyDtoH_v2``
(``libcuda.so.1`` through ctypes; synchronous copies run on the legacy default stream, the stream of
Taichi's launches, so they follow the kernels launched before them), on the CPU by ``memmove`` (Taichi's
CPU launches return when the kernel has run).

On CUDA the driver copies need Taichi's CUDA context current on the calling thread: Taichi makes it
current on the thread that initialised it, and restores a thread's own (none) after each of its launches
on another thread. Where no context is current, or the driver library is not found, the functions return
False and the caller copies through a kernel instead (same bytes).

``ti.ndarray`` formats the whole Python call stack into the new array's debug record (``get_traceback``) at
every allocation: 0.8 ms a call on the 2-core VM, 28 allocations a Forming step on the CUDA path.
:func:`new_ndarray` makes the same zero-filled array with an empty debug record.
"""

from __future__ import annotations

import ctypes
import functools
import threading
import weakref

import numpy as np
from taichi._lib import core as _ti_core
from taichi.lang._ndarray import Ndarray, ScalarNdarray
from taichi.lang.enums import Layout
from taichi.lang.util import cook_dtype, to_numpy_type

from sim_core.ti_backend import current_arch, ti

_CUDA_SUCCESS = 0


@functools.cache
def _driver() -> ctypes.CDLL | None:
    """The CUDA driver library with the argument types of the four entry points used, or None."""
    try:
        lib = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return None
    lib.cuMemcpyHtoD_v2.argtypes = (ctypes.c_uint64, ctypes.c_void_p, ctypes.c_size_t)
    lib.cuMemcpyDtoH_v2.argtypes = (ctypes.c_void_p, ctypes.c_uint64, ctypes.c_size_t)
    lib.cuCtxGetCurrent.argtypes = (ctypes.POINTER(ctypes.c_void_p),)
    lib.cuMemsetD8_v2.argtypes = (ctypes.c_uint64, ctypes.c_ubyte, ctypes.c_size_t)
    lib.cuMemHostAlloc.argtypes = (ctypes.POINTER(ctypes.c_void_p), ctypes.c_size_t, ctypes.c_uint)
    lib.cuMemFreeHost.argtypes = (ctypes.c_void_p,)
    return lib


_READY = threading.local()
"""Per thread: ``ready`` once a CUDA context was found current there (Taichi leaves its context current on the
thread that initialised it, and restores a thread's own after each launch, so it stays so)."""


def _cuda_ready(lib: ctypes.CDLL | None) -> bool:
    """Whether ``lib`` is loaded and a CUDA context is current on this thread."""
    if getattr(_READY, "ready", False):
        return True
    if lib is None:
        return False
    ctx = ctypes.c_void_p()
    _READY.ready = lib.cuCtxGetCurrent(ctypes.byref(ctx)) == _CUDA_SUCCESS and bool(ctx.value)
    return _READY.ready


def new_ndarray(dtype, shape: tuple[int, ...]) -> ScalarNdarray:
    """A zero-filled Taichi ndarray of scalar ``dtype`` (``ti.f64``, ``ti.i32``, ...) and ``shape``: what
    ``ti.ndarray(dtype, shape)`` makes (module docstring), freed as Taichi frees it (``ScalarNdarray.__del__``).

    Raises:
        ValueError: a dimension that is not a positive int (Taichi allocates no empty ndarray).
    """
    shape = tuple(int(n) for n in shape)
    if not shape or min(shape) <= 0:
        raise ValueError(f"new_ndarray: every dimension must be positive; got shape {shape}")
    array = ScalarNdarray.__new__(ScalarNdarray)
    Ndarray.__init__(array)
    array.dtype = cook_dtype(dtype)
    array.arr = ti.lang.impl.get_runtime().prog.create_ndarray(array.dtype, shape, layout=Layout.NULL, zero_fill=True,
                                                               dbg_info=_ti_core.DebugInfo())
    array.shape = tuple(array.arr.shape)
    array.element_type = array.dtype
    return array


def pinned_zeros(shape: tuple[int, ...]) -> np.ndarray:
    """A zero-filled float64 NumPy array of ``shape`` for the host side of recurring copies: on CUDA in page-locked
    host memory (the driver's ``cuMemHostAlloc``, freed by ``cuMemFreeHost`` when the array and its views are
    garbage-collected), which the driver copies to and from the device directly, where it stages pageable memory
    through a buffer of its own (copies of 14 MB took about 3 ms on the H200 host: docs/benchmarks_log.md,
    session 40, 28lock); ``np.zeros`` elsewhere, or where no CUDA context is current on this thread."""
    shape = tuple(int(n) for n in shape)
    nbytes = int(np.prod(shape)) * 8
    lib = _driver() if current_arch() == "cuda" and nbytes else None
    if lib is None or not _cuda_ready(lib):
        return np.zeros(shape)
    pointer = ctypes.c_void_p()
    if lib.cuMemHostAlloc(ctypes.byref(pointer), nbytes, 0) != _CUDA_SUCCESS or not pointer.value:
        return np.zeros(shape)
    block = (ctypes.c_byte * nbytes).from_address(pointer.value)
    weakref.finalize(block, lib.cuMemFreeHost, pointer.value)
    out = np.frombuffer(block, dtype=np.float64).reshape(shape)
    out.fill(0.0)
    return out


class PinnedBlocks:
    """Host arrays of one shape for the results of recurring downloads that are kept while in use (the lockstep
    solver's trial points): each :meth:`take` hands out a writeable float64 array over a block of its own, and a
    block is reused once no array over it is left (a ``weakref.finalize`` on the block's buffer object, which the
    array and its views keep alive). The blocks are page-locked on CUDA (``cuMemHostAlloc``, as :func:`pinned_zeros`),
    where the driver copies to them directly (a 14 MB download: 0.26 ms against 0.92 ms into pageable memory on the
    H100 host, docs/benchmarks_log.md, session 43, 28res); ordinary memory elsewhere.

    Args:
        shape: the arrays' shape.
        page_locked: None: page-locked where a CUDA context is current here, else ordinary memory; False: ordinary
            memory (ctypes buffers, reused as the page-locked blocks are).

    Attributes:
        page_locked: whether the blocks are page-locked.
        allocated: how many blocks were made so far (the most handed out at once).
    """

    def __init__(self, shape: tuple[int, ...], page_locked: bool | None = None) -> None:
        self.shape = tuple(int(n) for n in shape)
        self._nbytes = max(int(np.prod(self.shape)) * 8, 8)
        lib = _driver() if page_locked is None and current_arch() == "cuda" else None
        self.page_locked = lib is not None and _cuda_ready(lib)
        self._state = _BlockState(lib if self.page_locked else None)
        self.allocated = 0
        weakref.finalize(self, self._state.close)

    def take(self) -> np.ndarray:
        """A writeable float64 array of :attr:`shape` over a block no other array uses (its values: the block's
        last ones)."""
        state = self._state
        if state.free:
            pointer = state.free.pop()
        else:
            pointer = state.allocate(self._nbytes)
            self.allocated += 1
        buffer = (ctypes.c_byte * self._nbytes).from_address(pointer)
        weakref.finalize(buffer, state.release, pointer)
        return np.ndarray(self.shape, dtype=np.float64, buffer=buffer)


class _BlockState:
    """The blocks of a :class:`PinnedBlocks`: their allocation (page-locked through ``lib``, or ctypes buffers when
    ``lib`` is None), the free ones, and their release once the owner is gone (a block in use then is freed when its
    last array goes)."""

    def __init__(self, lib: ctypes.CDLL | None) -> None:
        self.lib = lib
        self.free: list[int] = []
        self.closed = False
        self._buffers: dict[int, ctypes.Array] = {}  # address -> ctypes buffer (ordinary memory: kept alive here)

    def allocate(self, nbytes: int) -> int:
        """A new block of ``nbytes``; its address.

        Raises:
            MemoryError: the driver refused the page-locked allocation.
        """
        if self.lib is None:
            buffer = (ctypes.c_byte * nbytes)()
            self._buffers[ctypes.addressof(buffer)] = buffer
            return ctypes.addressof(buffer)
        pointer = ctypes.c_void_p()
        if self.lib.cuMemHostAlloc(ctypes.byref(pointer), nbytes, 0) != _CUDA_SUCCESS or not pointer.value:
            raise MemoryError(f"PinnedBlocks: cuMemHostAlloc of {nbytes} bytes failed")
        return int(pointer.value)

    def release(self, pointer: int) -> None:
        """The block at ``pointer`` has no array left: free for reuse, or freed once the owner is gone."""
        if self.closed:
            self._free_block(pointer)
        else:
            self.free.append(pointer)

    def close(self) -> None:
        """The owner is gone: free the free blocks now, the others when their last array goes."""
        self.closed = True
        while self.free:
            self._free_block(self.free.pop())

    def _free_block(self, pointer: int) -> None:
        if self.lib is None:
            self._buffers.pop(pointer, None)
        else:
            self.lib.cuMemFreeHost(pointer)


def address(array) -> int:
    """The address of the Taichi ndarray ``array``'s first element (a device pointer on CUDA); read from Taichi
    once per array and kept on it (an ndarray keeps its allocation for its lifetime)."""
    kept = getattr(array, "_device_address", None)
    if kept is None:
        kept = array._device_address = int(ti.lang.impl.get_runtime().prog.get_ndarray_data_ptr_as_int(array.arr))
    return kept


def _checked(array, host: np.ndarray) -> int:
    """``host``'s byte count after checking that it matches ``array`` (shape and dtype; both kept on the array).

    Raises:
        ValueError: another shape or dtype, or ``host`` not C-contiguous.
    """
    layout = getattr(array, "_host_layout", None)
    if layout is None:
        layout = array._host_layout = (tuple(array.shape), np.dtype(to_numpy_type(array.dtype)))
    shape, dtype = layout
    if host.shape != shape or host.dtype != dtype or not host.flags.c_contiguous:
        raise ValueError(f"device_copy: a C-contiguous {dtype} array of shape {shape} is needed; "
                         f"got {host.dtype} {host.shape}")
    return host.nbytes


def to_device(array, host: np.ndarray, rows: int | None = None) -> bool:
    """Copy the C-contiguous ``host`` (``array``'s dtype and shape) into the Taichi ndarray ``array``, or only its
    first ``rows`` rows (along the first axis; the rest of ``array`` is left as it is); False (nothing copied) where
    no direct copy is possible here (module docstring).

    Raises:
        ValueError: ``host`` is not C-contiguous of ``array``'s shape and dtype, or ``rows`` is not in
            ``[0, host.shape[0]]``.
    """
    return _copy(array, host, True, rows)


def to_host(host: np.ndarray, array, rows: int | None = None) -> bool:
    """Copy the Taichi ndarray ``array`` into the writable C-contiguous ``host`` (``array``'s dtype and
    shape), or only its first ``rows`` rows (along the first axis: the bytes of a prefix; the rest of ``host``
    is left as it is); False (nothing copied) where no direct copy is possible here.

    Raises:
        ValueError: ``host`` is not C-contiguous of ``array``'s shape and dtype, or is read-only, or ``rows`` is
            not in ``[0, host.shape[0]]``.
    """
    return _copy(array, host, False, rows)


def zero(array) -> bool:
    """Set every byte of the Taichi ndarray ``array`` to 0 (0.0 in float64, 0 in the integer types) without a
    kernel launch: on CUDA the driver's ``cuMemsetD8_v2`` (device memory: asynchronous to the host, ordered on the
    legacy default stream after the kernels launched before it and before those launched after it), on the CPU
    ``memset``; False (nothing set) where neither can be made here (module docstring)."""
    nbytes = int(np.prod(array.shape)) * np.dtype(to_numpy_type(array.dtype)).itemsize
    if not nbytes:
        return True
    arch = current_arch()
    if arch == "cuda":
        lib = _driver()
        return _cuda_ready(lib) and lib.cuMemsetD8_v2(address(array), 0, nbytes) == _CUDA_SUCCESS
    if arch == "cpu":
        ctypes.memset(address(array), 0, nbytes)
        return True
    return False


def _copy(array, host: np.ndarray, upload: bool, rows: int | None = None) -> bool:
    """``host`` into ``array`` (``upload``) or back, all of it or its first ``rows`` rows; whether the bytes
    were copied."""
    nbytes = _checked(array, host)
    if not upload and not host.flags.writeable:
        raise ValueError("device_copy: the host array to copy into is read-only")
    if rows is not None:
        if not 0 <= rows <= (host.shape[0] if host.ndim else 1):
            raise ValueError(f"device_copy: {rows} rows asked of an array of shape {host.shape}")
        nbytes = nbytes // max(host.shape[0], 1) * rows if host.ndim else nbytes
    if not nbytes:
        return True
    arch = current_arch()
    if arch == "cuda":
        lib = _driver()
        if not _cuda_ready(lib):
            return False
        if upload:
            return lib.cuMemcpyHtoD_v2(address(array), host.ctypes.data, nbytes) == _CUDA_SUCCESS
        return lib.cuMemcpyDtoH_v2(host.ctypes.data, address(array), nbytes) == _CUDA_SUCCESS
    if arch == "cpu":
        if upload:
            ctypes.memmove(address(array), host.ctypes.data, nbytes)
        else:
            ctypes.memmove(host.ctypes.data, address(array), nbytes)
        return True
    return False
