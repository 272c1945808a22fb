"""The node benchmark's measuring client against a live node (FakeSimulation, own executor thread)."""

from __future__ import annotations

import time

import pytest
from rclpy.parameter import Parameter

from tests.thinshell_ros.conftest import spinning
from tests.thinshell_ros.fake_sim import FakeSimulation
from thinshell_ros.bench_node import measure_node
from thinshell_ros.sim_node import SimNode

pytestmark = pytest.mark.ros


class SlowStartSimulation(FakeSimulation):
    """FakeSimulation whose first ``slow_steps`` steps take 0.15 s of wall time each (as the kernel
    compiles of a Taichi backend's first steps)."""

    def __init__(self, slow_steps: int) -> None:
        super().__init__()
        self.slow_steps = slow_steps

    def step(self, control=None) -> None:
        if self.slow_steps:
            time.sleep(0.15)
            self.slow_steps -= 1
        super().step(control)


def _measure(ros_context, sim, **kwargs):
    node = SimNode(sim=sim, context=ros_context,
                   parameter_overrides=[Parameter("mode", value="realtime"), Parameter("mesh_rate", value=0.0)])
    try:
        with spinning(ros_context, node, period=0.01):
            return measure_node(ros_context, timeout=10.0, **kwargs)
    finally:
        node.destroy_node()


def test_measure_node_reports_rtf_and_latency(ros_context):
    result = _measure(ros_context, FakeSimulation(), window=1.0, commands=6)
    # realtime mode with a solver far faster than dt: the factor is close to 1 (timer-bound)
    assert 0.5 < result["real_time_factor"] < 1.2, result
    assert result["lost"] == 0
    lat = result["latency_ms"]
    assert 0 < lat["median"] <= lat["p95"] <= lat["max"] < 1000
    assert result["steps_per_second"] == pytest.approx(result["real_time_factor"] / 0.005, rel=0.05)


def test_window_starts_after_the_warm_up_steps(ros_context):
    # 10 slow steps first (1.5 s): measured from the first output, the 1 s window holds only slow
    # steps (factor about 0.005 / 0.15); after 20 warm-up steps it is timer-bound (about 1)
    result = _measure(ros_context, SlowStartSimulation(slow_steps=10), window=1.0, commands=2, warmup=20)
    assert 0.5 < result["real_time_factor"] < 1.2, result
    cold = _measure(ros_context, SlowStartSimulation(slow_steps=10), window=1.0, commands=2, warmup=0)
    assert not cold["real_time_factor"] > 0.2, cold
