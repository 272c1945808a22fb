"""Device arrays of the Taichi potentials: allocated once per shape, filled with ``from_numpy``.

A :class:`DeviceArray` wraps a ``ti.ndarray`` (device memory on CUDA, host memory on CPU). It is
allocated when first needed and again only when the shape changes, so a potential that is called
every Newton iteration moves data with ``from_numpy`` / ``to_numpy`` and never reallocates. Kernels
take ndarrays as arguments (``ti.types.ndarray``), so they compile once per dtype and rank and are
shared by every instance (no per-instance fields, no growth of Taichi's SNode trees).
:class:`LaunchArrays` keeps host (NumPy) arrays for kernels that take NumPy arrays, so that their
launches find the arrays they were bound to.
"""

from __future__ import annotations

import math
import sys
import threading
from typing import NamedTuple

import numpy as np

from sim_core.ti_backend import ti
from sim_core.ti_kernels import device_copy, transfer


class DeviceArray:
    """A ``ti.ndarray`` of fixed dtype, reallocated only when the requested shape changes.

    Args:
        dtype: ``ti.f64`` or ``ti.i32``.
    """

    def __init__(self, dtype) -> None:
        self.dtype = dtype
        self.array = None
        self.shape: tuple[int, ...] | None = None
        self._host: np.ndarray | None = None  # copy of the last uploaded values

    def ensure(self, shape: tuple[int, ...]):
        """The ndarray with ``shape`` (allocated on first use or when the shape changed)."""
        shape = tuple(int(s) for s in shape)
        if self.shape != shape:
            self.array = device_copy.new_ndarray(self.dtype, shape)
            self.shape = shape
            self._host = None
        return self.array

    def upload(self, values: np.ndarray):
        """Copy ``values`` (converted to the dtype, C order) into the ndarray; returns the ndarray.

        The copy is skipped when ``values`` equal the last upload (energy, gradient and Hessian of
        one Newton iterate share one transfer).
        """
        np_dtype = np.float64 if self.dtype == ti.f64 else np.int32
        values = np.ascontiguousarray(values, dtype=np_dtype)
        arr = self.ensure(values.shape)
        if self._host is None or self._host.shape != values.shape or not np.array_equal(self._host, values):
            _from_numpy(arr, values)
            self._host = values.copy()
        return arr

    def download(self) -> np.ndarray:
        """The ndarray's contents as a new NumPy array."""
        return _to_numpy(self.array)


def _from_numpy(array, values: np.ndarray) -> None:
    """``array.from_numpy(values)`` (``values`` of the ndarray's dtype): a byte copy
    (:mod:`sim_core.ti_kernels.device_copy`) where one can be made, else float64 through
    :func:`sim_core.ti_kernels.transfer.upload` and other dtypes through Taichi's call path."""
    if array.dtype == ti.f64:
        transfer.upload(array, values)
    elif not device_copy.to_device(array, np.ascontiguousarray(values)):
        array.from_numpy(values)


def _to_numpy(array) -> np.ndarray:
    """``array.to_numpy()``; float64 through :func:`sim_core.ti_kernels.transfer.download`."""
    return transfer.download(array) if array.dtype == ti.f64 else array.to_numpy()


def upload_constant(values: np.ndarray, dtype):
    """A new ndarray holding ``values`` (rest-shape data uploaded once per potential)."""
    buf = DeviceArray(dtype)
    return buf.upload(values)


