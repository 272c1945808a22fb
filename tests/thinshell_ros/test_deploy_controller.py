"""The deploy node driving a real arm's controller interfaces over DDS (tests/thinshell_ros/cell_controller.py):
frames and messages of each command interface, the sensor watchdog with a stream killed mid-press,
on_abort hold and retract, the wrench tare, and parameter validation."""

from __future__ import annotations

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from sim_core.errors import ConfigError
from sim_core.trajectory_file import Trajectory
from sim_core.transforms import matrix_to_pose, quat_from_rotvec, quat_multiply
from tests.thinshell_ros.cell_controller import (SENSOR_IN_TOOL, WORLD_IN_BASE, CellController, effector_in_world_truth,
                                                 tool_in_base_truth)
from tests.thinshell_ros.conftest import spin_until
from tests.thinshell_ros.fake_sim import HOME
from thinshell_ros import conversions as cv
from thinshell_ros.deploy_node import DeployNode
from thinshell_ros.deploy_plan import rotation_angle

pytestmark = pytest.mark.ros
CELL = {"world_in_base": WORLD_IN_BASE, "sensor_in_tool": SENSOR_IN_TOOL}


def _line(dx: float = 0.0, dz: float = 0.0, duration: float = 1.0, n: int = 11, yaw: float = 0.0) -> Trajectory:
    """From HOME to HOME + (dx, 0, dz), turning by ``yaw`` rad about world z, at constant speed."""
    a = np.linspace(0.0, 1.0, n)
    poses = np.tile(HOME, (n, 1))
    poses[:, 0] += a * dx
    poses[:, 2] += a * dz
    for i in range(n):
        poses[i, 3:] = quat_multiply(quat_from_rotvec(np.array([0.0, 0.0, yaw * a[i]])), HOME[3:])
    return Trajectory(t=np.linspace(0.0, duration, n), poses={"ee": poses}, scene_name="fake")


def _run(ctx, robot, traj, **params):
    node = DeployNode(trajectory=traj, context=ctx, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()])
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(robot)
    ex.add_node(node)
    return node, ex


def _close(ex, *nodes) -> None:
    ex.shutdown(timeout_sec=0)
    for n in nodes:
        n.destroy_node()


def test_pose_target_is_the_tool_link_in_the_base_frame_through_base_and_mount(ros_context):
    """A non-identity base and sensor mount: every target is tool0 in base_link, equal to the cell's own chain;
    the measured pose comes back as tool0 in base_link too, and the gel ends where the trajectory ends."""
    robot = CellController(ros_context, pose_in_base=True)
    traj = _line(dx=0.004, dz=0.001, duration=0.6, n=7, yaw=0.1)
    node, ex = _run(ros_context, robot, traj, command_interface="pose_target", sensor_timeout=2.0, start_timeout=20.0,
                    **CELL)
    try:
        assert spin_until(ex, node.done.is_set, 30.0), node.status()
        assert node.state == "completed", node.reason
        assert spin_until(ex, lambda: len(robot.received["pose_target"]) == node.published, 3.0)
        frames = {f for f, _, _ in robot.received["pose_target"]}
        assert frames == {"base_link"} and not robot.wrong_frames and not robot.received["thinshell"]
        for _, target, stamp in robot.received["pose_target"]:  # the trajectory at the tick's time, through the cell
            k = round((stamp * 1e-9 - node.schedule.t0) / node.schedule.period)
            expected = matrix_to_pose(tool_in_base_truth(traj.sample_pose("ee", k * node.schedule.period)))
            np.testing.assert_allclose(target[:3], expected[:3], atol=1e-9)
            assert rotation_angle(target[3:], expected[3:]) < 1e-9
        expected = matrix_to_pose(tool_in_base_truth(HOME))
        first = node.frames.tool_in_base(HOME)
        np.testing.assert_allclose(first[:3], expected[:3], atol=1e-12)
        assert rotation_angle(first[3:], expected[3:]) < 1e-9
        # by hand: HOME's gel at world (0.06, 0, 0.004) with R = diag(1, -1, -1); the tool origin in the sensor
        # frame is -R_ts^T p_ts = (0.05, 0, -0.01), in world (0.11, 0, 0.014); in base (world x = base y, origin
        # (0.4, -0.1, 0.2)): (0.4, 0.01, 0.214)
        np.testing.assert_allclose(first[:3], [0.4, 0.01, 0.214], atol=1e-12)
        end = traj.poses["ee"][-1]
        assert spin_until(ex, lambda: np.linalg.norm(robot.pose[:3] - end[:3]) < 1e-9, 3.0), robot.pose - end
        assert rotation_angle(robot.pose[3:], end[3:]) < 1e-9
    finally:
        _close(ex, node, robot)


