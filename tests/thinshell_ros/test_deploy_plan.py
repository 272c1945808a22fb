"""The deploy node's pure logic (thinshell_ros.deploy_plan): limits, schedule, monitor, approach, bag replay."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.trajectory_file import Trajectory
from tests.thinshell_ros.conftest import REPO
from thinshell_ros.commands import Workspace
from thinshell_ros.deploy_plan import (DeployLimits, DeploySchedule, SafetyMonitor, approach_trajectory,
                                       check_trajectory, rotation_angle, start_pose_error, trajectory_from_bag)

HOME = np.array([0.06, 0.0, 0.004, 1.0, 0.0, 0.0, 0.0])


def _traj(t, xs, rot_z=None) -> Trajectory:
    poses = np.tile(HOME, (len(t), 1))
    poses[:, 0] = xs
    if rot_z is not None:  # rotation about world z composed onto HOME's orientation: q = (0, 0, sin, cos) * (1, 0, 0, 0)
        a = np.asarray(rot_z) / 2
        poses[:, 3:] = np.stack([np.cos(a), np.sin(a), np.zeros_like(a), np.zeros_like(a)], axis=1)
    return Trajectory(t=np.asarray(t, float), poses={"ee": poses})


def test_speed_limits_name_the_waypoint_and_scale_with_time():
    lim = DeployLimits(max_linear_speed=0.01, max_linear_acceleration=10.0)
    traj = _traj([0.0, 1.0, 1.5, 2.0], [0.06, 0.065, 0.071, 0.072])  # 5, 12, 2 mm/s
    with pytest.raises(ConfigError, match=r"traj.yaml: waypoint 2 \(t=1.5 s\), effector 'ee': linear speed 0.012 m/s "
                                          r"from waypoint 1 exceeds max_linear_speed 0.01 m/s \(time_scale 1\)"):
        check_trajectory(traj, lim, where="traj.yaml")
    check_trajectory(traj, lim, time_scale=1.25)  # 9.6 mm/s
    rot = _traj([0.0, 0.5], [0.06, 0.06], rot_z=[0.0, 1.0])  # 2 rad/s
    with pytest.raises(ConfigError, match=r"waypoint 1 \(t=0.5 s\), effector 'ee': angular speed 2 rad/s"):
        check_trajectory(rot, DeployLimits(max_angular_speed=1.5))
    check_trajectory(rot, DeployLimits(max_angular_speed=2.5))


def test_acceleration_counts_start_and_stop_at_rest():
    # 10 mm/s reached within the first 0.1 s segment: a = 0.01 / 0.1 = 0.1 m/s^2 at waypoint 0
    traj = _traj([0.0, 0.1, 0.2], [0.06, 0.061, 0.062])
    with pytest.raises(ConfigError, match=r"waypoint 0 \(t=0 s\), effector 'ee': linear acceleration 0.1 m/s\^2 "
                                          "exceeds max_linear_acceleration 0.05"):
        check_trajectory(traj, DeployLimits(max_linear_acceleration=0.05))
    check_trajectory(traj, DeployLimits(max_linear_acceleration=0.11))
    # twice as slow: a quarter of the acceleration
    check_trajectory(traj, DeployLimits(max_linear_acceleration=0.026), time_scale=2.0)


def test_workspace_nan_and_order_refused():
    lim = DeployLimits(workspace=Workspace((0.0, -0.1, 0.0), (0.1, 0.1, 0.1)))
    with pytest.raises(ConfigError, match=r"waypoint 1 \(t=1 s\), effector 'ee': position \[0.2, 0.0, 0.004\] m is "
                                          r"outside the workspace"):
        check_trajectory(_traj([0.0, 1.0], [0.06, 0.2]), DeployLimits(workspace=lim.workspace, max_linear_speed=1.0))
    with pytest.raises(ConfigError, match=r"waypoint 1 \(t=1 s\), effector 'ee': pose has non-finite"):
        check_trajectory(_traj([0.0, 1.0], [0.06, np.inf]), lim)
    with pytest.raises(ConfigError, match=r"waypoint 1: time t=nan is not finite"):
        check_trajectory(_traj([0.0, np.nan], [0.06, 0.06]), lim)
    with pytest.raises(ConfigError, match=r"waypoint 2: time t=0.5 s is not after waypoint 1"):
        check_trajectory(_traj([0.0, 1.0, 0.5], [0.06] * 3), lim)
    with pytest.raises(ConfigError, match="time_scale must be finite and > 0"):
        check_trajectory(_traj([0.0], [0.06]), lim, time_scale=0.0)
    with pytest.raises(ConfigError, match="wrench_limit must be finite and > 0"):
        DeployLimits(wrench_limit=-1.0)


def test_schedule_grid_lookahead_free_and_no_bursts():
    traj = _traj([0.0, 1.0], [0.06, 0.07])
    s = DeploySchedule(traj, t0=10.0, rate=100.0, time_scale=2.0)
    assert s.tick_count == 201 and s.end == pytest.approx(12.0)
    k, poses, grip = s.due(10.0)
    assert k == 0 and poses["ee"][0] == pytest.approx(0.06) and grip == {}
    assert s.due(10.004) is None  # tick 1 is due from 10.005
    k, poses, _ = s.due(10.006)
    assert k == 1 and poses["ee"][0] == pytest.approx(0.06 + 0.01 * 0.005)  # trajectory time 0.01 / 2
    k, poses, _ = s.due(10.5)  # stalled: ticks 2..49 superseded by tick 50, one command
    assert k == 50 and poses["ee"][0] == pytest.approx(0.0625)
    assert len(s.lateness) == 51 and max(s.lateness) == pytest.approx(0.48)
    assert s.due(10.5) is None
    k, poses, _ = s.due(20.0)
    assert k == 200 and poses["ee"][0] == pytest.approx(0.07) and s.finished and s.progress() == 1.0
    assert s.due(21.0) is None


def test_monitor_wrench_and_pose_lag():
    mon = SafetyMonitor(DeployLimits(wrench_limit=5.0, pose_lag_tolerance=0.001, pose_lag_window=0.05))
    assert mon.check_wrench("tactile/wrench", [3.0, 0.0, -3.9, 100.0, 0, 0]) is None  # torque does not count
    assert "force 5.5 N on tactile/wrench exceeds wrench_limit 5 N" in mon.check_wrench("tactile/wrench", [0.0, 0, -5.5, 0, 0, 0])
    assert "exceeds" in mon.check_wrench("w", [np.nan, 0, 0, 0, 0, 0])
    assert mon.check_pose("ee", 0.0, HOME) is None  # no command yet
    for k in range(11):
        mon.commanded("ee", 0.01 * k, HOME + [0.001 * k, 0, 0, 0, 0, 0, 0])
    # at t = 0.1 the window holds the commands of t >= 0.05 and the one in force at 0.05
    assert mon.check_pose("ee", 0.1, HOME + [0.0055, 0, 0, 0, 0, 0, 0]) is None
    reason = mon.check_pose("ee", 0.1, HOME + [0.003, 0, 0, 0, 0, 0, 0])
    assert reason and "lags the command by 2 mm" in reason


def test_approach_is_straight_and_slow():
    traj = _traj([0.0, 1.0], [0.06, 0.07])
    traj.gripper = {"ee": np.array([0.02, 0.01])}
    measured = {"ee": HOME + [0, 0.003, 0.004, 0, 0, 0, 0]}
    assert start_pose_error(measured["ee"], HOME) == pytest.approx((0.005, 0.0))
    out = approach_trajectory(traj, measured, linear_speed=0.01, angular_speed=1.0)
    assert out.t.tolist() == pytest.approx([0.0, 0.5, 1.5]) and out.provenance["approach_s"] == pytest.approx(0.5)
    np.testing.assert_allclose(out.sample_pose("ee", 0.25)[:3], HOME[:3] + [0, 0.0015, 0.002])
    assert out.gripper["ee"].tolist() == [0.02, 0.02, 0.01]
    assert rotation_angle([0, 0, 0, 1], [0, 0, math.sin(0.25), math.cos(0.25)]) == pytest.approx(0.5)
    with pytest.raises(ConfigError, match=r"no measured pose for effectors \['ee'\]"):
        approach_trajectory(traj, {}, 0.01, 1.0)


def test_bag_replay_reads_the_recorded_commands():
    traj = trajectory_from_bag(REPO / "bags" / "nominal_s101")
    assert traj.effectors == ["ee"] and traj.t[0] == 0.0 and traj.waypoint_count > 100
    assert np.diff(traj.t).min() > 0 and traj.scene_name and traj.provenance["tool"] == "bag replay"
    check_trajectory(traj, DeployLimits())  # the scripted press-slide is within the default limits
