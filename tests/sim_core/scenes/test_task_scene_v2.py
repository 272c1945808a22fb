"""Task scenes version 2: grippers, rigid effectors, blocks, arched boxes, pinned sets, creases and mesh
objects, each built and simulated a few steps; version-1 files unchanged."""

from __future__ import annotations

import copy
from pathlib import Path

import meshio
import numpy as np
import pytest
import yaml

from sim_core.control import Control
from sim_core.energies.hinge_bending.reference import dihedral_angle
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.tet import tet_box
from sim_core.scenes import load_scene
from sim_core.scenes.task_scene import build_task_scene
from sim_core.simulation import Simulation
from sim_core.transforms import quat_to_matrix

SCENES = Path(__file__).resolve().parents[3] / "config" / "scenes"

SHEET = {"size": [0.02, 0.02], "resolution": [6, 6], "origin": [-0.01, -0.01, 0.0004], "thickness": 0.001,
         "areal_density": 40.0, "membrane": {"model": "spring", "k_length": 1000.0, "k_area": 1000.0},
         "bending": {"k_bend_thinshelllab": 100.0}, "yield_angle": 3.14, "clamped_edge": "none"}
GEL = {"youngs_modulus": 3.0e5, "poisson_ratio": 0.2, "density": 2000.0}


def v2_scene() -> dict:
    """A small version-2 scene with one of each new element."""
    return {
        "kind": "task", "version": 2, "name": "v2", "dt": 0.005, "gravity": [0.0, 0.0, -9.8],
        "contact": {"stiffness": 1.0e4, "eps": 4.0e-4, "self_contact": False},
        "sheets": {"sheet": {**SHEET, "pinned": [{"edge": "x0"}, {"vertices": [35]}],
                             "creases": [{"column": 3, "rest_angle": 0.3}]}},
        "boxes": {"table": {"size": [0.03, 0.03, 0.004], "resolution": [4, 4, 2], "origin": [-0.015, -0.015, -0.004],
                            "frozen": True, "arch_height": 0.002}},
        "blocks": {"cube": {"size": [0.004, 0.004, 0.004], "resolution": [2, 2, 2], "origin": [0.0, 0.0, 0.003],
                            "mode": "free", "mass": 0.001},
                   "wall": {"size": [0.002, 0.02, 0.004], "resolution": [2, 3, 2], "origin": [0.02, -0.01, 0.0],
                            "mode": "kinematic"}},
        "effectors": {"grip": {"shape": "gripper", "opening": 0.012, "axis": [1.0, 0.0, 0.0], "material": GEL,
                               "finger": {"shape": "pad", "size": [0.004, 0.004, 0.002], "resolution": [2, 2, 2],
                                          "rigid": True},
                               "initial_pose": [0.0, 0.0, 0.02, 0.0, 0.0, 0.0, 1.0], "max_translation_per_step": 0.002}},
        "friction": [{"pair": ["grip", "cube"], "mu": 1.0}, {"pair": ["table", "sheet"], "mu": 0.5}],
    }


def test_version_1_scenes_load_unchanged_and_reject_version_2_keys():
    forming = yaml.safe_load((SCENES / "forming.yaml").read_text())
    model = build_task_scene(forming)
    assert model.vertex_count == 566 and model.meta["version"] == 1
    assert model.meta["tactile_effectors"] == ["dome"] and model.effectors["dome"].finger_sign is None
    assert len(model.effectors["dome"].vertices) == 121  # mount only: inner surface + base
    bad = copy.deepcopy(forming)
    bad["sheets"]["sheet"]["pinned"] = [{"edge": "x0"}]
    with pytest.raises(ConfigError, match=r"unknown key sheets.sheet.pinned \(a version-2 key: set version: 2\)"):
        build_task_scene(bad)
    bad = copy.deepcopy(forming)
    bad["blocks"] = {}
    with pytest.raises(ConfigError, match=r"unknown key <top>.blocks \(a version-2 key"):
        build_task_scene(bad)


def test_unknown_version_2_key_is_named_with_its_path():
    scene = v2_scene()
    scene["effectors"]["grip"]["finger"]["stiffness"] = 1.0
    with pytest.raises(ConfigError, match=r"unknown key effectors.grip.finger.stiffness"):
        build_task_scene(scene)
    scene = v2_scene()
    scene["blocks"]["cube"]["density"] = 1000.0
    with pytest.raises(ConfigError, match=r"blocks.cube \(free\) needs exactly one of mass"):
        build_task_scene(scene)


