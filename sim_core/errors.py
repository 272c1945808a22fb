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


class InsufficientMemoryError(ConfigError):
    """Not even one copy of a batch fits in the memory free on the device (or the host)."""


class MeshError(ConfigError):
    """A mesh is unusable: NaN coordinates, degenerate triangle, inverted tetrahedron, bad indices."""


class SimulationDivergedError(ThinShellError):
    """A Newton solve did not converge (or produced NaN) at a given time step.

    Args:
        message: what failed, naming the step and time.
        step_index: index of the step that failed (``State.step_index`` at its start), None when
            the error is not tied to a step (a linear solver's own failure before its caller adds it).
        t: simulated time at the start of that step, s, or None.
    """

    def __init__(self, message: str, step_index: int | None = None, t: float | None = None) -> None:
        super().__init__(message)
        self.step_index = step_index
        self.t = t

    def __reduce__(self):
        """Pickle with the step and time (replay workers send their errors to the parent process)."""
        return type(self), (str(self), self.step_index, self.t)


class BagReadError(ThinShellError):
    """A recording cannot be read: missing/corrupt file, missing topic, wrong message type."""


class CalibrationError(ThinShellError):
    """System identification or diagnosis cannot proceed (e.g. no usable channel)."""
