"""Membrane (in-plane stretching) energies of thin shells: StVK triangles and ThinShellLab's springs.

- ``reference.py``: :class:`StVKMembrane` and :class:`SpringMembrane`, value, gradient and projected
  Hessian in NumPy (the reference and test oracle).
- ``kernel.py``: ``TiStVKMembrane``, the StVK quantities in Taichi kernels (imports Taichi).
- ``fused_stvk_kernel.py``, ``fused_spring_kernel.py``: ``FusedStVKMembrane``, ``FusedSpringMembrane``,
  energy, gradient and exact Hessian in one Taichi launch into the Newton matrix's CSR slots.
"""

from __future__ import annotations

from sim_core.energies.membrane.reference import SpringMembrane, StVKMembrane

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    'stvk_membrane':
        (('sim_core.energies.membrane.reference', 'StVKMembrane'),
         ('sim_core.energies.membrane.kernel', 'TiStVKMembrane')),
}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name):
the registration read by :func:`sim_core.energies.registry.make_elastic_potential`."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {
    ('sim_core.energies.membrane.reference', 'SpringMembrane'):
        ('sim_core.energies.membrane.fused_spring_kernel', 'FusedSpringMembrane'),
    ('sim_core.energies.membrane.reference', 'StVKMembrane'):
        ('sim_core.energies.membrane.fused_stvk_kernel', 'FusedStVKMembrane'),
}
"""Potential class -> fused part class, each as (module, name): the registration read by
:data:`sim_core.fused_elastic.FUSED_KERNELS`. Taichi modules are imported on first use."""

__all__ = ['SpringMembrane', 'StVKMembrane', 'ELASTIC_KINDS', 'FUSED_KERNELS']
