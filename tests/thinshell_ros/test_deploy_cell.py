"""The deploy node's cell logic without DDS (thinshell_ros.deploy_cell): frames, twist law, wrench frame,
tare and limits, watchdog, retract plan, the scene's mount."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from sim_core.errors import ConfigError
from sim_core.transforms import pose_to_matrix, quat_from_rotvec, quat_multiply
from tests.thinshell_ros.conftest import REPO
from thinshell_ros.commands import Workspace
from thinshell_ros.deploy_cell import (CellFrames, RetractPlan, Watchdog, WrenchGuard, WrenchTare, checked_pose,
                                       scene_mount, servo_twist, wrench_in_sensor)
from thinshell_ros.deploy_plan import rotation_angle

S = math.sqrt(0.5)
HOME = np.array([0.06, 0.0, 0.004, 1.0, 0.0, 0.0, 0.0])


def _random_pose(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return np.concatenate([rng.normal(scale=0.1, size=3), q / np.linalg.norm(q)])


def test_tool_in_base_is_the_chain_of_the_cell_and_inverts():
    rng = np.random.default_rng(3)
    world_in_base, sensor_in_tool, mount = (_random_pose(rng) for _ in range(3))
    frames = CellFrames(world_in_base=world_in_base, sensor_in_tool=sensor_in_tool, sensor_mount=mount)
    for _ in range(5):
        ee = _random_pose(rng)
        # T_base_tool = T_base_world T_world_ee T_ee_sensor T_tool_sensor^-1, with plain matrices
        T = pose_to_matrix(world_in_base) @ pose_to_matrix(ee) @ pose_to_matrix(mount) @ np.linalg.inv(
            pose_to_matrix(sensor_in_tool))
        got = frames.tool_in_base(ee)
        np.testing.assert_allclose(pose_to_matrix(got), T, atol=1e-12)
        back = frames.effector_in_world(got)
        np.testing.assert_allclose(back[:3], ee[:3], atol=1e-12)
        assert rotation_angle(back[3:], ee[3:]) < 1e-7
    # the sensor normal: HOME (180 deg about x, R = diag(1, -1, -1)) with a mount turned +90 deg about y:
    # sensor z = effector +x = world +x
    frames = CellFrames(sensor_mount=[0.0, 0.0, 0.0, 0.0, S, 0.0, S])
    np.testing.assert_allclose(frames.sensor_normal_in_world(HOME), [1.0, 0.0, 0.0], atol=1e-12)
    frames = CellFrames(world_in_base=[1.0, 2.0, 3.0, 0.0, 0.0, S, S])  # world x = base y
    np.testing.assert_allclose(frames.vector_to_base([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-12)


def test_servo_twist_is_the_finite_difference_plus_feedback_and_limited():
    dt = 0.01
    w_true = np.array([0.0, 0.3, 0.0])
    p0 = np.array([0.1, 0.2, 0.3, *quat_from_rotvec(np.array([0.2, 0.0, 0.1]))])
    p1 = np.concatenate([p0[:3] + dt * np.array([0.01, -0.02, 0.0]), quat_multiply(quat_from_rotvec(w_true * dt), p0[3:])])
    twist = servo_twist(p0, p1, dt, None, 5.0, 1.0, 1.0)
    np.testing.assert_allclose(twist, [0.01, -0.02, 0.0, *w_true], atol=1e-12)
    # feedback: the measured frame 1 mm behind along x and 0.01 rad behind about z -> + gain * error
    measured = np.concatenate([p0[:3] - [0.001, 0, 0], quat_multiply(quat_from_rotvec(np.array([0, 0, -0.01])), p0[3:])])
    twist = servo_twist(p0, p1, dt, measured, 5.0, 1.0, 1.0)
    np.testing.assert_allclose(twist, [0.015, -0.02, 0.0, 0.0, 0.3, 0.05], atol=1e-9)
    limited = servo_twist(p0, p1, dt, measured, 5.0, 0.01, 0.1)
    assert np.linalg.norm(limited[:3]) == pytest.approx(0.01) and np.linalg.norm(limited[3:]) == pytest.approx(0.1)
    np.testing.assert_allclose(limited[:3] / 0.01, twist[:3] / np.linalg.norm(twist[:3]), atol=1e-12)  # direction kept


def test_wrench_moves_to_the_sensor_frame_with_its_lever_arm():
    # F/T frame 3 cm behind the gel (z = -0.03 in the sensor frame), turned 90 deg about z (F/T x = sensor y)
    ft = checked_pose([0.0, 0.0, -0.03, 0.0, 0.0, S, S], "wrench_in_sensor")
    w = wrench_in_sensor([2.0, 0.0, -5.0, 0.0, 0.0, 0.0], ft)
    # force: F/T x -> sensor y; torque about the sensor origin of a force applied at (0, 0, -0.03): r x f
    np.testing.assert_allclose(w, [0.0, 2.0, -5.0, 0.06, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(wrench_in_sensor(w, checked_pose([0, 0, 0, 0, 0, 0, 1], "x")), w, atol=0)


@pytest.mark.parametrize("wrench, words", [
    ([0.0, 0.0, -4.5, 0.0, 0.0, 0.0], "measured normal force 4.5 N on w exceeds normal_force_limit 4 N"),
    ([1.5, 2.0, -1.0, 0.0, 0.0, 0.0], "measured shear force 2.5 N on w exceeds shear_force_limit 2 N"),
    ([0.0, 0.0, -1.0, 0.03, 0.04, 0.0], "measured torque 0.05 N*m on w exceeds torque_limit 0.04 N*m"),
    ([0.0, 0.0, np.nan, 0.0, 0.0, 0.0], "measured force nan N on w exceeds wrench_limit 10 N"),
    ([9.0, 0.0, -4.0, 0.0, 0.0, 0.0], "measured force 9.849 N on w exceeds wrench_limit 9 N"),
])
def test_wrench_guard_names_the_limit(wrench, words):
    guard = WrenchGuard(force_norm=9.0 if wrench[0] == 9.0 else 10.0, normal_force=4.0 if wrench[0] != 9.0 else math.inf,
                        shear_force=2.0 if wrench[0] != 9.0 else math.inf, torque=0.04)
    assert guard.check("w", np.array(wrench)) == words
    assert WrenchGuard(force_norm=10.0).check("w", np.array([0.0, 3.0, -9.0, 5.0, 0, 0])) is None  # others off
    margins = WrenchGuard(force_norm=10.0, normal_force=4.0, torque=0.5).margins(np.array([0.6, 0.8, -3.0, 0.3, 0.4, 0]))
    assert margins == pytest.approx({"wrench_limit": 10.0 - math.sqrt(10.0), "normal_force_limit": 1.0,
                                     "torque_limit": 0.0})  # the shear limit is off: no margin
    with pytest.raises(ConfigError, match="wrench limit torque must be > 0"):
        WrenchGuard(torque=0.0)


def test_tare_is_the_mean_and_refuses_contact():
    tare = WrenchTare(max_offset=2.0)
    for k in range(10):
        tare.add("w", [0.1, 0.0, -1.0 + 0.01 * (k - 4.5), 0.0, 0.002, 0.0])
    off = tare.finish(["w"])["w"]
    np.testing.assert_allclose(off, [0.1, 0.0, -1.0, 0.0, 0.002, 0.0], atol=1e-12)
    np.testing.assert_allclose(tare.apply("w", [0.1, 0.0, -3.0, 0.0, 0.002, 0.0]), [0, 0, -2.0, 0, 0, 0], atol=1e-12)
    busy = WrenchTare(max_offset=2.0)
    busy.add("w", [0.0, 0.0, -2.5, 0.0, 0.0, 0.0])
    with pytest.raises(ConfigError, match=r"mean force 2.5 N on w over 1 samples exceeds tare_max_force 2 N"):
        busy.finish(["w"])
    with pytest.raises(ConfigError, match="no sample on v within the tare window"):
        busy.finish(["v"])


def test_watchdog_names_the_stale_stream():
    dog = Watchdog(0.2)
    dog.seen("/a", 10.0)
    dog.seen("/b", 10.15)
    assert dog.stale(["/a", "/b"], 10.2) is None
    assert dog.stale(["/a", "/b"], 10.25) == "the newest message on /a is 0.25 s old (> sensor_timeout 0.2 s)"
    assert dog.stale(["/c"], 10.0) == "no message on /c (sensor_timeout 0.2 s)"
    # on /clock: stale only when old on the robot's clock and on the steady clock
    dog.seen("/a", 10.0, steady=100.0)
    assert dog.stale(["/a"], 10.5, steady=100.1) is None  # /clock jumped ahead of the queued messages
    assert dog.stale(["/a"], 10.1, steady=101.0) is None  # the simulator runs slower than real time
    assert "/a is 0.5 s old" in dog.stale(["/a"], 10.5, steady=100.5)
    # the watcher itself stalled until steady 101: the steady age restarts there
    dog.resumed(101.0)
    assert dog.stale(["/a"], 11.1, steady=101.1) is None
    assert "/a is 1.3 s old" in dog.stale(["/a"], 11.3, steady=101.3)
    with pytest.raises(ConfigError, match="sensor_timeout must be finite and > 0"):
        Watchdog(0.0)


def test_retract_lifts_at_speed_and_stops_at_the_workspace():
    start = np.array([0.0, 0.0, 0.095, 0.0, 0.0, 0.0, 1.0])
    plan = RetractPlan(start, [0.0, 0.0, 2.0], speed=0.01, distance=0.01, t0=5.0,
                       workspace=Workspace((-0.1, -0.1, 0.0), (0.1, 0.1, 0.1)))
    assert plan.reach == pytest.approx(0.005) and plan.duration == pytest.approx(0.5)  # the box ends 5 mm up
    np.testing.assert_allclose(plan.pose(5.2), [0.0, 0.0, 0.097, 0.0, 0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(plan.pose(9.0)[:3], [0.0, 0.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(plan.velocity(5.1), [0.0, 0.0, 0.01])
    np.testing.assert_allclose(plan.velocity(5.6), [0.0, 0.0, 0.0])
    free = RetractPlan(start, [1.0, 0.0, 0.0], speed=0.01, distance=0.01, t0=0.0)
    assert free.reach == 0.01


def test_scene_mount_and_pose_parameters(tmp_path):
    doc = yaml.safe_load((REPO / "config" / "scenes" / "press_slide.yaml").read_text())
    sensor = next(iter(doc["sensors"]))
    doc["sensors"][sensor]["mount"] = [0.0, 0.0, 0.01, 0.0, 0.0, S, S]
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(doc))
    mount, where = scene_mount(str(path))
    np.testing.assert_allclose(mount, [0.0, 0.0, 0.01, 0.0, 0.0, S, S], atol=1e-12)
    assert where == f"{path}: sensors.{sensor}.mount"
    np.testing.assert_allclose(scene_mount(None)[0], [0, 0, 0, 0, 0, 0, 1])
    np.testing.assert_allclose(checked_pose([0, 0, 0, 0, 0, 0, 1.0005], "p")[3:], [0, 0, 0, 1])
    with pytest.raises(ConfigError, match=r"parameter 'p': quaternion norm 2 is not 1"):
        checked_pose([0, 0, 0, 0, 0, 0, 2.0], "p")
    # the composition the node uses for the retract direction agrees with a plain matrix product
    frames = CellFrames(sensor_mount=mount)
    z = (pose_to_matrix(HOME) @ pose_to_matrix(mount))[:3, 2]
    np.testing.assert_allclose(frames.sensor_normal_in_world(HOME), z, atol=1e-12)
