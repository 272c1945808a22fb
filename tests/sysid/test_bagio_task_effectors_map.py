"""A task scene's (``kind: task``) effectors read through a recording map's ``effectors`` section: a real cell's
two arms (one as TF, one as a pose topic of another link in base_link, commands of a tool link, a gripper topic)
give the effector streams of the same recording under INTERFACES.md."""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest
import yaml

from sim_core.errors import BagReadError, ConfigError
from sysid.bagio import BagWriter, codec
from sysid.bagio.recording_map import parse_recording_map
from sysid.bagio.tf_buffer import pose_compose, pose_inverse
from sysid.evidence import load_evidence
from tests.sim_core.scenes.test_task_scene_v2 import v2_scene
from tests.support.real_cell import WORLD_IN_BASE

NS = "/thinshell"
N = 15
T_NS = 1_000_000_000 + 10_000_000 * np.arange(N, dtype=np.int64)
FLANGE_T_GEL = np.array([0.003, -0.002, 0.07, 0.0, np.sin(0.3), 0.0, np.cos(0.3)])
TOOL0_T_GEL = np.array([0.0, 0.001, 0.03, np.sin(0.2), 0.0, 0.0, np.cos(0.2)])
"""Static mounts: each arm's flange -> gel, and tool0 -> gel (the link a Cartesian controller commands)."""


def _scene() -> dict:
    scene = v2_scene()
    scene["effectors"]["push"] = copy.deepcopy(scene["effectors"]["grip"])
    scene["effectors"]["push"]["initial_pose"] = [0.02, 0.0, 0.02, 0.0, 0.0, 0.0, 1.0]
    return scene


def _motion(offset: float, lead_ns: int = 0) -> np.ndarray:
    """World poses ``(N, 7)`` of an effector: a press and a slide with a turn about z."""
    s = (T_NS - T_NS[0] + lead_ns) * 1e-9
    angle = 0.8 * s
    return np.stack([offset + 0.05 * s, 0.01 * s, 0.02 - 0.03 * s, np.zeros(N), np.zeros(N), np.sin(angle / 2),
                     np.cos(angle / 2)], axis=1)


def _transform(parent: str, child: str, t_ns: int, pose: np.ndarray):
    ts = codec.typestore().types
    return ts["geometry_msgs/msg/TransformStamped"](
        header=codec.pose_stamped(t_ns, pose, parent).header, child_frame_id=child,
        transform=ts["geometry_msgs/msg/Transform"](
            translation=ts["geometry_msgs/msg/Vector3"](x=pose[0], y=pose[1], z=pose[2]),
            rotation=ts["geometry_msgs/msg/Quaternion"](x=pose[3], y=pose[4], z=pose[5], w=pose[6])))


def _tf(transforms: list):
    return codec.typestore().types["tf2_msgs/msg/TFMessage"](transforms=transforms)


