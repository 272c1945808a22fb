"""Saint Venant-Kirchhoff tetrahedra: a solid whose elasticity is written in the Green strain (the law of the
reference engine's flex solids), opt-in as ``simulation.gel_element: green_strain``.

- ``reference.py``: :class:`GreenStrainSolid`, value, gradient and projected Hessian in NumPy, and
  ``parameter_gradient`` for the adjoint. No Taichi twin and no fused kernel: the NumPy class on both backends.
"""

from __future__ import annotations

from sim_core.energies.green_strain.reference import GreenStrainSolid, linear_lame_parameters

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    'green_strain':
        (('sim_core.energies.green_strain.reference', 'GreenStrainSolid'),
         ('sim_core.energies.green_strain.reference', 'GreenStrainSolid')),
}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name): the registration read by
:func:`sim_core.energies.registry.make_elastic_potential` (no Taichi twin: the NumPy class on both backends)."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {}
"""No fused kernel."""

__all__ = ['GreenStrainSolid', 'linear_lame_parameters', 'ELASTIC_KINDS', 'FUSED_KERNELS']