def test_version_2_elements_build():
    model = build_task_scene(v2_scene())
    sheet, cube, wall = model.bodies["sheet"], model.bodies["cube"], model.bodies["wall"]
    # pinned: edge x0 (6 vertices) and vertex 35
    fixed = np.flatnonzero(model.vertex_fixed[sheet.vertices])
    assert set(fixed) == set(range(0, 36, 6)) | {35}
    # free block: its mass is the given mass; kinematic block: all vertices fixed
    assert model.vertex_mass()[cube.vertices].sum() == pytest.approx(0.001)
    assert cube.kind == "solid" and model.vertex_fixed[wall.vertices].all() and wall.kind == "frozen"
    # arched box: the middle of the top raised by 2 mm, the ends not
    table = model.x_rest[model.bodies["table"].vertices]
    assert table[:, 2].max() == pytest.approx(0.002 * np.sin(np.pi / 3))  # 4 nodes along x: u = 1/3, 2/3
    assert table[np.isclose(table[:, 0], -0.015), 2].max() == pytest.approx(0.0)
    # crease: rest angle 0.3 rad on the hinges along grid column 3, 0 elsewhere
    theta_bar = model.state().hinge_theta_bar["sheet"]
    h = sheet.hinges - sheet.vertex_start
    on = (h[:, 0] % 6 == 3) & (h[:, 1] % 6 == 3)
    assert on.sum() == 5 and np.allclose(theta_bar[on], 0.3) and np.allclose(theta_bar[~on], 0.0)
    # gripper: two rigid pads facing each other along x, every vertex driven, signs +1 / -1
    eff = model.effectors["grip"]
    grip = model.bodies["grip"]
    assert len(eff.vertices) == grip.vertex_stop - grip.vertex_start == 16
    assert eff.initial_opening == 0.012 and sorted(set(eff.finger_sign)) == [-1.0, 1.0]
    x = model.x_rest[eff.vertices]
    assert np.all(x[eff.finger_sign > 0, 0] > 0.003) and np.all(x[eff.finger_sign < 0, 0] < -0.003)
    assert model.meta["tactile_effectors"] == []


def test_version_2_scene_simulates_and_the_gripper_opening_follows_its_target():
    model = build_task_scene(v2_scene())
    sim = Simulation(model)
    eff = model.effectors["grip"]
    x0 = sim.state.x.copy()
    theta0 = dihedral_angle(x0[model.bodies["sheet"].hinges])
    for opening in (0.011, 0.010, 0.009):
        sim.step(Control(gripper_target={"grip": opening}))
    x = sim.state.x
    assert sim.state.gripper_opening["grip"] == pytest.approx(0.009) and np.all(np.isfinite(x))
    # rigid fingers: each moved by -1.5 mm along +-x (the axis), in the effector frame = world here
    dx = x[eff.vertices] - x0[eff.vertices]
    np.testing.assert_allclose(dx[:, 0], -eff.finger_sign * 0.0015, atol=1e-12)
    np.testing.assert_allclose(dx[:, 1:], 0.0, atol=1e-12)
    # pinned vertices stay; the free block falls under gravity; the crease folds the sheet
    sheet = model.bodies["sheet"]
    pinned = sheet.vertex_start + np.array([0, 6, 12, 18, 24, 30, 35])
    np.testing.assert_array_equal(x[pinned], x0[pinned])
    cube = model.bodies["cube"].vertices
    assert np.mean(x[cube, 2] - x0[cube, 2]) < -1e-5
    theta = dihedral_angle(x[sheet.hinges])
    h = sheet.hinges - sheet.vertex_start
    on = (h[:, 0] % 6 == 3) & (h[:, 1] % 6 == 3)
    assert np.mean(theta[on] - theta0[on]) > 1e-4  # towards the 0.3 rad rest angle


def test_tactile_gripper_drives_the_mounts_and_orients_domes_towards_each_other():
    scene = v2_scene()
    scene["effectors"]["grip"]["finger"] = {"shape": "dome", "outer_radius": 0.0075, "inner_radius": 0.00375,
                                            "mesh": {"ring_step": 3, "ring_count": 2, "layer_count": 2}}
    scene["effectors"]["grip"]["opening"] = 0.03
    scene["effectors"]["grip"]["axis"] = [0.0, 0.0, 1.0]
    scene["effectors"]["grip"]["initial_pose"] = [0.0, 0.0, 0.0004, 0.0, 0.0, 0.0, 1.0]
    model = build_task_scene(scene)
    grip = model.bodies["grip"]
    assert model.meta["tactile_effectors"] == ["grip"] and len(model.effectors["grip"].vertices) < grip.vertex_stop - grip.vertex_start
    x = model.x_rest[grip.vertices]
    half = x.shape[0] // 2
    upper, lower = x[:half], x[half:]
    # upper dome: base at z = 0.0154, apex 7.5 mm lower; lower dome mirrored
    assert upper[:, 2].min() == pytest.approx(0.0004 + 0.015 - 0.0075) and upper[:, 2].max() == pytest.approx(0.0154)
    assert lower[:, 2].max() == pytest.approx(0.0004 - 0.015 + 0.0075) and lower[:, 2].min() == pytest.approx(0.0004 - 0.015)


def _write_obj(path: Path, vertices, faces) -> None:
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in vertices) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))


