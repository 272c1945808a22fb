"""The sim node on a version-2 task scene: ``gripper_cmd`` over DDS changes the simulated opening."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64

from sim_core.scenes.task_scene import build_task_scene
from sim_core.simulation import Simulation
from tests.sim_core.scenes.test_task_scene_v2 import v2_scene
from tests.thinshell_ros.conftest import spin_until
from thinshell_ros import conversions as cv
from thinshell_ros.runtime import COMMAND_QOS, SENSOR_QOS
from thinshell_ros.sim_node import SimNode

pytestmark = pytest.mark.ros


def test_gripper_cmd_over_dds_changes_the_simulated_opening(ros_context):
    sim = Simulation(build_task_scene(v2_scene()))
    eff = sim.model.effectors["grip"]
    x0 = sim.state.x[eff.vertices].copy()
    node = SimNode(sim=sim, context=ros_context, parameter_overrides=[Parameter("mode", value="fast")])
    client = Node("gripper_client", context=ros_context)
    pub = client.create_publisher(Float64, "/thinshell/grip/gripper_cmd", COMMAND_QOS)
    poses = []
    client.create_subscription(PoseStamped, "/thinshell/grip/pose", lambda m: poses.append(cv.pose_from_msg(m)), SENSOR_QOS)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    ex.add_node(client)
    assert spin_until(ex, lambda: pub.get_subscription_count() > 0 and poses, 10.0)
    assert sim.state.gripper_opening["grip"] == pytest.approx(0.012)
    pub.publish(Float64(data=0.008))
    assert spin_until(ex, lambda: sim.state.gripper_opening["grip"] == pytest.approx(0.008), 10.0)
    # the rigid fingers moved 2 mm each towards the other along the gripper axis (x)
    dx = sim.state.x[eff.vertices] - x0
    np.testing.assert_allclose(dx[:, 0], -eff.finger_sign * 0.002, atol=1e-12)
    pub.publish(Float64(data=-0.001))  # an opening below 0 is rejected; the opening holds
    spin_until(ex, lambda: False, 0.3)
    assert sim.state.gripper_opening["grip"] == pytest.approx(0.008)
    ex.shutdown()
    node.destroy_node()
    client.destroy_node()
