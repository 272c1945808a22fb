"""How each copy of a lockstep step ended, decided over every copy at once (issue 52 item 3).

The lockstep's Newton loop (:class:`~sim_core.batch.lockstep.LockstepSolver`) reads its per-copy scalars as ``(B,)``
arrays (the scaled Newton update, the gradient's largest entry, the line search's acceptance); :class:`CopyOutcomes`
makes the stopping tests and the acceptance records on those arrays, with no loop over the copies in the Newton
iterations: the stopping tests by :func:`~sim_core.newton_stop.stop_reasons` (the separate run's
:func:`~sim_core.newton_stop.stop_reason` in the same comparisons), an acceptance as ``(B,)`` columns (the iteration,
the residual, the test's name). The copies' :class:`~sim_core.step_info.StepInfo` objects are made once, at the end of
the step (:meth:`CopyOutcomes.infos`), each acceptance recorded there by :func:`~sim_core.newton_stop.accept`, the
separate run's record: the same fields as the loop over the copies that made them at each iteration."""

from __future__ import annotations

import numpy as np

from sim_core.newton_stop import STOP_CODES, accept, stop_reasons
from sim_core.solver_config import SolverConfig
from sim_core.step_info import StepInfo

REASONS: tuple[str | None, ...] = STOP_CODES + ("simplified", "line_search_relaxed")
"""The acceptance codes of :attr:`CopyOutcomes.reason`: :data:`~sim_core.newton_stop.STOP_CODES`, then the simplified
Newton test's and the relaxed acceptance after a failed line search."""


class CopyOutcomes:
    """The per-copy outcome of one lockstep attempt, ``(B,)`` arrays.

    Args:
        cfg: the solver settings (the copies').
        running: the copies stepped in the attempt, shape ``(B,)`` bool (the others get no :class:`StepInfo`).

    Attributes:
        done: copies accepted so far, ``(B,)`` bool.
        iteration, residual, reason: the accepting iteration, its residual (m/s) and its code into :data:`REASONS`
            (0 while open).
        line_search_failures, released_sides, backtracks: per copy counts, ``(B,)`` int64.
        limited: per copy the names of its rate-limited effectors (only the copies that have one).
    """

    def __init__(self, cfg: SolverConfig, running: np.ndarray) -> None:
        B = len(running)
        self.cfg = cfg
        self.running = np.asarray(running, dtype=bool)
        self.done = np.zeros(B, dtype=bool)
        self.iteration = np.zeros(B, dtype=np.int64)
        self.residual = np.zeros(B)
        self.reason = np.zeros(B, dtype=np.int8)
        self.line_search_failures = np.zeros(B, dtype=np.int64)
        self.released_sides = np.zeros(B, dtype=np.int64)
        self.backtracks = np.zeros(B, dtype=np.int64)
        self.limited: dict[int, list[str]] = {}

    def accept(self, copies: np.ndarray, it: int, residual: np.ndarray, reason: str) -> None:
        """Accept the ``copies`` (``(B,)`` bool) at iteration ``it`` with their ``residual`` (``(B,)``, m/s) by the
        test named ``reason`` (one of :data:`REASONS`)."""
        self.iteration[copies] = it
        self.residual[copies] = residual[copies]
        self.reason[copies] = REASONS.index(reason)
        self.done |= copies

    def stop_tests(self, it: int, open_: np.ndarray, residual: np.ndarray, g_max: np.ndarray,
                   history: np.ndarray) -> None:
        """The stopping tests of the ``open_`` copies at iteration ``it`` (:func:`~sim_core.newton_stop.stop_reasons`
        of their ``residual`` (m/s), gradients' largest entries ``g_max`` (J/m) and residual ``history``
        ``(it, B)``); the passing copies accepted by their test."""
        codes = np.where(open_, stop_reasons(self.cfg, residual, g_max, history), 0)
        passed = codes > 0
        self.iteration[passed] = it
        self.residual[passed] = residual[passed]
        self.reason[passed] = codes[passed]
        self.done |= passed

    def infos(self, stacked: StepInfo) -> list[StepInfo | None]:
        """Each running copy's :class:`StepInfo` (None for the others): its acceptance recorded by
        :func:`~sim_core.newton_stop.accept`, its counts, and the stacked step's factorisations, projected
        iterations and assembly and solve times (``stacked``); ``energy`` NaN (one incremental potential of all
        copies: the stacked step's)."""
        out: list[StepInfo | None] = [None] * len(self.running)
        cfg = self.cfg
        columns = zip(np.flatnonzero(self.running).tolist(), self.iteration[self.running].tolist(),
                      self.residual[self.running].tolist(), self.reason[self.running].tolist(),
                      self.backtracks[self.running].tolist(), self.line_search_failures[self.running].tolist(),
                      self.released_sides[self.running].tolist())
        for i, it, residual, reason, backtracks, failures, released in columns:
            info = StepInfo(backtracks=backtracks, energy=float("nan"), factorizations=stacked.factorizations,
                            projected_iterations=stacked.projected_iterations,
                            time_assembly=stacked.time_assembly, time_linear_solve=stacked.time_linear_solve,
                            line_search_failures=failures, released_sides=released,
                            limited_effectors=list(self.limited.get(i, ())))
            name = REASONS[reason]
            if name is not None:
                info.simplified_stops = int(name == "simplified")
                accept(cfg, info, it, residual, name)
            out[i] = info
        return out