def _map(effectors: dict | None = None) -> dict:
    return {
        "version": 1,
        "frames": {"base": "base_link", "world_in_base": [float(v) for v in WORLD_IN_BASE], "sensor": "grip_gel",
                   "effector": "grip_gel"},
        "pose": {"tf": True},
        "effectors": effectors or {
            "grip": {"frame": "grip_gel", "pose": {"tf": True},
                     "pose_cmd": {"topic": "/grip/target_frame", "link": "grip_tool0"},
                     "gripper_cmd": {"topic": "/grip/opening"}},
            "push": {"frame": "push_gel", "pose": {"topic": "/push/tool_pose", "link": "push_tool0"},
                     "pose_cmd": {"topic": "/push/target_frame", "link": "push_tool0"}},
        },
    }


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """The same two-arm recording under INTERFACES.md (``plain``) and as a real cell records it (``cell``)."""
    root = tmp_path_factory.mktemp("task")
    scene = _scene()
    pose = {"grip": _motion(0.0), "push": _motion(0.02)}
    cmd = {"grip": _motion(0.0, 5_000_000), "push": _motion(0.02, 5_000_000)}
    opening = 0.012 - 0.0002 * np.arange(N)
    log = T_NS + 2_000_000  # commands are taken (logged) 2 ms after their header stamp
    with BagWriter(root / "plain", scene=scene) as bag:
        for i, t in enumerate(T_NS):
            for e in ("grip", "push"):
                bag.write_pose(f"{NS}/{e}/pose", int(t), pose[e][i], "world")
                bag.write_message(f"{NS}/{e}/pose_cmd", codec.POSE_STAMPED, int(log[i]),
                                  codec.pose_stamped(int(t), cmd[e][i], "world"))
            bag.write_message(f"{NS}/grip/gripper_cmd", codec.FLOAT64, int(log[i]), codec.float64(opening[i]))
    base_T_world = WORLD_IN_BASE
    with BagWriter(root / "cell", scene=scene) as bag:
        bag.write_message("/tf_static", "tf2_msgs/msg/TFMessage", int(T_NS[0]), _tf(
            [_transform(f"{e}_flange", f"{e}_gel", int(T_NS[0]), FLANGE_T_GEL) for e in ("grip", "push")]
            + [_transform(f"{e}_gel", f"{e}_tool0", int(T_NS[0]), pose_inverse(TOOL0_T_GEL))
               for e in ("grip", "push")]))
        for i, t in enumerate(T_NS):
            t = int(t)
            base_T_gel = pose_compose(base_T_world, pose["grip"][i])
            bag.write_message("/tf", "tf2_msgs/msg/TFMessage", t, _tf(
                [_transform("base_link", "grip_flange", t, pose_compose(base_T_gel, pose_inverse(FLANGE_T_GEL)))]))
            push_tool0 = pose_compose(pose_compose(base_T_world, pose["push"][i]), pose_inverse(TOOL0_T_GEL))
            bag.write_pose("/push/tool_pose", t, push_tool0, "base_link")
            for e in ("grip", "push"):
                target = pose_compose(pose_compose(base_T_world, cmd[e][i]), pose_inverse(TOOL0_T_GEL))
                bag.write_message(f"/{e}/target_frame", codec.POSE_STAMPED, int(log[i]),
                                  codec.pose_stamped(t, target, "base_link"))
            bag.write_message("/grip/opening", codec.FLOAT64, int(log[i]), codec.float64(opening[i]))
    (root / "map.yaml").write_text(yaml.safe_dump(_map()))
    return root


def _evidence(path, rmap=None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_evidence(path, recording_map=rmap, include_image=False)


def test_each_effector_of_a_task_scene_is_read_through_the_map_as_the_contract_records_it(bags):
    plain = _evidence(bags / "plain")
    cell = _evidence(bags / "cell", bags / "map.yaml")
    assert set(plain.effectors) == set(cell.effectors) == {"grip", "push"}
    for e, streams in plain.effectors.items():
        assert set(cell.effectors[e]) == set(streams), e
        for kind, (t, values) in streams.items():
            t_cell, v_cell = cell.effectors[e][kind]
            np.testing.assert_array_equal(t_cell, t, err_msg=f"{e} {kind}")  # commands at their log time
            if kind != "gripper_cmd":  # q and -q are one rotation
                v_cell = v_cell.copy()
                v_cell[:, 3:] *= np.sign(np.sum(v_cell[:, 3:] * values[:, 3:], axis=1))[:, None]
            np.testing.assert_allclose(v_cell, values, rtol=0, atol=1e-9, err_msg=f"{e} {kind}")
    assert cell.effectors["grip"]["pose_cmd"][0][0] == T_NS[0] + 2_000_000
    np.testing.assert_allclose(cell.pose, plain.pose, rtol=0, atol=1e-9)  # the map's own pose role: grip by TF


def test_a_map_effector_the_scene_lacks_is_an_error_naming_it(bags, tmp_path):
    effectors = _map()["effectors"]
    effectors["left"] = effectors.pop("push")
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(_map(effectors)))
    with pytest.raises(BagReadError, match=r"map.yaml: effectors.left is not an effector of the scene "
                                           r"\(effectors: grip, push\)"):
        _evidence(bags / "cell", tmp_path / "map.yaml")


def test_an_effector_needs_a_pose_or_a_command():
    with pytest.raises(ConfigError, match="m.yaml: effectors.grip needs pose or pose_cmd"):
        parse_recording_map(_map({"grip": {"frame": "grip_gel", "gripper_cmd": {"topic": "/g"}}}), "m.yaml")
    with pytest.raises(ConfigError, match="m.yaml: unknown key effectors.grip.stamp"):
        parse_recording_map(_map({"grip": {"frame": "grip_gel", "pose": {"tf": True}, "stamp": "log"}}), "m.yaml")
