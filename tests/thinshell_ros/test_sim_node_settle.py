"""SimNode's start-up settling (``settle_steps_max``): the bundled scene starts at rest with its card
asleep from the first step; a scene that does not settle within the cap starts anyway and says so on
``/diagnostics``."""

from __future__ import annotations

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.parameter import Parameter

from sim_core.errors import ConfigError
from tests.thinshell_ros.conftest import call_trigger_collecting_diagnostics
from tests.thinshell_ros.fake_sim import FakeSimulation
from thinshell_ros.sim_node import SimNode

pytestmark = pytest.mark.ros


def _node(ctx, settle_steps_max: int | None = None) -> SimNode:
    """A stepped node on the bundled scene (NumPy backend)."""
    params = [Parameter("mode", value="stepped"), Parameter("backend", value="numpy")]
    if settle_steps_max is not None:
        params.append(Parameter("settle_steps_max", value=settle_steps_max))
    return SimNode(context=ctx, parameter_overrides=params)


def test_the_bundled_scene_starts_settled_with_the_card_asleep(ros_context):
    node = _node(ros_context)
    info = node.settle_info
    rest = node.sim.solver.config.sleep_velocity
    assert info.settled and 0 < info.steps <= 20 and info.residual_velocity <= rest, info
    assert info.sleeping == ("sheet",)
    assert node.sim.t == 0.0 and not np.any(node.sim.state.v)
    x = node.sim.state.x.copy()
    assert node.advance()
    first = node.sim.last_info
    assert first.sleeping == ("sheet",) and first.woken == () and np.array_equal(node.sim.state.x, x)
    node.destroy_node()
    # without settling, the scene file's state leaves the card awake in the first step (its Newton
    # update is above the threshold), and no step under zero commands brings it below
    plain = _node(ros_context, settle_steps_max=0)
    assert plain.settle_info is None
    for _ in range(3):
        assert plain.advance()
        assert plain.sim.last_info.sleeping == ()
    plain.destroy_node()


def test_a_scene_that_does_not_settle_within_the_cap_starts_and_says_so(ros_context):
    node = _node(ros_context, settle_steps_max=2)
    assert not node.settle_info.settled and node.settle_info.steps == 2
    # ~/reset settles again
    response, got = call_trigger_collecting_diagnostics(ros_context, node, "/thinshell_sim/reset", "settle_client")
    assert response.success
    status = got[-1]
    values = {kv.key: kv.value for kv in status.values}
    assert status.name == "thinshell_sim: settle" and status.level == DiagnosticStatus.WARN
    assert "did not settle in 2 steps (cap 2): still moving after 2 steps" in status.message
    assert values["settled"] == "false" and values["steps"] == "2" and values["max_steps"] == "2"
    assert float(values["residual_velocity"]) > node.sim.solver.config.sleep_velocity
    assert node.sim.t == 0.0 and node.advance()  # it runs anyway
    node.destroy_node()


def test_settle_steps_max_is_validated_and_a_given_simulation_starts_as_given(ros_context):
    with pytest.raises(ConfigError, match="'settle_steps_max' must be >= 0, got -1"):
        _node(ros_context, settle_steps_max=-1)
    sim = FakeSimulation()
    node = SimNode(sim=sim, context=ros_context, parameter_overrides=[Parameter("mode", value="stepped")])
    assert node.settle_info is None and node.settle_steps_max == 0 and sim.t == 0.0
    node.destroy_node()
