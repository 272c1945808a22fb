"""Discrete Kirchhoff plate bending with a Poisson ratio (the default sheet bending model).

- ``reference.py``: :class:`KirchhoffBending`, value, gradient and projected Hessian in NumPy (the
  reference and test oracle).
- ``fused_kernel.py``: ``FusedKirchhoffBending``, energy, gradient and exact Hessian in one Taichi
  launch into the Newton matrix's CSR slots (imports Taichi).
"""

from __future__ import annotations

from sim_core.energies.kirchhoff_bending.reference import KirchhoffBending

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name):
the registration read by :func:`sim_core.energies.registry.make_elastic_potential`."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {
    ('sim_core.energies.kirchhoff_bending.reference', 'KirchhoffBending'):
        ('sim_core.energies.kirchhoff_bending.fused_kernel', 'FusedKirchhoffBending'),
}
"""Potential class -> fused part class, each as (module, name): the registration read by
:data:`sim_core.fused_elastic.FUSED_KERNELS`. Taichi modules are imported on first use."""

__all__ = ['KirchhoffBending', 'ELASTIC_KINDS', 'FUSED_KERNELS']
