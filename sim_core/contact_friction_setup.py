"""The friction set-up of a contact set's pair contacts (:meth:`~sim_core.contact_set.ContactSet.friction`).

A step starts at the converged positions of the last one: ``x^n`` of step ``n`` is the ``x`` at which
:meth:`ContactSet.end_step` evaluated the last step's pair potentials. The new step's potentials are built over the
same candidate lists with the step's new sides (:meth:`ContactSet._step_sides`), and the lagged friction needs their
active pairs and distances at ``x^n``. A pair's distance depends on its four positions and its side only (and whether
it is active on ``eps``), so a pair whose side is unchanged has the distance the last step's evaluation kept, bit for
bit; a pair whose side changed (a new remembered side, or one unsigned now) may have another signed distance and is
measured again. :func:`keep_step_start_distances` keeps the new potentials' evaluation of ``x^n`` made so: the
unchanged pairs' from the last evaluation, the others from one launch of the pair batch's kernel over them only
(:meth:`~sim_core.energies.contact.batch_kernel.PairBatch.measure`, the functions of every evaluation), instead of a
launch over every candidate pair. :func:`pair_friction` builds the friction of the pair contacts from them, and
:class:`FrictionRowSource` records where a friction's rows come from.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim_core.collision.distances import DistanceDerivatives
from sim_core.energies.base import positions_key
from sim_core.energies.contact.reference import PairEvaluation
from sim_core.workspace import workspace_of


class FrictionRowSource(NamedTuple):
    """Where a run of consecutive rows of a :class:`~sim_core.energies.friction.reference.LaggedFriction` built by
    :meth:`~sim_core.contact_set.ContactSet.friction`
    comes from (kept as ``LaggedFriction.row_sources``, in row order, so that the adjoint
    differentiates the frozen frames without searching the pairs again).

    Attributes:
        obstacle: the plane / sphere body name, None for vertex-triangle and edge-edge pairs.
        potential: the step's contact potential of the rows (``VertexTriangleContact``,
            ``EdgeEdgeContact``, ``PlaneContact`` or ``SphereContact``; its sides fixed for the step).
        pair_index: the rows' pair (vertex) indices in ``potential``, int64 shape ``(r,)``.
    """

    obstacle: str | None
    potential: object
    pair_index: np.ndarray


def keep_step_start_distances(previous: tuple | None, current: tuple | None, x: np.ndarray) -> bool:
    """Keep, as the step's pair potentials' evaluation of ``x`` ``(n, 3)`` (m), their active pairs and distances
    taken from the last step's potentials' kept evaluation of ``x`` where a pair's side is unchanged, the other
    pairs measured in one launch of their pair batch. The same evaluation (active rows in increasing order, the
    same distances bit for bit) as the batch's launch over every pair.

    Args:
        previous: the contact set's step cache before the step's search (``(memory, candidates, (vt, ee), ee rows)``:
            the last step's potentials over ``candidates``, the edge-edge potential over the rows ``ee rows`` int64
            ``(r,)`` of the candidates' edge-edge list), or None.
        current: the step's cache after it, over the same ``candidates`` (the same object), or None.
        x: the positions of the step's start.

    Returns:
        whether the evaluation was kept; False (nothing done) without two caches over the same candidates, pair
        potentials of the same class and ``eps`` linked to one pair batch, an evaluation of ``x`` kept by the last
        step's potentials and none by the new ones.
    """
    if previous is None or current is None or previous is current or previous[1] is not current[1]:
        return False
    old, new = previous[2], current[2]
    batch = getattr(new[0], "_batch", None)
    if batch is None or new[1]._batch is not batch:
        return False
    key = positions_key(x)
    kept = [pot._kept(key, 0) for pot in old]
    if (any(k is None for k in kept) or any(pot._kept(key, 0) is not None for pot in new)
            or any(type(a) is not type(b) or a.eps != b.eps for a, b in zip(old, new))):
        return False
    q = len(current[1][2])  # the candidates' edge-edge pairs, whose rows the edge-edge potentials keep
    old_table, new_table = _table(previous[3], q), _table(current[3], q)
    same = (_same_sides(old[0].sides, new[0].sides, None, None),
            _same_sides(old[1].sides, new[1].sides, old_table, current[3]))
    if same[0] is None:
        return False
    changed = np.flatnonzero(~same[0]), np.flatnonzero(~same[1])
    found, d = batch.measure(x, np.concatenate([changed[0], changed[1] + batch.split]), key)
    cut = int(np.searchsorted(found, batch.split))
    measured = ((found[:cut], d[:cut]), (found[cut:] - batch.split, d[cut:]))
    reused = _reused(kept[0], same[0], None, None), _reused(kept[1], same[1], previous[3], new_table)
    for pot, (rows, dist), (more, more_d) in zip(new, reused, measured):
        active, dist = np.concatenate([rows, more]), np.concatenate([dist, more_d])
        order = np.argsort(active, kind="stable")  # (disjoint rows: unchanged sides, then measured)
        active, dist = np.take(active, order), np.take(dist, order)
        dd = DistanceDerivatives(dist, None, None, np.zeros(active.shape, np.int64))
        workspace_of(pot).put(pot, "evaluation", PairEvaluation(0, key, active, dd, pot.eps))
    return True


def _table(rows: np.ndarray, count: int) -> np.ndarray:
    """int64 ``(count,)``: the potential's row of each of ``count`` candidates, -1 where the potential has none
    (``rows``: its candidates' rows, int ``(r,)``, distinct)."""
    table = np.full(count, -1, dtype=np.int64)
    table[rows] = np.arange(len(rows), dtype=np.int64)
    return table


def _same_sides(old_sides: np.ndarray, new_sides: np.ndarray, old_table: np.ndarray | None,
                new_rows: np.ndarray | None) -> np.ndarray | None:
    """Bool ``(r,)``: whether each pair of the new potential (sides ``new_sides`` ``(r,)``, its pairs the candidates
    ``new_rows`` int ``(r,)``, or None: candidates ``0 .. r - 1``) was a pair of the old one (sides ``old_sides``; its
    row of each candidate ``old_table``, :func:`_table`, or None: as the new one's) with the same side, bit for bit;
    None where ``old_table`` is None and the lengths differ."""
    old_bits, new_bits = np.ascontiguousarray(old_sides).view(np.int64), np.ascontiguousarray(new_sides).view(np.int64)
    if old_table is None:
        return old_bits == new_bits if len(old_bits) == len(new_bits) else None
    pos = np.take(old_table, new_rows)
    same = pos >= 0
    if len(old_bits):
        same &= np.take(old_bits, pos) == new_bits  # (-1: the last row, ruled out by ``same``)
    return same


def _reused(evaluation: PairEvaluation, same: np.ndarray, old_rows: np.ndarray | None,
            new_table: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The active pairs of ``evaluation`` (the old potential's, over the candidates ``old_rows``, or None: candidates
    ``0 ..``) that are pairs of the new potential (its row of each candidate ``new_table``, :func:`_table`, or None:
    the old one's rows) with the same side (``same``, :func:`_same_sides`), as new rows int64 ``(a,)`` (in
    increasing order), and their distances."""
    active, dist = np.asarray(evaluation.active, dtype=np.int64), evaluation.distances.d
    if old_rows is not None:
        active = np.take(new_table, np.take(old_rows, active))
        keep = active >= 0
        active, dist = active[keep], dist[keep]
    keep = np.take(same, active)
    return active[keep], dist[keep]


def pair_friction(contact, x_n: np.ndarray, dt: float, vt, ee):
    """:meth:`ContactSet.friction` on the Taichi backend when only pair contacts touch: the frames and tangent
    bases of the active pairs of both kinds from one launch
    (:func:`sim_core.energies.contact.setup_kernel.friction_frames`; the values of the pair potentials'
    ``contact_frames`` and of ``tangent_basis``, bit for bit), rows in the same order.

    Args:
        contact: the :class:`~sim_core.contact_set.ContactSet` (its Coulomb coefficients, model and workspace).
        x_n: the step's start ``(n, 3)`` (m).
        dt: the time step (s).
        vt, ee: the step's vertex-triangle and edge-edge potentials.

    Returns:
        a :class:`~sim_core.energies.friction.kernel.TiLaggedFriction` with its ``row_sources``, or None when no pair
        touches or every pair's Coulomb coefficient is 0.
    """
    # optional heavy dependency: Taichi, loaded on a Taichi backend only
    from sim_core.energies.contact.setup_kernel import friction_frames
    from sim_core.energies.friction.kernel import TiLaggedFriction

    pots = (vt, ee)
    rows = [pot.active_distances(x_n) for pot in pots]
    split = len(rows[0][0])
    vertices = np.concatenate([np.take(pot.vertices, active, axis=0) for pot, (active, _) in zip(pots, rows)])
    if not len(vertices):
        return None
    # column 0 and the second side's column (1 for [p, a, b, c], 2 for [a0, a1, b0, b1]): its two sides
    mu = contact.coulomb.between(vertices[:, 0], np.concatenate([vertices[:split, 1], vertices[split:, 2]]))
    if not np.any(mu > 0):
        return None
    sides = np.concatenate([pot.sides[active] for pot, (active, _) in zip(pots, rows)])
    weights, normal, tangent = friction_frames(x_n, vertices, sides, split)
    lam = np.concatenate([pot.stiffness * (pot.eps - d) for pot, (_, d) in zip(pots, rows)])
    friction = TiLaggedFriction(vertices, weights, tangent, lam, mu, x_n, contact.model.contact.eps_v, dt)
    friction.workspace = contact.workspace
    friction.row_sources = [FrictionRowSource(None, pot, active) for pot, (active, _) in zip(pots, rows)
                            if len(active)]
    return friction
