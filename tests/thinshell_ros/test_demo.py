"""The scripted commander (planning, scheduling, over DDS against a kinematic sim) and ``thinshell demo``."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from sim_core.errors import ConfigError
from sim_core.scenes.scene_file import load_scene_file, load_yaml
from tests.thinshell_ros.conftest import REPO, spin_until
from tests.thinshell_ros.fake_sim import HOME, FakeSimulation
from thinshell_ros import conversions as cv
from thinshell_ros.commander import CommandSchedule, CommanderNode, plan_from_observation
from thinshell_ros.demo import make_run_dir
from thinshell_ros.runtime import SENSOR_QOS
from thinshell_ros.sim_node import SimNode
from thinshell_ros.trajectory import Trajectory

SCENE = REPO / "config" / "scenes" / "press_slide.yaml"


def _scene(**sensor_overrides):
    doc = load_yaml(SCENE.read_text())
    doc["sensors"]["tactile"].update(sensor_overrides)
    return load_scene_file(doc), doc


def _flat_sheet(doc) -> np.ndarray:
    sx, sy = np.meshgrid(np.linspace(0, 0.1, 5), np.linspace(-0.03, 0.03, 3))
    return np.stack([sx.ravel(), sy.ravel(), np.full(sx.size, doc["sheet"]["origin"][2])], axis=1)


def test_plan_presses_depth_below_the_sheet_top_slides_releases_and_lifts():
    scene, doc = _scene()
    start = np.array(doc["effectors"]["ee"]["initial_pose"], float)
    top = doc["sheet"]["origin"][2] + 0.5 * doc["sheet"]["thickness"]
    traj = plan_from_observation(scene, start, _flat_sheet(doc), depth=1e-3, slide=0.01, approach_speed=0.04,
                                 press_speed=0.005, slide_speed=0.02, hold=0.05, release=5e-4)
    assert traj.effector == "ee"
    x0, z0 = start[0], start[2]
    # the gel normal is world -z (quaternion (1,0,0,0)): touch, press, hold, slide, release, lift
    expected_xz = [(x0, z0), (x0, top), (x0, top - 1e-3), (x0, top - 1e-3), (x0 + 0.01, top - 1e-3),
                   (x0 + 0.01, top + 5e-4), (x0 + 0.01, z0)]
    np.testing.assert_allclose(traj.poses[:, [0, 2]], expected_xz, atol=1e-12)
    np.testing.assert_allclose(traj.poses[:, 3:], np.tile(start[3:], (len(traj.t), 1)))  # orientation kept
    durations = [(z0 - top) / 0.04, 1e-3 / 0.005, 0.05, 0.01 / 0.02, 1.5e-3 / 0.005, (z0 - top - 5e-4) / 0.04]
    np.testing.assert_allclose(np.diff(traj.t), durations)
    short = plan_from_observation(scene, start, _flat_sheet(doc), "press_slide", depth=1e-3, slide=0.01)
    np.testing.assert_allclose(short.poses, traj.poses[:5], atol=1e-12)  # press_slide stops after the slide


def test_plan_uses_the_sensor_mount_and_the_highest_sheet_point():
    scene, doc = _scene(mount=[0.0, 0.0, -0.002, 0.0, 0.0, 0.0, 1.0])  # 2 mm along the effector's -z = world +z
    start = np.array(doc["effectors"]["ee"]["initial_pose"], float)
    pts = _flat_sheet(doc)
    pts[7, 2] += 0.004  # a bump: the highest point decides first contact
    traj = plan_from_observation(scene, start, pts, depth=5e-4)
    top = pts[:, 2].max() + 0.5 * doc["sheet"]["thickness"]
    assert traj.poses[:, 2].min() == pytest.approx(top - 5e-4 - 0.002, abs=1e-12)


def test_plan_errors_name_the_problem():
    scene, doc = _scene()
    start = np.array(doc["effectors"]["ee"]["initial_pose"], float)
    up = start.copy()
    up[3:] = [0, 0, 0, 1]  # sensor z along world +z: faces away from the sheet
    with pytest.raises(ConfigError, match="does not face down"):
        plan_from_observation(scene, up, _flat_sheet(doc))
    with pytest.raises(ConfigError, match="sheet point"):
        plan_from_observation(scene, start, np.zeros((0, 3)))
    with pytest.raises(ConfigError, match="no sensor 'left'"):
        plan_from_observation(scene, start, _flat_sheet(doc), sensor="left")
    with pytest.raises(ConfigError, match="non-finite"):
        plan_from_observation(scene, np.r_[np.nan, start[1:]], _flat_sheet(doc))
    with pytest.raises(ConfigError, match="press_speed must be finite and > 0"):
        plan_from_observation(scene, start, _flat_sheet(doc), press_speed=0.0)
    with pytest.raises(ConfigError, match="unknown scripted trajectory 'wiggle'"):
        plan_from_observation(scene, start, _flat_sheet(doc), "wiggle")


def test_schedule_publishes_at_its_rate_with_one_period_of_look_ahead():
    poses = np.tile([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], (2, 1))
    poses[1, 0] = 1.0
    traj = Trajectory("ee", np.array([0.0, 1.0]), poses)  # x = t
    sched = CommandSchedule(traj, t0=2.0, rate=100.0, settle=0.05)
    ticks = 2.0 + 0.005 * np.arange(40)  # a clock at 200 Hz
    sent = [(t, sched.due(t)) for t in ticks]
    sent = [(t, p) for t, p in sent if p is not None]
    assert len(sent) == 20  # every other tick
    for t, p in sent:
        assert p[0] == pytest.approx(t - 2.0 + 0.01)
    assert sched.due(5.0)[0] == pytest.approx(1.0)  # a jump gives one command, held at the end
    assert sched.due(5.001) is None
    assert not sched.finished(3.04) and sched.finished(3.05)
    assert sched.progress(2.525) == pytest.approx(0.5) and sched.progress(9.0) == 1.0
    with pytest.raises(ConfigError, match="rate must be finite and > 0"):
        CommandSchedule(traj, 0.0, rate=0.0)


@pytest.mark.ros
def test_commander_drives_the_sim_node_through_press_slide_lift(ros_context):
    """Over DDS: the kinematic sim node follows the commander's plan (sim time from /clock)."""
    sim = SimNode(sim=FakeSimulation(), context=ros_context,
                  parameter_overrides=[Parameter("mode", value="fast"), Parameter("mesh_rate", value=0.0)])
    cmd = CommanderNode(context=ros_context, parameter_overrides=[
        Parameter("scene", value=str(SCENE)), Parameter("approach_speed", value=0.1), Parameter("depth", value=1e-3),
        Parameter("press_speed", value=0.05), Parameter("slide_speed", value=0.1), Parameter("slide", value=0.01),
        Parameter("hold", value=0.02), Parameter("rate", value=100.0), Parameter("use_sim_time", value=True)])
    poses = []
    cmd.create_subscription(PoseStamped, "/thinshell/ee/pose", lambda m: poses.append(cv.pose_from_msg(m)[1]),
                            SENSOR_QOS)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(sim)
    ex.add_node(cmd)
    try:
        assert spin_until(ex, cmd.done.is_set, 30.0), (cmd.progress(), cmd.sim_time)
        assert cmd.schedule is not None and cmd.progress() == 1.0
        # the fake sheet points lie at z = 0.3 mm; the scene's half thickness is 0.15 mm
        top = 0.0003 + 0.00015
        p = np.array(poses)
        assert p[:, 2].min() == pytest.approx(top - 1e-3, abs=1e-4)
        assert p[:, 0].max() == pytest.approx(HOME[0] + 0.01, abs=1e-4)
        assert p[-1, 2] == pytest.approx(HOME[2], abs=2e-4) and p[-1, 0] == pytest.approx(HOME[0] + 0.01, abs=1e-4)
        assert np.abs(np.diff(p[:, :3], axis=0)).max() <= 1e-3 + 1e-12  # never beyond the per-step limit
        assert cmd.schedule.sent > 10
    finally:
        ex.shutdown(timeout_sec=0)
        cmd.destroy_node()
        sim.destroy_node()


