"""``thinshell sim`` on a version-2 task scene (gripper, blocks, arched box, pinned set, crease, mesh
object, gravity scale) to a bag."""

from __future__ import annotations

import numpy as np
import yaml

from tests.sim_core.scenes.test_task_scene_v2 import _write_obj, v2_scene
from tests.thinshell_ros.test_recorder import read_with_rosbags
from thinshell_ros.headless import sim_main


def test_v2_task_scene_runs_through_thinshell_sim_to_a_bag(tmp_path):
    doc = v2_scene()
    _write_obj(tmp_path / "patch.obj", [(0, 0, 0), (0.01, 0, 0), (0, 0.01, 0)], [(0, 1, 2)])
    doc["meshes"] = {"patch": {"file": "patch.obj", "kind": "sheet", "translation": [0.03, 0.0, 0.0], "gravity_scale": 0.0,
                               "material": {"youngs_modulus": 1.0e6, "poisson_ratio": 0.3, "thickness": 0.001,
                                            "density": 100.0, "bending_stiffness": 1.0e-4}}}
    scene = tmp_path / "scene.yaml"
    scene.write_text(yaml.safe_dump(doc, sort_keys=False))
    traj = tmp_path / "traj.yaml"
    traj.write_text("version: 1\neffector: grip\nwaypoints:\n"
                    "  - {t: 0.0, pose: [0.0, 0.0, 0.02, 0, 0, 0, 1], gripper: 0.012}\n"
                    "  - {t: 0.015, pose: [0.0, 0.0, 0.018, 0, 0, 0, 1], gripper: 0.009}\n")
    assert sim_main(["--scene", str(scene), "--trajectory", str(traj), "--out", str(tmp_path / "bag")]) == 0
    msgs = read_with_rosbags(tmp_path / "bag")
    assert yaml.safe_load((tmp_path / "bag" / "scene.yaml").read_text())["version"] == 2
    grip = [m.data for _, _, m in msgs["/thinshell/grip/gripper_cmd"]]
    assert len(grip) == 3 and grip[-1] == 0.009
    poses = msgs["/thinshell/grip/pose"]
    assert len(poses) == 4 and abs(poses[-1][2].pose.position.z - 0.018) < 1e-12
    points = msgs["/thinshell/sheet/points"]
    assert len(points) == 4 and points[-1][2].width == 36
