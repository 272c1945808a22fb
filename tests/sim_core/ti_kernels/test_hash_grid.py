"""The Taichi spatial-hash broad phase finds exactly the k-d tree reference's box pairs and lists."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision import candidates
from sim_core.collision.candidates import PairFilter
from sim_core.collision.rest_exclusion import RestExclusion
from sim_core.errors import ConfigError
from tests.sim_core.ti_kernels.test_broad_phase import _boxes, _sorted
from tests.sim_core.ti_kernels.test_sweep_candidates import _scene, assert_lists_equal_the_reference


@pytest.mark.parametrize("seed", range(6))
def test_same_pairs_as_the_grouped_kdtree_on_random_boxes(ti_cpu, seed):
    """Random boxes of interleaved bodies with a random body filter, within one set and between two
    (degenerate point boxes included), with and without inflation: the reference's pairs, sorted."""
    from sim_core.ti_kernels.hash_grid import HashSearch, grouped_box_pairs

    rng = np.random.default_rng(seed)
    bodies = 3
    allowed = rng.random((bodies, bodies)) < 0.7
    allowed |= allowed.T
    a_lo, a_hi = _boxes(rng, 300, 1.0, 0.05 * (seed + 1))
    b_lo, b_hi = _boxes(rng, 200, 1.0, 0.05)
    a_body = rng.integers(0, bodies, 300)
    b_body = rng.integers(0, bodies, 200)
    search = HashSearch()  # kept buffers across searches of different sizes
    for args in ((a_lo, a_hi, a_body, None, None, None), (a_lo, a_lo, a_body, b_lo, b_hi, b_body),
                 (a_lo[:50], a_hi[:50], a_body[:50], None, None, None)):
        for radius in (0.0, 0.02):
            ref = _sorted(candidates._grouped_box_pairs(*args, radius, allowed))
            assert len(ref) > 0 or radius == 0.0 or len(args[0]) < 100
            np.testing.assert_array_equal(grouped_box_pairs(*args, radius, allowed), ref)
            np.testing.assert_array_equal(search(*args, radius, allowed), ref)


def test_touching_zero_size_and_empty_boxes(ti_cpu):
    """Boxes exactly ``radius`` apart are pairs, a hair further apart are not; zero-size boxes (all of
    them: the cell size then comes from the scene's extent) pair only at coinciding or inflated
    overlap; an empty set gives no pairs; many pairs outgrow the first output buffer."""
    from sim_core.ti_kernels.hash_grid import grouped_box_pairs

    allowed = np.ones((1, 1), bool)
    lo = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [3.0, 0.0, 0.0], [4.5000001, 0.0, 0.0]])
    np.testing.assert_array_equal(grouped_box_pairs(lo, lo + 1.0, np.zeros(4, int), None, None, None, 0.5, allowed),
                                  [[0, 1], [1, 2]])
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1e-3, 0.0, 0.0], [5.0, 5.0, 5.0]])
    body = np.zeros(4, int)
    np.testing.assert_array_equal(grouped_box_pairs(points, points, body, None, None, None, 0.0, allowed), [[0, 1]])
    np.testing.assert_array_equal(grouped_box_pairs(points, points, body, None, None, None, 1e-3, allowed),
                                  [[0, 1], [0, 2], [1, 2]])
    for radius in (0.0, 5e-4, 3.0):
        ref = candidates._grouped_box_pairs(points, points, body, points[:2], points[:2], body[:2], radius, allowed)
        np.testing.assert_array_equal(grouped_box_pairs(points, points, body, points[:2], points[:2], body[:2],
                                                        radius, allowed), _sorted(ref))
    empty = np.zeros((0, 3))
    assert grouped_box_pairs(empty, empty, np.zeros(0, int), None, None, None, 0.1, allowed).shape == (0, 2)
    assert grouped_box_pairs(lo, lo, body, empty, empty, np.zeros(0, int), 0.1, allowed).shape == (0, 2)
    rng = np.random.default_rng(3)
    lo = rng.uniform(0.0, 0.1, size=(100, 3))
    pairs = grouped_box_pairs(lo, lo + 0.5, np.zeros(100, int), None, None, None, 0.0, allowed)
    assert len(pairs) == 4950


def test_nan_coordinates_are_refused(ti_cpu):
    from sim_core.ti_kernels.hash_grid import grouped_box_pairs

    lo = np.array([[0.0, 0.0, 0.0], [1.0, np.nan, 0.0]])
    allowed = np.ones((1, 1), bool)
    with pytest.raises(ConfigError, match="NaN or infinite"):
        grouped_box_pairs(lo, lo + 1.0, np.zeros(2, int), None, None, None, 0.1, allowed)
    with pytest.raises(ConfigError, match="NaN or infinite"):
        grouped_box_pairs(lo[:1], lo[:1] + 1.0, np.zeros(1, int), lo, lo + 1.0, np.zeros(2, int), 0.1, allowed)


