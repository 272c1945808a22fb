"""The lockstep's per-copy stopping tests and acceptance over ``(B,)`` arrays (:mod:`sim_core.batch.copy_outcomes`):
the separate run's tests and records, copy by copy."""

import dataclasses

import numpy as np

from sim_core.batch.copy_outcomes import CopyOutcomes
from sim_core.newton_stop import STOP_CODES, accept, stop_reason, stop_reasons
from sim_core.solver_config import SolverConfig
from sim_core.step_info import StepInfo


def _cases(cfg: SolverConfig, B: int, it: int, seed: int):
    """Residuals, gradients' largest entries and histories around every threshold of the tests, with NaN and
    infinities: ``(residual (B,), g_max (B,), history (it, B))``."""
    rng = np.random.default_rng(seed)
    tol_v, tol_f = cfg.tol_velocity, cfg.tol_force
    levels_v = np.array([0.0, 0.5, 0.999999, 1.0, 1.000001, 0.5 * cfg.stall_tolerance_factor,
                         cfg.stall_tolerance_factor, 2 * cfg.stall_tolerance_factor]) * tol_v
    levels_v = np.r_[levels_v, np.nan, np.inf]
    levels_f = np.r_[np.array([0.0, 0.5, 1.0, 1.5]) * tol_f, np.nan, np.inf]
    residual = rng.choice(levels_v, B)
    g_max = rng.choice(levels_f, B)
    history = rng.uniform(0.5, 1.5, (it, B)) * residual
    near = rng.random(B) < 0.3  # a residual 10 % below the one stall_iterations before: the boundary itself
    if it > cfg.stall_iterations:
        history[-1 - cfg.stall_iterations, near] = residual[near] / 0.9
    history[-1] = residual
    return residual, g_max, history


def test_stop_reasons_are_the_separate_runs_stop_reason_copy_by_copy():
    cfg = SolverConfig()
    seen = set()
    for it in range(1, cfg.stall_iterations + 4):
        residual, g_max, history = _cases(cfg, 400, it, seed=it)
        codes = stop_reasons(cfg, residual, g_max, history)
        for i in range(len(residual)):
            expected = stop_reason(cfg, residual[i], g_max[i:i + 1], history[:, i])
            assert STOP_CODES[codes[i]] == expected, (it, i, residual[i], g_max[i], history[:, i])
            seen.add(expected)
    assert seen == set(STOP_CODES)  # every outcome met, NaN copies not accepted


def test_copy_outcomes_record_what_accept_records_copy_by_copy():
    cfg = SolverConfig()
    B = 64
    running = np.ones(B, dtype=bool)
    running[[3, 17]] = False  # held copies: no StepInfo
    outcomes = CopyOutcomes(cfg, running)
    outcomes.limited[5] = ["pad"]
    reference = [StepInfo() if r else None for r in running]
    reference[5].limited_effectors.append("pad")
    rng = np.random.default_rng(7)
    history = np.zeros((cfg.max_iterations, B))
    for it in range(1, 8):
        open_ = running & ~outcomes.done
        residual, g_max, _ = _cases(cfg, B, 1, seed=100 + it)
        residual = np.where(np.isnan(residual), 10 * cfg.tol_velocity, residual)
        history[it - 1] = residual
        if it == 2:  # the simplified Newton test of some copies
            test = open_ & (rng.random(B) < 0.2)
            outcomes.accept(test, it, residual, "simplified")
            for i in np.flatnonzero(test):
                reference[i].simplified_stops = 1
                accept(cfg, reference[i], it, residual[i], "simplified")
            open_ = running & ~outcomes.done
        outcomes.stop_tests(it, open_, residual, g_max, history[:it])
        for i in np.flatnonzero(open_):
            reason = stop_reason(cfg, residual[i], g_max[i:i + 1], history[:it, i])
            if reason is not None:
                accept(cfg, reference[i], it, residual[i], reason)
        open_ = running & ~outcomes.done
        backtracks = rng.integers(0, 4, B)
        outcomes.backtracks[open_] += backtracks[open_]
        failed = open_ & (rng.random(B) < 0.15)
        outcomes.line_search_failures[failed] += 1
        relaxed = failed & (residual < cfg.line_search_tolerance_factor * cfg.tol_velocity)
        outcomes.accept(relaxed, it, residual, "line_search_relaxed")
        outcomes.released_sides[failed & ~relaxed] += 2
        for i in np.flatnonzero(open_):
            reference[i].backtracks += int(backtracks[i])
            reference[i].line_search_failures += int(failed[i])
            reference[i].released_sides += 2 * int(failed[i] and not relaxed[i])
            if relaxed[i]:
                accept(cfg, reference[i], it, residual[i], "line_search_relaxed")
    stacked = StepInfo(factorizations=6, projected_iterations=1, time_assembly=0.25, time_linear_solve=0.5)
    infos = outcomes.infos(stacked)
    reasons = set()
    for got, want in zip(infos, reference):
        if want is None:
            assert got is None
            continue
        want.energy = float("nan")
        for name in ("factorizations", "projected_iterations", "time_assembly", "time_linear_solve"):
            setattr(want, name, getattr(stacked, name))
        got_fields, want_fields = dataclasses.asdict(got), dataclasses.asdict(want)
        assert np.isnan(got_fields.pop("energy")) and np.isnan(want_fields.pop("energy"))
        assert got_fields == want_fields
        reasons.add(got.stop_reason)
    assert {"velocity", "force", "simplified", "line_search_relaxed"} <= reasons
