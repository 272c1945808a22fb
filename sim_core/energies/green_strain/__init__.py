"""Saint Venant-Kirchhoff tetrahedra: a solid whose elasticity is written in the Green strain (the law of the
reference engine's flex solids), opt-in as ``simulation.gel_element: green_strain``.

- ``reference.py``: :class:`GreenStrainSolid`, value, gradient and projected Hessian in NumPy (the reference and
  test oracle), and ``parameter_gradient`` for the adjoint (NumPy on both backends, as the Stable Neo-Hookean gel's).
- ``kernel.py``: ``TiGreenStrainSolid``, the same quantities in Taichi kernels (imports Taichi).
- ``fused_kernel.py``: ``FusedGreenStrainSolid``, energy, gradient and exact Hessian in one Taichi launch into the
  Newton matrix's CSR slots (:class:`sim_core.fused_elastic.FusedElastic`): what the Taichi backends run.
"""

from __future__ import annotations

from sim_core.energies.green_strain.reference import GreenStrainSolid, GreenStrainTets, linear_lame_parameters

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    'green_strain':
        (('sim_core.energies.green_strain.reference', 'GreenStrainSolid'),
         ('sim_core.energies.green_strain.kernel', 'TiGreenStrainSolid')),
}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name): the registration read by
:func:`sim_core.energies.registry.make_elastic_potential`."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {
    ('sim_core.energies.green_strain.reference', 'GreenStrainSolid'):
        ('sim_core.energies.green_strain.fused_kernel', 'FusedGreenStrainSolid'),
}
"""Potential class -> fused part class, each as (module, name): the registration read by
:data:`sim_core.fused_elastic.FUSED_KERNELS`. Taichi modules are imported on first use."""

__all__ = ['GreenStrainSolid', 'GreenStrainTets', 'linear_lame_parameters', 'ELASTIC_KINDS', 'FUSED_KERNELS']
