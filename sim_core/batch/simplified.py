"""The simplified Newton test per copy of a lockstep step (``SolverConfig.simplified_newton_check``).

A separate run (:meth:`sim_core.solver.NewtonSolver._newton_iterations`) may stop at an iterate ``x_k`` without
assembling and factorising its Newton matrix: when the iteration before factorised the exact Hessian, took its full
step, and the same contacts touch at ``x_{k-1}`` and ``x_k``, it solves ``H(x_{k-1}) dbar = g(x_k)`` with the kept
factorisation and stops when ``max_v |dbar_v| / dt`` is below ``simplified_newton_check * tol_velocity`` (Deuflhard,
Newton Methods for Nonlinear Problems, 2004, Sec. 2.1). The lockstep solver runs the same test for each copy
(:class:`SimplifiedNewtonTest`): a copy is a candidate when its last iteration took its full step along the stacked
exact factorisation (one factorisation for all copies) and its own touching contacts are those of its last iterate
(:func:`same_active_by_copy`, the entries of each copy compared as sets). The candidates' simplified corrections are
one solve with the kept factorisation; a step whose open copies all pass assembles and factorises no matrix in its
last iteration.
"""

from __future__ import annotations

import numpy as np

from sim_core.contact_set import active_contacts


def active_by_copy(terms: list, x: np.ndarray, copy_of_vertex: np.ndarray) -> list[tuple] | None:
    """The touching contacts of the penalty ``terms`` at the stacked positions ``x`` ``(N, 3)`` m
    (:func:`~sim_core.contact_set.active_contacts`), per term ``(copies, rows)``: the copy of each active entry
    ``(a,)`` and its vertex rows ``(a, r)`` (``r`` = 4 for a pair, 1 for a plane or sphere entry), sorted by copy,
    then by rows. None when a term is not a penalty contact (the test does not apply).

    ``copy_of_vertex``: the copy of each stacked vertex, shape ``(N,)`` int.
    """
    active = active_contacts(terms, x)
    if active is None:
        return None
    out = []
    for rows in active:
        rows = rows[:, None] if rows.ndim == 1 else rows
        copies = copy_of_vertex[rows[:, 0]] if len(rows) else np.zeros(0, dtype=np.int64)
        order = np.lexsort(tuple(rows.T[::-1]) + (copies,))  # the last key is the primary one
        out.append((copies[order], rows[order]))
    return out


def same_active_by_copy(a: list[tuple] | None, b: list[tuple] | None, copies: int) -> np.ndarray:
    """Per copy whether two :func:`active_by_copy` results name the same touching contacts, shape ``(copies,)``
    bool (all False when either is None or their terms differ)."""
    same = np.zeros(copies, dtype=bool)
    if a is None or b is None or len(a) != len(b):
        return same
    same[:] = True
    for (ca, ra), (cb, rb) in zip(a, b):
        if ra.shape[1] != rb.shape[1]:
            return np.zeros(copies, dtype=bool)
        equal_count = np.bincount(ca, minlength=copies) == np.bincount(cb, minlength=copies)
        same &= equal_count
        # the copies with as many entries in both: their sorted rows line up entry by entry
        ka, kb = equal_count[ca], equal_count[cb]
        differs = np.any(ra[ka] != rb[kb], axis=1)
        same[ca[ka][differs]] = False
    return same


class SimplifiedNewtonTest:
    """The per-copy state of the simplified Newton test within one lockstep step (module docstring).

    Args:
        copy_of_vertex: the copy of each stacked vertex, shape ``(N,)`` int.
        copies: ``B``.
        enabled: whether the step may use the test (``StepTerms.simplified`` with a direct linear solver, whose
            kept factorisation makes the simplified correction a back-substitution).

    Attributes:
        ready: copies whose last iteration took its full step along the stacked exact factorisation, ``(B,)`` bool.
    """

    def __init__(self, copy_of_vertex: np.ndarray, copies: int, enabled: bool) -> None:
        self.copy_of_vertex = copy_of_vertex
        self.enabled = enabled
        self.ready = np.zeros(copies, dtype=bool)
        self._active_before: list[tuple] | None = None

    def candidates(self, open_: np.ndarray, terms: list, x: np.ndarray) -> np.ndarray:
        """The copies of ``open_`` ``(B,)`` to test at the iterate ``x`` ``(N, 3)`` with the contact ``terms`` there:
        ready, with the touching contacts of their last iterate."""
        ready = self.ready & open_
        if not self.enabled or not ready.any():
            return np.zeros_like(ready)
        now = active_by_copy(terms, x, self.copy_of_vertex)
        return ready & same_active_by_copy(self._active_before, now, len(ready))

    def after_direction(self, exact_stacked: bool, terms: list, x: np.ndarray) -> None:
        """Keep the touching contacts at the iterate ``x`` whose update came from the stacked exact factorisation
        (``exact_stacked``), else forget them; no copy is ready until :meth:`after_line_search`."""
        self.ready[:] = False
        self._active_before = (active_by_copy(terms, x, self.copy_of_vertex) if self.enabled and exact_stacked
                               else None)

    def after_line_search(self, full_step: np.ndarray) -> None:
        """The copies that took their full step (``(B,)`` bool) along the kept factorisation are ready."""
        self.ready = full_step & (self._active_before is not None)
