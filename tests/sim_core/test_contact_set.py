"""Contact set: the sides of a step are fixed for all its Newton iterates (one energy per step)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.builder import ModelBuilder
from sim_core.contact_set import ContactSet
from sim_core.mesh.sheet import TriMesh
from sim_core.model import ContactSettings

EPS = 4e-4
MATERIAL = {"youngs_modulus": 1e8, "poisson_ratio": 0.3, "thickness": 1e-4, "density": 1000.0,
            "bending_stiffness": 1e-4}


def _two_triangles(x_b: float, z_b: float) -> np.ndarray:
    """Sheet a: edge a0-a1 along x at z = 0 (triangle towards -y). Sheet b: edge b0-b1 along y at
    (x_b, z_b) (triangle towards +x)."""
    a = [[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, -0.01, 0.0]]
    b = [[x_b, -0.005, z_b], [x_b, 0.005, z_b], [x_b + 0.01, 0.0, z_b]]
    return np.array(a + b)


def _contact_set(x0: np.ndarray) -> ContactSet:
    builder = ModelBuilder()
    builder.add_sheet("a", TriMesh(x0[:3], np.array([[0, 1, 2]])), MATERIAL)
    builder.add_sheet("b", TriMesh(x0[3:], np.array([[0, 1, 2]])), MATERIAL)
    return ContactSet(builder.finalize(contact=ContactSettings(eps=EPS)))


def _edge_pair_distance(cs: ContactSet, x: np.ndarray, x_n: np.ndarray) -> float:
    memory = cs.begin_step(x_n, None)
    ee = cs.potentials(x, x_n, memory)[1]
    rows = [i for i, v in enumerate(ee.vertices) if {*v[:2]} == {0, 1} and {*v[2:]} == {3, 4}
            or {*v[:2]} == {3, 4} and {*v[2:]} == {0, 1}]
    assert len(rows) == 1
    return float(ee.distance(x)[rows[0]])


def test_pair_beyond_an_edge_end_at_step_start_is_unsigned():
    """At x^n edge b passes beyond the end of edge a (closest point a1, not interior) on the +z side
    of the lines; the iterate has it under the middle of a. That is no crossing of the segments, so
    d is +0.1 mm. Taking the side from x^n (the lines' side) gave d = -0.1 mm, a phantom
    penetration that made Newton cycle between iterates (a sysid replay failed at t = 1.87 s)."""
    x_n = _two_triangles(0.0103, 1e-4)
    x = _two_triangles(0.005, -1e-4)
    cs = _contact_set(x_n)
    assert _edge_pair_distance(cs, x, x_n) == pytest.approx(1e-4)


def test_pair_interior_at_step_start_keeps_its_side_and_is_remembered():
    """Edges crossing in their interiors at x^n (b above a) that cross during the step are pushed
    back (d = -0.1 mm), and the converged step remembers the side of the active interior pair."""
    x_n = _two_triangles(0.005, 1e-4)
    x = _two_triangles(0.005, -1e-4)
    cs = _contact_set(x_n)
    assert _edge_pair_distance(cs, x, x_n) == pytest.approx(-1e-4)
    memory = cs.begin_step(x_n, None)
    remembered = cs.end_step(x_n, memory).edge_edge
    assert len(remembered) >= 1
    # a pair beside its triangle / beyond the edge ends is not remembered (its side has no meaning)
    far = _two_triangles(0.0103, 1e-4)
    cs = _contact_set(far)
    memory = cs.begin_step(far, None)
    ee_pairs = {tuple(sorted(p)) for p in cs.end_step(far, memory).edge_edge.pairs.tolist()}
    ee = cs.potentials(far, far, memory)[1]
    beyond = [tuple(sorted(p)) for p, v in zip(ee.pairs.tolist(), ee.vertices) if {*v} == {0, 1, 3, 4}]
    assert beyond and not (set(beyond) & ee_pairs)


def test_a_second_search_of_the_step_gives_the_sides_of_a_fresh_search():
    """Sides and kept edge pairs of a second candidate list of the step equal those of a fresh search; a search over
    the step's last lists (the same arrays) takes their sides as they are."""
    from sim_core.collision import CollisionMemory

    rng = np.random.default_rng(4)
    x0 = _two_triangles(0.2, 0.02)
    cs = _contact_set(x0)
    vt_all, ee_all = np.array([[v, t] for v in range(6) for t in range(2)]), np.array([[0, 5], [1, 4], [2, 6], [3, 7]])
    ee_all = ee_all[(ee_all < len(cs.edges)).all(axis=1)]
    memory = CollisionMemory()
    cs.begin_step(x0 + rng.normal(scale=1e-3, size=x0.shape), memory)
    first = (x0, vt_all[::2], ee_all[::2])
    second = (x0, vt_all, ee_all)
    cs._search(x0, memory, first)
    (vt, ee), rows = cs._search(x0, memory, second)
    again = cs._search(x0, memory, second)[0]
    assert np.shares_memory(again[0].sides, vt.sides)  # kept, not computed again
    cs._step_table = None
    (vt_fresh, ee_fresh), rows_fresh = cs._search(x0, memory, second)
    np.testing.assert_array_equal(rows, rows_fresh)
    for a, b in ((vt, vt_fresh), (ee, ee_fresh)):
        np.testing.assert_array_equal(a.pairs, b.pairs)
        np.testing.assert_array_equal(a.sides, b.sides)


def test_iterates_covered_by_one_search_share_the_potentials_and_a_new_step_rebuilds_them():
    """Within a step, iterates covered by the same candidate search get the same potential objects
    (same pairs and sides; their kept evaluation is matched against x), with the energies of a
    fresh contact set; the next step builds new ones."""
    x_n = _two_triangles(0.005, 1e-4)
    x = x_n.copy()
    x[3:, 2] -= 2e-4
    cs = _contact_set(x_n)
    memory = cs.begin_step(x_n, None)
    first = cs.potentials(x_n, x_n, memory)
    assert cs.covers(cs.search_position, x)
    second = cs.potentials(x, x_n, memory)
    assert all(a is b for a, b in zip(first[:2], second[:2]))
    fresh = _contact_set(x_n)
    fresh_memory = fresh.begin_step(x_n, None)
    for a, b in zip(second[:2], fresh.potentials(x, x_n, fresh_memory)[:2]):
        assert a.energy(x) == b.energy(x) and a.energy(x_n) == b.energy(x_n)
    assert second[1].energy(x) > 0.0
    memory = cs.begin_step(x, cs.end_step(x, memory))
    assert all(a is not b for a, b in zip(second[:2], cs.potentials(x, x, memory)[:2]))


@pytest.mark.parametrize("empty", ["vt", "ee"])
def test_a_search_with_one_pair_kind_empty_and_every_pair_known_keeps_the_sides(empty):
    """A second search of the step whose pairs are all known from the first (one kind with no pairs)
    takes every side from there: the potentials equal the first search's, the empty kind stays empty."""
    from sim_core.collision import CollisionMemory

    x0 = _two_triangles(0.005, 1e-4)
    cs = _contact_set(x0)
    vt = np.array([[v, t] for v in range(6) for t in range(2) if cs.triangles[t, 0] // 3 != v // 3])
    ee = np.array([[i, j] for i in range(len(cs.edges)) for j in range(i + 1, len(cs.edges))
                   if cs.edges[i, 0] // 3 != cs.edges[j, 0] // 3])
    vt, ee = (vt[:0], ee) if empty == "vt" else (vt, ee[:0])
    memory = CollisionMemory()
    cs.begin_step(x0, memory)
    first, first_rows = cs._search(x0, memory, (x0, vt, ee))
    again, again_rows = cs._search(x0, memory, (x0, vt, ee))
    np.testing.assert_array_equal(first_rows, again_rows)  # the edge-edge candidates kept
    np.testing.assert_array_equal(first[1].pairs, ee[first_rows])
    first_sides, again_sides = [p.sides for p in first], [p.sides for p in again]
    assert len(vt) + len(ee) > 0
    for a, b in zip(first_sides, again_sides):
        assert a.dtype == np.float64
        np.testing.assert_array_equal(a, b)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.pairs, b.pairs)
        np.testing.assert_array_equal(a.sides, b.sides)
    assert len((first[0] if empty == "vt" else first[1]).pairs) == 0
    assert np.any(np.concatenate(first_sides) != 0)  # signed pairs (interior / above the face) too


def _brute_force_close_pairs(cs: ContactSet, x: np.ndarray, eps: float) -> tuple[set, set]:
    """Every vertex-triangle and edge-edge pair the filter allows that is closer than ``eps`` at ``x``,
    by measuring all pairs (no broad phase)."""
    from sim_core.collision.distances import edge_edge_distance, point_triangle_distance

    body, xr = cs.vertex_body, cs.model.x_rest
    vt = np.array([(v, t) for v in cs.surface_vertices for t in range(len(cs.triangles))
                   if v not in cs.triangles[t]], dtype=np.int64)
    tri = cs.triangles[vt[:, 1]]
    d = point_triangle_distance(x[vt[:, 0]], x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]])
    rest = lambda idx: point_triangle_distance(xr[vt[idx, 0]], xr[tri[idx, 0]], xr[tri[idx, 1]], xr[tri[idx, 2]])
    keep = cs.filter.keep(body[vt[:, 0]], body[tri[:, 0]], rest)
    close_vt = {tuple(p) for p in vt[keep & (d < eps)].tolist()}
    e = cs.edges
    ee = np.array([(i, j) for i in range(len(e)) for j in range(i + 1, len(e)) if not set(e[i]) & set(e[j])],
                  dtype=np.int64)
    ea, eb = e[ee[:, 0]], e[ee[:, 1]]
    d = edge_edge_distance(x[ea[:, 0]], x[ea[:, 1]], x[eb[:, 0]], x[eb[:, 1]])
    rest = lambda idx: edge_edge_distance(xr[ea[idx, 0]], xr[ea[idx, 1]], xr[eb[idx, 0]], xr[eb[idx, 1]])
    keep = cs.filter.keep(body[ea[:, 0]], body[eb[:, 0]], rest)
    close_ee = {tuple(p) for p in ee[keep & (d < eps)].tolist()}
    return close_vt, close_ee


def test_searches_ahead_of_the_motion_never_miss_a_close_pair():
    """Two sheets closing on each other by up to 0.9 margin per step, with the iterates of a step
    spread around the step's end point: the candidate search runs ahead of the step's motion
    (ContactSet._search_position) and is reused while it covers the iterate; every pair a brute-force
    measurement of all pairs finds within eps at an iterate is in that iterate's candidate list,
    the look-ahead needs fewer searches than searching at the iterate itself, and the search position
    always covers the iterate it was made for."""
    from sim_core.mesh.sheet import grid_sheet

    def build(lookahead: float) -> ContactSet:
        builder = ModelBuilder()
        builder.add_sheet("a", grid_sheet((0.01, 0.01), (5, 5)), MATERIAL)
        builder.add_sheet("b", grid_sheet((0.01, 0.01), (5, 5), origin=(0.001, 0.0005, 0.004)), MATERIAL)
        cs = ContactSet(builder.finalize(contact=ContactSettings(eps=EPS, candidate_margin=1e-3)))
        cs.lookahead = lookahead
        return cs

    searches = {}
    for lookahead in (0.0, 0.5):
        cs = build(lookahead)
        rng = np.random.default_rng(11)
        x_n = cs.model.x_rest.copy()
        memory, count, checked = None, 0, 0
        last = None
        for step in range(14):
            memory = cs.begin_step(x_n, memory)
            motion = np.zeros_like(x_n)
            motion[25:, 2] = -0.9 * cs.margin * (1.0 - step / 20.0)  # sheet b descends onto a
            x_end = x_n + motion + rng.normal(scale=0.05 * cs.margin, size=x_n.shape)
            for k in range(3):  # iterates spread around the step's end point
                x = x_end + rng.normal(scale=0.05 * cs.margin, size=x_n.shape) / (k + 1)
                vt, ee = cs.potentials(x, x_n, memory)[:2]
                if cs._candidates is not last:
                    count, last = count + 1, cs._candidates
                    assert cs.covers(cs.search_position, x)
                close_vt, close_ee = _brute_force_close_pairs(cs, x, cs.eps)
                candidates_vt = {tuple(p) for p in cs._candidates[1].tolist()}
                candidates_ee = {tuple(p) for p in cs._candidates[2].tolist()}
                assert close_vt <= candidates_vt and close_ee <= candidates_ee
                checked += len(close_vt) + len(close_ee)
            memory = cs.end_step(x, memory)
            x_n = x
        assert checked > 0  # the sheets came into contact
        searches[lookahead] = count
    assert searches[0.5] < searches[0.0]


def _two_grid_sheets(candidate_margin: float = 1e-3) -> ContactSet:
    from sim_core.mesh.sheet import grid_sheet

    builder = ModelBuilder()
    builder.add_sheet("a", grid_sheet((0.01, 0.01), (5, 5)), MATERIAL)
    builder.add_sheet("b", grid_sheet((0.01, 0.01), (5, 5), origin=(0.001, 0.0005, 0.004)), MATERIAL)
    return ContactSet(builder.finalize(contact=ContactSettings(eps=EPS, candidate_margin=candidate_margin)))


def test_a_search_covers_bodies_moving_together_and_no_gap_closing_by_more_than_the_margin():
    """``covers``: a common translation of both sheets (any size) closes no gap; sheet b moving onto
    sheet a by more than the margin, one vertex of a (self-contact) moving away from its sheet by
    more than the margin, or NaN positions are not covered; every vertex within margin / 2 is."""
    cs = _two_grid_sheets()
    x0 = cs.model.x_rest.copy()
    m = cs.margin
    assert cs.covers(x0, x0 + np.array([3.0 * m, -5.0 * m, 2.0 * m]))
    x = x0.copy()
    x[:, 2] += 0.45 * m
    x[25:, 0] -= 0.45 * m
    assert cs.covers(x0, x)  # every vertex within margin / 2
    x = x0 + np.array([4.0 * m, 0.0, 0.0])
    x[25:, 2] -= 0.6 * m
    x[:25, 2] += 0.5 * m  # the sheets close by 1.1 margin along z
    assert not cs.covers(x0, x)
    x[:25, 2] -= 0.2 * m  # by 0.9 margin
    assert cs.covers(x0, x)
    x = x0 + 2.0 * m
    x[7, 1] += 1.1 * m  # a self-contact gap of sheet a may have closed by 1.1 margin
    assert not cs.covers(x0, x)
    x[7] = np.nan
    assert not cs.covers(x0, x)


def test_covers_keeps_its_answer_for_two_frozen_arrays_and_the_search_position_is_frozen():
    """Asked again with the same two read-only arrays (frozen: their values cannot change), ``covers`` gives
    its kept answer without reading the positions; another array, or a writeable one changed in place (the
    test above), is measured anew. The search position is such a frozen array."""
    cs = _two_grid_sheets()
    x0 = cs.model.x_rest.copy()
    m = cs.margin
    measured = []
    gaps_hold = cs._gaps_hold
    cs._gaps_hold = lambda moved: measured.append(1) or gaps_hold(moved)
    x_search, x = x0.copy(), x0 + np.array([4.0 * m, 0.0, 0.0])
    x[25:, 2] -= 0.6 * m
    x[:25, 2] += 0.5 * m  # the sheets close by 1.1 margin along z
    for a in (x_search, x):
        a.flags.writeable = False
    assert not cs.covers(x_search, x) and not cs.covers(x_search, x)
    assert len(measured) == 1
    closer = x.copy()
    closer[:25, 2] -= 0.2 * m  # by 0.9 margin
    closer.flags.writeable = False
    assert cs.covers(x_search, closer) and len(measured) == 2
    memory = cs.begin_step(x0, None)
    cs.potentials(x0, x0, memory)
    assert not cs.search_position.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        cs.search_position[0, 0] = 1.0


def test_searches_of_sheets_drifting_together_never_miss_a_close_pair_and_are_fewer():
    """Both sheets drift by 0.8 margin per step in x and y (a common motion the margin / 2 rule
    counts as a move) while b descends onto a: every pair a brute-force measurement finds within
    eps is in the candidate list of its iterate, with fewer searches than the margin / 2 rule."""
    searches = {}
    for general in (True, False):
        cs = _two_grid_sheets()
        if not general:
            cs._gaps_hold = lambda moved: False  # the margin / 2 rule alone
        rng = np.random.default_rng(5)
        x_n = cs.model.x_rest.copy()
        memory, count, checked, last = None, 0, 0, None
        for step in range(12):
            memory = cs.begin_step(x_n, memory)
            motion = np.zeros_like(x_n)
            motion[:, :2] = 0.8 * cs.margin
            motion[25:, 2] = -0.6 * cs.margin * (1.0 - step / 16.0)
            for k in range(3):
                x = x_n + motion + rng.normal(scale=0.03 * cs.margin, size=x_n.shape) / (k + 1)
                cs.potentials(x, x_n, memory)
                if cs._candidates is not last:
                    count, last = count + 1, cs._candidates
                close_vt, close_ee = _brute_force_close_pairs(cs, x, cs.eps)
                assert close_vt <= {tuple(p) for p in cs._candidates[1].tolist()}
                assert close_ee <= {tuple(p) for p in cs._candidates[2].tolist()}
                checked += len(close_vt) + len(close_ee)
            memory = cs.end_step(x, memory)
            x_n = x
        assert checked > 0  # the sheets came into contact
        searches[general] = count
    assert searches[True] < searches[False]


def test_the_search_position_is_ahead_of_the_motion_and_covers_its_point():
    """``x + clip(lookahead (x - x^n), +-lookahead_cap margin)`` per coordinate; at x^n, before any
    step, or with lookahead 0 the search is at x; a cap above margin / 2 is refused."""
    x_n = _two_triangles(0.005, 1e-4)
    cs = _contact_set(x_n)
    x = x_n.copy()
    assert np.array_equal(cs._search_position(x), x)  # no step started
    cs.begin_step(x_n, None)
    x[0, 2] += 2e-4  # a small move: half of it ahead
    x[1, 0] -= 5e-3  # a large one: capped
    ahead = cs._search_position(x)
    assert ahead[0, 2] == pytest.approx(x[0, 2] + 1e-4, abs=1e-15)
    assert ahead[1, 0] == pytest.approx(x[1, 0] - 0.25 * cs.margin, abs=1e-15)
    np.testing.assert_array_equal(np.delete(ahead, [0, 1], axis=0), np.delete(x, [0, 1], axis=0))
    assert cs.covers(ahead, x)
    cs.lookahead = 0.0
    assert np.array_equal(cs._search_position(x), x)
    cs.lookahead, cs.lookahead_cap = 0.5, 0.6
    with pytest.raises(ValueError, match="lookahead_cap"):
        cs._search_position(x)


def test_a_trial_point_is_searched_where_the_list_also_covers_its_line_search_segment_first_halving():
    """Sheet b 1.1 mm above sheet a at x^n (the line search's start), its trial point 1.6 margin further down: the
    search ahead of the trial point (``x + clip(lookahead (x - x^n))``) does not cover the segment's first halving
    ``h`` (b 0.3 mm above a, in contact), so a backtrack to it would search again; given the segment's start, the
    search is made ahead of the point 3/4 of the way, whose list covers both the trial point and ``h`` (every pair
    within eps at either, by brute force): one search for both. A trial point whose own search covers ``h`` is
    searched there, as without a segment."""
    cs = _two_grid_sheets()
    m = cs.margin
    start = cs.model.x_rest.copy()
    start[25:, 2] -= 0.004 - 1.1e-3  # sheet b (vertices 25-49) 1.1 mm above sheet a
    start.flags.writeable = False
    memory = cs.begin_step(start, None)
    trial = start.copy()
    trial[25:, 2] -= 1.6 * m
    trial.flags.writeable = False
    half = 0.5 * (start + trial)
    ahead = cs._search_position(trial)
    assert cs.covers(ahead, trial) and not cs.covers(ahead, half)
    searched = cs._search_position(trial, start)
    assert cs.covers(searched, trial) and cs.covers(searched, half)

    cs.potentials(trial, start, memory, segment_start=start)
    lists = cs._candidates
    assert cs.search_position is not None and cs.covers(cs.search_position, half)
    cs.potentials(half, start, memory)
    assert cs._candidates is lists  # no second search at the first halving
    for x in (trial, half):
        close_vt, close_ee = _brute_force_close_pairs(cs, x, cs.eps)
        assert close_vt <= {tuple(p) for p in lists[1].tolist()}
        assert close_ee <= {tuple(p) for p in lists[2].tolist()}
    assert len(_brute_force_close_pairs(cs, half, cs.eps)[0]) > 0  # the sheets touch at h

    plain = _two_grid_sheets()  # without the segment: a second search at h
    memory = plain.begin_step(start, None)
    plain.potentials(trial, start, memory)
    first = plain._candidates
    plain.potentials(half, start, memory)
    assert plain._candidates is not first

    near = start.copy()
    near[25:, 2] -= 0.6 * m  # a short segment: the search ahead of the trial point covers its halving
    near.flags.writeable = False
    np.testing.assert_array_equal(cs._search_position(near, start), cs._search_position(near))


def test_a_side_gone_stale_beyond_an_edge_end_is_released_for_the_rest_of_the_step():
    """Edge b above the middle of edge a at x^n (interior: the pair keeps the side +1 for the step).
    At the iterate x, b has moved beyond the end of a and below the line of a: the lines crossed
    beyond a's end, not the edges. Entering the interior again from there, the pair's distance
    would jump from +0.1 mm to -0.1 mm (a step in the energy that stalled Newton on folding.yaml).
    release_stale_sides unsigns it: the energy at x is unchanged, back in the interior the distance
    is +0.1 mm, later searches of the step keep it unsigned, and the next step signs it afresh."""
    x_n = _two_triangles(0.005, 1e-4)
    x_round = _two_triangles(0.0103, -1e-4)  # beyond a1, on the other side of the lines
    x_back = _two_triangles(0.005, -1e-4)  # interior again, below
    cs = _contact_set(x_n)
    memory = cs.begin_step(x_n, None)
    before = [p.energy(x_round) for p in cs.potentials(x_round, x_n, memory)]
    assert _distance_in_step(cs, x_back, memory) == pytest.approx(-1e-4)
    assert cs.release_stale_sides(x_round, memory) >= 1
    assert [p.energy(x_round) for p in cs.potentials(x_round, x_n, memory)] == pytest.approx(before, abs=1e-18)
    assert _distance_in_step(cs, x_back, memory) == pytest.approx(1e-4)
    cs._candidates = None  # a new broad-phase search within the step: still unsigned
    assert _distance_in_step(cs, x_back, memory) == pytest.approx(1e-4)
    assert cs.release_stale_sides(x_round, memory) == 0  # nothing more to release
    assert _edge_pair_distance(cs, x_back, x_n) == pytest.approx(-1e-4)  # a new step: signed again


def test_a_penetrating_pair_in_the_interior_keeps_its_side():
    """Edge b pushed through the middle of edge a (interior, other geometric side) is a crossing
    the side must undo: release_stale_sides leaves it signed (d = -0.1 mm)."""
    x_n = _two_triangles(0.005, 1e-4)
    x = _two_triangles(0.005, -1e-4)
    cs = _contact_set(x_n)
    memory = cs.begin_step(x_n, None)
    assert cs.release_stale_sides(x, memory) == 0
    assert _distance_in_step(cs, x, memory) == pytest.approx(-1e-4)


def _distance_in_step(cs: ContactSet, x: np.ndarray, memory) -> float:
    """Contact distance (m) of the a0-a1 / b0-b1 edge pair at ``x`` within the current step."""
    ee = cs.potentials(x, cs.x_prev, memory)[1]
    rows = [i for i, v in enumerate(ee.vertices) if {*v[:2]} == {0, 1} and {*v[2:]} == {3, 4}
            or {*v[:2]} == {3, 4} and {*v[2:]} == {0, 1}]
    assert len(rows) == 1
    return float(ee.distance(x)[rows[0]])


def _forming_model_deformed(seed: int):
    """The Forming scene (hairpin sheet with self contact, frozen table box, dome gel) at its initial
    state with every vertex jittered by 0.3 mm: sheet layers, gel and table within the search radius."""
    from pathlib import Path

    from sim_core.scenes.task_scene import load_task_scene, task_initial_state

    model = load_task_scene(Path(__file__).resolve().parents[2] / "config" / "scenes" / "forming.yaml")
    x = task_initial_state(model).x + np.random.default_rng(seed).normal(scale=3e-4, size=(model.vertex_count, 3))
    return model, x


@pytest.mark.parametrize("seed", range(2))
def test_every_broad_phase_gives_the_same_candidate_lists_on_the_numpy_path(seed):
    """NumPy backend: the spatial hash (the default) and the k-d trees give identical sorted lists;
    ``sweep`` runs its reference there; an unknown name is refused."""
    from sim_core.errors import ConfigError

    model, x = _forming_model_deformed(seed)
    assert ContactSet(model).broad_phase == "spatial_hash"
    lists = {}
    for name in ("spatial_hash", "sweep", "kdtree"):
        cs = ContactSet(model, broad_phase=name)
        _, vt, ee = cs._candidate_pairs(x)
        lists[name] = (vt, ee)
        assert len(vt) > 50 and len(ee) > 50
    for name in ("spatial_hash", "sweep"):
        np.testing.assert_array_equal(lists[name][0], lists["kdtree"][0])
        np.testing.assert_array_equal(lists[name][1], lists["kdtree"][1])
    with pytest.raises(ConfigError, match="broad_phase.*'bvh'"):
        ContactSet(model, broad_phase="bvh")


def test_friction_coefficients_are_those_of_each_pairs_two_bodies_and_follow_edits():
    """Each friction row's mu is ``model.friction_coefficient`` of the bodies on the pair's two sides,
    also after ``model.friction`` is edited between steps (as the generated friction effects do)."""
    model, x = _forming_model_deformed(0)
    cs = ContactSet(model)
    body_names = list(model.bodies)
    body = model.body_of_vertex()

    def expected(friction) -> np.ndarray:
        out = []
        for source in friction.row_sources:
            vertices = source.potential.vertices[source.pair_index]
            second = 1 if source.potential is cs._pairs(x, memory)[0] else 2
            out += [model.friction_coefficient(body_names[body[a]], body_names[body[b]])
                    for a, b in zip(vertices[:, 0], vertices[:, second])]
        return np.array(out)

    for scale in (1.0, 0.5):
        for i, a in enumerate(body_names):  # a different coefficient for every body pair
            for j, b in enumerate(body_names[i:]):
                model.friction[frozenset((a, b))] = scale * (0.1 + 0.1 * i + 0.03 * j)
        memory = cs.begin_step(x, None)
        friction = cs.friction(x, 0.005, memory)
        assert all(s.obstacle is None for s in friction.row_sources) and len(friction.mu) > 10
        np.testing.assert_array_equal(friction.mu, expected(friction))
        assert np.all(friction.mu != 0.1 * scale)  # no pair within one body (its coefficient is 0.1 here)


def test_a_step_starting_where_the_last_ended_reuses_its_geometry_with_the_same_sides(monkeypatch):
    """end_step measures every candidate pair at the converged positions; the next step, starting
    there with the same candidate lists, takes its sides from that measurement (no geometry of its
    own) and gets the sides and kept edge pairs of a contact set that measures them again."""
    model, x_n = _forming_model_deformed(1)
    x = x_n + np.random.default_rng(5).normal(scale=5e-5, size=x_n.shape)
    cs, fresh = ContactSet(model), ContactSet(model)
    memory = cs.begin_step(x_n, None)
    cs.potentials(x, x_n, memory)
    memory = cs.end_step(x, memory)
    lists = cs._candidates
    calls = []
    measure = ContactSet._pair_geometry
    monkeypatch.setattr(ContactSet, "_pair_geometry", lambda self, *a: (calls.append(self), measure(self, *a))[1])
    pots = cs.potentials(x, x, cs.begin_step(x, memory))
    assert cs._candidates is lists and cs not in calls
    fresh.begin_step(x, None)
    fresh._candidates = lists  # the same lists, their sides measured again
    fresh_pots = fresh.potentials(x, x, fresh.begin_step(x, memory))
    assert fresh in calls
    for a, b in zip(pots[:2], fresh_pots[:2]):
        np.testing.assert_array_equal(a.pairs, b.pairs)
        np.testing.assert_array_equal(a.sides, b.sides)
    assert np.any(pots[1].sides != 0) and len(pots[0].pairs) and len(pots[1].pairs)
