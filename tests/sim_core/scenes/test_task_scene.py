"""Task scenes (kind: task), the dome mesh, the Forming trajectory and task rewards."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from sim_core.energies.hinge_bending.reference import dihedral_angle
from sim_core.errors import ConfigError
from sim_core.mesh.dome import dome_shell, dome_vertex_count
from sim_core.mesh.tet import tet_boundary_triangles
from sim_core.mesh.validate import tet_signed_volumes
from sim_core.scenes.task_scene import build_task_scene, hairpin_fold, task_initial_state
from sim_core.tasks import crease_columns, folding_reward, forming_benchmark_offsets, forming_reward, pose_targets

SCENES = Path(__file__).resolve().parents[3] / "config" / "scenes"


def _scene(name: str) -> dict:
    return yaml.safe_load((SCENES / f"{name}.yaml").read_text())


def test_forming_scene_counts():
    model = build_task_scene(_scene("forming"))
    assert model.dof_count == 1698 and model.vertex_count == 566
    sizes = {k: b.vertex_stop - b.vertex_start for k, b in model.bodies.items()}
    assert sizes == {"sheet": 128, "table": 162, "dome": 276}
    assert model.bodies["table"].kind == "frozen" and model.vertex_fixed[model.bodies["table"].vertices].all()
    sheet = model.bodies["sheet"]
    fixed = np.flatnonzero(model.vertex_fixed[sheet.vertices])
    assert fixed.size == 8 and np.all(fixed % 16 == 15)  # last grid column (ThinShellLab's last row)
    assert np.allclose(model.gravity, 0.0) and model.contact.stiffness == 2e4 and model.contact.eps == 4e-4
    assert model.friction_coefficient("dome", "sheet") == 5.0
    dx = 0.1 / 15
    assert model.get_parameter("sheet.bending_stiffness") == pytest.approx(2 * 200 * dx**2 / 9)
    assert model.meta["membrane"]["sheet"] == {"model": "spring", "k_length": 1000.0, "k_area": 1000.0}
    assert model.meta["dt"] == 0.005 and model.meta["task"]["horizon"] == 50


def test_folding_and_card_scenes_build():
    folding = build_task_scene(_scene("folding"))
    assert folding.get_parameter("sheet.yield_angle") == 0.5
    card = build_task_scene(_scene("card"))
    assert card.meta["task"]["type"] == "inverse"
    assert card.meta["task"]["identify"] == [f"card_{i}.bending_stiffness" for i in range(3)]
    assert len(card.effectors) == 3


def test_dome_mesh_has_276_nodes_positive_volumes_and_watertight_boundary():
    dome = dome_shell(0.0075, 0.00375)
    x, tets = dome.mesh
    assert x.shape == (276, 3) == (dome_vertex_count(3, 5, 6), 3)
    vol = tet_signed_volumes(x, tets)
    assert np.all(vol > 0)
    exact = 2.0 / 3.0 * np.pi * (0.0075**3 - 0.00375**3)
    assert 0.85 * exact < vol.sum() < exact  # inscribed polyhedral shell
    faces = tet_boundary_triangles(tets, x)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # closed 2-manifold
    v = np.unique(faces).size
    assert v - counts.size + faces.shape[0] == 2  # sphere topology (a ball-like solid)
    # outward orientation: divergence theorem gives the enclosed volume with the right sign
    a, b, c = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0 == pytest.approx(vol.sum())
    assert np.allclose(np.linalg.norm(x[dome.inner_vertices], axis=1), 0.00375)
    assert np.allclose(x[dome.base_vertices, 2], 0.0, atol=1e-12)


def test_hairpin_fold_is_isometric_and_places_layers():
    from sim_core.mesh.sheet import grid_sheet, sheet_topology

    mesh = grid_sheet((0.1, 0.1 * 7 / 15), (16, 8), (-0.07, -0.02, 0.00035))
    x, r = hairpin_fold(mesh.x, (16, 8), 10, 5)
    topo = sheet_topology(mesh.triangles)
    e = topo.edges
    assert np.allclose(np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1), np.linalg.norm(mesh.x[e[:, 0]] - mesh.x[e[:, 1]], axis=1))
    assert r == pytest.approx((0.1 / 15) / (2 * np.sin(np.pi / 10)))
    assert np.allclose(x[np.arange(128) % 16 >= 10, 2], 0.00035)
    assert np.allclose(x[np.arange(128) % 16 <= 5, 2], 0.00035 + 2 * r)
    theta = dihedral_angle(x[topo.hinges])
    creases = crease_columns(topo.hinges, 16)
    # chordal half circle with tangent straight layers: pi/n inside, pi/(2n) at both ends, pi in all
    assert np.allclose(np.abs(theta[np.isin(creases, [6, 7, 8, 9])]), np.pi / 5)
    assert np.allclose(np.abs(theta[np.isin(creases, [5, 10])]), np.pi / 10)
    assert np.allclose(theta[~np.isin(creases, [5, 6, 7, 8, 9, 10])], 0.0, atol=1e-9)
    assert abs(theta[creases >= 0].sum()) / 7 == pytest.approx(np.pi)  # 7 hinges per column


def test_rest_angles_initial_reaches_the_state():
    scene = _scene("folding")
    scene["sheets"]["sheet"]["rest_angles"] = "initial"
    model = build_task_scene(scene)
    tb = task_initial_state(model).hinge_theta_bar["sheet"]
    creases = crease_columns(model.bodies["sheet"].hinges - model.bodies["sheet"].vertex_start, 16)
    # 3 curve segments between columns 6 and 9, 3 crease hinges per column (ny = 4)
    assert np.count_nonzero(np.abs(tb) > 1e-6) == 4 * 3
    assert np.allclose(np.abs(tb[np.isin(creases, [7, 8])]), np.pi / 3)
    assert np.allclose(np.abs(tb[np.isin(creases, [6, 9])]), np.pi / 6)
    np.testing.assert_allclose(model.state().hinge_theta_bar["sheet"], tb)  # Model.state() seeds the crease too


@pytest.mark.parametrize("path, key", [
    (("contact",), "stifness"),
    (("sheets", "sheet"), "colour"),
    (("sheets", "sheet", "membrane"), "k_lenght"),
    (("effectors", "dome"), "radius"),
    ((), "gravty"),
])
def test_unknown_keys_are_rejected_by_name(path, key):
    scene = copy.deepcopy(_scene("forming"))
    block = scene
    for p in path:
        block = block[p]
    block[key] = 1.0
    with pytest.raises(ConfigError, match=rf"unknown key .*{key}"):
        build_task_scene(scene)


def test_bad_values_are_rejected():
    scene = _scene("forming")
    scene["sheets"]["sheet"]["density"] = 700.0
    with pytest.raises(ConfigError, match="exactly one of density"):
        build_task_scene(scene)
    scene = _scene("card")
    scene["task"]["identify"] = ["card_0.bending_stifness"]
    with pytest.raises(ConfigError, match="unknown parameter 'card_0.bending_stifness'"):
        build_task_scene(scene)
    scene = _scene("forming")
    scene["kind"] = "tactile"
    with pytest.raises(ConfigError, match="kind must be 'task'"):
        build_task_scene(scene)


@pytest.mark.parametrize("step, expected", [
    (1, (0.00023, -0.00011)),
    (19, (19 * 0.00023, -19 * 0.00011)),
    (20, (19 * 0.00023 + 0.00027, -19 * 0.00011 - 0.0002)),
    (34, (19 * 0.00023 + 15 * 0.00027, -19 * 0.00011 - 15 * 0.0002)),
    (35, (19 * 0.00023 + 15 * 0.00027 + 0.0002, -19 * 0.00011 - 15 * 0.0002)),
    (49, (19 * 0.00023 + 15 * 0.00027 + 15 * 0.0002, -19 * 0.00011 - 15 * 0.0002)),
])
def test_forming_trajectory_matches_design(step, expected):
    offsets = forming_benchmark_offsets()
    assert offsets.shape == (49, 3)
    assert offsets[step - 1] == pytest.approx((expected[0], 0.0, expected[1]), abs=1e-12)
    assert np.max(np.linalg.norm(np.diff(offsets, axis=0), axis=1)) < 1e-3  # within the 1 mm/step limit
    poses = pose_targets(np.array([0.1, 0.0, 0.2, 1.0, 0.0, 0.0, 0.0]), offsets)
    assert np.allclose(poses[:, 3:], [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ConfigError, match="1..49"):
        forming_benchmark_offsets(50)


def test_rewards():
    x = np.random.default_rng(0).normal(size=(5, 3))
    assert forming_reward(x, x) == 0.0
    assert forming_reward(x + [0.0, 0.0, 0.1], x) == pytest.approx(-5 * 0.01)
    hinges = np.array([[7, 23, 6, 8], [8, 24, 7, 9], [7, 8, 23, 24]])  # nx = 16: columns 7, 8, diagonal
    tb = np.array([0.3, -0.2, 5.0])
    assert folding_reward(tb, hinges, 16, {7: 1.0, 8: -1.0}) == pytest.approx(-0.3 - 0.2)
    with pytest.raises(ConfigError, match="column 3 has no crease"):
        folding_reward(tb, hinges, 16, {3: 1.0})


@pytest.mark.parametrize("name", ["spatial_hash", "sweep", "kdtree"])
def test_contact_broad_phase_is_parsed(name):
    scene = _scene("forming")
    assert build_task_scene(scene).contact.broad_phase == "spatial_hash"  # the default
    scene["contact"]["broad_phase"] = name
    assert build_task_scene(scene).contact.broad_phase == name


def test_an_unknown_broad_phase_is_rejected_by_key():
    scene = _scene("forming")
    scene["contact"]["broad_phase"] = "octree"
    with pytest.raises(ConfigError, match=r"contact\.broad_phase: unknown broad phase 'octree'.*spatial_hash"):
        build_task_scene(scene)
