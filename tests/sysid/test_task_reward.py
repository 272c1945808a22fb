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


def test_compare_task_measures_the_reward_the_recording_scene_predicts(tmp_path, capsys):
    """``thinshell compare --task``: on a Forming bag of ``thinshell sim``, the recording's own scene predicts
    the reward the recording achieved (to rounding); a scene with another sheet stiffness does not; a
    rest-angle reward is refused naming it."""
    import json

    import yaml

    from sysid.compare import compare_main
    from thinshell_ros.headless import sim_main

    task = task_at_horizon("forming", 5)
    scene = tmp_path / "forming.yaml"
    scene.write_text(yaml.safe_dump(task.scene, sort_keys=False))
    start = list(task.scene["effectors"]["dome"]["initial_pose"])
    end = [start[0] + 0.0012, start[1], start[2] - 0.0006, *start[3:]]
    traj = tmp_path / "push.yaml"
    traj.write_text(yaml.safe_dump({"version": 1, "effector": "dome", "waypoints": [
        {"t": 0.0, "pose": start}, {"t": 0.025, "pose": end}]}))
    bag = tmp_path / "bag"
    assert sim_main(["--scene", str(scene), "--trajectory", str(traj), "--out", str(bag)]) == 0
    stiff = dict(task.scene, sheets={"sheet": dict(task.scene["sheets"]["sheet"], bending={"bending_stiffness": 4e-3})})
    other = tmp_path / "stiff.yaml"
    other.write_text(yaml.safe_dump(stiff, sort_keys=False))
    out = tmp_path / "cmp"
    assert compare_main([str(bag), "--scene", str(other), "--label", "stiff", "--task", "forming", "--horizon", "5",
                         "--dt", "0.005", "--arch", "numpy", "--out", str(out)]) == 0
    reward = json.loads((out / "compare.json").read_text())["reward"]
    assert reward["task"] == "Forming" and reward["unit"] == "m^2" and reward["recording"] < 0
    # the bag's own scene predicts the recorded reward to the recorder's stopping error: each recorded step stops within
    # tol_velocity * dt of its minimiser (the replay's steps are solved tighter, sysid.observation.REPLAY_TOL_VELOCITY),
    # so a vertex is at most delta = steps * tol_velocity * dt off, and R = -sum |e_i|^2 over n vertices moves by at most
    # 2 sqrt(n |R|) delta + n delta^2 (Cauchy-Schwarz)
    from sim_core.solver_config import SolverConfig

    nx, ny = task.scene["sheets"]["sheet"]["resolution"]
    n, delta = (nx + 1) * (ny + 1), 5 * SolverConfig().tol_velocity * 0.005
    bound = 2.0 * np.sqrt(n * abs(reward["recording"])) * delta + n * delta ** 2
    assert abs(reward["predicted"]["nominal"] - reward["recording"]) < bound
    assert abs(reward["predicted"]["stiff"] - reward["recording"]) > 1e-3 * abs(reward["recording"])
    assert "reward achieved on the recording" in capsys.readouterr().out
    assert compare_main([str(bag), "--scene", str(other), "--task", "folding_l", "--horizon", "5", "--dt", "0.005",
                         "--arch", "numpy", "--out", str(tmp_path / "cmp2")]) == 1
    assert "reward 'crease_rest_angle' reads more than the recorded sheet points" in capsys.readouterr().err