@pytest.mark.parametrize("seed", range(3))
def test_lists_equal_the_reference_lists(ti_cpu, seed):
    """Crumpled sheet (self contact, rest-distance exclusion), floor and cap with a body filter:
    the same sorted int64 lists as the k-d tree reference with its NumPy exclusions, over several
    radii and successive searches, with vertex and triangle subsets."""
    from sim_core.ti_kernels.hash_candidates import HashCandidates

    x, lists = assert_lists_equal_the_reference(seed, HashCandidates)
    y = x.copy()
    y[7, 1] = np.nan
    with pytest.raises(ConfigError, match="NaN or infinite"):
        lists.edge_edge(y, 0.001)


def test_the_search_keeps_the_sorted_keys_of_its_lists_and_the_contact_set_takes_them(ti_cpu):
    """``HashCandidates.keys_of``: the packed keys ``first << 32 | second`` of the lists its last searches returned
    (made by the sort: increasing, equal to the keys made from the pairs again), None for any other array; the
    contact set's candidate lists take them (both lists: the sheet-vs-solid filter is inside the kernel):
    :meth:`CandidateVertices.keys` equal the keys made from the lists."""
    from sim_core.contact_set import ContactSet
    from sim_core.energies.contact.pair_lists import _sorted_keys
    from sim_core.ti_kernels.hash_grid import sorted_pairs_and_keys
    from tests.sim_core.test_contact_set import _forming_model_deformed

    rng = np.random.default_rng(0)
    out = rng.integers(0, 1 << 31, size=(500, 2), dtype=np.int32)
    out[:, 0] = rng.integers(0, 7, size=500)  # pairs sharing a first index, ordered by the second
    out = np.unique(out, axis=0)[rng.permutation(len(np.unique(out, axis=0)))]
    pairs, keys = sorted_pairs_and_keys(out)
    np.testing.assert_array_equal(pairs, np.unique(out.astype(np.int64), axis=0))
    np.testing.assert_array_equal(keys, (pairs[:, 0] << 32) | pairs[:, 1])
    model, x = _forming_model_deformed(1)
    cs = ContactSet(model, broad_phase="spatial_hash", backend="taichi-cpu")
    _, vt, ee = cs._candidate_pairs(x)
    search = cs._candidate_lists(None)
    assert len(vt) > 50 and len(ee) > 50
    for pairs in (vt, ee):
        np.testing.assert_array_equal(search.keys_of(pairs), _sorted_keys(pairs))
    assert search.keys_of(ee.copy()) is None
    lists = cs._list_vertices(vt, ee)
    assert lists.keys()[0] is search.keys_of(vt) and lists.keys()[1] is search.keys_of(ee)
    for pairs, k in zip((vt, ee), lists.keys()):
        np.testing.assert_array_equal(k, _sorted_keys(pairs))


def test_the_lists_two_grids_send_frozen_positions_to_the_device_once(ti_cpu, monkeypatch):
    """CUDA launch path (emulated on the CPU arch: the arch queries answer "cuda", the copies stay host copies): the
    vertex-triangle and edge-edge grids share the positions' device copy; frozen positions (read-only, owning their
    memory) are sent once for both lists and a later search of the same array, writeable ones at every launch; the
    lists equal the host path's."""
    from sim_core import ti_backend
    from sim_core.ti_kernels import buffers, hash_grid
    from sim_core.ti_kernels.hash_candidates import HashCandidates

    x, vertices, triangles, edges, pair_filter = _scene(2)
    make = lambda: HashCandidates(vertices, triangles, edges, pair_filter,  # noqa: E731
                                  RestExclusion(pair_filter, vertices, triangles, edges))
    host = make()
    want = (host.vertex_triangle(x, 0.002), host.edge_edge(x, 0.002))
    assert len(want[0]) > 20 and len(want[1]) > 20
    for module in (hash_grid, ti_backend):
        monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    sent = []
    from_numpy = buffers._from_numpy
    monkeypatch.setattr(buffers, "_from_numpy", lambda dev, host: (sent.append(host), from_numpy(dev, host))[1])
    lists = make()
    assert lists.vt_grid._positions is lists.ee_grid._positions
    frozen = x.copy()
    frozen.flags.writeable = False
    for positions, uploads in ((frozen, (1, 0)), (x.copy(), (2, 2))):  # two searches of the same array each
        for expected in uploads:
            sent.clear()
            got = (lists.vertex_triangle(positions, 0.002), lists.edge_edge(positions, 0.002))
            for pairs, reference in zip(got, want):
                np.testing.assert_array_equal(pairs, reference)
            assert sum(host is positions for host in sent) == expected


def test_filter_without_body_table_or_another_filters_rest_table_is_refused(ti_cpu):
    from sim_core.ti_kernels.hash_candidates import HashCandidates

    x, vertices, triangles, edges, pair_filter = _scene(0)
    no_table = PairFilter(vertex_body=pair_filter.vertex_body)
    with pytest.raises(ConfigError, match="body_pair_allowed"):
        HashCandidates(vertices, triangles, edges, no_table, RestExclusion(no_table, vertices, triangles, edges))
    with pytest.raises(ConfigError, match="another pair filter"):
        HashCandidates(vertices, triangles, edges, pair_filter, RestExclusion(no_table, vertices, triangles, edges))