class LaunchArrays(threading.local):
    """NumPy arrays kept for a module's kernel launches, per thread, grown but never shrunk.

    A kernel launched with the same array objects as at its last launch re-binds none of them
    (:mod:`sim_core.ti_kernels.launch`; a re-bind costs ~5-10 us of Python per array). Functions
    whose callers pass new arrays at every call copy them into kept arrays instead (a copy of a few
    thousand entries costs ~1 us) and pass the row count as a scalar; the kernel's outputs are
    kept arrays too, copied out. One set per thread: concurrent calls from two threads never share
    an array.
    """

    def rows(self, name: str, rows: int, tail: tuple[int, ...] = (), dtype=np.float64) -> np.ndarray:
        """The kept array ``name``, shape ``(capacity, *tail)`` with ``capacity >= rows`` (replaced
        by one twice as long, at least, when it has fewer rows)."""
        array = self.__dict__.get(name)
        if array is None or array.shape[0] < rows:
            capacity = max(rows, 16, 2 * array.shape[0] if array is not None else 0)
            array = self.__dict__[name] = np.zeros((capacity,) + tuple(tail), dtype=dtype)
        return array

    def device(self) -> dict:
        """This thread's cache of device copies of its kept arrays (the ``kept`` of :func:`on_device`)."""
        return self.__dict__.setdefault("_device", {})

    def spares(self) -> dict:
        """This thread's device arrays that launches hand to their results (the ``kept`` of :func:`unheld_rows`)."""
        return self.__dict__.setdefault("_spares", {})

    def copy_of(self, name: str, values: np.ndarray) -> np.ndarray:
        """The kept float64 array ``name`` of ``values``' shape, holding a copy of ``values``."""
        array = self.__dict__[name] = copy_into(self.__dict__.get(name), values)
        return array


def copy_into(kept: np.ndarray | None, values: np.ndarray) -> np.ndarray:
    """``values`` copied into the float64 array ``kept`` (a new one when ``kept`` is None or of another
    shape); returns the array holding the copy. A kernel argument passed through a kept array is the
    same array object at every launch, so it is bound once (:mod:`sim_core.ti_kernels.launch`)."""
    if kept is None or kept.shape != np.shape(values):
        kept = np.empty(np.shape(values))
    np.copyto(kept, values)
    return kept


def on_device(kept: dict, name: str, host: np.ndarray, scratch: bool = False, refresh: bool = False,
              changed: bool = False):
    """The array a kernel launch should take for ``host``: on CUDA a Taichi ndarray in device memory kept in
    ``kept[name]`` (copied from ``host`` when ``host`` is another object than at the last call, or at every
    call with ``refresh``; a ``scratch`` array is only allocated, never copied: the kernels write it before
    they read it), so that a constant array crosses to the device once instead of at every launch (a NumPy
    argument of a CUDA launch is copied to the device and back each time); elsewhere ``host`` itself.

    Args:
        kept: the caller's cache (one per owner of the arrays).
        name: the array's name in it.
        host: the array, C-contiguous (float64, int32, int64 or int8), never changed in place while it is used here
            (a changed array is a new object) unless ``refresh``.
        scratch: a work array of the kernels (device contents only).
        refresh: copy ``host`` at every call (a kept host array whose contents change in place).
        changed: with ``refresh``, copy ``host`` only when its contents differ from the last copy's (kept on the
            host: a comparison of a few thousand entries costs less than a copy's round trip); for arrays the
            kernels only read, so that the device copy still holds the last copy's values.
    """
    entry = kept.get(name)
    if entry is not None and entry[0] is host and not refresh:  # kept on the device (only CUDA keeps entries)
        return entry[1]
    from sim_core.ti_backend import current_arch, ti

    if current_arch() != "cuda":
        return host
    if entry is None or entry[0] is not host or refresh:
        if changed and entry is not None and entry[0] is host and entry[2] is not None \
                and np.array_equal(entry[2], host):
            return entry[1]
        dtype = _taichi_dtype(host.dtype)
        dev = entry[1] if entry is not None and tuple(entry[1].shape) == host.shape and entry[1].dtype == dtype \
            else device_copy.new_ndarray(dtype, host.shape)
        if not scratch and host.size:
            _from_numpy(dev, np.ascontiguousarray(host))
        entry = kept[name] = (host, dev, host.copy() if changed else None)
    return entry[1]


def _taichi_dtype(dtype: np.dtype):
    """The Taichi dtype of a host array's ``dtype`` (float64, int32, int64 or int8) for its device copy."""
    from sim_core.ti_backend import ti

    return {np.dtype(np.float64): ti.f64, np.dtype(np.int32): ti.i32, np.dtype(np.int64): ti.i64,
            np.dtype(np.int8): ti.i8}[np.dtype(dtype)]


