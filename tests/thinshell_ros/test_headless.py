"""Trajectories (files, scripted) and the headless bag writer (no DDS)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.transforms import quat_from_rotvec, quat_multiply, quat_to_rotvec
from sysid.bagio import BagWriter
from tests.thinshell_ros.fake_sim import HOME, FakeSimulation
from tests.thinshell_ros.test_recorder import read_with_mcap, read_with_rosbags
from thinshell_ros.headless import run_headless, scene_trajectory
from thinshell_ros.trajectory import load_trajectory, scripted_trajectory

DOWN = np.array([1.0, 0.0, 0.0, 0.0])  # 180 deg about x: sensor z axis = world -z


def test_yaml_and_csv_trajectories_agree_and_interpolate(tmp_path):
    q1 = quat_multiply(quat_from_rotvec([0, 0, 0.4]), DOWN)
    (tmp_path / "a.yaml").write_text(
        "version: 1\neffector: ee\nwaypoints:\n"
        f"  - {{t: 0.0, pose: [0.0, 0.0, 0.01, 1, 0, 0, 0]}}\n"
        f"  - {{t: 1.0, pose: [0.1, 0.0, 0.0, {q1[0]}, {q1[1]}, {q1[2]}, {q1[3]}]}}\n")
    (tmp_path / "a.csv").write_text("# same trajectory\nt,x,y,z,qx,qy,qz,qw\n0,0,0,0.01,1,0,0,0\n"
                                    f"1.0,0.1,0,0,{q1[0]},{q1[1]},{q1[2]},{q1[3]}\n")
    a, b = load_trajectory(tmp_path / "a.yaml"), load_trajectory(tmp_path / "a.csv")
    assert a.effector == "ee" and b.effector is None and a.duration == 1.0
    for t in (-1.0, 0.0, 0.25, 0.5, 1.0, 2.0):
        np.testing.assert_allclose(a.sample(t), b.sample(t), atol=1e-15)
    mid = a.sample(0.25)
    np.testing.assert_allclose(mid[:3], [0.025, 0.0, 0.0075])
    rel = quat_to_rotvec(quat_multiply(mid[3:], DOWN * np.r_[-1, -1, -1, 1]))
    np.testing.assert_allclose(rel, [0, 0, 0.1], atol=1e-12)  # slerp: a quarter of the rotation
    # the same motion as a thinshell-trajectory file (what thinshell deploy plays) samples the same
    from sim_core.trajectory_file import Trajectory as TrajectoryFile, write_trajectory

    c = load_trajectory(write_trajectory(tmp_path / "c.yaml", TrajectoryFile(t=a.t, poses={"ee": a.poses})))
    assert c.effector == "ee"
    for t in (0.0, 0.25, 0.5, 1.0):
        np.testing.assert_allclose(c.sample(t), a.sample(t), atol=1e-15)
    two = TrajectoryFile(t=a.t, poses={"ee": a.poses, "ee2": a.poses})
    with pytest.raises(ConfigError, match="plays one effector"):
        load_trajectory(write_trajectory(tmp_path / "two.yaml", two))


def test_trajectory_errors_name_the_problem(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("version: 1\nwaypoints:\n  - {t: 0.0, pose: [0, 0, 0, 0, 0, 0, 2]}\n")
    with pytest.raises(ConfigError, match="bad.yaml: waypoint 0 has quaternion norm 2"):
        load_trajectory(p)
    p.write_text("version: 1\nspeed: 3\nwaypoints: []\n")
    with pytest.raises(ConfigError, match=r"unknown keys \['speed'\]"):
        load_trajectory(p)
    p.write_text("version: 1\nwaypoints:\n  - {t: 1.0, pose: [0, 0, 0, 0, 0, 0, 1]}\n  - {t: 0.5, pose: [0, 0, 0, 0, 0, 0, 1]}\n")
    with pytest.raises(ConfigError, match="strictly increasing"):
        load_trajectory(p)
    c = tmp_path / "bad.csv"
    c.write_text("t,x,y,z,qx,qy,qz\n0,0,0,0,0,0,0\n")
    with pytest.raises(ConfigError, match=r"missing \['qw'\]"):
        load_trajectory(c)
    with pytest.raises(ConfigError, match="not found"):
        load_trajectory(tmp_path / "none.yaml")
    with pytest.raises(ConfigError, match="unknown scripted trajectory 'wiggle'"):
        scripted_trajectory("wiggle", HOME, HOME, 0.0)
    with pytest.raises(ConfigError, match="does not face down"):
        scripted_trajectory("press_slide", HOME, np.r_[HOME[:3], 0, 0, 0, 1], 0.0)


def test_scripted_press_slide_geometry():
    sensor = HOME + np.r_[0, 0, -0.001, 0, 0, 0, 0]  # sensor frame 1 mm below the effector frame
    traj = scripted_trajectory("press_slide_lift", HOME, sensor, sheet_top=0.0003, depth=0.001, slide=0.015)
    touch, pressed, held, slid, lifted = traj.poses[1:]
    assert sensor[2] - (HOME[2] - touch[2]) == pytest.approx(0.0003)  # gel surface touches the sheet top
    assert touch[2] - pressed[2] == pytest.approx(0.001) and np.array_equal(pressed, held)
    assert slid[0] - pressed[0] == pytest.approx(0.015) and slid[2] == pressed[2]
    assert lifted[2] == HOME[2] and lifted[0] == slid[0]
    assert np.all(np.diff(traj.t) > 0)
    assert len(scripted_trajectory("press_slide", HOME, sensor, 0.0003).t) == len(traj.t) - 1


def test_headless_bag_has_interface_topics(tmp_path):
    sim = FakeSimulation()
    traj = scene_trajectory(sim, "press_slide", depth=0.001, slide=0.002)
    with BagWriter(tmp_path / "bag") as bag:
        stats = run_headless(sim, traj, bag, image=True)
    steps = int(stats["steps"])
    assert steps == int(np.ceil(traj.duration / sim.dt - 1e-9)) and stats["sim_time"] == pytest.approx(steps * sim.dt)
    msgs = read_with_rosbags(tmp_path / "bag")
    assert len(msgs["/thinshell/ee/pose_cmd"]) == steps and len(msgs["/clock"]) == steps + 1
    for topic in ("/thinshell/ee/pose", "/thinshell/tactile/markers", "/thinshell/tactile/wrench",
                  "/thinshell/tactile/image", "/thinshell/sheet/points"):
        assert len(msgs[topic]) == steps + 1, topic
    fz = np.array([m.wrench.force.z for _, _, m in msgs["/thinshell/tactile/wrench"]])
    assert fz[0] == 0.0 and fz.min() == pytest.approx(-1.0, rel=1e-6)  # 1 mm press, k = 1000 N/m
    cloud = msgs["/thinshell/tactile/markers"][-1][2]
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "u", "v"] and cloud.header.frame_id == "tactile"
    cmd_t = [t for _, t, _ in msgs["/thinshell/ee/pose_cmd"]]
    assert cmd_t[:3] == [0, 5_000_000, 10_000_000]
    assert len(read_with_mcap(tmp_path / "bag")["/thinshell/ee/pose"]) == steps + 1


def test_headless_rate_subsamples_outputs(tmp_path):
    sim = FakeSimulation()
    traj = scene_trajectory(sim, "press_slide", slide=0.001)
    with BagWriter(tmp_path / "bag") as bag:
        run_headless(sim, traj, bag, duration=0.1, rate=50.0)
    msgs = read_with_rosbags(tmp_path / "bag")
    t_pose = [t for _, t, _ in msgs["/thinshell/ee/pose"]]
    assert t_pose == [k * 20_000_000 for k in range(6)] and len(msgs["/clock"]) == 21