def test_mesh_objects_from_files_build_and_simulate(tmp_path):
    _write_obj(tmp_path / "patch.obj", [(0, 0, 0), (0.01, 0, 0), (0, 0.01, 0), (0.01, 0.01, 0)], [(0, 1, 2), (1, 3, 2)])
    box = tet_box((0.004, 0.004, 0.004), (2, 2, 2), (0.0, 0.0, 0.0))
    meshio.write(tmp_path / "block.msh", meshio.Mesh(box.x, [("tetra", box.tets)]), file_format="gmsh22", binary=False)
    scene = v2_scene()
    scene["meshes"] = {
        "patch": {"file": "patch.obj", "kind": "sheet", "translation": [0.03, 0.0, 0.0], "pinned": [{"vertices": [0, 1]}],
                  "material": {"youngs_modulus": 1.0e6, "poisson_ratio": 0.3, "thickness": 0.001, "density": 100.0,
                               "bending_stiffness": 1.0e-4}},
        "rock": {"file": "block.msh", "kind": "solid", "scale": 1.0, "translation": [0.03, 0.0, 0.01], "material": GEL},
    }
    model = build_task_scene(scene, base_dir=tmp_path)
    patch, rock = model.bodies["patch"], model.bodies["rock"]
    assert patch.kind == "sheet" and patch.vertex_stop - patch.vertex_start == 4
    assert rock.kind == "solid" and rock.tets.shape[0] == box.tets.shape[0]
    np.testing.assert_allclose(model.x_rest[patch.vertices][:, 0].min(), 0.03)
    sim = Simulation(model)
    for _ in range(2):
        sim.step()
    x = sim.state.x
    assert np.all(np.isfinite(x)) and np.mean(x[rock.vertices, 2] - model.x_rest[rock.vertices, 2]) < 0  # falls
    np.testing.assert_array_equal(x[patch.vertices[:2]], model.x_rest[patch.vertices[:2]])


def test_degenerate_mesh_file_is_named_with_the_element(tmp_path):
    path = tmp_path / "bad.obj"
    _write_obj(path, [(0, 0, 0), (0.01, 0, 0), (0, 0.01, 0), (0.02, 0, 0)], [(0, 1, 2), (0, 1, 3)])  # 2nd collinear
    scene = v2_scene()
    scene["meshes"] = {"bad": {"file": str(path), "kind": "sheet",
                               "material": {"youngs_modulus": 1.0e6, "poisson_ratio": 0.3, "thickness": 0.001,
                                            "density": 100.0, "bending_stiffness": 1.0e-4}}}
    with pytest.raises(MeshError, match=r"bad\.obj.*triangle 1"):
        build_task_scene(scene)
    scene["meshes"]["bad"]["kind"] = "solid"
    scene["meshes"]["bad"]["file"] = str(tmp_path / "missing.stl")
    with pytest.raises(ConfigError, match=r"missing\.stl"):
        build_task_scene(scene)


def test_load_scene_resolves_mesh_files_next_to_the_scene(tmp_path):
    _write_obj(tmp_path / "patch.obj", [(0, 0, 0), (0.01, 0, 0), (0, 0.01, 0)], [(0, 1, 2)])
    scene = v2_scene()
    scene["meshes"] = {"patch": {"file": "patch.obj", "kind": "sheet", "translation": [0.03, 0.0, 0.0],
                                 "material": {"youngs_modulus": 1.0e6, "poisson_ratio": 0.3, "thickness": 0.001,
                                              "density": 100.0, "bending_stiffness": 1.0e-4}}}
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(scene))
    assert "patch" in load_scene(tmp_path / "scene.yaml").bodies


def test_rotation_of_fingers_is_proper():
    from sim_core.scenes.task_scene_v2 import rotation_z_to

    for u in ([1, 0, 0], [0, 0, -1], [0, 0, 1], [0.3, -0.4, 0.5]):
        u = np.asarray(u, float) / np.linalg.norm(u)
        R = quat_to_matrix(rotation_z_to(u))
        np.testing.assert_allclose(R @ [0, 0, 1], u, atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_gravity_scale_per_body():
    scene = v2_scene()
    scene["sheets"]["sheet"]["gravity_scale"] = 0.0
    scene["sheets"]["sheet"].pop("creases")
    model = build_task_scene(scene)
    sheet, cube = model.bodies["sheet"], model.bodies["cube"]
    assert np.all(model.vertex_gravity_scale[sheet.vertices] == 0.0) and np.all(model.vertex_gravity_scale[cube.vertices] == 1.0)
    sim = Simulation(model)
    sim.step()
    x = sim.state.x
    np.testing.assert_allclose(x[sheet.vertices], model.x_rest[sheet.vertices], atol=1e-12)  # weightless, untouched
    # the free cube falls freely in its first step: dz = g dt^2
    np.testing.assert_allclose(x[cube.vertices, 2] - model.x_rest[cube.vertices, 2], -9.8 * 0.005**2, rtol=1e-6)
    assert build_task_scene(v2_scene()).vertex_gravity_scale is None
