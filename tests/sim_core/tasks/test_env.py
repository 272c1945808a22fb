"""Gymnasium environments of the tasks: the checker, spaces, termination and rendering."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import subprocess
import sys

from sim_core.tasks.env import ThinShellTaskEnv
from sim_core.tasks.gym_ids import env_id, register_envs
from sim_core.tasks.registry import load_task, task_names


def cheap(name):
    """The task with its reward replaced when it needs the full reference rollout (its target);
    those rewards are tested in test_tasks.py."""
    t = load_task(name)
    if t.reward_name in ("sheet_target", "observed_motion"):
        t = dataclasses.replace(t, reward=lambda model, state: float(-np.sum(state.x ** 2)))
    return t


@pytest.mark.parametrize("name", task_names())
def test_every_task_env_passes_the_checker(name):
    env = ThinShellTaskEnv(cheap(name), horizon=2, sheet_samples=16, marker_count=4)  # the checker needs > 1 step
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert env.action_space.shape == (env.task.action_dim,)


def test_ids_registered_and_make_builds_the_task():
    ids = register_envs()
    assert len(ids) == 10 and env_id("folding_l") == "thinshell/Folding-L-v0" and "thinshell/Lifting-v0" in ids
    env = gym.make("thinshell/Folding-L-v0", horizon=1)
    assert env.unwrapped.task.name == "Folding-L"
    env.close()


@pytest.mark.parametrize("code", [
    "import gymnasium as gym, sim_core.tasks; gym.register_envs(sim_core.tasks); e = gym.make('thinshell/Forming-v0')",
    "import gymnasium as gym; e = gym.make('sim_core.tasks:thinshell/Forming-v0')",
])
def test_gym_make_in_a_fresh_interpreter(code):
    """The Gymnasium forms a user types work from a fresh interpreter: registration comes with the
    package import (or the ``module:id`` form), not with a side import of the environment module."""
    probe = code + "; print(type(e.unwrapped).__name__, e.unwrapped.task.name, e.spec.id); e.close()"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["ThinShellTaskEnv", "Forming", "thinshell/Forming-v0"]


def test_episode_ends_with_the_task_reward_and_renders_a_frame():
    env = ThinShellTaskEnv(cheap("folding_l"), horizon=2, render_mode="rgb_array")
    obs, _ = env.reset(seed=1)
    row = env.task.reference_actions[0].astype(np.float32)
    _, r1, term, trunc, info = env.step(row)
    assert r1 == 0.0 and not term and not trunc
    _, r2, term, trunc, info = env.step(row)
    assert trunc and not term and r2 == pytest.approx(info["task_reward"])
    frame = env.render()
    assert frame.shape == (480, 640, 3) and frame.dtype == np.uint8 and frame.std() > 0


def test_tactile_markers_move_when_the_gel_touches():
    env = ThinShellTaskEnv(cheap("separating"), horizon=4, sheet_samples=4, marker_count=8)
    obs0, _ = env.reset()
    close = np.zeros(env.task.action_dim, np.float32)
    close[-1] = -0.0006
    for _ in range(4):
        obs, *_ = env.step(close)
    n_sheet = 3 * 4
    markers0, markers = obs0[n_sheet:n_sheet + 8 * 3], obs[n_sheet:n_sheet + 8 * 3]
    assert np.allclose(markers0, 0.0, atol=1e-9)
    assert np.max(np.abs(markers)) > 1e-6


def test_infeasible_state_terminates_with_a_penalty():
    t = dataclasses.replace(cheap("folding_l"))
    from sim_core.tasks.spec import Infeasibility

    t = dataclasses.replace(t, infeasible=Infeasibility(max_force_N=1e-9))
    env = ThinShellTaskEnv(t, horizon=5, infeasible_penalty=2.0)
    env.reset()
    for _ in range(5):
        _, r, term, trunc, info = env.step(t.reference_actions[0].astype(np.float32))
        if term:
            break
    assert term and info["infeasible"].startswith("excessive force")
    assert r == pytest.approx(info["task_reward"] - 2.0)
