"""spin_until_stopped: spins the given executor until the stop event, then shuts it down;
freeze_start_up_objects: start-up garbage collected, the rest frozen."""

from __future__ import annotations

import gc
import threading
import time
import weakref

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node

from thinshell_ros.runtime import freeze_start_up_objects, spin_until_stopped

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


def test_freeze_start_up_objects_collects_garbage_and_freezes_what_lives():
    class Held:
        """An object the collector can hold or free."""

    live, cycle = Held(), Held()
    cycle.self = cycle  # cyclic garbage: only the collector frees it
    dead = weakref.ref(cycle)
    del cycle
    try:
        frozen = freeze_start_up_objects()
        assert dead() is None, "the start-up garbage was frozen instead of collected"
        assert frozen == gc.get_freeze_count() > 0
        # frozen: no collection traverses the live start-up object any more; new objects are collected
        assert all(obj is not live for obj in gc.get_objects())
        later = Held()
        later.self = later
        dead_later = weakref.ref(later)
        del later
        gc.collect()
        assert dead_later() is None
    finally:
        gc.unfreeze()