def rows_on_device(kept: dict, name: str, host: np.ndarray, refresh: bool = False):
    """:func:`on_device` for a kernel that takes its row count as an argument (and reads no more rows): on CUDA a
    Taichi ndarray kept in ``kept[name]`` of at least ``host``'s rows (``host.shape[0]``, the other dimensions and
    the dtype equal), whose first rows hold ``host`` (copied when ``host`` is another object than at the last call),
    replaced by one of twice the rows at least only when it has fewer; elsewhere ``host`` itself. A constant array
    of an owner that is rebuilt every few Newton iterations (a contact pair batch, a friction) then costs one copy
    per owner and no allocation: a device allocation and its release cost about 30 us of Python each (2-core VM),
    a copy of a few thousand entries about 2 us.

    Args:
        kept: the caller's cache (one per thread: the array is shared by every owner that names it).
        name: the array's name in it.
        host: the array, C-contiguous (float64, int32 or int64), at least one-dimensional, never changed in place
            while it is used here (a changed array is a new object) unless ``refresh``.
        refresh: copy ``host`` at this call even when it is the last call's object (its contents changed in place).
    """
    entry = kept.get(name)
    if entry is not None and entry[0] is host and not refresh:  # (only CUDA keeps entries)
        return entry[1]
    from sim_core.ti_backend import current_arch, ti

    if current_arch() != "cuda":
        return host
    rows, tail = host.shape[0], host.shape[1:]
    dtype = _taichi_dtype(host.dtype)
    if entry is not None and entry[1].dtype == dtype and tuple(entry[1].shape[1:]) == tail \
            and entry[1].shape[0] >= rows:
        dev, staging = entry[1], entry[2]
    else:
        capacity = max(rows, 16, 2 * entry[1].shape[0] if entry is not None else 0)
        dev = device_copy.new_ndarray(dtype, (capacity,) + tail)
        staging = np.zeros((capacity,) + tail, dtype=host.dtype)
    if rows:
        staging[:rows] = host
        if not device_copy.to_device(dev, staging, rows):
            dev.from_numpy(staging)
    kept[name] = (host, dev, staging)
    return dev


def copy_back(host: np.ndarray, array, rows: int | None = None) -> np.ndarray:
    """``array``'s values (a Taichi ndarray of ``host``'s shape and dtype, or a NumPy array: what
    :func:`on_device` returned) copied into ``host``, returned: a byte copy
    (:mod:`sim_core.ti_kernels.device_copy`) where one can be made, else through
    :func:`sim_core.ti_kernels.transfer.download` (float64) or Taichi's ``to_numpy``. ``rows``: copy only the
    first ``rows`` rows (a kept array of a larger capacity whose launch wrote those), the others left as they are.

    Raises:
        ValueError: ``host`` is not a C-contiguous array of ``array``'s shape and dtype, or ``rows`` is not in
            ``[0, host.shape[0]]``.
    """
    if isinstance(array, np.ndarray):  # what on_device returns off CUDA: the host array itself, or another
        if array is not host:
            np.copyto(host[:rows], array[:rows])
        return host
    if not device_copy.to_host(host, array, rows):
        np.copyto(host[:rows], _to_numpy(array)[:rows])
    return host


