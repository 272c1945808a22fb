"""The sim node's diagnostic statuses (``diagnostic_msgs/DiagnosticStatus``): how the start-up settling
and each solver step ended (:mod:`thinshell_ros.sim_node` publishes them on ``/diagnostics``)."""

from __future__ import annotations

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
