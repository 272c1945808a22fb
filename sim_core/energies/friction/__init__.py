"""Lagged smoothed Coulomb friction after IPC (Li et al. 2020).

- ``reference.py``: :class:`LaggedFriction`, value, gradient and projected Hessian in NumPy (the
  reference and test oracle), and the smoothed friction functions ``f0``, ``f1``.
- ``kernel.py``: ``TiLaggedFriction``, the same quantities in Taichi kernels (imports Taichi).
"""

from __future__ import annotations

from sim_core.energies.friction.reference import LaggedFriction

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name):
the registration read by :func:`sim_core.energies.registry.make_elastic_potential`."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {}
"""Potential class -> fused part class, each as (module, name): the registration read by
:data:`sim_core.fused_elastic.FUSED_KERNELS`. Taichi modules are imported on first use."""

__all__ = ['LaggedFriction', 'ELASTIC_KINDS', 'FUSED_KERNELS']
