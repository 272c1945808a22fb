"""Collision detection: narrow-phase distances, spatial-hash broad phase, contact side memory.

Layers (IPC Toolkit's): :mod:`distances` (closest points and contact distances with derivatives)
-> :mod:`candidates` (broad phase over :mod:`spatial_hash`, exclusions) -> :mod:`memory` (side
memory of active pairs). The penalty and friction energies built on them live in
``sim_core.energies.contact.reference`` and ``sim_core.energies.friction.reference``.
"""

from __future__ import annotations

from sim_core.collision.candidates import PairFilter, edge_edge_candidates, vertex_triangle_candidates
from sim_core.collision.distances import (
    EdgeEdgeRegion,
    PointTriangleRegion,
    edge_edge_closest_points,
    edge_edge_contact_distance,
    edge_edge_distance,
    edge_edge_side,
    point_triangle_closest_point,
    point_triangle_contact_distance,
    point_triangle_distance,
    point_triangle_region,
    point_triangle_side,
)
from sim_core.collision.memory import (
    CollisionMemory,
    ContactMemory,
    edge_edge_pair_sides,
    vertex_triangle_pair_sides,
)
from sim_core.collision.spatial_hash import SpatialHash

__all__ = [
    "CollisionMemory",
    "ContactMemory",
    "EdgeEdgeRegion",
    "PairFilter",
    "PointTriangleRegion",
    "SpatialHash",
    "edge_edge_candidates",
    "edge_edge_closest_points",
    "edge_edge_contact_distance",
    "edge_edge_distance",
    "edge_edge_pair_sides",
    "edge_edge_side",
    "point_triangle_closest_point",
    "point_triangle_contact_distance",
    "point_triangle_distance",
    "point_triangle_region",
    "point_triangle_side",
    "vertex_triangle_candidates",
    "vertex_triangle_pair_sides",
]
