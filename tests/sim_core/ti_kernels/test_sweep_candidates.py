"""Candidate lists with the exclusions inside the sweep kernel equal the NumPy reference lists."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision.candidates import PairFilter, edge_edge_candidates, vertex_triangle_candidates
from sim_core.collision.rest_exclusion import RestExclusion
from sim_core.errors import ConfigError


def _scene(seed: int):
    """A crumpled sheet (self contact, rest-distance exclusion), a floor under it (no self contact)
    and a small cap over it that may touch the sheet but not the floor; vertices jittered."""
    from sim_core.mesh.sheet import grid_sheet, sheet_topology

    rng = np.random.default_rng(seed)
    sheet = grid_sheet((0.04, 0.04), (12, 12), (0.0, 0.0, 0.002))
    sx = sheet.x.copy()
    sx[:, 2] += 0.004 * np.sin(150.0 * sx[:, 0]) * np.cos(120.0 * sx[:, 1])  # folds near each other
    floor = grid_sheet((0.05, 0.05), (6, 6), (-0.005, -0.005, 0.0))  # long edges: wide boxes
    cap = grid_sheet((0.01, 0.01), (5, 5), (0.015, 0.015, 0.007))
    parts = [sheet, floor, cap]
    x_rest = np.concatenate([p.x for p in parts])
    x = np.concatenate([sx, floor.x, cap.x]) + rng.normal(scale=2e-4, size=x_rest.shape)
    offsets = np.cumsum([0] + [len(p.x) for p in parts])
    triangles = np.concatenate([p.triangles + o for p, o in zip(parts, offsets)])
    edges = np.concatenate([sheet_topology(p.triangles)[0] + o for p, o in zip(parts, offsets)])
    vertex_body = np.repeat(np.arange(3), np.diff(offsets))
    allowed = np.array([[True, True, True], [True, False, False], [True, False, False]])
    pair_filter = PairFilter(vertex_body=vertex_body, body_pair_allowed=allowed, x_rest=x_rest,
                             self_rest_distance=0.003)
    return x, np.arange(len(x)), triangles, edges, pair_filter


@pytest.mark.parametrize("seed", range(3))
def test_lists_equal_the_reference_lists(ti_cpu, seed):
    """Same sorted int64 lists as the k-d tree reference with its NumPy exclusions, over several
    radii and successive searches (kept and re-chosen sweep axes), with vertex and triangle subsets
    whose bodies lack some elements."""
    from sim_core.ti_kernels.broad_phase import SweepSearch
    from sim_core.ti_kernels.sweep_candidates import SweepCandidates

    assert_lists_equal_the_reference(seed, lambda v, t, e, f, rest: SweepCandidates(v, t, e, f, rest,
                                                                               SweepSearch(refresh=2)))


def assert_lists_equal_the_reference(seed: int, make):
    """Assert that ``make(vertices, triangles, edges, pair_filter, rest_exclusion)``'s lists equal the
    k-d tree reference's (sorted int64) on :func:`_scene` over several radii and successive searches,
    for all elements and for a subset without the cap's vertices and triangles; returns the scene's
    positions and the last candidate-list object."""
    x, vertices, triangles, edges, pair_filter = _scene(seed)
    rng = np.random.default_rng(100 + seed)
    for subset in (slice(None), slice(0, 144 + 36)):  # all, and no cap vertices/triangles in the lists
        v = vertices[subset]
        t = triangles[(triangles < (len(vertices) if subset == slice(None) else 180)).all(axis=1)]
        rest = RestExclusion(pair_filter, v, t, edges)
        lists = make(v, t, edges, pair_filter, rest)
        for step, radius in enumerate((0.0, 0.0005, 0.002, 0.002, 0.0005)):
            y = x + rng.normal(scale=1e-4, size=x.shape) * step
            vt_ref = vertex_triangle_candidates(y, v, t, radius, pair_filter, rest_exclusion=rest)
            ee_ref = edge_edge_candidates(y, edges, radius, pair_filter, rest_exclusion=rest)
            vt, ee = lists.vertex_triangle(y, radius), lists.edge_edge(y, radius)
            assert vt.dtype == ee.dtype == np.int64
            np.testing.assert_array_equal(vt, vt_ref)
            np.testing.assert_array_equal(ee, ee_ref)
            if radius > 0.001:
                assert len(vt_ref) > 100 and len(ee_ref) > 100
    return x, lists


def test_boxes_exactly_radius_apart_and_an_output_buffer_that_grows(ti_cpu):
    """Boxes whose gap equals the radius on the sweep axis (the inclusive bound of the reference's
    test) are kept, as the reference keeps them; a list longer than the first output buffer (many
    stacked triangles) comes out whole."""
    from sim_core.ti_kernels.broad_phase import SweepSearch
    from sim_core.ti_kernels.sweep_candidates import SweepCandidates

    k = 60  # stacked unit triangles 1 mm apart, points on a line beside them
    tri_x = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])
    x = np.concatenate([tri_x + [0.0, 0.0, 1e-3 * i] for i in range(k)] + [
        np.stack([np.full(k, 0.0125), np.full(k, 0.005), 1e-3 * np.arange(k)], axis=1)])
    triangles = np.arange(3 * k).reshape(k, 3)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    vertex_body = np.concatenate([np.arange(k).repeat(3), np.full(k, k)])
    allowed = np.ones((k + 1, k + 1), bool)
    pair_filter = PairFilter(vertex_body=vertex_body, body_pair_allowed=allowed)
    vertices = np.arange(len(x))
    rest = RestExclusion(pair_filter, vertices, triangles, edges)
    lists = SweepCandidates(vertices, triangles, edges, pair_filter, rest, SweepSearch())
    found = {}
    for radius in (0.0025, 0.03):
        vt_ref = vertex_triangle_candidates(x, vertices, triangles, radius, pair_filter, rest_exclusion=rest)
        ee_ref = edge_edge_candidates(x, edges, radius, pair_filter, rest_exclusion=rest)
        np.testing.assert_array_equal(lists.vertex_triangle(x, radius), vt_ref)
        np.testing.assert_array_equal(lists.edge_edge(x, radius), ee_ref)
        found[radius] = (vt_ref, ee_ref)
    beside = found[0.0025][0][:, 0] >= 3 * k  # the points 2.5 mm beside the triangles, at radius 2.5 mm
    assert np.any(beside)
    assert len(found[0.03][1]) > 2 * 1024  # the edge list outgrew the first output buffer (1024 rows)


def test_filter_without_body_table_or_another_filters_rest_table_is_refused(ti_cpu):
    from sim_core.ti_kernels.broad_phase import SweepSearch
    from sim_core.ti_kernels.sweep_candidates import SweepCandidates

    x, vertices, triangles, edges, pair_filter = _scene(0)
    no_table = PairFilter(vertex_body=pair_filter.vertex_body)
    with pytest.raises(ConfigError, match="body_pair_allowed"):
        SweepCandidates(vertices, triangles, edges, no_table, RestExclusion(no_table, vertices, triangles, edges),
                        SweepSearch())
    with pytest.raises(ConfigError, match="another pair filter"):
        SweepCandidates(vertices, triangles, edges, pair_filter, RestExclusion(no_table, vertices, triangles, edges),
                        SweepSearch())


def test_the_kernel_is_compiled_with_the_step_kernels_before_any_fork(ti_cpu, monkeypatch):
    """``kernel_compile.compile_kernels`` (run in a parent before it forks replay workers) compiles
    the candidate kernel too; its own compile call leaves a launch plan for the lists' signature."""
    from sim_core.energies.membrane.reference import SpringMembrane
    from sim_core.kernel_compile import compile_kernels
    from sim_core.mesh.sheet import grid_sheet, sheet_topology
    from sim_core.ti_kernels import sweep_candidates

    sweep_candidates.compile_kernels()
    assert any(plan is not None for plan in sweep_candidates._sweep_candidates._plans.values())
    calls = []
    monkeypatch.setattr(sweep_candidates, "compile_kernels", lambda: calls.append(1))
    sheet = grid_sheet((0.01, 0.01), (3, 3))
    compile_kernels([SpringMembrane(sheet.triangles, sheet_topology(sheet.triangles)[0], sheet.x, 1.0, 1.0)], sheet.x)
    assert calls == [1]
