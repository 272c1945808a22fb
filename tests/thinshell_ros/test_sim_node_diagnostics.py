"""SimNode solver diagnostics over real DDS (in-process): a step accepted at a relaxed tolerance and
an impossible step reach ``/diagnostics`` with how they ended."""

from __future__ import annotations

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from sim_core.builder import ModelBuilder
from sim_core.control import Control
from sim_core.mesh.sheet import grid_sheet
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig, StepInfo
from tests.thinshell_ros.conftest import call_trigger_collecting_diagnostics
from thinshell_ros.node_status import solver_status
from thinshell_ros.sim_node import SimNode

pytestmark = pytest.mark.ros

DT = 0.01


def _falling_sheet(config: SolverConfig) -> Simulation:
    """A free sheet in gravity, its first Newton update ``g dt`` = 0.098 m/s (scaled), and a second sheet
    held by the effector ``ee`` far above it (the node needs an effector to command)."""
    b = ModelBuilder()
    material = {"youngs_modulus": 1e8, "poisson_ratio": 0.3, "thickness": 1e-3, "density": 1000.0,
                "bending_stiffness": 1e-3}
    b.add_sheet("sheet", grid_sheet((0.02, 0.01), (3, 2), (0, 0, 1.0)), material)
    b.add_sheet("handle", grid_sheet((0.02, 0.01), (3, 2), (0, 0, 2.0)), material)
    b.add_effector("ee", "handle", range(6), [0, 0, 2.0, 0, 0, 0, 1])
    return Simulation(b.finalize(gravity=(0, 0, -9.81)), dt=DT, solver_config=config)


def _step_and_receive(ctx, sim: Simulation) -> tuple[SimNode, Trigger.Response, list[DiagnosticStatus]]:
    """Start a stepped node on ``sim``, call ``~/step`` once, return the solver statuses received."""
    node = SimNode(sim=sim, context=ctx, parameter_overrides=[Parameter("mode", value="stepped")])
    response, got = call_trigger_collecting_diagnostics(ctx, node, "/thinshell_sim/step", "diagnostics_client")
    return node, response, got


def test_a_step_accepted_at_a_relaxed_tolerance_is_published_as_a_warning(ros_context):
    # no backtrack allowed: the line search fails, and the first update is below 100 x tol
    sim = _falling_sheet(SolverConfig(tol_velocity=9.81 * DT / 50.0, max_backtracks=0))
    node, response, got = _step_and_receive(ros_context, sim)
    assert response.success and node.relaxed_steps == 1
    status = got[-1]
    values = {kv.key: kv.value for kv in status.values}
    assert status.level == DiagnosticStatus.WARN and status.name == "thinshell_sim: solver"
    assert "relaxed tolerance (line_search_relaxed" in status.message
    assert values["stop_reason"] == "line_search_relaxed" and values["line_search_failures"] == "1"
    assert values["relaxed_accepts"] == "1" and values["t"] == "0.000000"
    node.destroy_node()


def test_an_impossible_step_is_published_as_an_error(ros_context):
    sim = _falling_sheet(SolverConfig(max_iterations=1, tol_velocity=1e-14, dt_halvings_on_failure=1))
    node, response, got = _step_and_receive(ros_context, sim)
    assert not response.success and node.failed_steps == 1
    status = got[-1]
    assert status.level == DiagnosticStatus.ERROR
    assert "SimulationDivergedError: step 0 (t = 0 s): Newton failed at dt = 0.01 s" in status.message
    assert "1 retries" in status.message and "did not converge in 1 iterations" in status.message
    node.destroy_node()


def test_sleeping_bodies_are_in_the_solver_status():
    info = StepInfo(stop_reason="velocity", residual_velocity=5e-5, accepted_tolerance=1e-4, iterations=3,
                    sleeping=("sheet",), fell_asleep=("card",), wake_redos=1)
    status = solver_status("thinshell_sim: solver", 0.25, info)
    values = {kv.key: kv.value for kv in status.values}
    assert status.level == DiagnosticStatus.OK and status.message == "converged (fell asleep: card)"
    assert values["sleeping"] == "sheet" and values["fell_asleep"] == "card" and values["woken"] == ""
    assert values["wake_redos"] == "1"
    woken = solver_status("s", 0.3, StepInfo(stop_reason="velocity", woken=("card", "sheet")))
    assert woken.message == "converged (woken: card, sheet)"


def test_the_node_lets_the_resting_card_sleep(ros_context):
    # the node's own simulation of the bundled scene: sleeping on; a 0.1 mm move of the pad settles the card
    node = SimNode(context=ros_context, parameter_overrides=[Parameter("mode", value="stepped"),
                                                             Parameter("backend", value="numpy")])
    assert node.sim.solver.config.sleeping and node.sim.solver.config.repeat_fixed_points
    pose = np.array(node.sim.state.effector_pose["ee"])
    for k in range(16):
        target = pose.copy()
        target[2] += 1e-4 if k == 8 else 0.0
        control = Control()
        control.effector_pose_target["ee"] = target
        node.sim.step(control)
    assert node.sim.last_info.sleeping == ("sheet",)
    node.destroy_node()
