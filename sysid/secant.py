"""Least squares by Gauss-Newton on secant columns with Broyden updates: a fit of a few parameters
that have no tangents (no adjoint or forward sensitivity), at one residual evaluation (a replay)
per iteration after the first columns.

The residual ``r(u)`` ``(m,)`` of ``p`` search coordinates ``u`` is modelled as linear,
``r(u_b + d) ~ r_b + J d``. The first columns of ``J`` are secants over one probe step per
coordinate, ``J[:, i] = (r(u_0 + h_i e_i) - r(u_0)) / h_i`` (``p`` evaluations; a large step that
doubles as a trial point, not a local derivative). Each further iteration takes the Gauss-Newton
step ``d = argmin |r_b + J d|`` from the best point ``u_b`` (within the bounds and a step cap),
evaluates ``r(u_b + d)`` and updates ``J`` by Broyden's rank-one secant update
``J += (r(u_b + d) - r_b - J d) d^T / (d^T d)`` (Broyden 1965, "A class of methods for solving
nonlinear simultaneous equations", Math. Comp. 19; Dennis & Schnabel 1983, "Numerical Methods for
Unconstrained Optimization and Nonlinear Equations", sec. 8.1 and 10.3), so that the model
reproduces every evaluated difference along its step. For a linear ``r`` the first columns are exact
and the first step lands on the least-squares solution. The best point evaluated is returned; the
number of evaluations is a count given in advance, so the result does not depend on the machine.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass
class SecantResult:
    """How :func:`secant_least_squares` ended.

    Attributes:
        u: ``(p,)`` best point evaluated.
        r: ``(m,)`` its residual.
        cost: ``0.5 r.r`` there.
        cost_initial: ``0.5 r.r`` at the start.
        evaluations: residual evaluations made (the start's not counted).
        status: ``"budget"`` (the evaluation count was spent), ``"converged"`` (the next step was
            shorter than ``xtol`` in every coordinate) or ``"no_columns"`` (a probe failed, so no
            step could be taken).
        jacobian: ``(m, p)`` the secant model at the end (None without columns).
        history: ``(u, cost)`` of every evaluation in order, the start first (a failed one: cost inf).
    """

    u: np.ndarray
    r: np.ndarray
    cost: float
    cost_initial: float
    evaluations: int
    status: str
    jacobian: np.ndarray | None = None
    history: list[tuple[np.ndarray, float]] = field(default_factory=list)


def _cost(r: np.ndarray | None) -> float:
    return float("inf") if r is None else 0.5 * float(r @ r)


def secant_least_squares(residual: Callable[[np.ndarray], np.ndarray | None], u0: np.ndarray, r0: np.ndarray,
                         first_steps: np.ndarray, lower: np.ndarray, upper: np.ndarray, max_evals: int,
                         max_step: np.ndarray | None = None, xtol: float = 1e-3) -> SecantResult:
    """Minimise ``0.5 |r(u)|^2`` within ``[lower, upper]`` by Gauss-Newton on Broyden-updated secant
    columns (see the module docstring).

    Args:
        residual: ``u (p,) -> r (m,)``, or None where the evaluation failed (a diverged replay; it
            counts, and the point is treated as worse than any other).
        u0: ``(p,)`` start, within the bounds; ``r0``: ``(m,)`` its residual (already evaluated).
        first_steps: ``(p,)`` probe step of each coordinate (nonzero; a probe that leaves the bounds
            is reflected to the other side of ``u0``).
        lower, upper: ``(p,)`` bounds of ``u``.
        max_evals: evaluations allowed (the probes included); fewer than ``p`` leaves the start.
        max_step: ``(p,)`` cap on a Gauss-Newton step's size per coordinate (None: the bounds only).
        xtol: stop when the next step is shorter than this in every coordinate.

    Returns:
        the :class:`SecantResult`.

    Raises:
        ValueError: mismatched shapes, a zero probe step, or a start outside the bounds.
    """
    u0 = np.asarray(u0, dtype=float)
    r0 = np.asarray(r0, dtype=float)
    h = np.asarray(first_steps, dtype=float)
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    p = u0.shape[0]
    if h.shape != (p,) or lower.shape != (p,) or upper.shape != (p,):
        raise ValueError(f"first_steps, lower and upper must have shape ({p},)")
    if np.any(h == 0.0):
        raise ValueError("every probe step must be nonzero")
    if np.any(u0 < lower) or np.any(u0 > upper):
        raise ValueError(f"start {u0} outside the bounds [{lower}, {upper}]")
    best_u, best_r, best_cost = u0.copy(), r0, _cost(r0)
    history: list[tuple[np.ndarray, float]] = [(u0.copy(), best_cost)]
    evals = 0
    if max_evals < p:
        return SecantResult(best_u, best_r, best_cost, best_cost, 0, "budget", None, history)
    J = np.zeros((r0.shape[0], p))
    for i in range(p):
        step = h[i] if lower[i] <= u0[i] + h[i] <= upper[i] else -h[i]
        u = u0.copy()
        u[i] += step
        r = residual(u)
        evals += 1
        history.append((u.copy(), _cost(r)))
        if r is None:
            return SecantResult(best_u, best_r, best_cost, history[0][1], evals, "no_columns", None, history)
        J[:, i] = (np.asarray(r, dtype=float) - r0) / step
        if _cost(r) < best_cost:
            best_u, best_r, best_cost = u, np.asarray(r, dtype=float), _cost(r)
    status = "budget"
    while evals < max_evals:
        d, *_ = np.linalg.lstsq(J, -best_r, rcond=None)
        if max_step is not None:
            d = np.clip(d, -np.asarray(max_step, dtype=float), np.asarray(max_step, dtype=float))
        d = np.clip(best_u + d, lower, upper) - best_u
        if np.all(np.abs(d) < xtol):
            status = "converged"
            break
        u = best_u + d
        r = residual(u)
        evals += 1
        history.append((u.copy(), _cost(r)))
        if r is None:  # no secant information: shorten the next step towards the best point
            max_step = 0.5 * np.abs(d)
            continue
        r = np.asarray(r, dtype=float)
        J += np.outer(r - best_r - J @ d, d) / float(d @ d)
        if _cost(r) < best_cost:
            best_u, best_r, best_cost = u, r, _cost(r)
    return SecantResult(best_u, best_r, best_cost, history[0][1], evals, status, J, history)
