"""Copies between NumPy arrays and float64 Taichi ndarrays, and fills, without Taichi's call path.

``ndarray.to_numpy()``, ``from_numpy()`` and ``fill()`` go through Taichi's own call path (a kernel
launched with its per-call argument analysis, then a synchronisation): about 0.23 ms a call on the
H200 host, 41 calls a Forming step on CUDA (``benchmarks/profile_single.py``). The copies here are
byte copies by address (:mod:`sim_core.ti_kernels.device_copy`: the CUDA driver's synchronous copies,
``memmove`` on the CPU) where the calling thread can make them, else one launch of a copy kernel
through :func:`sim_core.ti_kernels.launch.fast_kernel` (its plans bind NumPy arrays and Taichi ndarrays
alike; on CUDA the NumPy side then crosses to the device and back with the launch, as Taichi copies
every host array of a launch both ways). A zero fill is a memset, another fill one planned launch. The
values are the same. :func:`add_into` adds one array into another where they are (a term's gradient into a
device-resident sum, :class:`~sim_core.energies.base.DeviceGradient`). :func:`offer_positions` and
:func:`positions_on_device` let the terms of one solver read positions already copied to the device by another
(a single environment's fused elastic terms copy every iterate and trial point there) instead of copying them again.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np

from sim_core.ti_backend import ti
from sim_core.ti_kernels import device_copy
from sim_core.ti_kernels.launch import fast_kernel

_F64_ANY = ti.types.ndarray(dtype=ti.f64)  # float64 of any rank (a kernel compiled per rank)
_F64_2 = ti.types.ndarray(dtype=ti.f64, ndim=2)


@fast_kernel
def _copy_f64(source: _F64_ANY, target: _F64_ANY):
    """``target[I] = source[I]`` for every index of ``source`` (same shapes)."""
    for I in ti.grouped(source):
        target[I] = source[I]


@fast_kernel
def _fill_f64(target: _F64_ANY, value: ti.f64):
    """``target[I] = value`` for every index."""
    for I in ti.grouped(target):
        target[I] = value


def download(array, out: "np.ndarray | None" = None) -> np.ndarray:
    """The values of the float64 ndarray ``array`` in ``out`` (a C-contiguous float64 NumPy array of its
    shape; None: a new one), returned: ``array.to_numpy()`` in one byte copy or planned launch.

    Raises:
        ValueError: ``out`` is not a C-contiguous float64 array of ``array``'s shape.
    """
    shape = tuple(array.shape)
    if out is None:
        out = np.empty(shape)
    elif out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ValueError(f"download: out must be C-contiguous float64 of shape {shape}; got {out.dtype} {out.shape}")
    if out.size and not device_copy.to_host(out, array):
        _copy_f64(array, out)
    return out


def upload(array, values: np.ndarray):
    """Copy ``values`` (float64 after conversion, ``array``'s shape) into the float64 ndarray ``array``:
    ``array.from_numpy(values)`` in one byte copy or planned launch; returns ``array``.

    Raises:
        ValueError: ``values`` has another shape than ``array``.
    """
    values = np.ascontiguousarray(values, dtype=np.float64)
    if values.shape != tuple(array.shape):
        raise ValueError(f"upload: values of shape {values.shape} for an ndarray of shape {tuple(array.shape)}")
    if values.size and not device_copy.to_device(array, values):
        _copy_f64(values, array)
    return array


def fill(array, value: float):
    """Set every entry of the float64 ndarray ``array`` to ``value`` (``array.fill(value)``; returns ``array``): a
    zero by the driver's memset where it can be made (:func:`sim_core.ti_kernels.device_copy.zero`: no launch, the
    bytes of +0.0), else one planned launch, no host array in it."""
    value = float(value)
    if int(np.prod(array.shape)) and not (value == 0.0 and not np.signbit(value) and device_copy.zero(array)):
        _fill_f64(array, value)
    return array


@fast_kernel
def _add_f64_2(source: _F64_2, target: _F64_2):
    """``target[i, j] += source[i, j]`` (same shapes). A loop over rows and a runtime one over columns: on the CPU
    arch 8 ms for 580,000 x 3 entries where a ``ti.grouped`` loop took 41 ms (2-core VM)."""
    for i in range(source.shape[0]):
        for j in range(source.shape[1]):
            target[i, j] += source[i, j]


def add_into(array, values):
    """``array += values`` for the float64 ndarray ``array`` of rank 2 (e.g. a gradient ``(n, 3)``) and ``values`` of
    its shape (a float64 ndarray where the kernels run, or a C-contiguous float64 NumPy array: on CUDA Taichi then
    copies it to the device and back with the launch) in one planned launch; returns ``array``. Each entry is one
    addition: the sum of ``array.to_numpy() + values`` bit for bit.

    Raises:
        ValueError: ``values`` has another shape than ``array``, or the arrays are not of rank 2.
    """
    if len(array.shape) != 2:
        raise ValueError(f"add_into: an ndarray of rank 2 is needed; got shape {tuple(array.shape)}")
    if tuple(values.shape) != tuple(array.shape):
        raise ValueError(f"add_into: values of shape {tuple(values.shape)} for an ndarray of shape "
                         f"{tuple(array.shape)}")
    if int(np.prod(array.shape)):
        _add_f64_2(values, array)
    return array


def same_shapes(where: str, x: np.ndarray, x_device, gradient_device) -> tuple:
    """The shape of positions ``x`` ``(n, 3)`` after checking that the device positions ``x_device`` and gradient
    ``gradient_device`` (the arguments of :class:`~sim_core.energies.base.DeviceGradient`) have it.

    Raises:
        ValueError: ``x_device`` or ``gradient_device`` is of another shape (the message names ``where``).
    """
    shape = np.shape(x)
    for name, array in (("x_device", x_device), ("gradient_device", gradient_device)):
        if tuple(array.shape) != shape:
            raise ValueError(f"{where}: {name} of shape {tuple(array.shape)}, positions {shape}")
    return shape


_POSITIONS = "positions on the device"
"""The workspace entry of :func:`offer_positions` (owned by the workspace itself)."""


def offer_positions(workspace, source) -> None:
    """Let the terms sharing ``workspace`` (a :class:`~sim_core.workspace.Workspace`) read positions from ``source``:
    an object whose ``device_positions(x)`` gives the float64 ndarray ``(n, 3)`` holding the positions ``x`` where it
    copied them last, or None (:meth:`~sim_core.fused_elastic.FusedElastic.device_positions`). Forgetting the entry
    (the workspace's ``clear``) only brings back the copies."""
    workspace.put(workspace, _POSITIONS, source)


def positions_on_device(workspace, x: np.ndarray):
    """The float64 ndarray ``(n, 3)`` (only to be read) that holds the positions ``x`` ``(n, 3)`` (m) on the device,
    offered in ``workspace`` (:func:`offer_positions`; None: no workspace), or None where none holds them now."""
    source = None if workspace is None else workspace.get(workspace, _POSITIONS)
    return None if source is None else source.device_positions(x)
