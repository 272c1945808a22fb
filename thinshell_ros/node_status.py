"""The nodes' diagnostic statuses (``diagnostic_msgs/DiagnosticStatus``, published on ``/diagnostics``):
the sim node's (how the start-up settling and each solver step ended, and its 1 Hz runtime status:
real-time factor, step p95, rejected commands, :class:`RuntimeStats`) and the sysid node's 1 Hz
progress (:func:`sysid_status`)."""

from __future__ import annotations

import math
from typing import Callable, Mapping

import numpy as np

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from sim_core.settle import SettleInfo
from sim_core.solver import StepInfo


def settle_status(name: str, info: SettleInfo) -> DiagnosticStatus:
    """The diagnostic status of a start-up settling (:func:`sim_core.settle.settle`): ``OK`` when the
    scene settled, else ``WARN``; the message is :meth:`SettleInfo.describe`, the values ``settled``,
    ``steps``, ``max_steps``, ``residual_velocity`` (m/s), ``displacement`` (m), ``sleeping`` and
    ``awake`` (names comma-separated) and ``reason``."""
    status = DiagnosticStatus(name=name, hardware_id="thinshell", message=info.describe(),
                              level=DiagnosticStatus.OK if info.settled else DiagnosticStatus.WARN)
    values = {"settled": str(info.settled).lower(), "steps": str(info.steps), "max_steps": str(info.max_steps),
              "residual_velocity": f"{info.residual_velocity:.6g}", "displacement": f"{info.displacement:.6g}",
              "sleeping": ",".join(info.sleeping), "awake": ",".join(info.awake), "reason": info.reason}
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    return status


def solver_status(name: str, t: float, info: StepInfo | None = None, error: str | None = None) -> DiagnosticStatus:
    """The solver's diagnostic status for the step that started at sim time ``t`` (s).

    Args:
        name: status name.
        t: sim time at the start of the step, s.
        info: how the step ended (None for a failed step).
        error: the failure's message (``ERROR`` status), or None.

    Returns:
        ``ERROR`` with ``error``; ``WARN`` when ``info.needs_attention`` (accepted above the strict
        tolerance or retried in substeps); else ``OK``. Values: ``t``, and from ``info`` the stopping
        test, residual, accepted tolerance, iterations, substeps, retries, relaxed acceptances,
        stalled acceptances, line-search failures, whether the step repeated a fixed point, and the
        sleeping bodies (``sleeping``: held during the step; ``fell_asleep``: after it; ``woken``: at it;
        ``wake_redos``: solves redone after a sleeping body was reached; names comma-separated).
    """
    status = DiagnosticStatus(name=name, hardware_id="thinshell")
    values = {"t": f"{t:.6f}"}
    if error is not None:
        status.level, status.message = DiagnosticStatus.ERROR, f"step failed: {error}"
    else:
        if not info.converged_strict:
            status.level = DiagnosticStatus.WARN
            status.message = (f"step accepted at a relaxed tolerance ({info.stop_reason}, "
                              f"{info.accepted_tolerance:g} m/s)")
        elif info.retries:
            status.level = DiagnosticStatus.WARN
            status.message = f"step converged after {info.retries} substep retries ({info.substeps} substeps)"
        else:
            status.level, status.message = DiagnosticStatus.OK, "converged"
            changes = [f"{what}: {', '.join(names)}" for what, names in
                       (("fell asleep", info.fell_asleep), ("woken", info.woken)) if names]
            if changes:
                status.message += " (" + "; ".join(changes) + ")"
        values.update({
            "stop_reason": info.stop_reason, "residual_velocity": f"{info.residual_velocity:.6g}",
            "accepted_tolerance": f"{info.accepted_tolerance:.6g}", "iterations": str(info.iterations),
            "substeps": str(info.substeps), "retries": str(info.retries),
            "relaxed_accepts": str(info.relaxed_accepts), "stalled_accepts": str(info.stalled_accepts),
            "line_search_failures": str(info.line_search_failures), "repeated": str(info.repeated).lower(),
            "sleeping": ",".join(info.sleeping), "fell_asleep": ",".join(info.fell_asleep),
            "woken": ",".join(info.woken), "wake_redos": str(info.wake_redos),
        })
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    return status