def test_commander_rejects_bad_parameters(ros_context):
    with pytest.raises(ConfigError, match="'script' must be one of"):
        CommanderNode(context=ros_context, parameter_overrides=[Parameter("script", value="wiggle")])
    with pytest.raises(ConfigError, match="'slide_speed' must be finite and > 0"):
        CommanderNode(context=ros_context, parameter_overrides=[Parameter("slide_speed", value=0.0)])
    with pytest.raises(ConfigError, match="'depth' must be finite and >= 0"):
        CommanderNode(context=ros_context, parameter_overrides=[Parameter("depth", value=-1e-3)])


@pytest.mark.slow
@pytest.mark.ros
def test_quick_demo_records_a_bag_and_writes_a_sysid_report(ros_env, tmp_path):
    """``thinshell demo --quick`` end to end: hidden robot (sim node subprocess) + commander over DDS, SIGINT,
    sysid with the fitted scene, trajectory file, deploy node on the robot (recorded), comparison, and the
    task stage at a tiny budget."""
    from sysid.bagio import open_bag
    from sysid.results import load_fit_json
    from thinshell_ros.demo import demo_main

    assert demo_main(["--quick", "--out", tmp_path]) == 0
    (run,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    bag = open_bag(run / "recorded_bag")
    counts = {t: i.message_count for t, i in bag.topics.items()}
    for topic in ("/thinshell/ee/pose_cmd", "/thinshell/ee/pose", "/thinshell/tactile/wrench",
                  "/thinshell/tactile/markers", "/thinshell/sheet/points", "/clock"):
        assert counts.get(topic, 0) > 10, counts
    pose = bag.series["pose"].values
    wrench = bag.series["wrench"].values
    assert pose[:, 2].min() < pose[0, 2] - 3e-3  # pressed down onto the card ...
    assert wrench[:, 2].min() < -0.05  # ... with a normal force ON the gel along -z of the sensor frame
    assert pose[-1, 2] == pytest.approx(pose[0, 2], abs=2e-4) and pose[-1, 0] > pose[0, 0] + 5e-4  # slid, lifted
    doc = load_fit_json(run / "sysid" / "fit.json")
    # the demo's parameter, with the calibration's stick speed fitted beside it (FitOptions.fit_eps_v), and the gel
    # law: thinshell sysid's default --gel-element auto keeps the scene's law on the quick demo's coarse replay mesh
    # (3,3,2 against the scene's: the comparison would measure the mesh, sysid.gel_law.auto_not_applicable)
    assert set(doc["fit"]["parameters"]) == {"gel.youngs_modulus", "contact.eps_v"}
    assert doc["diagnostics"]["gel_law"]["requested"] == "auto"
    assert doc["diagnostics"]["gel_law"]["element"] == "stable_neohookean"
    assert "mesh" in doc["diagnostics"]["gel_law"]["kept"]
    assert {"report.html", "report.md"} <= {p.name for p in (run / "sysid").iterdir()}
    summary = json.loads((run / "demo.json").read_text())
    assert summary["message_counts"] == counts and summary["timings_s"]["total_s"] > 0
    # the phases (thinshell_ros.demo_clock): the deployment and the task's identification run beside the
    # diagnosis (none with --quick), the comparison beside the task; each with its wall and CPU seconds
    phases = summary["phases"]
    assert list(phases) == ["robot", "deploy, task identification run", "sysid", "compare | task"]
    assert phases["compare | task"]["stages"][0] == "compare" and "task_optimise" in phases["compare | task"]["stages"]
    assert all(ph["cpu_s"] > 0 and ph["wall_s"] > 0 for ph in phases.values()), phases
    assert sum(ph["wall_s"] for ph in phases.values()) <= summary["timings_s"]["total_s"]
    assert (run / "compare.log").is_file() and summary["timings_s"]["compare_cpu_s"] > 0
    # the loop: the recording states the nominal scene, the robot ran the hidden one
    from sim_core.scenes.scene_file import load_scene_file
    from sim_core.simulation import Simulation
    from sim_core.trajectory_file import read_trajectory

    assert load_scene_file(run / "recorded_bag" / "scene.yaml").sensors["tactile"].gel_material.youngs_modulus == 3.0e5
    hidden = Simulation.from_scene(run / "robot_hidden_scene.yaml")
    assert hidden.get_parameter("gel.youngs_modulus") == summary["hidden"]["gel.youngs_modulus"] != 3.0e5
    assert hidden.model.candidates  # the concealed effect
    fitted = Simulation.from_scene(run / "fitted_scene.yaml")
    assert fitted.get_parameter("gel.youngs_modulus") == pytest.approx(summary["fit"]["params"]["gel.youngs_modulus"])
    assert read_trajectory(run / "trajectory.yaml").effectors == ["ee"]
    assert summary["deploy"]["state"] == "completed" and summary["deploy"]["published"] > 10
    deployed = open_bag(run / "deployed_bag")
    # the robot records the commands it took: keep-last-1 command QoS (INTERFACES.md) lets a newer command
    # replace one not yet taken while a step runs
    assert 0.5 * summary["deploy"]["published"] <= len(deployed.series["pose_cmd"]) <= summary["deploy"]["published"]
    assert deployed.series["wrench"].values[:, 2].min() < -0.05  # the deployed press touched the card
    assert set(summary["comparison"]["rms"]["wrench"]) == {"fitted", "nominal"}
    assert (run / "compare" / "report.html").is_file() and (run / "report.md").is_file()
    # the task stage: Forming optimised on the fitted task scene, deployed, scored (tests/thinshell_ros/test_demo_task.py)
    task = summary["task"]
    assert task["carried"] == {"dome.youngs_modulus": summary["fit"]["params"]["gel.youngs_modulus"]}
    assert task["deploy"]["state"] == "completed" and task["optimise"]["method"] == "gd"
    assert set(task["comparison"]["reward"]["predicted"]) == {"fitted", "nominal"}
    assert "achieved on the robot by the optimised trajectory" in (run / "report.md").read_text()
    with pytest.raises(ConfigError, match="exists; use --force"):
        make_run_dir(tmp_path, force=False, stamp=run.name)


@pytest.mark.ros
@pytest.mark.parametrize("namespace", [None, "/cell2"])
def test_commander_runs_on_wall_time_without_clock(ros_context, namespace):
    """Over DDS against a robot that publishes no /clock: the commander plans and completes on wall time
    (in the default /thinshell topics, or in the ROS namespace it is started in)."""
    from tests.thinshell_ros.wall_robot import WallRobot

    robot = WallRobot(ros_context, namespace=namespace or "/thinshell")
    cmd = CommanderNode(context=ros_context, cli_args=["--ros-args", "-r", f"__ns:={namespace}"] if namespace else None,
                        parameter_overrides=[
        Parameter("scene", value=str(SCENE)), Parameter("approach_speed", value=0.1), Parameter("depth", value=1e-3),
        Parameter("press_speed", value=0.05), Parameter("slide_speed", value=0.1), Parameter("slide", value=0.01),
        Parameter("hold", value=0.02), Parameter("rate", value=100.0)])
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(robot)
    ex.add_node(cmd)
    try:
        assert robot.count_publishers("/clock") == 0
        t0 = time.monotonic()
        assert spin_until(ex, cmd.done.is_set, 15.0), (cmd.progress(), cmd.sim_time)
        assert cmd.schedule is not None and cmd.progress() == 1.0 and cmd.schedule.sent > 10
        # wall time: the motion took about its planned duration
        assert time.monotonic() - t0 >= cmd.schedule.end - cmd.schedule.t0 - 0.05
        assert not robot.rejected
        assert spin_until(ex, lambda: abs(robot.sim.state.effector_pose["ee"][0] - HOME[0] - 0.01) < 1e-4, 2.0)
    finally:
        ex.shutdown(timeout_sec=0)
        cmd.destroy_node()
        robot.destroy_node()
