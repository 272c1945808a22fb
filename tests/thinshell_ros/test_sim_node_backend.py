"""The sim node's ``backend`` parameter: validated, and passed to the solver it builds."""

from __future__ import annotations

import pytest
from rclpy.parameter import Parameter

from sim_core.errors import ConfigError
from thinshell_ros.sim_node import SimNode

pytestmark = pytest.mark.ros


def test_an_unknown_backend_is_rejected_naming_the_allowed_values(ros_context):
    with pytest.raises(ConfigError, match=r"node parameter 'backend' must be one of numpy, taichi-cpu, taichi-cuda, "
                                          r"auto; got 'gpu'"):
        SimNode(context=ros_context, parameter_overrides=[Parameter("backend", value="gpu")])


def test_the_backend_reaches_the_solver_of_the_scene(ros_context):
    node = SimNode(context=ros_context, parameter_overrides=[Parameter("backend", value="numpy"),
                                                             Parameter("mode", value="stepped")])
    assert node.sim.solver.config.backend == "numpy" and node.sim.solver.backend == "numpy"
    assert node.get_parameter("backend").value == "numpy"
    node.destroy_node()


def test_the_node_repeats_a_resting_scene_and_reports_it(ros_context):
    node = SimNode(context=ros_context, parameter_overrides=[Parameter("backend", value="numpy"),
                                                             Parameter("mode", value="stepped")])
    assert node.sim.solver.config.repeat_fixed_points
    infos = []
    for _ in range(8):  # the bundled scene settles in a few steps (the pad does not touch the card)
        assert node.advance()
        infos.append(node.sim.last_info)
    assert not infos[0].repeated and infos[-1].repeated and infos[-1].iterations == 0
    assert node.sim.step_totals.repeated_steps == sum(i.repeated for i in infos)
    assert node.failed_steps == 0 and node.relaxed_steps == 0
    node.destroy_node()