class RuntimeStats:
    """What the sim node did over one status period, for its 1 Hz ``<node name>: status``.

    Args:
        wall_clock: the clock, s (``time.monotonic`` in the node).
        sim_time: sim time at the start of the first period, s.
    """

    def __init__(self, wall_clock: Callable[[], float], sim_time: float) -> None:
        self._clock = wall_clock
        self._rejected0: dict[str, int] = {}
        self.restart(sim_time, {})

    def restart(self, sim_time: float, rejected_by_kind: Mapping[str, int]) -> None:
        """Start a new period at ``sim_time`` (s) with the rejection counts so far."""
        self._wall0, self._sim0 = self._clock(), float(sim_time)
        self._step_seconds: list[float] = []
        self._rejected0 = dict(rejected_by_kind)

    def stepped(self, seconds: float) -> None:
        """Count a step that took ``seconds`` of wall time (the solver's step alone)."""
        self._step_seconds.append(seconds)

    def status(self, name: str, sim_time: float, rejected_by_kind: Mapping[str, int], counters: Mapping[str, int],
               mode: str, paused: bool) -> DiagnosticStatus:
        """The status of the period that ends now (and a new period starts).

        Args:
            name: status name.
            sim_time: sim time now, s.
            rejected_by_kind: rejected commands so far per kind (``<effector>/pose_cmd non_finite``, ...).
            counters: totals so far published as they are (``rejected_commands``, ``failed_steps``, ...).
            mode, paused: the node's mode and whether it is paused.

        Returns:
            ``WARN`` when commands were rejected in the period (the message says how many), else ``OK``.
            Values: ``real_time_factor`` (sim time advanced / wall time of the period), ``steps``,
            ``step_p95_ms`` and ``step_max_ms`` (wall ms of the solver's steps in the period),
            ``rejected_in_period``, ``rejected <kind>`` (in the period), the ``counters``, ``mode``,
            ``paused``, ``period_s``.
        """
        wall = self._clock() - self._wall0
        steps = np.asarray(self._step_seconds, dtype=float)
        rtf = (float(sim_time) - self._sim0) / wall if wall > 0 else math.nan
        p95 = float(np.percentile(steps, 95)) * 1e3 if steps.size else math.nan
        worst = float(steps.max()) * 1e3 if steps.size else math.nan
        period = {k: n - self._rejected0.get(k, 0) for k, n in rejected_by_kind.items()
                  if n > self._rejected0.get(k, 0)}
        rejected = sum(period.values())
        status = DiagnosticStatus(name=name, hardware_id="thinshell")
        summary = f"real-time factor {rtf:.3g}, {steps.size} steps, step p95 {p95:.3g} ms"
        if rejected:
            status.level = DiagnosticStatus.WARN
            status.message = f"{rejected} commands rejected in the last {wall:.2g} s; {summary}"
        else:
            status.level, status.message = DiagnosticStatus.OK, ("paused; " if paused else "") + summary
        values = {"real_time_factor": f"{rtf:.6g}", "steps": str(steps.size), "step_p95_ms": f"{p95:.6g}",
                  "step_max_ms": f"{worst:.6g}", "rejected_in_period": str(rejected),
                  **{f"rejected {k}": str(n) for k, n in sorted(period.items())},
                  **{k: str(v) for k, v in counters.items()},
                  "mode": mode, "paused": str(bool(paused)).lower(), "period_s": f"{wall:.6g}", "t": f"{sim_time:.6f}"}
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        self.restart(sim_time, rejected_by_kind)
        return status


def sysid_status(name: str, state: str, elapsed: float, budget: float, fits_done: int, fits_failed: int,
                 last: str, bag: str) -> DiagnosticStatus:
    """The sysid node's 1 Hz progress status.

    Args:
        name: status name.
        state: ``idle`` | ``fitting`` | ``applying``.
        elapsed: wall s since the running fit started (0 when idle).
        budget: the fit's wall-time budget, s (``max_time``; 0: none).
        fits_done, fits_failed: fits finished so far, and of them those that failed.
        last: the last fit's outcome (``ok``, ``error: ...``; empty before the first).
        bag: the recording being fitted (or last fitted).

    Returns:
        ``ERROR`` when the last fit failed and none runs, else ``OK``; values ``state``,
        ``elapsed_s``, ``budget_s``, ``budget_fraction`` (``elapsed / budget``, empty without a
        budget), ``fits_done``, ``fits_failed``, ``last``, ``bag``.
    """
    status = DiagnosticStatus(name=name, hardware_id="thinshell")
    failed = state == "idle" and last.startswith("error")
    status.level = DiagnosticStatus.ERROR if failed else DiagnosticStatus.OK
    if state == "idle":
        status.message = f"idle; last fit: {last}" if last else "idle; no fit yet"
    else:
        status.message = f"{state} {bag} for {elapsed:.0f} s" + (f" of a {budget:g} s budget" if budget > 0 else "")
    values = {"state": state, "elapsed_s": f"{elapsed:.3f}", "budget_s": f"{budget:g}",
              "budget_fraction": f"{elapsed / budget:.4f}" if budget > 0 else "", "fits_done": str(fits_done),
              "fits_failed": str(fits_failed), "last": last, "bag": bag}
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    return status
