"""The task stage of ``thinshell demo`` (thinshell_ros.demo_task) at a tiny budget, over real DDS: the task
robot (sim node subprocess on a hidden Forming scene), the deploy node, sysid on the task recording,
the optimiser on the fitted task scene, the deployed optimised run and its comparison with the reward."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from rich.console import Console

from sim_core.scenes import load_scene
from sim_core.trajectory_file import read_trajectory
from sysid.bagio import open_bag
from sysid.compare import compare_recording
from sysid.observation import ObservationWarning
from thinshell_ros.demo_loop import HIDDEN
from thinshell_ros.demo_task import TASK_HIDDEN, TaskStageSettings, carried_values, recorded_reward, run_task_stages

TINY = TaskStageSettings(horizon=10, episodes=1, sysid_args=("--params", "sheet.bending_stiffness", "--max-nfev", "2"))


def test_the_task_robot_starts_from_the_scene_state_as_it_would_after_the_nodes_settling(tmp_path):
    """The task robot runs with ``settle_steps_max:=0`` (TASK_ROBOT_ARGS): the sim node's start-up settling
    (its cap, the solver it builds) does not bring the Forming sheet to rest and puts it back to the scene's
    own state, the state the optimiser's rollouts and the task replays start from; off, it starts there at
    once instead of after 400 Forming steps."""
    from sim_core.optim.tasks import task_at_horizon
    from sim_core.settle import settle
    from sim_core.simulation import Simulation
    from sim_core.solver_config import SolverConfig
    from thinshell_ros.demo_task import TASK_ROBOT_ARGS, write_task_scenes
    from thinshell_ros.sim_node import DEFAULT_SETTLE_STEPS_MAX

    assert TASK_ROBOT_ARGS == ("-p", "settle_steps_max:=0")
    _, hidden = write_task_scenes(task_at_horizon("forming", None), tmp_path, {**carried_values(HIDDEN), **TASK_HIDDEN})
    sim = Simulation.from_scene(hidden, solver_config=SolverConfig(repeat_fixed_points=True, sleeping=True,
                                                                   carried_start=True))
    x_file = sim.state.x.copy()
    info = settle(sim, DEFAULT_SETTLE_STEPS_MAX)
    assert not info.settled and info.steps == DEFAULT_SETTLE_STEPS_MAX, info
    assert info.displacement > 1e-4, info       # the sheet keeps moving (0.02 m after 400 steps)
    assert np.array_equal(sim.state.x, x_file) and not np.any(sim.state.v) and sim.state.step_index == 0


def test_carried_values_map_the_tactile_gel_onto_the_task_dome():
    assert carried_values({"gel.youngs_modulus": 4.1e5, "friction.gel_sheet": 0.6}) == {"dome.youngs_modulus": 4.1e5}
    assert carried_values({"friction.gel_sheet": 0.6}) == {}


@pytest.mark.ros
def test_task_stage_optimises_on_the_fitted_scene_deploys_and_scores_the_robot(ros_env, tmp_path):
    res = run_task_stages(tmp_path, TINY, {"gel.youngs_modulus": 4.2e5}, HIDDEN, Console(quiet=True))
    out = tmp_path / "task"
    nominal, hidden, fitted = (load_scene(p) for p in (res.nominal_scene, res.hidden_scene, res.fitted_scene))
    d0, d_true = nominal.get_parameter("sheet.bending_stiffness"), TASK_HIDDEN["sheet.bending_stiffness"]
    assert hidden.get_parameter("sheet.bending_stiffness") == d_true != d0
    assert hidden.get_parameter("dome.youngs_modulus") == HIDDEN["gel.youngs_modulus"]   # the tactile robot's gel
    assert fitted.get_parameter("dome.youngs_modulus") == 4.2e5                          # carried from the fit
    d_fit = fitted.get_parameter("sheet.bending_stiffness")
    assert d_fit == res.fit["params"]["sheet.bending_stiffness"]
    assert abs(d_fit - d_true) < 0.5 * abs(d0 - d_true)        # the identification run moved it towards the truth
    # both robot runs state the nominal scene and hold the deploy node's commands and the sheet
    # (every command the deploy node published is in the robot's bag)
    for bag, run in ((res.id_bag, res.id_deploy), (res.deployed_bag, res.deploy)):
        assert load_scene(bag / "scene.yaml").get_parameter("sheet.bending_stiffness") == d0
        counts = {t: i.message_count for t, i in open_bag(bag).topics.items()}
        assert counts["/thinshell/dome/pose_cmd"] == run["published"] >= 10, (counts, run)
        assert counts["/thinshell/sheet/points"] > 10, counts
    assert res.id_deploy["state"] == res.deploy["state"] == "completed"
    # the optimiser ran on the fitted scene and wrote the trajectory that was deployed
    result = json.loads((out / "optimise" / "result.json").read_text())
    assert result["episodes"] == 1 and result["method"] == "gd" and result["horizon"] == 10
    traj = read_trajectory(res.trajectory)
    assert traj.effectors == ["dome"] and traj.waypoint_count == 11 and res.deploy["published"] >= 10
    assert traj.prediction["reward"] == pytest.approx(result["best_reward"])
    # the comparison: the fitted task scene predicts the deployed run better than the nominal one, and the
    # reward achieved on the robot is the one measured on the recording
    cmp = res.comparison
    assert cmp["better"] == {"sheet_points": "fitted"}
    assert cmp["rms"]["sheet_points"]["fitted"] < 0.5 * cmp["rms"]["sheet_points"]["nominal"]
    reward = cmp["reward"]
    assert reward["task"] == "Forming" and reward["unit"] == "m^2"
    assert reward["recording"] == pytest.approx(recorded_reward_at(res.deployed_bag), rel=1e-12)
    assert abs(reward["predicted"]["fitted"] - reward["recording"]) < abs(reward["predicted"]["nominal"] - reward["recording"])
    assert np.isfinite(res.id_reward) and res.id_reward < 0
    # the chain deploy -> record -> replay is exact: the robot's own (hidden) scene replays the deployed run
    # to the robot's sheet-point noise (10 um per axis) and predicts the reward it achieved
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ObservationWarning)   # "no tactile sensor"
        truth = compare_recording(res.deployed_bag, [("hidden", res.hidden_scene)], dt=0.005, task="forming",
                                  horizon=10)
    assert truth.rms["hidden"]["sheet_points"]["whitened_rms"] < 1.5
    assert truth.reward["predicted"]["hidden"] == pytest.approx(reward["recording"], rel=0.02)
    assert (out / "compare" / "report.html").is_file() and "reward achieved on the recording" in (
        out / "compare" / "report.md").read_text()


def recorded_reward_at(bag):
    from sim_core.optim.tasks import task_at_horizon

    return recorded_reward(task_at_horizon("forming", 10), bag)
