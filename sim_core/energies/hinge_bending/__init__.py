"""Discrete-shell hinge bending (Grinspun, Hirani, Desbrun, Schroeder 2003) and bending plasticity.

- ``reference.py``: :class:`DiscreteShellBending`, value, gradient and projected Hessian in NumPy
  (the reference and test oracle); dihedral angles and their derivatives; :func:`plastic_update`.
- ``kernel.py``: ``TiDiscreteShellBending``, the same quantities in Taichi kernels (imports Taichi).
- ``fused_kernel.py``: ``FusedAnisotropicBending``, hinge bending with per-hinge weights (the
  anisotropic bending candidate, :mod:`sim_core.candidates.anisotropic_bending`) in one Taichi launch.
"""

from __future__ import annotations

from sim_core.energies.hinge_bending.reference import DiscreteShellBending, plastic_update

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    'discrete_shell_bending':
        (('sim_core.energies.hinge_bending.reference', 'DiscreteShellBending'),
         ('sim_core.energies.hinge_bending.kernel', 'TiDiscreteShellBending')),
}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name):
the registration read by :func:`sim_core.energies.registry.make_elastic_potential`."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {}
"""Potential class -> fused part class, each as (module, name): the registration read by
:data:`sim_core.fused_elastic.FUSED_KERNELS`. Taichi modules are imported on first use."""

__all__ = ['DiscreteShellBending', 'plastic_update', 'ELASTIC_KINDS', 'FUSED_KERNELS']
