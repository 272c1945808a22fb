"""The node latency trace (benchmarks/node_latency_trace.py): each probe's latency split into the wait,
the step that applied it, the publication and the way back, and the step's CPU time, over real DDS
with a stand-in whose steps take a known wall time and a known CPU time."""

from __future__ import annotations

import time

import pytest
from rclpy.parameter import Parameter

from benchmarks.node_latency_trace import TracedSimNode, probe_rows
from tests.thinshell_ros.conftest import ros_context, ros_env  # noqa: F401 - the DDS fixtures
from tests.thinshell_ros.conftest import spinning
from tests.thinshell_ros.fake_sim import FakeSimulation
from thinshell_ros.bench_node import measure_node

pytestmark = pytest.mark.ros

STEP_S = 0.03
"""Wall seconds every step of the stand-in sleeps (six times its dt: the node is never ahead of a command)."""

BURN_S = 0.005
"""CPU seconds every step of the stand-in computes besides its sleep."""


def burn_cpu(seconds: float) -> None:
    """Keep this thread computing for ``seconds`` of its own CPU time (a stand-in for a step's work)."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        sum(range(100))


class SlowStepSimulation(FakeSimulation):
    """A simulation whose every step computes :data:`BURN_S` of CPU and sleeps :data:`STEP_S`."""

    def step(self, control=None) -> None:
        burn_cpu(BURN_S)
        time.sleep(STEP_S)
        super().step(control)


def test_each_probe_is_split_into_wait_step_publication_and_way_back(ros_context):
    node = TracedSimNode(sim=SlowStepSimulation(), context=ros_context,
                         parameter_overrides=[Parameter("mode", value="realtime"), Parameter("mesh_rate", value=0.0)])
    with spinning(ros_context, node):
        result = measure_node(ros_context, window=0.3, commands=6, timeout=10.0, warmup=3, keep_probes=True)
    events = list(node.events)
    node.destroy_node()
    assert result["lost"] == 0 and len(result["probes_sent"]) == 6
    rows = probe_rows(result["probes_sent"], events)
    assert len(rows) == 6
    for row, (sent, received, _) in zip(rows, result["probes_sent"]):
        assert row["latency"] == pytest.approx(1e3 * (received - sent))
        parts = row["wait"] + row["step"] + row["publish"] + row["back"]
        assert parts == pytest.approx(row["latency"], abs=1e-6)
        # the step that applied the probe holds the stand-in's sleep; a probe sent while the node was
        # stepping (busy_at_send > 0, every step is a slow one) waited for the rest of that step
        assert 1e3 * STEP_S <= row["step"] < 1e3 * STEP_S + 50.0, row
        assert 0.0 <= row["publish"] < 50.0 and row["back"] > -1.0, row
        assert row["busy_at_send"] == 0.0 or row["busy_at_send"] >= 1e3 * STEP_S, row
        assert row["wait"] > -1.0, row
        # the step's CPU holds the stand-in's computation, not its sleep
        assert 1e3 * BURN_S <= row["step_cpu"] < 1e3 * (BURN_S + 0.5 * STEP_S), row
        assert row["busy_cpu"] == 0.0 or row["busy_cpu"] >= 1e3 * BURN_S, row
