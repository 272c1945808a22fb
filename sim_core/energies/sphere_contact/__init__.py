"""Penalty contact between vertices and a rigid sphere whose centre is a (kinematic) vertex.

- ``reference.py``: :class:`SphereContact` in NumPy (no Taichi kernel).
"""

from __future__ import annotations

from sim_core.energies.sphere_contact.reference import SphereContact

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name):
the registration read by :func:`sim_core.energies.registry.make_elastic_potential`."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {}
"""Potential class -> fused part class, each as (module, name): the registration read by
:data:`sim_core.fused_elastic.FUSED_KERNELS`. Taichi modules are imported on first use."""

__all__ = ['SphereContact', 'ELASTIC_KINDS', 'FUSED_KERNELS']
