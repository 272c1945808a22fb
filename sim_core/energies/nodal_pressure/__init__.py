"""Average-nodal-pressure Stable Neo-Hookean tetrahedra: the gel element that does not lock (Bonet and
Burton 1998): the shear per tet, the volume change per vertex ring.

- ``reference.py``: :class:`NodalPressureNeoHookean`, value, gradient and projected Hessian in NumPy (the
  reference and test oracle), and ``parameter_gradient`` for the adjoint; its two parts for the solver:
  the shear part, a Stable Neo-Hookean (on the Taichi backends the fused Stable Neo-Hookean kernel), and
  :class:`NodalVolume`, the nodal volumetric term, NumPy on every backend (``FusedElastic``'s reference part).
"""

from __future__ import annotations

from sim_core.energies.nodal_pressure.reference import NodalPressureNeoHookean, NodalVolume, nodal_pressure_moduli

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    'nodal_pressure_neohookean':
        (('sim_core.energies.nodal_pressure.reference', 'NodalPressureNeoHookean'),
         ('sim_core.energies.nodal_pressure.reference', 'NodalPressureNeoHookean')),
}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name): the registration
read by :func:`sim_core.energies.registry.make_elastic_potential` (no Taichi twin yet: the NumPy class on
both backends)."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {}
"""No fused kernel of its own (its shear part takes Stable Neo-Hookean's)."""

__all__ = ['NodalPressureNeoHookean', 'NodalVolume', 'nodal_pressure_moduli', 'ELASTIC_KINDS', 'FUSED_KERNELS']