def test_twist_commands_drive_the_tool_link_along_the_trajectory(ros_context):
    robot = CellController(ros_context, pose_in_base=True)
    traj = _line(dx=0.004, duration=0.8, n=9, yaw=0.2)
    node, ex = _run(ros_context, robot, traj, command_interface="twist", sensor_timeout=2.0, start_timeout=20.0,
                    max_linear_speed=0.02, **CELL)
    try:
        assert spin_until(ex, node.done.is_set, 30.0), node.status()
        assert node.state == "completed", node.reason
        assert spin_until(ex, lambda: len(robot.received["twist"]) > node.published
                          and np.all(robot.received["twist"][-1][1] == 0.0), 3.0)
        twists = np.array([t for _, t, _ in robot.received["twist"]])
        assert {f for f, _, _ in robot.received["twist"]} == {"base_link"} and not robot.wrong_frames
        assert np.linalg.norm(twists[:, :3], axis=1).max() <= 0.02 * (1 + 1e-9)  # limited
        assert np.all(twists[-1] == 0.0) and not np.any(np.all(twists[:-1] == 0.0, axis=1))  # one zero twist: the end
        # the first twist, the robot at the start (no feedback): the tool origin 5 cm and 1 cm off the gel
        # (r = (0.05, 0, 0.01) m in world) moves at v_ee + w x r = (0.005, 0.0125, 0) m/s in world, i.e.
        # (-0.0125, 0.005, 0) in base; the yaw about world z is a rotation about base z (0.25 rad/s)
        # (a busy process may skip tick 0; later ticks add the feedback on a lagging arm)
        stamps = [st for _, _, st in robot.received["twist"]]
        if cv.seconds_to_ns(node.schedule.t0) in stamps:
            first = twists[stamps.index(cv.seconds_to_ns(node.schedule.t0))]
            np.testing.assert_allclose(first, [-0.0125, 0.005, 0.0, 0.0, 0.0, 0.25], atol=1e-4)
        during = twists[:node.published - 1]  # the last tick has no feed-forward
        assert np.abs(twists[:, 3:5]).max() < 1e-9 and np.all(during[:, 5] > 0.15)
        assert 0.2 < np.median(during[:, 5]) < 0.4 and np.all(during[:, 0] < 0) and np.all(during[:, 1] > 0)
        # completed once settled: the measured pose within settle_tolerance 0.2 mm / 0.005 rad of the end; the
        # arm then runs on for the zero twist's latency (the line ends at full speed: 5 mm/s, 0.25 rad/s)
        end = traj.poses["ee"][-1]
        measured = node._measured["ee"]
        assert np.linalg.norm(measured[:3] - end[:3]) <= 2e-4 and rotation_angle(measured[3:], end[3:]) <= 0.005
        assert np.linalg.norm(robot.pose[:3] - end[:3]) < 1e-3, robot.pose - end
        assert rotation_angle(robot.pose[3:], end[3:]) < 0.03
    finally:
        _close(ex, node, robot)


TOP = 0.0035  # the plane the cell presses on: contact from 0.5 mm below HOME
TIMEOUT = 1.0  # sensor_timeout where a stream is killed: a busy test process stalls for a few tenths of a second


def _press(duration: float = 4.0) -> Trajectory:
    """0.375 mm/s down, ending 1 mm into the plane: contact after 1.3 s; a stream killed 0.1 mm into the plane
    (1.6 s) is found stale after TIMEOUT, well before the end even when this process is starved."""
    return _line(dz=-0.0015, duration=duration, n=41)


