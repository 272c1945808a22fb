"""A task's reward on recorded sheet points (sysid.task_reward): the reward a robot achieved."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.optim.episode import Episode
from sim_core.optim.tasks import task_at_horizon
from sysid.task_reward import TaskRewardProbe, reward_sample_index


def test_forming_reward_on_points_is_the_task_reward_and_its_analytic_value():
    task = task_at_horizon("forming", 4)
    probe = TaskRewardProbe(task)
    ep = Episode(task, 4)
    res = ep.run(np.asarray(task.reference_actions)[:4], keep_states=True)
    final = res.final_state
    points = final.x[probe.tracked]
    assert probe.tracked.size == 128                       # the 16 x 8 sheet
    assert probe(points) == pytest.approx(res.reward, abs=1e-15) == pytest.approx(0.0, abs=1e-15)  # the target
    d = np.array([1e-3, -2e-3, 5e-4])                     # -sum |x + d - x_target|^2 = -p |d|^2
    assert probe(points + d) == pytest.approx(-128 * float(d @ d), rel=1e-12)
    rng = np.random.default_rng(1)
    moved = points + 1e-3 * rng.standard_normal(points.shape)
    final.x[probe.tracked] = moved                        # the task's own reward on a state with those points
    assert probe(moved) == pytest.approx(task.reward(ep.model, final), rel=1e-12)
    with pytest.raises(ConfigError, match="3 sheet points, the task's scene tracks 128"):
        probe(points[:3])


def test_a_reward_that_reads_rest_angles_is_refused():
    with pytest.raises(ConfigError, match="reward 'crease_rest_angle' reads more than the recorded sheet points"):
        TaskRewardProbe(task_at_horizon("folding_l", 2))


def test_the_reward_sample_is_the_first_after_the_last_pose_command():
    def evidence(cmd_ns):
        streams = {"dome": {"pose_cmd": (np.asarray(cmd_ns, dtype=np.int64), np.zeros((len(cmd_ns), 7)))}}
        return SimpleNamespace(effectors=streams, source=SimpleNamespace(bag_path="bag"))

    sheet_t = np.array([0, 5, 10, 15, 20], dtype=np.int64)
    assert reward_sample_index(evidence([0, 5, 10]), sheet_t) == 3      # the state after the last command's step
    assert reward_sample_index(evidence([0, 4]), sheet_t) == 1
    with pytest.raises(ConfigError, match="bag: no sheet/points sample after the last pose command"):
        reward_sample_index(evidence([0, 20]), sheet_t)
    with pytest.raises(ConfigError, match="bag: no <effector>/pose_cmd recorded"):
        reward_sample_index(evidence([]), sheet_t)