def unheld_rows(kept: dict, name: str, rows: int, tail: tuple[int, ...] = (), spares: int = 6, dtype=None,
                exact: bool = False):
    """A Taichi ndarray ``(capacity, *tail)`` of ``dtype`` (None: float64; one ``dtype`` a ``name``), ``capacity >= rows``
    (with ``exact``, ``capacity == rows``: arrays whose kernels read their shape), that no one but ``kept`` holds, for a
    launch whose results stay where it wrote them (:class:`DeviceRows` of an evaluation, read lazily): one of the
    arrays made here before under ``name`` (``kept[name]``, at most ``spares`` of them) to which ``kept`` holds the
    only reference (:func:`sys.getrefcount`: no evaluation's :class:`DeviceRows`, no caller, keeps it), else a new
    one of ``rows`` and a quarter more, rounded up to a power of ``sqrt(2)`` (so that lists a few rows longer or shorter
    find it again; in place of a free one too short, else beside them, or outside ``kept`` when
    ``spares`` are all held). So an evaluation's rows are never written while anything can read them, and a launch
    whose former results are gone allocates nothing. Its values are a former launch's: the caller's kernel writes
    the rows that will be read (and zeroes its sums). The host arrays' :class:`sim_core.array_pool.ArrayPool` keeps
    the same rule but hands out row views of a longer block; a Taichi ndarray has no views, so here a whole array of
    a capacity is handed out and the launch is told its rows.

    Raises:
        ValueError: ``rows`` or a ``tail`` dimension not positive (Taichi allocates no empty ndarray).
    """
    arrays = kept.setdefault(name, [])
    short = None
    for i in range(len(arrays)):
        if sys.getrefcount(arrays[i]) == 2:  # the list's reference and getrefcount's argument alone
            if (arrays[i].shape[0] == rows if exact else arrays[i].shape[0] >= rows) \
                    and tuple(arrays[i].shape[1:]) == tuple(tail):
                return arrays[i]
            short = i
    capacity = int(rows) if exact else _bucket(int(rows) + int(rows) // 4 + 64)
    array = device_copy.new_ndarray(ti.f64 if dtype is None else dtype, (capacity,) + tuple(tail))
    if short is not None:
        arrays[short] = array
    elif len(arrays) < spares:
        arrays.append(array)
    return array


def _bucket(rows: int) -> int:
    """The smallest ``ceil(sqrt(2)^k) >= rows`` (:func:`unheld_rows`' capacities)."""
    k = math.ceil(2.0 * math.log2(max(rows, 1)))
    while math.ceil(2.0 ** (0.5 * k)) < rows:  # (round-off of the logarithm)
        k += 1
    return math.ceil(2.0 ** (0.5 * k))


class DeviceRows:
    """Rows ``start:stop`` of a Taichi ndarray kept where a kernel wrote it (device memory on CUDA), read on
    the host only when asked: e.g. the contact pair batch's penalty Hessian blocks ``(a, 12, 12)``, which
    the batched CG expands on the device (:meth:`sim_core.ti_kernels.pcg.BatchedPCG.factorize`) without a
    round trip through the host.

    Args:
        array: the ndarray, shape ``(rows, ...)``.
        start, stop: the rows meant (``0 <= start <= stop <= rows``).
        shared: a dict shared by the :class:`DeviceRows` of one ``array`` (its host copy, downloaded once
            for all of them); None: its own.

    Attributes:
        array, start, stop: as given.
        shape: ``(stop - start,) + array.shape[1:]``.
    """

    def __init__(self, array, start: int, stop: int, shared: dict | None = None) -> None:
        self.array, self.start, self.stop = array, int(start), int(stop)
        self.shape = (self.stop - self.start,) + tuple(array.shape[1:])
        self._shared = {} if shared is None else shared

    def to_numpy(self) -> np.ndarray:
        """The rows as a read-only NumPy array (the whole ndarray downloaded once, kept, and sliced)."""
        host = self._shared.get("host")
        if host is None:
            host = self._shared["host"] = _to_numpy(self.array)
            host.flags.writeable = False
        return host[self.start:self.stop]


class DeviceHessianBlocks(NamedTuple):
    """Per-element Hessian blocks kept on the device: :class:`~sim_core.energies.base.HessianBlocks` with the
    blocks as :class:`DeviceRows`.

    Attributes:
        vertices: global vertex indices of each element, shape ``(element_count, m)``, int.
        blocks: :class:`DeviceRows` of shape ``(element_count, 3 m, 3 m)`` (J/m^2), local DoF order as in
            ``HessianBlocks``.
    """

    vertices: np.ndarray
    blocks: DeviceRows