@pytest.mark.parametrize("interface, stream", [("pose_target", "wrench"), ("thinshell", "wrench"),
                                               ("twist", "wrench"), ("thinshell", "pose")])
def test_a_stream_killed_mid_press_aborts_and_hold_commands_the_measured_pose(ros_context, interface, stream):
    robot = CellController(ros_context, pose_in_base=interface != "thinshell", top=TOP)
    node, ex = _run(ros_context, robot, _press(), command_interface=interface, sensor_timeout=TIMEOUT, start_timeout=20.0,
                    on_abort="hold", abort_hold_time=0.4, **CELL)
    try:
        assert spin_until(ex, lambda: robot.pose[2] < TOP - 1e-4 or node.done.is_set(), 30.0), node.status()
        assert node.state == "running", node.reason  # pressing: 0.1 mm into the plane
        assert node.status()["sensor_age_s"]["/thinshell/tactile/wrench"] < TIMEOUT
        setattr(robot, f"publish_{stream}", False)
        assert spin_until(ex, node.done.is_set, 20.0), node.status()
        assert node.state == "aborted" and node.abort_action == "done"
        topic = "/thinshell/tactile/wrench" if stream == "wrench" else "/thinshell/ee/pose"
        assert f"the newest message on {topic} is" in node.reason and "sensor_timeout 1 s" in node.reason, node.reason
        held = node._abort["start"]["ee"]  # the measured pose at the abort
        n_traj = node.published
        spin_until(ex, lambda: False, 0.3)
        cmds = robot.received[interface][n_traj:]
        assert len(cmds) == node.abort_published >= 2
        for _, c, _ in cmds:
            if interface == "pose_target":  # q and -q are one orientation: at a 180 deg turn (the tool flipped
                # about x) the matrix-to-quaternion conversion's sign follows the rounding of the matrix's entries
                back = effector_in_world_truth(c)
                back[3:] *= np.sign(np.dot(back[3:], held[3:]))
                np.testing.assert_allclose(back, held, atol=1e-9)
            elif interface == "thinshell":
                np.testing.assert_allclose(c, held, atol=0.0)
            else:
                assert np.all(c == 0.0)
        # the controller stopped pressing: the gel stays where it was measured, short of the trajectory's end
        end_z = _press().poses["ee"][-1, 2]
        assert robot.pose[2] > end_z + 1e-4
        assert abs(robot.pose[2] - held[2]) < (1e-9 if interface != "twist" else 2e-4), (robot.pose[2], held[2])
    finally:
        _close(ex, node, robot)


@pytest.mark.parametrize("interface", ["pose_target", "twist"])
def test_retract_lifts_along_the_sensor_normal_at_the_approach_speed(ros_context, interface):
    robot = CellController(ros_context, pose_in_base=True, top=TOP)
    node, ex = _run(ros_context, robot, _press(), command_interface=interface, sensor_timeout=TIMEOUT, start_timeout=20.0,
                    on_abort="retract", retract_distance=0.003, approach_speed=0.01, abort_hold_time=0.3, **CELL)
    try:
        assert spin_until(ex, lambda: robot.pose[2] < TOP - 1e-4 or node.done.is_set(), 30.0), node.status()
        robot.publish_wrench = False
        assert spin_until(ex, node.done.is_set, 20.0), node.status()
        assert node.state == "aborted" and "tactile/wrench" in node.reason
        held = node._abort["start"]["ee"]
        plan = node._abort["plans"]["ee"]
        np.testing.assert_allclose(plan.direction, [0.0, 0.0, 1.0], atol=1e-12)  # the gel's normal is world -z
        spin_until(ex, lambda: False, 0.3)
        cmds = [c for _, c, _ in robot.received[interface][node.published:]]
        if interface == "pose_target":
            world = np.array([effector_in_world_truth(c) for c in cmds])
            assert np.all(np.diff(world[:, 2]) >= -1e-12) and world[-1, 2] == pytest.approx(held[2] + 0.003, abs=1e-9)
            np.testing.assert_allclose(world[:, :2], np.tile(held[:2], (len(world), 1)), atol=1e-9)
            assert robot.pose[2] == pytest.approx(held[2] + 0.003, abs=1e-9)
        else:
            lin = np.array([c[:3] for c in cmds])
            moving = lin[np.linalg.norm(lin, axis=1) > 0]
            np.testing.assert_allclose(moving, np.tile([0.0, 0.0, 0.01], (len(moving), 1)), atol=1e-12)  # base z = world z
            assert np.all(cmds[-1] == 0.0)
            assert 0.5 * 0.003 < robot.pose[2] - held[2] < 1.5 * 0.003
    finally:
        _close(ex, node, robot)


