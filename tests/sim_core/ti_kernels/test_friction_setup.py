"""The step's pair distances at ``x^n`` taken from the last step's evaluation where a pair's side is unchanged
(:func:`sim_core.contact_friction_setup.keep_step_start_distances`) equal a launch over every pair, bit for bit,
also where the new step's sides flip, zero or sign a pair (its signed distance changes) and the edge-edge potential
keeps other rows of the candidate list."""

from __future__ import annotations

import numpy as np

from sim_core.workspace import workspace_of

from tests.sim_core.ti_kernels.test_contact_distance import EPS, _random_pairs

K = 1.0e4


def _lists(count: int = 600):
    """Positions and candidate lists: ``count`` random vertex-triangle and edge-edge pairs in every region."""
    rng = np.random.default_rng(7)
    x = _random_pairs(rng, count).reshape(-1, 3)
    quads = np.arange(x.shape[0]).reshape(-1, 4)
    vt = np.stack([quads[:, 0], np.arange(len(quads))], axis=1)
    edges = np.arange(x.shape[0]).reshape(-1, 2)
    ee = np.stack([np.arange(0, len(edges), 2), np.arange(1, len(edges), 2)], axis=1)
    return rng, x, (x, vt, ee), quads[:, 1:], edges


def _changed(rng, sides: np.ndarray) -> np.ndarray:
    """``sides`` with a fifth of them changed: a side flipped, a signed pair unsigned, an unsigned one signed."""
    out = sides.copy()
    rows = rng.random(len(sides)) < 0.2
    out[rows] = np.where(sides[rows] == 0.0, rng.choice([-1.0, 1.0], size=int(rows.sum())),
                         np.where(rng.random(int(rows.sum())) < 0.5, -sides[rows], 0.0))
    return out


def _step(candidates, triangles, edges, vt_sides, ee_sides, ee_rows):
    """A step's cache ``(memory, candidates, (vt, ee), ee rows)``: the two potentials over ``candidates`` (every
    vertex-triangle pair, the edge-edge pairs ``ee_rows``) linked by a pair batch."""
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.energies.contact.kernel import TiEdgeEdgeContact, TiVertexTriangleContact

    _, vt, ee = candidates
    pots = (TiVertexTriangleContact(vt, triangles, vt_sides, K, EPS),
            TiEdgeEdgeContact(ee[ee_rows], edges, ee_sides[ee_rows], K, EPS))
    PairBatch(*pots)
    return None, candidates, pots, ee_rows


def test_distances_kept_from_the_last_evaluation_equal_a_launch_over_every_pair_bit_for_bit(ti_cpu, monkeypatch):
    from sim_core.contact_friction_setup import keep_step_start_distances
    from sim_core.energies.contact import batch_kernel

    rng, x, candidates, triangles, edges = _lists()
    vt_sides = rng.choice([-1.0, 0.0, 1.0], size=len(candidates[1]))
    ee_sides = rng.choice([-1.0, 0.0, 1.0], size=len(candidates[2]))
    q = len(candidates[2])
    old_rows, new_rows = (np.flatnonzero(rng.random(q) < 0.7) for _ in range(2))
    previous = _step(candidates, triangles, edges, vt_sides, ee_sides, old_rows)
    for pot in previous[2]:
        pot.active_distances(x)  # the last step's end
    new_vt, new_ee = _changed(rng, vt_sides), _changed(rng, ee_sides)
    current = _step(candidates, triangles, edges, new_vt, new_ee, new_rows)
    reference = _step(candidates, triangles, edges, new_vt, new_ee, new_rows)
    launched = []
    kernel = batch_kernel._batch_kernel
    monkeypatch.setattr(batch_kernel, "_batch_kernel", lambda *a: (launched.append(a[4]), kernel(*a)))
    assert keep_step_start_distances(previous, current, x)
    same_ee = np.isin(new_rows, old_rows)
    same_ee[same_ee] = ee_sides[new_rows[same_ee]] == new_ee[new_rows[same_ee]]
    changed = int(np.sum(vt_sides != new_vt)) + int(np.sum(~same_ee))
    assert launched == [changed]  # one launch, over the changed pairs only
    flipped = 0
    for old, pot, ref in zip(previous[2], current[2], reference[2]):
        kept = workspace_of(pot).get(pot, "evaluation")
        active, d = ref.active_distances(x)
        np.testing.assert_array_equal(kept.active, active)
        assert kept.active.dtype == active.dtype
        np.testing.assert_array_equal(kept.distances.d.view(np.int64), d.view(np.int64))
        assert pot.active_distances(x)[0] is kept.active  # the kept evaluation serves the friction
        # the case that matters: an active pair whose side changed has another distance than the last step's
        old_d = dict(zip(map(tuple, old.pairs[old.active_distances(x)[0]]), old.active_distances(x)[1]))
        flipped += sum(1 for pair, dk in zip(map(tuple, pot.pairs[active]), d) if pair in old_d and old_d[pair] != dk)
    assert flipped > 0


def test_nothing_is_kept_without_the_same_candidates_or_an_evaluation_of_the_positions(ti_cpu):
    from sim_core.contact_friction_setup import keep_step_start_distances

    rng, x, candidates, triangles, edges = _lists(200)
    vt_sides = rng.choice([-1.0, 0.0, 1.0], size=len(candidates[1]))
    ee_sides = rng.choice([-1.0, 0.0, 1.0], size=len(candidates[2]))
    rows = np.arange(len(candidates[2]))
    previous = _step(candidates, triangles, edges, vt_sides, ee_sides, rows)
    current = _step(candidates, triangles, edges, _changed(rng, vt_sides), ee_sides, rows)
    assert not keep_step_start_distances(previous, current, x)  # the last step kept no evaluation of x
    for pot in previous[2]:
        pot.active_distances(x + 1e-5)  # of other positions
    assert not keep_step_start_distances(previous, current, x)
    for pot in previous[2]:
        pot.active_distances(x)
    other = (x, candidates[1].copy(), candidates[2])  # equal lists, another search's
    assert not keep_step_start_distances(previous, current[:1] + (other,) + current[2:], x)
    assert not keep_step_start_distances(None, current, x)
    assert all(workspace_of(pot).get(pot, "evaluation") is None for pot in current[2])
    assert keep_step_start_distances(previous, current, x)
