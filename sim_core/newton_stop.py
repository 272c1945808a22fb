"""The stopping tests of a Newton step (:class:`sim_core.solver.NewtonSolver`): when an iterate is
accepted, at which tolerance, and how that is recorded in :class:`~sim_core.step_info.StepInfo`
(``SolverConfig`` names the tolerances; gradients and Newton updates have shape ``(3 n,)``)."""

from __future__ import annotations

import numpy as np

from sim_core.solver_config import SolverConfig
from sim_core.step_info import STRICT_STOPS, StepInfo


def stop_reason(cfg: SolverConfig, residual: float, g: np.ndarray, history: list[float]) -> str | None:
    """The convergence test of an iterate with Newton update of scaled size ``residual`` (m/s) and
    free-DoF gradient ``g`` (J/m): ``"velocity"`` (``residual < tol_velocity``), ``"force"``
    (``max |g| < tol_force``), ``"stalled"`` (relaxed: ``residual`` below ``stall_tolerance_factor
    * tol_velocity`` and not 10 % below the residual ``stall_iterations`` iterations earlier), or
    None (not converged)."""
    if residual < cfg.tol_velocity:
        return "velocity"
    if float(np.max(np.abs(g))) < cfg.tol_force:
        return "force"
    if (len(history) > cfg.stall_iterations and residual < cfg.stall_tolerance_factor * cfg.tol_velocity
            and residual > 0.9 * history[-1 - cfg.stall_iterations]):
        return "stalled"
    return None


STOP_CODES: tuple[str | None, ...] = (None, "velocity", "force", "stalled")
"""The codes of :func:`stop_reasons`: index ``k`` is :func:`stop_reason`'s answer ``STOP_CODES[k]``."""


def stop_reasons(cfg: SolverConfig, residual: np.ndarray, g_max: np.ndarray, history: np.ndarray) -> np.ndarray:
    """:func:`stop_reason` of ``B`` iterates at once, in the same float64 comparisons: copy ``i``'s Newton update of
    scaled size ``residual[i]`` (m/s), its gradient's largest entry ``g_max[i]`` (J/m, ``max |g_i|``) and its
    residuals so far ``history[:, i]`` (``(it, B)``, the last row this iterate's; only the row ``stall_iterations``
    before the last is read). NaN compares false, as there: a copy with a NaN residual or gradient is not accepted.

    Returns:
        ``(B,)`` int8 codes into :data:`STOP_CODES` (0: not converged).
    """
    residual, g_max = np.asarray(residual, dtype=float), np.abs(np.asarray(g_max, dtype=float))
    velocity = residual < cfg.tol_velocity
    force = ~velocity & (g_max < cfg.tol_force)
    codes = np.where(velocity, 1, np.where(force, 2, 0)).astype(np.int8)
    s = cfg.stall_iterations
    if len(history) > s:
        stalled = (codes == 0) & (residual < cfg.stall_tolerance_factor * cfg.tol_velocity) & (
            residual > 0.9 * history[-1 - s])
        codes[stalled] = 3
    return codes


def line_search_failure_acceptance(cfg: SolverConfig, slope: float, e0: float, residual: float) -> str | None:
    """Whether an iterate whose line search failed is accepted (relaxed): ``"line_search_roundoff"``
    when the predicted decrease ``|g.d|`` is below ``stationary_slope_rtol * |E|`` (x is stationary
    to working precision), ``"line_search_relaxed"`` when ``residual`` (m/s) is below
    ``line_search_tolerance_factor * tol_velocity``; else None."""
    if abs(slope) <= cfg.stationary_slope_rtol * max(abs(e0), 1e-30):
        return "line_search_roundoff"
    if residual < cfg.line_search_tolerance_factor * cfg.tol_velocity:
        return "line_search_relaxed"
    return None


def accept(cfg: SolverConfig, info: StepInfo, it: int, residual: float, reason: str) -> None:
    """Record in ``info`` that iteration ``it`` ended the step with ``residual`` (m/s) by the stopping
    test ``reason`` (:data:`STRICT_STOPS` or a relaxed one, which is counted)."""
    info.iterations = it
    info.residual_velocity = residual
    info.stop_reason = reason
    info.converged_strict = reason in STRICT_STOPS
    if reason in STRICT_STOPS:
        info.accepted_tolerance = cfg.tol_velocity
        return
    info.relaxed_accepts += 1
    if reason == "stalled":
        info.stalled_accepts += 1
        info.accepted_tolerance = cfg.stall_tolerance_factor * cfg.tol_velocity
    elif reason == "line_search_relaxed":
        info.accepted_tolerance = cfg.line_search_tolerance_factor * cfg.tol_velocity
    else:  # the round-off test bounds the predicted energy decrease, not the residual
        info.accepted_tolerance = np.inf


def largest_move(d: np.ndarray) -> float:
    """The largest vertex displacement ``max_i |d_i|`` (m) of a Newton update ``d`` ``(3 n,)``; 0 when
    there are no DoFs."""
    d3 = d.reshape(-1, 3)
    return float(np.max(np.linalg.norm(d3, axis=1))) if d3.size else 0.0


def rate_stops(history: list[float], tol_velocity: float) -> bool:
    """Whether a full Newton update with scaled size ``history[-1]`` (m/s) after one of size
    ``history[-2]`` ends the step under ``SolverConfig.rate_stopping``: its estimated remaining
    error ``theta / (1 - theta) * history[-1]``, ``theta = history[-1] / history[-2] < 1``, is below
    ``tol_velocity``."""
    theta = history[-1] / history[-2]
    return theta < 1.0 and theta / (1.0 - theta) * history[-1] < tol_velocity
