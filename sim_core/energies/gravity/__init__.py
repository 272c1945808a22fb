"""Gravity: ``E = - sum_i m_i g . x_i``.

- ``reference.py``: :class:`GravityPotential` in NumPy (linear, no Hessian).
- ``kernel.py``: ``TiGravityPotential``, its constant gradient added into a device array (imports Taichi).
"""

from __future__ import annotations

from sim_core.energies.gravity.reference import GravityPotential

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name):
the registration read by :func:`sim_core.energies.registry.make_elastic_potential`."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {}
"""Potential class -> fused part class, each as (module, name): the registration read by
:data:`sim_core.fused_elastic.FUSED_KERNELS`. Taichi modules are imported on first use."""

__all__ = ['GravityPotential', 'ELASTIC_KINDS', 'FUSED_KERNELS']