def test_wrench_tare_and_the_normal_force_limit(ros_context):
    """A sensor offset of -3 N along the normal: without a tare the normal force limit refuses the start;
    with a tare the line (out of contact) completes; a tare over tare_max_force is refused."""
    offset = np.array([0.0, 0.0, -3.0, 0.0, 0.0, 0.0])
    traj = _line(dx=0.002, duration=0.4, n=5)
    for params, state, words in (({}, "refused", "before the start: measured normal force 3 N on "
                                                  "/thinshell/tactile/wrench exceeds normal_force_limit 2 N"),
                                 ({"tare_window": 0.3}, "completed", ""),
                                 ({"tare_window": 0.3, "tare_max_force": 1.0}, "refused", "wrench tare: mean force 3 N")):
        robot = CellController(ros_context, wrench_offset=offset)
        node, ex = _run(ros_context, robot, traj, normal_force_limit=2.0, sensor_timeout=2.0, start_timeout=20.0,
                        **params)
        try:
            assert spin_until(ex, node.done.is_set, 30.0), node.status()
            assert node.state == state and words in node.reason, node.reason
            if state == "completed":
                np.testing.assert_allclose(node.tare.offset["tactile/wrench"], offset, atol=1e-12)
                # the 1 Hz diagnostics: state, the smallest force margin (tared: the whole normal limit), ages
                diag = {kv.key: kv.value for kv in node.diagnostic().values}
                assert diag["state"] == "completed" and diag["force_margin_limit"] == "normal_force_limit"
                assert float(diag["force_margin_N"]) == pytest.approx(2.0, abs=1e-9)
                assert float(diag["age_s /thinshell/tactile/wrench"]) < 2.0 and "age_s /thinshell/ee/pose" in diag
                got = []
                probe = Node("diag_probe", context=ros_context)
                probe.create_subscription(DiagnosticArray, "/diagnostics", lambda m: got.extend(m.status), 10)
                ex.add_node(probe)
                assert spin_until(ex, lambda: any(st.name == "/thinshell/thinshell_deploy: deploy" for st in got), 5.0)
                probe.destroy_node()
        finally:
            _close(ex, node, robot)


@pytest.mark.parametrize("params, match", [
    ({"command_interface": "joint"}, r"parameter 'command_interface': 'joint' is not one of \['thinshell', 'pose_target', 'twist'\]"),
    ({"on_abort": "stop"}, r"parameter 'on_abort': 'stop' is not one of \['hold', 'retract'\]"),
    ({"world_in_base": [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]}, r"parameter 'world_in_base' must be 7 finite numbers"),
    ({"sensor_in_tool": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]}, r"parameter 'sensor_in_tool': quaternion norm 0"),
    ({"base_frame": ""}, r"parameter 'base_frame' must be a frame name"),
    ({"wrench_in_sensor": [0.0, 0.0, float("nan"), 0.0, 0.0, 0.0, 1.0]}, r"parameter 'wrench_in_sensor' must be 7 finite"),
])
def test_bad_parameters_name_the_parameter(ros_context, params, match):
    with pytest.raises(ConfigError, match=match):
        DeployNode(trajectory=_line(), context=ros_context,
                   parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])


def test_a_measured_pose_in_an_unknown_frame_is_refused_naming_both(ros_context):
    robot = CellController(ros_context, pose_in_base=True)  # tool0 in base_link, but the node expects robot_base
    node, ex = _run(ros_context, robot, _line(), command_interface="pose_target", base_frame="robot_base",
                    start_timeout=20.0, **CELL)
    try:
        assert spin_until(ex, node.done.is_set, 20.0), node.status()
        assert node.state == "refused"
        assert ("/thinshell/ee/pose: frame_id 'base_link' is neither world_frame 'world' nor base_frame 'robot_base'"
                in node.reason), node.reason
        assert robot.received["pose_target"] == []
    finally:
        _close(ex, node, robot)


