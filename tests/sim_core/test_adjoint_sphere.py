"""Adjoint through frictional contact with an exact rigid sphere (sim_core.energies.sphere_contact.reference).

A 2 x 2 x 1 mm gel block, clamped at its base, is pressed by a sphere (R 2 mm, Coulomb mu 0.5) and
dragged sideways so that friction is active; the loss is a random linear function of every
state's positions. Gradients w.r.t. the sphere's pose commands, the gel modulus and the friction
coefficient are compared with central finite differences of full rollouts.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core import indentation as ind
from sim_core.adjoint import StepLinearization, rollout, rollout_gradient
from sim_core.contact_set import ContactSet
from sim_core.control import Control
from sim_core.elastic import ElasticTerms
from sim_core.mesh.tet import box_face_vertices
from sim_core.model import ContactSettings
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig

CONFIG = SolverConfig(tol_velocity=1e-10, tol_force=1e-9, projection="none", max_iterations=60)
PARAMS = ["gel.youngs_modulus", "friction.gel_indenter"]


def _make() -> Simulation:
    gel = ind.graded_gel_block(1e-3, 1e-3, 2.5e-4, 0.0, 0.0, 1.0)
    setup = ind.build_indentation(
        gel, box_face_vertices(gel, 2, "min"), ind.RigidSphere(np.array([0.0, 0.0, 2e-3]), 2e-3), 3e5, 0.3,
        ContactSettings(stiffness=200.0, eps=1e-5, eps_v=1e-4, self_contact=False, candidate_margin=1e-4),
        friction=0.5, indenter_lift=None)
    return Simulation(setup.model, dt=0.01, solver_config=CONFIG)


def _controls() -> list[Control]:
    moves = [(0.0, -3e-5), (0.0, -6e-5), (2e-5, -6e-5), (4e-5, -6e-5)]
    return [Control({"indenter": np.array([x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}) for x, z in moves]


@pytest.fixture(scope="module")
def case():
    sim = _make()
    C = np.random.default_rng(5).normal(size=(len(_controls()) + 1, sim.model.vertex_count, 3))
    traj = rollout(sim, _controls())
    grad = rollout_gradient(sim, traj, lambda tr: (float(np.sum(C * tr.x)), C), PARAMS)
    return sim, traj, C, grad


def _loss(C, modify=None, control_modify=None) -> float:
    sim, controls = _make(), _controls()
    if modify is not None:
        modify(sim)
    if control_modify is not None:
        control_modify(controls)
    return float(np.sum(C * rollout(sim, controls, record=False).x))


def test_the_sphere_drags_the_gel_with_friction_active(case):
    sim, traj, _, _ = case
    lin = StepLinearization(sim.model, traj.records[-1], traj.states[-2], ElasticTerms(sim.model),
                            ContactSet(sim.model), sim.model.vertex_mass(), factorize=False)
    assert frozenset(("gel", "indenter")) in set(lin.rows.body_pairs)
    force = traj.states[-1].contact_force[sim.model.bodies["indenter"].vertex_start]
    assert force[2] > 0 and force[0] < 0  # the gel pushes up and resists the drag along +x


@pytest.mark.parametrize("name", PARAMS)
def test_parameter_gradient_through_sphere_contact_matches_finite_differences(case, name):
    _, _, C, grad = case
    value = _make().get_parameter(name)
    h = 1e-4 * abs(value)
    fd = (_loss(C, lambda s: s.set_parameter(name, value + h)) - _loss(C, lambda s: s.set_parameter(name, value - h))) / (2 * h)
    assert fd != 0.0
    assert abs(grad.params[name] - fd) < 1e-3 * abs(fd)


def test_sphere_pose_gradient_matches_finite_differences(case):
    _, _, C, grad = case
    direction = np.array([0.4, -0.3, 0.8, 0.0, 0.0, 0.0, 0.0])
    h = 1e-8

    def shifted(sign):
        def apply(controls):
            controls[2].effector_pose_target["indenter"] = controls[2].effector_pose_target["indenter"] + sign * h * direction
        return apply

    fd = (_loss(C, control_modify=shifted(1)) - _loss(C, control_modify=shifted(-1))) / (2 * h)
    assert abs(float(grad.controls[2]["indenter"] @ direction) - fd) < 1e-3 * abs(fd)
