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

The test keeps each iterate's touching contacts as :func:`active_sets`: a pair potential's active pairs as indices
into its candidate pairs (the kept evaluation's, ascending), so that two iterates whose potentials are the same objects
(the same candidate list, pairs and sides) compare by those indices (:func:`same_active_sets`: equal arrays, else
each side's entries missing from the other by a binary search, their copies marked), with no sort of the active rows:
at B = 1024 Forming copies, ~55,000 active pairs, a sort by copy and rows was ~60 ms an iterate on the VM against
~0.02 ms for equal index arrays and ~1 ms for a search. Potentials of a new candidate list fall back to the rows
(:func:`active_by_copy`'s comparison).
"""

from __future__ import annotations

import numpy as np

from sim_core.contact_set import active_contacts
from sim_core.energies.contact.reference import EdgeEdgeContact, VertexTriangleContact

PAIR_POTENTIALS = (VertexTriangleContact, EdgeEdgeContact)
"""The pair potentials whose touching pairs :func:`active_sets` keeps as indices into their pairs."""


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
    return [_by_copy(rows, copy_of_vertex) for rows in active]


def same_active_by_copy(a: list[tuple] | None, b: list[tuple] | None, copies: int) -> np.ndarray:
    """Per copy whether two :func:`active_by_copy` results name the same touching contacts, shape ``(copies,)``
    bool (all False when either is None or their terms differ)."""
    same = np.zeros(copies, dtype=bool)
    if a is None or b is None or len(a) != len(b):
        return same
    same[:] = True
    for (ca, ra), (cb, rb) in zip(a, b):
        if not _same_rows(ca, ra, cb, rb, same):
            return np.zeros(copies, dtype=bool)
    return same


def _same_rows(ca: np.ndarray, ra: np.ndarray, cb: np.ndarray, rb: np.ndarray, same: np.ndarray) -> bool:
    """Clear in ``same`` ``(B,)`` the copies whose entries of one term differ between two :func:`active_by_copy`
    results ``(ca, ra)`` and ``(cb, rb)`` of it (sorted by copy, then rows); False when their rows are not alike
    (another kind of term)."""
    if ra.shape[1] != rb.shape[1]:
        return False
    equal_count = np.bincount(ca, minlength=len(same)) == np.bincount(cb, minlength=len(same))
    same &= equal_count
    # the copies with as many entries in both: their sorted rows line up entry by entry
    ka, kb = equal_count[ca], equal_count[cb]
    differs = np.any(ra[ka] != rb[kb], axis=1)
    same[ca[ka][differs]] = False
    return True


def active_sets(terms: list, x: np.ndarray) -> list[tuple] | None:
    """The touching contacts of the penalty ``terms`` at ``x`` ``(N, 3)`` m, per term ``(term, entries)``: a pair
    potential's (:class:`~sim_core.energies.contact.reference.VertexTriangleContact`,
    :class:`~sim_core.energies.contact.reference.EdgeEdgeContact`) the indices of its active pairs into its pairs,
    int64 ``(a,)`` ascending (its kept evaluation of ``x``, ``active_distances``); another's the vertex rows of its
    active entries (:func:`~sim_core.contact_set.active_contacts`). None when a term is not a penalty contact."""
    active = active_contacts([p for p in terms if not isinstance(p, PAIR_POTENTIALS)], x)
    if active is None:
        return None
    rows = iter(active)
    out = []
    for p in terms:
        if isinstance(p, PAIR_POTENTIALS):
            pairs = np.asarray(p.active_distances(x)[0], dtype=np.int64)
            if pairs.size > 1 and not np.all(pairs[1:] > pairs[:-1]):
                pairs = np.sort(pairs)
            out.append((p, pairs))
        else:
            out.append((p, next(rows)))
    return out


def same_active_sets(a: list[tuple] | None, b: list[tuple] | None, copy_of_vertex: np.ndarray,
                     copies: int, every: np.ndarray | None = None) -> np.ndarray:
    """Per copy whether two :func:`active_sets` results name the same touching contacts, shape ``(copies,)`` bool
    (all False when either is None or their terms differ in number or kind): the pairs of a potential that both
    results hold by the same object by their indices (the entries of each missing from the other, their copies the
    copies of their first vertices), else by their vertex rows as :func:`same_active_by_copy` compares them.

    ``copy_of_vertex``: the copy of each stacked vertex, shape ``(N,)`` int.

    ``every`` (bool ``(copies,)``, optional): the caller needs only whether every copy of ``every`` is the same (the
    device solvers' test, made only where every open copy may pass): all False is returned as soon as one copy of
    ``every`` is known to differ, the rest uncompared. Of a potential held by the same object whose index lists
    differ, one entry of their symmetric difference comes first from their first mismatch (:func:`_first_difference`:
    one comparison of the two ascending lists, no search); where that entry's copy is in ``every`` nothing more is
    compared. Where every copy of ``every`` is the same the result is the one without ``every``."""
    same = np.zeros(copies, dtype=bool)
    if a is None or b is None or len(a) != len(b):
        return same
    same[:] = True
    for (ta, ea), (tb, eb) in zip(a, b):
        if ta is tb and isinstance(ta, PAIR_POTENTIALS):
            if ea.shape == eb.shape and np.array_equal(ea, eb):
                continue
            if every is not None and every[copy_of_vertex[np.take(ta.vertices, [_first_difference(ea, eb)],
                                                                  axis=0)[0, 0]]]:
                return np.zeros(copies, dtype=bool)
            differing = np.concatenate([_missing(ea, eb), _missing(eb, ea)])
            same[copy_of_vertex[np.take(ta.vertices, differing, axis=0)[:, 0]]] = False
        elif not _same_rows(*_by_copy(_rows_of(ta, ea), copy_of_vertex),
                            *_by_copy(_rows_of(tb, eb), copy_of_vertex), same):
            return np.zeros(copies, dtype=bool)
        if every is not None and not same[every].all():
            return np.zeros(copies, dtype=bool)
    return same


def _first_difference(u: np.ndarray, v: np.ndarray) -> int:
    """One entry of the symmetric difference of ``u`` and ``v`` (int ``(k,)`` ascending, distinct entries, not equal):
    at their first position ``i`` where they differ, the smaller of ``u[i]`` and ``v[i]`` (every earlier entry being
    common, it is below all of the other list's later ones), or, where one list is the other's beginning, the longer
    one's next entry."""
    n = min(u.size, v.size)
    at = np.flatnonzero(u[:n] != v[:n])
    if at.size:
        return int(min(u[at[0]], v[at[0]]))
    return int((u if u.size > n else v)[n])


def _missing(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The entries of ``u`` that ``v`` lacks (both int ``(k,)`` ascending)."""
    if not v.size:
        return u
    at = np.minimum(np.searchsorted(v, u), v.size - 1)
    return u[v[at] != u]


def _rows_of(term, entries: np.ndarray) -> np.ndarray:
    """A term's :func:`active_sets` entries as vertex rows: a pair potential's indices as its pairs' vertices (those
    rows only: a :class:`~sim_core.energies.contact.reference.PairVertices` gathers no whole array)."""
    return np.take(term.vertices, entries, axis=0) if isinstance(term, PAIR_POTENTIALS) else entries


def _by_copy(rows: np.ndarray, copy_of_vertex: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One term's active rows ``(a, r)`` (or ``(a,)``) as :func:`active_by_copy` gives them: ``(copies, rows)``
    sorted by copy, then by rows."""
    rows = rows[:, None] if rows.ndim == 1 else rows
    copies = copy_of_vertex[rows[:, 0]] if len(rows) else np.zeros(0, dtype=np.int64)
    order = np.lexsort(tuple(rows.T[::-1]) + (copies,))  # the last key is the primary one
    return copies[order], rows[order]


class SimplifiedNewtonTest:
    """The per-copy state of the simplified Newton test within one lockstep step (module docstring).

    Args:
        copy_of_vertex: the copy of each stacked vertex, shape ``(N,)`` int.
        copies: ``B``.
        enabled: whether the step may use the test (``StepTerms.simplified`` with a direct linear solver, whose
            kept factorisation makes the simplified correction a back-substitution: the host's, or the envelope
            Cholesky on the device).

    Attributes:
        ready: copies whose last iteration took its full step along the stacked exact factorisation, ``(B,)`` bool.
    """

    def __init__(self, copy_of_vertex: np.ndarray, copies: int, enabled: bool) -> None:
        self.copy_of_vertex = copy_of_vertex
        self.enabled = enabled
        self.ready = np.zeros(copies, dtype=bool)
        self._active_before: list[tuple] | None = None
        self._last: tuple | None = None  # (x, terms, active_sets) of the last iterate measured

    def _active(self, terms: list, x: np.ndarray) -> list[tuple] | None:
        """:func:`active_sets` of ``terms`` at ``x``, measured once an iterate (the test and the direction after it
        ask at the same ``x``)."""
        last = self._last
        if last is None or last[0] is not x or len(last[1]) != len(terms) or any(
                p is not q for p, q in zip(last[1], terms)):
            last = self._last = (x, list(terms), active_sets(terms, x))
        return last[2]

    def candidates(self, open_: np.ndarray, terms: list, x: np.ndarray, every: bool = False) -> np.ndarray:
        """The copies of ``open_`` ``(B,)`` to test at the iterate ``x`` ``(N, 3)`` with the contact ``terms`` there:
        ready, with the touching contacts of their last iterate. ``every``: the caller tests only where every copy of
        ``open_`` is a candidate (the device solvers: a test that cannot end the step saves nothing there); then all
        False wherever one is not, found without comparing the other copies' contacts (:func:`same_active_sets`'
        ``every``), and otherwise the same copies."""
        ready = self.ready & open_
        if not self.enabled or not ready.any() or every and not np.array_equal(ready, open_):
            return np.zeros_like(ready)
        now = self._active(terms, x)
        return ready & same_active_sets(self._active_before, now, self.copy_of_vertex, len(ready),
                                        open_ if every else None)

    def after_direction(self, exact_stacked: bool, terms: list, x: np.ndarray) -> None:
        """Keep the touching contacts at the iterate ``x`` whose update came from the stacked exact factorisation
        (``exact_stacked``), else forget them; no copy is ready until :meth:`after_line_search`."""
        self.ready[:] = False
        self._active_before = self._active(terms, x) if self.enabled and exact_stacked else None

    def after_line_search(self, full_step: np.ndarray) -> None:
        """The copies that took their full step (``(B,)`` bool) along the kept factorisation are ready."""
        self.ready = full_step & (self._active_before is not None)
