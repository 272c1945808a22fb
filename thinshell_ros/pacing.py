"""When the sim node's ``realtime`` mode takes its steps: step ``k`` after an anchor is due at wall
time ``anchor + k dt`` (:class:`RealtimePacer`).

A ROS timer of period ``dt`` alone does not keep simulated time with wall time: rcl moves a timer's
next call past the periods it missed (``rcl_timer_call``), so every step that ends after the next tick
(a slow Newton step, the process descheduled on a loaded machine) loses the time to that tick for
good. The pacer counts steps against the wall clock instead: the node's timer callback takes the
steps that are due back to back (after a step slower than ``dt`` the rest wait for the next tick), so
a scene whose steps take less than ``dt`` on average runs at a real-time factor of 1 however they
are spread; and a command that arrives
between ticks may start its step at once when that step would be due within one ``dt``
(:meth:`RealtimePacer.may_start`), or else as soon as it would be (:meth:`RealtimePacer.start_time`):
simulated time then runs at most one step ahead of wall time, and the command does not wait for the
next tick. A lag beyond ``max_lag`` (the solver slower than
real time for a while) is dropped, not caught up: the node then runs slower than real time, as the
mode's documentation says, instead of racing to make up seconds.

Fixed-step pacing of this kind is the "accumulator" loop of real-time simulation (Fiedler, "Fix Your
Timestep!", 2004), with a bounded accumulator.
"""

from __future__ import annotations

import math


class RealtimePacer:
    """The wall-clock schedule of a fixed-step simulation run in real time.

    Args:
        dt: the step, s (> 0).
        max_lag: s of lag behind the schedule beyond which the schedule restarts at the current
            time (the lag is dropped), >= 0.

    Raises:
        ValueError: ``dt`` not > 0 or ``max_lag`` not >= 0 (or not finite).

    Attributes:
        dt, max_lag: as given.
        dropped: s of lag dropped since construction (the time the simulation fell behind for good).
    """

    def __init__(self, dt: float, max_lag: float) -> None:
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"RealtimePacer: dt must be a finite number > 0 s, got {dt!r}")
        if not (math.isfinite(max_lag) and max_lag >= 0):
            raise ValueError(f"RealtimePacer: max_lag must be a finite number >= 0 s, got {max_lag!r}")
        self.dt = float(dt)
        self.max_lag = float(max_lag)
        self.dropped = 0.0
        self._anchor: float | None = None  # wall time of step 0 of the schedule
        self._steps = 0  # steps taken since the anchor

    def restart(self) -> None:
        """Forget the schedule (after a pause or a reset): the next query starts a new one at its time."""
        self._anchor = None

    def _next_due(self, now: float) -> float:
        """Wall time (s) at which the next step is due, the schedule started or its lag dropped at ``now``."""
        if self._anchor is None:
            self._anchor, self._steps = now, 0
        due = self._anchor + self._steps * self.dt
        if now - due > self.max_lag:
            self.dropped += now - due
            self._anchor, self._steps = now, 0
            due = now
        return due

    def due(self, now: float) -> bool:
        """Whether the next step is due at wall time ``now`` (s, a monotonic clock)."""
        return now >= self._next_due(now)

    def start_time(self, now: float) -> float:
        """Wall time (s) from which the next step may start for a new command (:meth:`may_start`): one
        ``dt`` before it is due (the schedule as it stands at ``now``)."""
        return self._next_due(now) - self.dt

    def may_start(self, now: float) -> bool:
        """Whether the next step may start at ``now`` (s) for a new command: due, or due within one
        ``dt`` (simulated time then stays at most one step ahead of wall time)."""
        return now >= self.start_time(now)

    def stepped(self) -> None:
        """Count a step taken (the next one is due ``dt`` after this one's due time)."""
        if self._anchor is not None:
            self._steps += 1
