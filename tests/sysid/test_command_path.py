"""The commanded path as the robot took its commands, and the replay step that follows it (sysid.command_path).

A robot stepping at 5 ms under a commander that falls behind it holds a command and then takes the queued ones at
once: its path is a staircase at its own step (:func:`tests.sysid.simbag.lagging_commander`). A replay at 10 ms
moves the effector linearly between its step ends and interpolates its observations in between, so it cannot
follow a hold-and-jump inside one of its steps; such a recording is replayed at the robot's step. A smooth path's
straight-line cut inside a replay step counts only where the recording's own pose resolves it.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from sysid.command_path import anchor_path, commanded_path, held_path_jumps_inside, logged_at_stamps, replay_step
from sysid.evidence import resample_pose
from sysid.observation import REPLAY_TOL_VELOCITY
from tests.sysid.simbag import lagging_commander

STEP_NS = 5_000_000
"""The robot's step (the sim node's demo scene), ns."""


def _robot(lags, path=lambda s: np.column_stack([0.02 * s, np.zeros_like(s), 0.004 - 0.01 * s]), pose_noise=0.0):
    """Evidence of a kinematic robot at 5 ms: command ``j`` (``path(t_{j+1})``, stamped ``t_j``) taken ``lags[j]``
    steps late (logged then), the pose following the newest taken (``pose_noise`` m of white noise on it)."""
    lags = np.asarray(lags)
    taken, in_force = lagging_commander(lags)
    t = np.arange(lags.size + 1, dtype=np.int64) * STEP_NS
    cmd = np.zeros((lags.size, 7))
    cmd[:, :3] = path(t[1:] * 1e-9)
    cmd[:, 3] = 1.0
    start = np.array([*path(np.zeros(1))[0], 1.0, 0.0, 0.0, 0.0])
    pose = np.array([start] + [cmd[j] if j >= 0 else start for j in in_force])
    pose[:, :3] += np.random.default_rng(0).normal(0.0, pose_noise, pose[:, :3].shape)
    keep = taken < lags.size
    last = np.r_[taken[keep][1:] != taken[keep][:-1], True]  # several taken at one time: the last is in force
    log = taken[keep] * STEP_NS
    return SimpleNamespace(t_ns={"pose": t, "pose_cmd": t[:-1][keep]}, pose=pose, pose_cmd=cmd[keep],
                           pose_cmd_taken=(log[last], cmd[keep][last]), channels_present=("pose", "pose_cmd"))


def test_a_hold_and_jump_inside_a_replay_step_asks_for_the_robots_step():
    lags = np.random.default_rng(1).choice(4, size=60, p=(0.5, 0.3, 0.15, 0.05))
    ev = _robot(lags)
    path, held = commanded_path(ev)
    assert held and np.max(np.abs(path[:, :3] - ev.pose[:, :3])) < 1e-15
    jumps = held_path_jumps_inside(ev, 2 * STEP_NS, REPLAY_TOL_VELOCITY)
    assert 10 < jumps <= 30  # of the 30 replay steps of 10 ms
    assert replay_step(ev, 0.01, REPLAY_TOL_VELOCITY) == 0.005
    # the commander on time: the robot's path is the commands' straight ramp, which a 10 ms replay follows
    assert held_path_jumps_inside(_robot(np.zeros(60, dtype=int)), 2 * STEP_NS, REPLAY_TOL_VELOCITY) == 0
    assert replay_step(_robot(np.zeros(60, dtype=int)), 0.01, REPLAY_TOL_VELOCITY) == 0.01
    # a replay at the robot's own step follows any path it holds
    assert held_path_jumps_inside(ev, STEP_NS, REPLAY_TOL_VELOCITY) == 0


def test_a_smooth_paths_cut_counts_only_where_the_pose_resolves_it():
    """A circle of 2 mm at 1 Hz: a 10 ms replay cuts its chord by up to 1 um at the stamps inside its steps; on an
    exact pose (the sim node's) that is a departure, on a pose measured with 5 um of noise it is not."""
    def circle(s):
        return np.column_stack([0.05 + 0.002 * np.cos(2 * np.pi * s), 0.002 * np.sin(2 * np.pi * s), 0.004 + 0 * s])

    exact, noisy = _robot(np.zeros(80, dtype=int), circle), _robot(np.zeros(80, dtype=int), circle, pose_noise=5e-6)
    assert commanded_path(noisy)[1]
    assert held_path_jumps_inside(exact, 2 * STEP_NS, REPLAY_TOL_VELOCITY) > 30
    assert held_path_jumps_inside(noisy, 2 * STEP_NS, REPLAY_TOL_VELOCITY) == 0


def test_the_drives_anchor_takes_the_robots_timing_only_where_the_recording_holds_it():
    """Commands logged after their stamps: the held path; every command logged at its own stamp (the reference
    engine's recorder): the interpolated commands, whatever the tracking error prefers."""
    late = _robot(np.random.default_rng(1).choice(3, size=40, p=(0.6, 0.3, 0.1)))
    t = late.t_ns["pose"]
    assert not logged_at_stamps(late.pose_cmd_taken[0], late.t_ns["pose_cmd"])
    assert np.array_equal(anchor_path(late, t), commanded_path(late, t)[0])
    assert np.max(np.abs(anchor_path(late, t)[:, :3] - late.pose[:, :3])) < 1e-15
    on_time = _robot(np.zeros(40, dtype=int))
    assert logged_at_stamps(on_time.pose_cmd_taken[0], on_time.t_ns["pose_cmd"]) and commanded_path(on_time)[1]
    want = resample_pose(on_time.t_ns["pose_cmd"], on_time.pose_cmd, t, outside="clamp")
    assert np.array_equal(anchor_path(on_time, t), want)
    # a window of the recording: the log times cover it all, the stamps the window
    assert logged_at_stamps(on_time.pose_cmd_taken[0], on_time.t_ns["pose_cmd"][5:20])
