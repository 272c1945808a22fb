"""Rows of positions and gradients moved where a Taichi array is: the contact pair batch's device-side gather and
scatter (:class:`~sim_core.energies.base.DeviceGradient`).

The lockstep batch keeps its iterates and stacked gradient as Taichi ndarrays on a Taichi backend; the pair batch
(:mod:`sim_core.energies.contact.batch_kernel`) reads the positions of the vertices its pairs name from the
positions' ndarray (:func:`gather_rows`) and adds its per-vertex gradient sums into the gradient's ndarray
(:func:`add_rows`: ``g[v] += row``, the host's ``g[vertices] += rows`` entry by entry), so that neither crosses
to the host.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np

from sim_core.ti_backend import serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.launch import fast_kernel

_F64_2 = linalg.F64_2
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@fast_kernel
def gather_rows(x: _F64_2, own: _I32_1, out: _F64_2):
    """``out[j] = x[own[j]]`` for ``j < len(own)``: rows ``(u, 3)`` of ``x`` ``(n, 3)`` (e.g. the positions, m, of
    the vertices a batch's pairs name), read where ``x`` is."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for j in range(own.shape[0]):
        for c in ti.static(range(3)):
            out[j, c] = x[own[j], c]


@fast_kernel
def add_rows(gradient: _F64_2, vertices: _I32_1, rows: _F64_2, first: ti.i32):
    """``gradient[vertices[j]] += rows[first + j]`` for ``j < len(vertices)``, ``gradient`` ``(n, 3)`` (N): distinct
    ``vertices``, so one addition per entry, as the host's ``g[vertices] += rows``."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for j in range(vertices.shape[0]):
        for c in ti.static(range(3)):
            gradient[vertices[j], c] += rows[first + j, c]


def add_rows_on_device(gradient_device, vertices: np.ndarray | None, rows: np.ndarray) -> None:
    """Add host rows ``rows`` ``(u, 3)`` (N) into the Taichi float64 ndarray ``gradient_device`` ``(n, 3)`` at the
    distinct ``vertices`` ``(u,)`` (int), or every row (``vertices`` None, ``rows`` ``(n, 3)``), on the device."""
    if not len(rows):
        return
    index = (np.arange(len(rows), dtype=np.int32) if vertices is None
             else np.ascontiguousarray(vertices, dtype=np.int32))
    add_rows(gradient_device, index, np.ascontiguousarray(rows, dtype=np.float64), 0)