def test_the_per_cell_template_is_a_valid_params_file(ros_context):
    """config/nodes/deploy_node.yaml: every key is a parameter the node declares, and the node takes the file."""
    from tests.thinshell_ros.conftest import REPO

    path = REPO / "config" / "nodes" / "deploy_node.yaml"
    keys = set(__import__("yaml").safe_load(path.read_text())["/**/thinshell_deploy"]["ros__parameters"])
    node = DeployNode(trajectory=_line(dx=0.002), context=ros_context,
                      cli_args=["--ros-args", "--params-file", str(path), "-p", "dry_run:=true"])
    try:
        assert keys <= set(node._parameters), keys - set(node._parameters)
        assert node.state == "completed", node.reason
        assert node.interface == "pose_target" and node.on_abort_action == "retract"
        assert node.get_parameter("torque_limit").value == 0.3 and node.guard.torque == 0.3
        np.testing.assert_allclose(node.frames.sensor_in_tool, [0.0, 0.0, 0.065, 0.0, 0.0, 0.0, 1.0])
        assert "pose_target ('tool0' in 'base_link' on /cartesian_motion_controller/target_frame)" in node.reason
    finally:
        node.destroy_node()


@pytest.mark.parametrize("interface, topic", [("pose_target", "/thinshell/ee/pose_cmd"),
                                              ("twist", "/thinshell/ee/twist_cmd")])
def test_the_sim_node_stands_in_for_the_controller(ros_context, interface, topic):
    """The sim node as the controller: its world is the base frame (base_frame:=world, identity transforms)
    and the command topic is remapped onto its own pose_cmd / twist_cmd."""
    from tests.thinshell_ros.fake_sim import FakeSimulation
    from thinshell_ros.sim_node import SimNode

    sim = SimNode(sim=FakeSimulation(), context=ros_context, parameter_overrides=[
        Parameter("mode", value="realtime"), Parameter("mesh_rate", value=0.0)])
    traj = _line(dx=0.003, duration=0.6, n=7, yaw=0.1)
    node, ex = _run(ros_context, sim, traj, command_interface=interface, command_topic=topic, base_frame="world",
                    sensor_timeout=2.0, start_timeout=20.0)
    try:
        assert spin_until(ex, node.done.is_set, 30.0), node.status()
        assert node.state == "completed", node.reason
        spin_until(ex, lambda: False, 0.2)
        end, got = traj.poses["ee"][-1], sim.sim.state.effector_pose["ee"]
        if interface == "pose_target":
            np.testing.assert_allclose(got, end, atol=1e-12)
        else:  # settled within 0.2 mm / 0.005 rad, then the zero twist's latency at 5 mm/s, 0.17 rad/s
            assert np.linalg.norm(got[:3] - end[:3]) < 1e-3 and rotation_angle(got[3:], end[3:]) < 0.03
    finally:
        _close(ex, node, sim)


def test_a_stall_of_the_deploy_process_is_not_a_dead_sensor(ros_context):
    """The test process (robot and deploy node on one executor) stops for twice the sensor_timeout mid-motion,
    its queues drained first: the robot could send nothing meanwhile. The late tick restarts the watchdog's
    ages (the node's stall is not the sensor's) and the motion completes."""
    import time

    robot = CellController(ros_context, pose_in_base=True)
    node, ex = _run(ros_context, robot, _line(dx=0.004, duration=1.5, n=16), command_interface="pose_target",
                    sensor_timeout=0.4, start_timeout=20.0, **CELL)
    try:
        assert spin_until(ex, lambda: node.published > 20 or node.done.is_set(), 30.0), node.status()
        assert node.state == "running", node.reason
        robot.publish_pose = robot.publish_wrench = False  # take what is queued, then the process stops
        spin_until(ex, lambda: False, 0.05)
        time.sleep(0.8)
        robot.publish_pose = robot.publish_wrench = True
        assert spin_until(ex, node.done.is_set, 30.0), node.status()
        assert node.state == "completed", node.reason
    finally:
        _close(ex, node, robot)