def test_the_kernel_is_compiled_with_the_step_kernels(ti_cpu, monkeypatch):
    """``kernel_compile.compile_kernels`` (run before replay workers fork) compiles the hash kernel too."""
    from sim_core.energies.membrane.reference import SpringMembrane
    from sim_core.kernel_compile import compile_kernels
    from sim_core.mesh.sheet import grid_sheet, sheet_topology
    from sim_core.ti_kernels import hash_candidates, hash_grid

    hash_candidates.compile_kernels()
    assert hash_grid._hash_pairs._primal.compiled_kernels  # the grids launch it through plans of their own
    calls = []
    monkeypatch.setattr(hash_candidates, "compile_kernels", lambda: calls.append(1))
    sheet = grid_sheet((0.01, 0.01), (3, 3))
    compile_kernels([SpringMembrane(sheet.triangles, sheet_topology(sheet.triangles)[0], sheet.x, 1.0, 1.0)], sheet.x)
    assert calls == [1]


@pytest.mark.parametrize("seed, sheet_vs_solid", [(0, False), (1, False), (0, True)])
def test_every_broad_phase_gives_the_same_contact_lists_on_the_taichi_path(ti_cpu, seed, sheet_vs_solid):
    """Forming's sheet + gel + table model, deformed, on the Taichi backend: the hash kernel (the
    default), the sweep and the k-d trees give the same sorted lists over successive searches; the sheet's vertices
    against the gel's triangles left out inside the hash and sweep kernels (their vertex-triangle body table) equal
    the k-d trees' lists filtered on the host (``sheet_vertices_off_solids``), and are there with
    ``sheet_vertices_vs_solids`` on; the setting changed between searches is followed."""
    from sim_core.contact_set import ContactSet
    from tests.sim_core.test_contact_set import _forming_model_deformed

    model, x = _forming_model_deformed(seed)
    model.contact.sheet_vertices_vs_solids = sheet_vs_solid
    sets = {name: ContactSet(model, broad_phase=name, backend="taichi-cpu") for name in ("spatial_hash", "sweep", "kdtree")}
    sheet_vertex, solid_triangle = sets["kdtree"]._sheet_vertex, sets["kdtree"]._solid_triangle
    rng = np.random.default_rng(seed)
    for on in (sheet_vs_solid, sheet_vs_solid, not sheet_vs_solid):
        model.contact.sheet_vertices_vs_solids = on
        lists = {name: cs._candidate_pairs(x)[1:] for name, cs in sets.items()}
        for name in ("spatial_hash", "sweep"):
            np.testing.assert_array_equal(lists[name][0], lists["kdtree"][0])
            np.testing.assert_array_equal(lists[name][1], lists["kdtree"][1])
        assert len(lists["kdtree"][0]) > 50 and len(lists["kdtree"][1]) > 50
        vt = lists["kdtree"][0]
        sheet_on_solid = np.count_nonzero(sheet_vertex[vt[:, 0]] & solid_triangle[vt[:, 1]])
        assert (sheet_on_solid > 0) if on else (sheet_on_solid == 0)
        x = x + rng.normal(scale=1e-3, size=x.shape)  # beyond margin / 2: searched again
    from sim_core.ti_kernels.hash_candidates import HashCandidates

    assert isinstance(sets["spatial_hash"]._candidate_lists(None), HashCandidates)


def test_forming_trajectory_is_the_same_with_every_broad_phase(ti_cpu):
    """Six steps of the Forming benchmark on the Taichi CPU backend with each broad phase: the
    same Newton iterations and positions (to round-off: the candidate lists are identical)."""
    from pathlib import Path

    import yaml

    from sim_core.control import Control
    from sim_core.scenes.task_scene import build_task_scene, task_initial_state
    from sim_core.simulation import Simulation
    from sim_core.solver import SolverConfig
    from sim_core.tasks.trajectories import forming_benchmark_offsets, pose_targets

    scene_path = Path(__file__).resolve().parents[3] / "config" / "scenes" / "forming.yaml"
    runs = {}
    for name in ("spatial_hash", "sweep", "kdtree"):
        scene = yaml.safe_load(scene_path.read_text())
        scene["contact"]["broad_phase"] = name
        model = build_task_scene(scene)
        sim = Simulation(model, solver_config=SolverConfig(backend="taichi-cpu"))
        sim.state = task_initial_state(model)
        effector = next(iter(model.effectors))
        targets = pose_targets(model.effectors[effector].initial_pose, forming_benchmark_offsets(6))
        iterations = []
        for target in targets[:6]:
            control = Control()
            control.effector_pose_target[effector] = target
            iterations.append(sim.step(control).iterations)
        runs[name] = (iterations, sim.state.x.copy(), sim.state.contact_force.copy())
    ref_iterations, ref_x, ref_force = runs["kdtree"]
    assert np.max(np.abs(ref_force)) > 0  # the dome presses the sheet: contact is exercised
    for name in ("spatial_hash", "sweep"):
        iterations, x, force = runs[name]
        assert iterations == ref_iterations
        np.testing.assert_allclose(x, ref_x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(force, ref_force, rtol=0, atol=1e-9 * np.max(np.abs(ref_force)))
