"""SimNode's realtime mode: steps counted against the wall clock (a test clock here), over real DDS
with the kinematic FakeSimulation."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher

from tests.thinshell_ros.conftest import spin_until
from tests.thinshell_ros.fake_sim import HOME, FakeSimulation
from thinshell_ros import conversions as cv
from thinshell_ros.runtime import COMMAND_QOS
from thinshell_ros.sim_node import REALTIME_MAX_LAG, REALTIME_STEPS_PER_TICK, SimNode

pytestmark = pytest.mark.ros


class TestClock:
    """A wall clock that moves only when told (s)."""

    __test__ = False

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _realtime_node(ctx, clock: TestClock) -> SimNode:
    return SimNode(sim=FakeSimulation(), context=ctx, wall_clock=clock,
                   parameter_overrides=[Parameter("mode", value="realtime")])


def _steps(node: SimNode) -> int:
    return int(round(node.sim.t / node.dt))


@contextmanager
def _commanding(ctx) -> Iterator[tuple[TestClock, SimNode, Publisher, SingleThreadedExecutor]]:
    """A realtime node on a test clock, a client publishing pose commands to it and an executor spinning
    both, after the node's first step; the nodes are destroyed on exit."""
    clock = TestClock()
    node = _realtime_node(ctx, clock)
    client = Node("client", context=ctx)
    pub = client.create_publisher(PoseStamped, "/thinshell/ee/pose_cmd", COMMAND_QOS)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(client)
    try:
        assert spin_until(ex, lambda: pub.get_subscription_count() > 0 and _steps(node) == 1, 10.0)
        yield clock, node, pub, ex
    finally:
        ex.shutdown(timeout_sec=0)
        client.destroy_node()
        node.destroy_node()


def test_the_timer_takes_every_due_step_up_to_its_bound(ros_context):
    clock = TestClock()
    node = _realtime_node(ros_context, clock)
    try:
        node._on_timer()  # starts the schedule: step 0 is due now
        assert _steps(node) == 1
        node._on_timer()
        assert _steps(node) == 1  # step 1 is due one dt later
        clock.now += 2.5 * node.dt  # a late tick: steps 1 and 2 are due
        node._on_timer()
        assert _steps(node) == 3
        clock.now += 6 * node.dt  # six more due (< REALTIME_MAX_LAG): taken over two callbacks
        assert 6 * node.dt < REALTIME_MAX_LAG and REALTIME_STEPS_PER_TICK < 6
        node._on_timer()
        assert _steps(node) == 3 + REALTIME_STEPS_PER_TICK
        node._on_timer()
        assert _steps(node) == 9
        clock.now += 10 * REALTIME_MAX_LAG  # stalled: the lag is dropped, one step due
        node._on_timer()
        node._on_timer()
        assert _steps(node) == 10
        node.paused = True
        clock.now += 1.0
        node._on_timer()  # paused: no step, and the schedule restarts when it runs again
        node.paused = False
        node._on_timer()
        assert _steps(node) == 11
        assert 0 < node._pacer.dropped <= 10 * REALTIME_MAX_LAG  # the stall's lag, not the pause's
    finally:
        node.destroy_node()


class SlowSimulation(FakeSimulation):
    """The stand-in whose every step takes ``step_time`` s of the test clock."""

    def __init__(self, clock: TestClock, step_time: float) -> None:
        super().__init__()
        self.clock, self.step_time = clock, step_time

    def step(self, control=None) -> None:
        super().step(control)
        self.clock.now += self.step_time


def test_after_a_slow_step_the_lag_waits_for_the_next_tick(ros_context):
    """Steps of 1.5 dt: each tick takes one step (a slow step: the steps it leaves due wait for the
    next tick); steps of 0.3 dt: a late tick takes the due ones back to back."""
    clock = TestClock()
    node = SimNode(sim=SlowSimulation(clock, 0.0075), context=ros_context, wall_clock=clock,
                   parameter_overrides=[Parameter("mode", value="realtime")])
    try:
        for k in range(1, 4):
            node._on_timer()
            assert _steps(node) == k  # one step a tick, although behind the schedule
        node.sim.step_time = 0.0015
        node._on_timer()  # 1.5 steps behind, quick steps: caught up within the tick
        assert _steps(node) == 6
    finally:
        node.destroy_node()


def test_a_command_between_ticks_starts_its_step_at_once(ros_context):
    """With the wall clock standing still between ticks, a pose command is applied by a step that it
    starts itself (one step ahead of the schedule at most); a second command waits for the clock."""
    with _commanding(ros_context) as (clock, node, pub, ex):
        spin_until(ex, lambda: False, 0.1)
        assert _steps(node) == 1  # the timer ticks, the clock stands: nothing more is due
        first = HOME.copy()
        first[2] += 2e-4
        pub.publish(cv.pose_to_msg(first, 0))
        assert spin_until(ex, lambda: _steps(node) == 2, 10.0)
        np.testing.assert_allclose(node.sim.state.effector_pose["ee"], first)
        second = HOME.copy()
        pub.publish(cv.pose_to_msg(second, 0))
        spin_until(ex, lambda: False, 0.3)
        assert _steps(node) == 2  # already one step ahead: the command waits for its due step
        clock.now += 2.001 * node.dt  # step 2 was due two steps after step 0
        assert spin_until(ex, lambda: _steps(node) == 3, 10.0)
        np.testing.assert_allclose(node.sim.state.effector_pose["ee"], second)


def test_a_command_one_step_ahead_starts_its_step_as_soon_as_the_schedule_lets_it(ros_context):
    """A command that arrives while the node is one step ahead of the schedule starts its step as
    soon as that step is due within one ``dt`` (the pacer's start time), not at the timer's tick at
    its due time one ``dt`` later."""
    with _commanding(ros_context) as (clock, node, pub, ex):
        first = HOME.copy()
        first[2] += 2e-4
        pub.publish(cv.pose_to_msg(first, 0))
        assert spin_until(ex, lambda: _steps(node) == 2, 10.0)  # one step ahead of the schedule
        second = HOME.copy()
        pub.publish(cv.pose_to_msg(second, 0))
        spin_until(ex, lambda: False, 0.3)
        assert _steps(node) == 2  # the schedule does not let it start yet
        clock.now += 1.001 * node.dt  # its step is now due within one dt (due itself only at 2 dt)
        assert spin_until(ex, lambda: _steps(node) == 3, 2.0)
        np.testing.assert_allclose(node.sim.state.effector_pose["ee"], second)
        spin_until(ex, lambda: False, 0.3)
        assert _steps(node) == 3  # the wake-up took one step: the schedule is one step ahead again
