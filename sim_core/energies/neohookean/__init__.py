"""Stable Neo-Hookean tetrahedra: the tactile gel (Smith, de Goes, Kim 2018).

- ``reference.py``: :class:`StableNeoHookean`, value, gradient and projected Hessian in NumPy (the
  reference and test oracle), and ``parameter_gradient`` for the adjoint.
- ``kernel.py``: ``TiStableNeoHookean``, the same quantities in Taichi kernels (imports Taichi).
- ``fused_kernel.py``: ``FusedStableNeoHookean``, energy, gradient and exact Hessian in one Taichi
  launch into the Newton matrix's CSR slots (:class:`sim_core.fused_elastic.FusedElastic`).
"""

from __future__ import annotations

from sim_core.energies.neohookean.reference import StableNeoHookean, snh_lame_parameters

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    'stable_neohookean':
        (('sim_core.energies.neohookean.reference', 'StableNeoHookean'),
         ('sim_core.energies.neohookean.kernel', 'TiStableNeoHookean')),
}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name):
the registration read by :func:`sim_core.energies.registry.make_elastic_potential`."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {
    ('sim_core.energies.neohookean.reference', 'StableNeoHookean'):
        ('sim_core.energies.neohookean.fused_kernel', 'FusedStableNeoHookean'),
}
"""Potential class -> fused part class, each as (module, name): the registration read by
:data:`sim_core.fused_elastic.FUSED_KERNELS`. Taichi modules are imported on first use."""

__all__ = ['StableNeoHookean', 'snh_lame_parameters', 'ELASTIC_KINDS', 'FUSED_KERNELS']
