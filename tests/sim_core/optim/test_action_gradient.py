"""The adjoint gradient of a task reward w.r.t. every per-step action (sim_core.optim.episode)
against central finite differences of the rollout, on Forming and Folding (short horizons)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.optim.actions import ControlPointDecoder
from sim_core.optim.episode import Episode
from sim_core.solver_config import SolverConfig
from tests.sim_core.optim.task_support import folding_task, forming_task, short_task

TIGHT = SolverConfig(tol_velocity=1e-9, tol_force=5e-8, projection="none", dt_halvings_on_failure=0)


def _actions(task, seed, press):
    """Random actions within 40 % of the bounds, pressing down by at least ``press`` m per step
    (Folding's dome must reach the fold to act on it)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-0.4, 0.4, size=(task.horizon, task.action_dim)) * task.action_high
    a[:, 2] = -np.abs(a[:, 2]) * (1 - press / 1e-3) - press
    return a


@pytest.mark.parametrize("make, press, entries", [
    (forming_task, 0.0, [(0, 0), (0, 2), (1, 4), (2, 1), (2, 3), (2, 5)]),
    (folding_task, 6e-4, [(0, 0), (0, 2), (1, 3), (2, 2), (2, 4), (1, 5)]),
])
def test_reward_gradient_matches_central_differences(make, press, entries):
    task = make(horizon=3)
    ep = Episode(task, solver_config=TIGHT)
    a = _actions(task, 3, press)
    res, grad, _ = ep.reward_gradient(a)
    assert res.feasible and np.isfinite(res.reward)
    assert np.abs(grad).max() > 0.0
    for i, j in entries:
        h = 1e-6 if j < 3 else 1e-5
        up, down = a.copy(), a.copy()
        up[i, j] += h
        down[i, j] -= h
        fd = (ep.run(up).reward - ep.run(down).reward) / (2 * h)
        scale = np.abs(grad).max()
        assert grad[i, j] == pytest.approx(fd, rel=2e-3, abs=2e-4 * scale), (i, j, grad[i, j], fd)


def test_control_points_decode_piecewise_constant_in_original_units():
    task = forming_task(horizon=5)
    d = ControlPointDecoder.for_task(task, control_points=2)
    z = np.zeros(d.dim)
    z[0], z[6 + 2] = 1.0, -100.0  # 1 unit of x at point 0; far below the z bound at point 1
    a = d.decode(z)
    assert a.shape == (5, 6)
    np.testing.assert_allclose(a[:3, 0], 0.0003 / 5)  # steps 0-2: control point 0
    np.testing.assert_allclose(a[3:, 0], 0.0)
    np.testing.assert_allclose(a[3:, 2], -1e-3)  # clipped to the per-step bound
    low, high = d.bounds()
    np.testing.assert_allclose(high[:3], 1e-3 / (0.0003 / 5))


def test_gripper_action_gradient_matches_central_differences():
    """The finger-opening increments (reverse cumulative sum of the adjoint's opening derivatives)."""
    task = short_task("following", 2)
    ep = Episode(task, solver_config=TIGHT)
    a = np.zeros((2, task.action_dim))
    a[:, 6] = -0.3 * task.action_high[6]  # close the fingers
    a[:, 2] = -2e-4
    res, grad, _ = ep.reward_gradient(a)
    assert res.feasible and abs(grad[0, 6]) > 1e-3  # the fingers touch: the opening matters
    for i, j in [(0, 6), (1, 6), (0, 0)]:
        h = 1e-6
        up, down = a.copy(), a.copy()
        up[i, j] += h
        down[i, j] -= h
        fd = (ep.run(up).reward - ep.run(down).reward) / (2 * h)
        assert grad[i, j] == pytest.approx(fd, rel=2e-3, abs=1e-5 * np.abs(grad).max()), (i, j, grad[i, j], fd)
