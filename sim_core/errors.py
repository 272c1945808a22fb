"""Exception hierarchy of thinshell.

Every boundary (file readers, YAML loaders, the Newton solver, the bag reader) raises one of these
with a message that names what failed: the file, the YAML key, the mesh element, the topic or the
time step. Callers re-raise with ``from err`` to keep the cause.
"""

from __future__ import annotations


class ThinShellError(Exception):
    """Base class of every error raised on purpose by thinshell."""


class ConfigError(ThinShellError):
    """A scene/material/node/sysid configuration is invalid (unknown key, bad value, wrong version)."""


class MeshError(ConfigError):
    """A mesh is unusable: NaN coordinates, degenerate triangle, inverted tetrahedron, bad indices."""


class SimulationDivergedError(ThinShellError):
    """A Newton solve did not converge (or produced NaN) at a given time step."""


class BagReadError(ThinShellError):
    """A recording cannot be read: missing/corrupt file, missing topic, wrong message type."""


class CalibrationError(ThinShellError):
    """System identification or diagnosis cannot proceed (e.g. no usable channel)."""
