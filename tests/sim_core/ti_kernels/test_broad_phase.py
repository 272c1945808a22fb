"""The Taichi sweep broad phase finds exactly the k-d tree reference's box pairs (no pair missed)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision import candidates
from sim_core.collision.candidates import PairFilter, edge_edge_candidates, vertex_triangle_candidates


def _sorted(pairs: np.ndarray) -> np.ndarray:
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def _boxes(rng, count, spread, size):
    lo = rng.uniform(0.0, spread, size=(count, 3))
    return lo, lo + rng.uniform(0.0, size, size=(count, 3))


@pytest.mark.parametrize("seed", range(6))
def test_same_pairs_as_the_grouped_kdtree(ti_cpu, seed):
    from sim_core.ti_kernels.broad_phase import grouped_box_pairs

    rng = np.random.default_rng(seed)
    bodies = 3
    allowed = rng.random((bodies, bodies)) < 0.7
    allowed |= allowed.T
    a_lo, a_hi = _boxes(rng, 300, 1.0, 0.05)
    b_lo, b_hi = _boxes(rng, 200, 1.0, 0.05)
    a_body = rng.integers(0, bodies, 300)  # bodies interleaved: the pair orientation rule matters
    b_body = rng.integers(0, bodies, 200)
    for args in ((a_lo, a_hi, a_body, None, None, None), (a_lo, a_lo, a_body, b_lo, b_hi, b_body),
                 (a_lo, a_hi, np.sort(a_body), b_lo, b_hi, b_body)):
        for radius in (0.0, 0.02):
            ref = candidates._grouped_box_pairs(*args, radius, allowed)
            new = grouped_box_pairs(*args, radius, allowed)
            assert len(ref) > 0 or radius == 0.0
            np.testing.assert_array_equal(_sorted(new), _sorted(ref))
            if args[3] is None:
                assert np.all(new[:, 0] < new[:, 1])


def test_touching_boxes_and_a_full_output_buffer(ti_cpu):
    """Boxes exactly ``radius`` apart are pairs, a hair further apart are not; 4950 pairs overflow the first buffer (run again)."""
    from sim_core.ti_kernels.broad_phase import grouped_box_pairs

    allowed = np.ones((1, 1), bool)
    lo = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [3.0, 0.0, 0.0], [4.5000001, 0.0, 0.0]])
    hi = lo + 1.0
    pairs = grouped_box_pairs(lo, hi, np.zeros(4, int), None, None, None, 0.5, allowed)
    np.testing.assert_array_equal(_sorted(pairs), [[0, 1], [1, 2]])
    ref = candidates._grouped_box_pairs(lo, hi, np.zeros(4, int), None, None, None, 0.5, allowed)
    np.testing.assert_array_equal(_sorted(pairs), _sorted(ref))
    rng = np.random.default_rng(3)
    lo = rng.uniform(0.0, 0.1, size=(100, 3))
    hi = lo + 0.5  # every pair overlaps
    pairs = grouped_box_pairs(lo, hi, np.zeros(100, int), None, None, None, 0.0, allowed)
    assert len(pairs) == 4950
    np.testing.assert_array_equal(_sorted(pairs), _sorted(
        candidates._grouped_box_pairs(lo, hi, np.zeros(100, int), None, None, None, 0.0, allowed)))


def test_empty_sets(ti_cpu):
    from sim_core.ti_kernels.broad_phase import grouped_box_pairs

    empty = np.zeros((0, 3))
    one = np.zeros((1, 3))
    allowed = np.ones((1, 1), bool)
    assert grouped_box_pairs(empty, empty, np.zeros(0, int), one, one, np.zeros(1, int), 0.1, allowed).shape == (0, 2)
    assert grouped_box_pairs(one, one, np.zeros(1, int), None, None, None, 0.1, allowed).shape == (0, 2)


def test_candidate_lists_of_a_crumpled_sheet_over_a_block(ti_cpu):
    """Vertex-triangle and edge-edge candidates (with self contact and rest-distance filter) are identical."""
    from sim_core.mesh.sheet import grid_sheet, sheet_topology
    from sim_core.ti_kernels.broad_phase import grouped_box_pairs

    rng = np.random.default_rng(7)
    sheet = grid_sheet((0.04, 0.04), (12, 12), (0.0, 0.0, 0.002))
    sx = sheet.x.copy()
    sx[:, 2] += 0.004 * np.sin(150.0 * sx[:, 0]) * np.cos(120.0 * sx[:, 1])  # folds near each other
    floor = grid_sheet((0.05, 0.05), (10, 10), (-0.005, -0.005, 0.0))
    x = np.concatenate([sx, floor.x]) + rng.normal(scale=2e-4, size=(len(sx) + len(floor.x), 3))
    x_rest = np.concatenate([sheet.x, floor.x])
    ns = len(sheet.x)
    triangles = np.concatenate([sheet.triangles, floor.triangles + ns])
    edges = np.concatenate([sheet_topology(sheet.triangles)[0], sheet_topology(floor.triangles)[0] + ns])
    vertex_body = np.repeat([0, 1], [ns, len(floor.x)])
    exclude = PairFilter(vertex_body=vertex_body, body_pair_allowed=np.array([[True, True], [True, False]]),
                         x_rest=x_rest, self_rest_distance=0.003)
    vertices = np.arange(len(x))
    for radius in (0.0005, 0.002):
        vt_ref = vertex_triangle_candidates(x, vertices, triangles, radius, exclude)
        vt_new = vertex_triangle_candidates(x, vertices, triangles, radius, exclude, grouped_search=grouped_box_pairs)
        ee_ref = edge_edge_candidates(x, edges, radius, exclude)
        ee_new = edge_edge_candidates(x, edges, radius, exclude, grouped_search=grouped_box_pairs)
        assert len(vt_ref) > 0 and len(ee_ref) > 0
        np.testing.assert_array_equal(vt_new, vt_ref)
        np.testing.assert_array_equal(ee_new, ee_ref)


def test_sweep_search_keeps_its_axis_between_choices_and_finds_the_same_pairs(ti_cpu, monkeypatch):
    """Boxes spread along x (so x leaves the fewest to scan), then along z as they move: every search
    gives the reference's pairs; the axis is chosen again (3 sorts) only every ``refresh`` searches of
    a kind, the searches between sort once."""
    from sim_core.errors import ConfigError
    from sim_core.ti_kernels import broad_phase

    rng = np.random.default_rng(40)
    allowed = np.ones((2, 2), bool)
    sorts = []
    argsort = np.argsort
    monkeypatch.setattr(broad_phase.np, "argsort", lambda *a, **k: (sorts.append(1), argsort(*a, **k))[1])
    search = broad_phase.SweepSearch(refresh=3)
    stretch = np.array([5.0, 0.2, 0.2])  # x the long axis
    a_lo, b_lo = rng.uniform(0.0, 1.0, size=(300, 3)) * stretch, rng.uniform(0.0, 1.0, size=(200, 3)) * stretch
    a_hi, b_hi = a_lo + 0.05, b_lo + 0.05
    a_body, b_body = rng.integers(0, 2, 300), rng.integers(0, 2, 200)
    axes, counts = [], []
    for k in range(7):
        if k == 4:  # the layout turns: now z is the long axis
            a_lo, a_hi, b_lo, b_hi = (v[:, ::-1].copy() for v in (a_lo, a_hi, b_lo, b_hi))
        for args in ((a_lo, a_hi, a_body, None, None, None), (a_lo, a_hi, a_body, b_lo, b_hi, b_body)):
            sorts.clear()
            pairs = search(*args, 0.01, allowed)
            ref = candidates._grouped_box_pairs(*args, 0.01, allowed)
            assert len(ref) > 0
            np.testing.assert_array_equal(_sorted(pairs), _sorted(ref))
            counts.append(len(sorts))
        axes.append([search.axes[kind][0] for kind in sorted(search.axes)])
    assert counts == [3, 3, 1, 1, 1, 1, 3, 3, 1, 1, 1, 1, 3, 3]
    assert axes[:6] == [[0, 0]] * 6 and axes[6] == [2, 2]  # x kept through the turn, z after the next choice
    with pytest.raises(ConfigError):
        broad_phase.SweepSearch(refresh=0)
