"""A pair batch's derivatives at new positions in one launch, the active pairs listed in row order on the device.

:class:`~sim_core.energies.contact.batch_kernel.PairBatch` evaluates derivatives at positions it has not measured in
two launches where arrays cross to a GPU (:attr:`~sim_core.energies.contact.batch_kernel.PairBatch.two_pass`): the
distance of every candidate pair, then, after the host has read the active list back, sorted it and sent its rows up
again, the derivatives of the active pairs. That is three host round trips a trial point of the lockstep line search
(the list's read, waiting for the pass over every candidate; the rows' upload; the regions' read after the second pass).
:func:`listed_derivatives` makes both passes in one launch of :func:`_listed_kernel`, the list between them kept where
it is: every pair measured (:func:`~sim_core.energies.contact.pair_measure.measure_pair`), the active ones (``d < eps``)
marked, their places in increasing row order the marks' running sums (:func:`~sim_core.ti_kernels.scan.running_sums`),
then each active pair measured again with derivatives into its place; its launch row, distance and region packed for
one copy back after the launch. The same functions in the same order of pairs as the two launches: the same values bit
for bit (on the CPU's serial loops also the same gradient sums; on a GPU they are summed in any order, as there).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

from sim_core.energies.contact.pair_measure import measure_pair, zero_sums
from sim_core.ti_backend import serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.scan import SCAN_CHUNK, running_sums

_F64_1, _F64_2, _F64_3, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_2
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)

LISTED_FIELDS = 3
"""Entries of :func:`_listed_kernel`'s ``out`` a listed pair: its launch row, distance (m) and region."""


@fast_kernel
def _listed_kernel(x: _F64_2, vertices: _I32_2, side: _F64_1, rows: _I32_1, count: ti.i32, split: ti.i32,
                   capacity: ti.i32, eps_vt: ti.f64, eps_ee: ti.f64, stiffness_vt: ti.f64, stiffness_ee: ti.f64,
                   z: _F64_3, d: _F64_1, region: _I32_1, marks: _I32_1, chunk_total: _I32_1, total: _I32_1,
                   order: _I32_1, z_active: _F64_3, d_active: _F64_1, region_active: _I32_1, layout_rows: _I32_1,
                   grad: _F64_2, hess: _F64_3, gradients: _F64_2, out: _F64_1):
    """Pairs ``k = rows[i]`` for ``i < count`` (``k < split`` vertex-triangle, else edge-edge), as the two launches
    of :func:`~sim_core.energies.contact.batch_kernel._batch_kernel` (distances of every pair, then derivatives of the
    active ones) make them: the distance of each into ``d[i]`` (positions gathered into ``z[i]``, region into
    ``region[i]``); the active pairs' count ``a`` into ``total[0]`` and their places ``p`` in increasing ``i``; for
    ``p < capacity`` the pair's launch row into ``order[p]``, its layout row into ``layout_rows[p]``, its distance,
    region, distance gradient and penalty Hessian into row ``p`` of ``d_active``, ``region_active``, ``grad`` and
    ``hess`` (positions into ``z_active[p]``), its penalty gradient summed per vertex into ``gradients`` (``(2 n,
    3)``, zeroed first); ``out[0] = a``, ``out[1 + 3 p .. 3 + 3 p] = (i, d, region)``. Scratch: ``marks`` (at least
    ``count + 1``), ``chunk_total`` (at least ``ceil(count / SCAN_CHUNK)``). The arrays of ``capacity`` rows hold the
    first ``min(a, capacity)`` places; ``a > capacity`` asks for a launch with more."""
    n = x.shape[0]
    zero_sums(gradients, 2 * n, total)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for _ in range(1):
        marks[0] = 0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(count):
        marks[i + 1] = measure_pair(x, vertices, side, rows[i], i, split, eps_vt, eps_ee, stiffness_vt, stiffness_ee,
                                    n, 0, z, d, region, grad, hess, gradients)
    running_sums(marks, count, chunk_total, total, 0)  # marks[i]: the active pairs before pair i
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(count):
        if marks[i + 1] != marks[i] and marks[i] < capacity:
            order[marks[i]] = i
    ti.loop_config(serialize=ti.static(serial_loops()))
    for p in range(capacity):
        if p < total[0]:
            i = order[p]
            layout_rows[p] = rows[i]
            measure_pair(x, vertices, side, rows[i], p, split, eps_vt, eps_ee, stiffness_vt, stiffness_ee, n, 1,
                         z_active, d_active, region_active, grad, hess, gradients)
            out[1 + 3 * p] = ti.cast(i, ti.f64)
            out[2 + 3 * p] = d_active[p]
            out[3 + 3 * p] = ti.cast(region_active[p], ti.f64)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for _ in range(1):
        out[0] = ti.cast(total[0], ti.f64)


def listed_derivatives(x, vertices, side, rows, count: int, split: int, capacity: int, parameters: tuple,
                       work: tuple, listed: tuple, grad, hess, gradients, out) -> None:
    """Launch :func:`_listed_kernel` over the pairs ``rows[:count]`` (``parameters``: ``(eps_vt, eps_ee, k_vt,
    k_ee)``; ``work``: ``(z, d, region, marks, chunk_total, total)`` of at least ``count`` rows, ``marks`` one more,
    ``chunk_total`` ``ceil(count / SCAN_CHUNK)``; ``listed``: ``(order, z_active, d_active, region_active,
    layout_rows)`` of at least ``capacity`` rows, as ``grad`` and ``hess``; ``gradients`` ``(2 n, 3)``; ``out`` at
    least ``1 + 3 capacity``): NumPy arrays on the CPU arch, Taichi ndarrays where they live on a GPU."""
    _listed_kernel(x, vertices, side, rows, int(count), int(split), int(capacity), *parameters, *work, *listed, grad,
                   hess, gradients, out)


def chunk_count(count: int) -> int:
    """Entries of :func:`_listed_kernel`'s ``chunk_total`` for ``count`` pairs (at least 1)."""
    return max(1, -(-int(count) // SCAN_CHUNK))
