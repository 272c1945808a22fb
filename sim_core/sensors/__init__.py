"""Tactile sensor model: markers on the gel surface, pinhole camera, net wrench, rendered image.

Pure functions of the simulated state (ARCHITECTURE.md, "Sensors"); conventions in INTERFACES.md
(sensor frame, marker order ``iy * nx + ix``, pixel model, wrench ON the gel).
"""

from __future__ import annotations

from sim_core.sensors.camera import PinholeCamera
from sim_core.sensors.image import render_marker_image
from sim_core.sensors.markers import (
    MarkerEmbedding,
    embed_markers,
    marker_grid,
    marker_positions,
    marker_vertex_weights,
)
from sim_core.sensors.tactile import TactileReading, TactileSensorSpec, read_tactile
from sim_core.sensors.wrench import net_wrench

__all__ = [
    "MarkerEmbedding",
    "PinholeCamera",
    "TactileReading",
    "TactileSensorSpec",
    "embed_markers",
    "marker_grid",
    "marker_positions",
    "marker_vertex_weights",
    "net_wrench",
    "read_tactile",
    "render_marker_image",
]
