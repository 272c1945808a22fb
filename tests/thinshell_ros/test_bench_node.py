"""The node benchmark's measuring client against a live node (FakeSimulation, own executor thread)."""

from __future__ import annotations

import threading

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from tests.thinshell_ros.fake_sim import FakeSimulation
from thinshell_ros.bench_node import measure_node
from thinshell_ros.sim_node import SimNode

pytestmark = pytest.mark.ros


def test_measure_node_reports_rtf_and_latency(ros_context):
    node = SimNode(sim=FakeSimulation(), context=ros_context,
                   parameter_overrides=[Parameter("mode", value="realtime"), Parameter("mesh_rate", value=0.0)])
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    stop = threading.Event()
    thread = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.01) for _ in iter(stop.is_set, True)])
    thread.start()
    try:
        result = measure_node(ros_context, window=1.0, commands=6, timeout=10.0)
    finally:
        stop.set()
        thread.join(timeout=5)
        node.destroy_node()
    # realtime mode with a solver far faster than dt: the factor is close to 1 (timer-bound)
    assert 0.5 < result["real_time_factor"] < 1.2, result
    assert result["lost"] == 0
    lat = result["latency_ms"]
    assert 0 < lat["median"] <= lat["p95"] <= lat["max"] < 1000
    assert result["steps_per_second"] == pytest.approx(result["real_time_factor"] / 0.005, rel=0.05)
