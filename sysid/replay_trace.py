"""What a replay of a recording gives: the simulated observations at every step (:class:`SimTrace`), and
the start of a replay that resumes another one (:class:`Resume`); :mod:`sysid.observation` makes both."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

PREDICTABLE_CHANNELS = ("markers_xyz", "markers_uv", "wrench", "sheet_points")
"""Evidence channels the simulator predicts."""


@dataclass(frozen=True)
class SimTrace:
    """Simulated observations at the simulation steps.

    Attributes:
        t_ns: step times ``(K + 1,)`` int64 ns (recording clock), ``t_ns[0]`` the initial state.
        markers_xyz: ``(K + 1, k, 3)`` m, sensor frame.
        markers_uv: ``(K + 1, k, 2)`` px.
        wrench: ``(K + 1, 6)`` N, N m, on the gel in the sensor frame.
        sheet_points: ``(K + 1, p, 3)`` m, world.
        wall_time_s: time spent simulating.
        positions: ``(K + 1, n, 3)`` m, every vertex of the simulation per step, when the replay
            was asked to keep them (``ObservationModel.simulate(keep_positions=True)``; the warm
            start of later replays, :attr:`ObservationModel.warm_start`), else None.
        states: the ``K + 1`` simulation states (``sim_core.state.State``) when the replay was
            asked to keep them (``ObservationModel.simulate(keep_states=True)``; the starts of
            :class:`Resume`), else None.
        step_totals: how the replay's steps ended (``sim_core.step_info.StepTotals``: substep
            retries, relaxed acceptances), or None when not recorded.
        drive: of a replay through a series drive, :meth:`sysid.replay_drive.ReplayDrive.summary`; else None.
    """

    t_ns: np.ndarray
    markers_xyz: np.ndarray
    markers_uv: np.ndarray
    wrench: np.ndarray
    sheet_points: np.ndarray
    wall_time_s: float
    positions: np.ndarray | None = None
    states: list | None = None
    step_totals: Any = None
    drive: dict | None = None

    def head(self, step: int) -> "SimTrace":
        """The observations of steps ``0..step`` (no positions, no states; same wall time)."""
        k = int(step) + 1
        return SimTrace(self.t_ns[:k].copy(), self.markers_xyz[:k].copy(), self.markers_uv[:k].copy(),
                        self.wrench[:k].copy(), self.sheet_points[:k].copy(), self.wall_time_s)

    def channel(self, name: str) -> np.ndarray:
        """The per-step array of evidence channel ``name`` (one of :data:`PREDICTABLE_CHANNELS`)."""
        if name not in PREDICTABLE_CHANNELS:
            raise KeyError(f"channel {name!r} is not simulated (simulated: {', '.join(PREDICTABLE_CHANNELS)})")
        return getattr(self, name)


@dataclass(frozen=True)
class Resume:
    """Start of a replay that is known to equal another one up to step ``step``.

    A replay whose parameters change the simulation only from some step on (a plastic yield
    angle above every dihedral angle reached before it: ``sysid.diagnose.resume``) runs the same
    steps as the replay it differs from until then; :meth:`ObservationModel.simulate` then takes
    that replay's observations of steps ``0..step`` and its state at ``step`` and simulates the
    steps after it only.

    Attributes:
        step: last step taken from the other replay (0 <= step <= K).
        state: its simulation state after that step (``sim_core.state.State``; copied on use).
        prefix: its observations of steps ``0..step`` at least (:meth:`SimTrace.head`).
    """

    step: int
    state: Any
    prefix: SimTrace
