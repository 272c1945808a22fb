"""The sim node's publication order over real DDS: a step's effector pose is published before its
tactile observation is read (:meth:`SimNode.publish_outputs`), so a command's pose does not wait for
the sensor model."""

from __future__ import annotations

import time

import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2

from tests.thinshell_ros.conftest import spinning
from tests.thinshell_ros.fake_sim import FakeSimulation
from thinshell_ros import conversions as cv
from thinshell_ros.runtime import SENSOR_QOS
from thinshell_ros.sim_node import SimNode

pytestmark = pytest.mark.ros

OBSERVE_S = 0.4
"""Wall seconds the stand-in's tactile observation takes (far above DDS transport on loopback)."""


class SlowObservationSimulation(FakeSimulation):
    """FakeSimulation whose ``observe`` (the tactile model) takes :data:`OBSERVE_S` of wall time."""

    def observe(self, render_image: bool = False):
        time.sleep(OBSERVE_S)
        return super().observe(render_image)


def test_a_steps_pose_is_received_before_its_tactile_observation_is_read(ros_context):
    node = SimNode(sim=SlowObservationSimulation(), context=ros_context,
                   parameter_overrides=[Parameter("mode", value="stepped"), Parameter("mesh_rate", value=0.0)])
    client = Node("publication_order_client", context=ros_context)
    received: dict[str, list[tuple[float, int]]] = {"pose": [], "markers": []}
    client.create_subscription(PoseStamped, "/thinshell/ee/pose",
                               lambda m: received["pose"].append((time.monotonic(), cv.ns_from_stamp(m.header.stamp))),
                               SENSOR_QOS)
    client.create_subscription(PointCloud2, "/thinshell/tactile/markers",
                               lambda m: received["markers"].append((time.monotonic(), cv.ns_from_stamp(m.header.stamp))),
                               SENSOR_QOS)
    try:
        with spinning(ros_context, client):
            deadline = time.monotonic() + 10.0
            while node.count_subscribers("/thinshell/ee/pose") < 1 or node.count_subscribers("/thinshell/tactile/markers") < 1:
                assert time.monotonic() < deadline, "the client's subscriptions were not matched"
                time.sleep(0.01)
            time.sleep(0.2)  # matched both ways (best effort drops what the writer sends before)
            for _ in range(3):
                start = time.monotonic()
                assert node.advance()
                t_ns = cv.seconds_to_ns(node.sim.t)
                deadline = time.monotonic() + 5.0
                while not all(any(stamp == t_ns for _, stamp in msgs) for msgs in received.values()):
                    assert time.monotonic() < deadline, f"no pose and markers stamped {t_ns} ns"
                    time.sleep(0.005)
                pose_at = next(t for t, stamp in received["pose"] if stamp == t_ns) - start
                markers_at = next(t for t, stamp in received["markers"] if stamp == t_ns) - start
                # the pose left before the observation was read; the markers after it
                assert pose_at < 0.5 * OBSERVE_S, (pose_at, markers_at)
                assert markers_at >= OBSERVE_S, (pose_at, markers_at)
    finally:
        client.destroy_node()
        node.destroy_node()


class CountingSimulation(FakeSimulation):
    """FakeSimulation counting its observations (the tactile model's reads)."""

    def __init__(self) -> None:
        super().__init__()
        self.observations = 0

    def observe(self, render_image: bool = False):
        self.observations += 1
        return super().observe(render_image)


def test_the_observation_is_read_only_for_outputs_someone_subscribes_to(ros_context):
    sim = CountingSimulation()
    node = SimNode(sim=sim, context=ros_context,
                   parameter_overrides=[Parameter("mode", value="stepped"), Parameter("mesh_rate", value=0.0)])
    client = Node("observation_client", context=ros_context)
    poses: list[int] = []
    markers: list[int] = []
    client.create_subscription(PoseStamped, "/thinshell/ee/pose",
                               lambda m: poses.append(cv.ns_from_stamp(m.header.stamp)), SENSOR_QOS)
    try:
        with spinning(ros_context, client):
            deadline = time.monotonic() + 10.0
            while node.count_subscribers("/thinshell/ee/pose") < 1:
                assert time.monotonic() < deadline, "the client's pose subscription was not matched"
                time.sleep(0.01)
            time.sleep(0.2)
            before = sim.observations
            for _ in range(3):
                assert node.advance()
            stamp = cv.seconds_to_ns(node.sim.t)
            deadline = time.monotonic() + 5.0
            while stamp not in poses:
                assert time.monotonic() < deadline, "the poses were not published"
                time.sleep(0.005)
            # nobody reads the markers, wrench, image, points or mesh: the tactile model was not run
            assert sim.observations == before
            client.create_subscription(PointCloud2, "/thinshell/tactile/markers",
                                       lambda m: markers.append(cv.ns_from_stamp(m.header.stamp)), SENSOR_QOS)
            deadline = time.monotonic() + 10.0
            while node.count_subscribers("/thinshell/tactile/markers") < 1:
                assert time.monotonic() < deadline, "the client's markers subscription was not matched"
                time.sleep(0.01)
            time.sleep(0.2)
            assert node.advance()
            stamp = cv.seconds_to_ns(node.sim.t)
            assert sim.observations == before + 1
            deadline = time.monotonic() + 5.0
            while stamp not in markers:
                assert time.monotonic() < deadline, f"no markers stamped {stamp} ns"
                time.sleep(0.005)
    finally:
        client.destroy_node()
        node.destroy_node()
