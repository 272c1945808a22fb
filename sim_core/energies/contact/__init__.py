"""Penalty contact with side memory (IPC-style barrier on the pair distance): vertex-triangle,
edge-edge and vertex-plane pairs.

- ``reference.py``: :class:`VertexTriangleContact`, :class:`EdgeEdgeContact`, :class:`PlaneContact`,
  value, gradient and projected Hessian in NumPy (the reference and test oracle).
- ``kernel.py``: ``TiVertexTriangleContact``, ``TiEdgeEdgeContact``, the pair distances on Taichi.
- ``batch_kernel.py``: one launch evaluates the step's vertex-triangle and edge-edge potentials.
- ``gradient_kernel.py``: rows of positions and gradients gathered and added where a Taichi array is.
- ``distance_kernel.py``: pair distances and their derivatives in Taichi (twin of
  :mod:`sim_core.collision.distances`).
- ``setup_kernel.py``: start- and end-of-step pair geometry, contact frames and tangent bases in Taichi.

The candidate search (broad phase) is shared infrastructure: :mod:`sim_core.collision` (NumPy) and
:mod:`sim_core.ti_kernels` (Taichi); the step's contact set is :mod:`sim_core.contact_set`.
"""

from __future__ import annotations

from sim_core.energies.contact.reference import EdgeEdgeContact, PlaneContact, VertexTriangleContact

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {}
"""Elastic potential kind -> (NumPy class, Taichi twin class), each as (module, name):
the registration read by :func:`sim_core.energies.registry.make_elastic_potential`."""

FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {}
"""Potential class -> fused part class, each as (module, name): the registration read by
:data:`sim_core.fused_elastic.FUSED_KERNELS`. Taichi modules are imported on first use."""

__all__ = ['EdgeEdgeContact', 'PlaneContact', 'VertexTriangleContact', 'ELASTIC_KINDS', 'FUSED_KERNELS']
