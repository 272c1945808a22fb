"""spin_until_stopped: spins the given executor until the stop event, then shuts it down."""

from __future__ import annotations

import threading
import time

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node

from thinshell_ros.runtime import spin_until_stopped

pytestmark = pytest.mark.ros


@pytest.mark.parametrize("executor_type", [None, SingleThreadedExecutor, EventsExecutor])
def test_spin_until_stopped_runs_timers_and_returns_on_stop(ros_context, executor_type):
    node = Node("runtime_test", context=ros_context)
    ticks: list[float] = []
    node.create_timer(0.01, lambda: ticks.append(time.monotonic()))
    executor = executor_type(context=ros_context) if executor_type else None
    stop = threading.Event()
    thread = threading.Thread(target=spin_until_stopped, args=(node, stop, 0.02, executor))
    thread.start()
    try:
        time.sleep(0.5)
    finally:
        stop.set()
        thread.join(timeout=2.0)
    assert not thread.is_alive(), "spin_until_stopped did not return after stop"
    n = len(ticks)
    assert n >= 10, f"a 100 Hz timer fired {n} times in 0.5 s"
    time.sleep(0.1)
    assert len(ticks) == n, "callbacks ran after spin_until_stopped returned"
    if executor is not None:
        assert node not in executor.get_nodes()
    node.destroy_node()
