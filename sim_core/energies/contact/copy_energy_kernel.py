"""The contact pairs' penalty energies summed by copy where the pair batch's kernel left its distances.

A lockstep line search's trial point asks every term for its energy split by copy
(:class:`~sim_core.energies.base.DeviceCopyEnergies`); the pair potentials' share is
``E_c = k_c / 2 sum_{pairs of c, d < eps} (d - eps)^2`` (:meth:`~sim_core.energies.contact.reference._PairPenalty.
copy_energies`: a pair belongs to the copy of its first vertex). The host sums it over the active list it read back;
here :func:`penalty_energy_by_copy` adds it into the shared per-copy sums
(:class:`~sim_core.ti_kernels.copy_vectors.CopySums`) from the distances and launch rows the pair batch's last launch
left where it ran (:class:`~sim_core.energies.contact.batch_kernel.PairBatch`), so that nothing of the pairs crosses to
the host for the energy. The same terms as the host's, summed per pair (``k_c / 2 (d - eps)^2`` each, in pair order on
the CPU arch, by atomic additions on a GPU): equal to the host's to round-off.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

from sim_core.ti_backend import serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.launch import fast_kernel

_F64_1, _I32_2 = linalg.F64_1, linalg.I32_2
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@fast_kernel
def _penalty_energy_by_copy(d: _F64_1, rows: _I32_1, vertices: _I32_2, own_copy: _I32_1, start: ti.i32, stop: ti.i32,
                            eps: ti.f64, half_stiffness: ti.f64, sums: _F64_1):
    """``sums[c] += k_c / 2 (d[i] - eps)^2`` for the launch rows ``start <= i < stop`` with ``d[i] < eps`` (``d``
    ``(>= stop,)`` m; an unmeasured pair's ``inf`` adds nothing), ``c = own_copy[vertices[rows[i], 0]]``: the copy of
    the pair's first vertex (``rows`` the launch rows' layout rows, ``vertices`` the layout's ``local`` ``(r, 4)`` into
    the batch's vertices ``own``, ``own_copy`` ``(u,)`` their copies)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(start, stop):
        gap = d[i] - eps
        if gap < 0.0:
            sums[own_copy[vertices[rows[i], 0]]] += half_stiffness * gap * gap


def penalty_energy_by_copy(d, rows, vertices, own_copy, start: int, stop: int, eps: float, stiffness: float,
                           sums) -> None:
    """Launch :func:`_penalty_energy_by_copy` (arrays as it reads them: NumPy arrays on the CPU arch, Taichi ndarrays
    where they live on a GPU) adding the penalties ``k_c / 2 (d - eps)^2`` (J) of the rows ``start .. stop - 1``
    into ``sums`` (float64 ``(B,)``)."""
    if stop > start:
        _penalty_energy_by_copy(d, rows, vertices, own_copy, int(start), int(stop), float(eps), 0.5 * float(stiffness),
                                sums)

