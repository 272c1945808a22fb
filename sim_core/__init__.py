"""thinshell simulation core: implicit FEM for thin shells and tactile elastomers.

Physics only; this package never imports ROS or bag libraries.
"""

from __future__ import annotations

from sim_core.errors import (
    BagReadError,
    CalibrationError,
    ConfigError,
    MeshError,
    SimulationDivergedError,
    ThinShellError,
)

__all__ = [
    "BagReadError",
    "CalibrationError",
    "ConfigError",
    "MeshError",
    "SimulationDivergedError",
    "ThinShellError",
]
