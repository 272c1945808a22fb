"""The modified Saint Venant-Kirchhoff solid: Green-strain shear, a volumetric energy ``lam / 2 (ln J)^2`` that keeps
``J > 0``; opt-in as ``simulation.gel_element: modified_stvk``.

- ``reference.py``: :class:`ModifiedStVKSolid`, value, gradient and projected Hessian in NumPy, and
  ``parameter_gradient`` for the adjoint. No Taichi twin: on the Taichi backends the solver evaluates it as a
  reference part (:class:`sim_core.fused_elastic.FusedElastic`'s NumPy fallback).
"""

from __future__ import annotations

from sim_core.energies.modified_stvk.reference import ModifiedStVKSolid

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    'modified_stvk':
        (('sim_core.energies.modified_stvk.reference', 'ModifiedStVKSolid'),
         ('sim_core.energies.modified_stvk.reference', 'ModifiedStVKSolid')),
}
"""Elastic potential kind -> (NumPy class, Taichi class), each as (module, name): the registration read by
:func:`sim_core.energies.registry.make_elastic_potential` (the NumPy class on both backends)."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {}
"""Potential class -> fused part class: none yet (the registration read by :data:`sim_core.fused_elastic.FUSED_KERNELS`;
the reference part evaluates this law)."""

__all__ = ['ModifiedStVKSolid', 'ELASTIC_KINDS', 'FUSED_KERNELS']
