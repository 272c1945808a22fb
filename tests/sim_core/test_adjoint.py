"""Adjoint and forward sensitivities of rollouts vs central finite differences of full rollouts.

Scene: a 5 x 4 card clamped at x0 on a table (friction), a 3 x 3 x 2 gel pad pressing it and
sliding; damping on; a small yield angle so that bending plasticity is in its yielding branch.
The penalty stiffness is 500 N/m so that the card vertices resting on the table sit 0.4 um inside
the contact offset (with 2e4 N/m they sit 10 nm from the activation kink, closer than the finite
difference steps). Loss: a random linear function of every state's positions.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.adjoint import StepLinearization, rollout, rollout_gradient
from sim_core.contact_set import ContactSet
from sim_core.control import Control
from sim_core.elastic import ElasticTerms
from sim_core.errors import ConfigError
from sim_core.sensitivity import observation_sensitivities, parameter_sensitivities
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig

CONFIG = SolverConfig(tol_velocity=1e-9, tol_force=5e-8, projection="none")


def _scene() -> dict:
    return {
        "version": 1, "name": "tiny_press_slide", "dt": 0.005, "gravity": [0.0, 0.0, -9.81],
        "table": {"height": 0.0, "friction": 0.3},
        "sheet": {"size": [0.04, 0.03], "resolution": [5, 4], "thickness": 0.0003, "density": 700.0,
                  "origin": [0.0, -0.015, 0.00015], "clamped_edge": "x0",
                  "material": {"youngs_modulus": 3.0e7, "poisson_ratio": 0.3, "bending_stiffness": 2e-4}},
        "sensors": {"tactile": {
            "effector": "ee", "gel_size": [0.012, 0.012, 0.004],
            "gel_material": {"youngs_modulus": 3.0e5, "poisson_ratio": 0.45, "density": 1100.0},
            "friction": 0.8, "marker_grid": [3, 3], "marker_pitch": 0.004,
            "camera": {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240,
                       "distance": 0.025}}},
        "effectors": {"ee": {"initial_pose": [0.025, 0.0, 0.00035, 1.0, 0.0, 0.0, 0.0]}},
        "simulation": {"gel_resolution": [3, 3, 2], "contact_stiffness": 500.0, "sheet_yield_angle": 0.002,
                       "damping": 3.0},
    }


def _controls() -> list[Control]:
    zs = [0.00026, 0.00022, 0.00022, 0.00022]
    xs = [0.025, 0.025, 0.0255, 0.026]
    return [Control({"ee": np.array([x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}) for x, z in zip(xs, zs)]


def _make() -> Simulation:
    return Simulation.from_scene(_scene(), solver_config=CONFIG)


PARAMS = ["sheet.youngs_modulus", "sheet.poisson_ratio", "sheet.thickness", "sheet.bending_stiffness",
          "sheet.density", "sheet.yield_angle", "gel.youngs_modulus", "gel.poisson_ratio", "gel.density",
          "friction.sheet_table", "friction.gel_sheet", "contact.stiffness", "damping"]


@pytest.fixture(scope="module")
def case():
    sim = _make()
    n = sim.model.vertex_count
    C = np.random.default_rng(0).normal(size=(len(_controls()) + 1, n, 3))
    traj = rollout(sim, _controls())
    grad = rollout_gradient(sim, traj, lambda tr: (float(np.sum(C * tr.x)), C), PARAMS)
    return sim, traj, C, grad


def _loss(C, modify=None, control_modify=None) -> float:
    sim = _make()
    controls = _controls()
    if modify is not None:
        modify(sim)
    if control_modify is not None:
        control_modify(controls)
    return float(np.sum(C * rollout(sim, controls, record=False).x))


def _rel(a: float, b: float) -> float:
    return abs(a - b) / max(abs(b), 1e-300)


def test_scene_exercises_friction_contact_and_plasticity(case):
    sim, traj, _, _ = case
    model = sim.model
    lin = StepLinearization(model, traj.records[-1], traj.states[-2], ElasticTerms(model), ContactSet(model),
                            model.vertex_mass(), factorize=False)
    pairs = set(lin.rows.body_pairs)
    assert frozenset(("gel", "sheet")) in pairs and frozenset(("sheet", "table")) in pairs
    assert lin.rows.friction.lam.max() > 0
    _, _, yielding, _ = lin.bending["sheet"]
    assert np.any(yielding) and not np.all(yielding)


@pytest.mark.parametrize("name", PARAMS)
def test_parameter_gradient_matches_finite_differences(case, name):
    _, _, C, grad = case
    value = _make().get_parameter(name)
    h = 1e-3 * abs(value)
    plus = _loss(C, lambda s: s.set_parameter(name, value + h))
    minus = _loss(C, lambda s: s.set_parameter(name, value - h))
    fd = (plus - minus) / (2 * h)
    assert fd != 0.0
    assert _rel(grad.params[name], fd) < 1e-3


def test_control_gradient_of_a_middle_step_matches_finite_differences(case):
    _, _, C, grad = case
    direction = np.array([0.3, -0.5, 0.8, 0.0, 0.2, -0.4, 0.1])
    h = 1e-7  # the pad's contact pairs lie about 1e-6 m from their activation kink

    def shifted(sign):
        def apply(controls):
            controls[2].effector_pose_target["ee"] = controls[2].effector_pose_target["ee"] + sign * h * direction
        return apply

    fd = (_loss(C, control_modify=shifted(1)) - _loss(C, control_modify=shifted(-1))) / (2 * h)
    assert _rel(float(grad.controls[2]["ee"] @ direction), fd) < 1e-3
    # q = (1, 0, 0, 0): its qx component is the radial direction that the normalisation removes
    assert grad.controls[2]["ee"][3] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("which, h", [("x0", 1e-7), ("v0", 1e-5)])
def test_initial_state_gradient_matches_finite_differences(case, which, h):
    sim, _, C, grad = case
    d = np.random.default_rng(3).normal(size=(sim.model.vertex_count, 3))

    def shifted(sign):
        def apply(s):
            if which == "x0":
                s.state.x = s.state.x + sign * h * d
            else:
                s.state.v = s.state.v + sign * h * d
        return apply

    fd = (_loss(C, shifted(1)) - _loss(C, shifted(-1))) / (2 * h)
    assert _rel(float(np.sum(getattr(grad, which) * d)), fd) < 1e-3


def test_forward_sensitivities_equal_reverse_gradient(case):
    sim, traj, C, grad = case
    _, dX = parameter_sensitivities(sim, None, PARAMS, trajectory=traj)
    assert dX.shape == (traj.step_count + 1, sim.model.vertex_count, 3, len(PARAMS))
    forward = np.einsum("tnd,tndp->p", C, dX)
    reverse = np.array([grad.params[p] for p in PARAMS])
    np.testing.assert_allclose(forward, reverse, rtol=1e-8, atol=1e-12 * np.abs(reverse).max())


def test_observation_sensitivities_match_finite_differences(case):
    sim, traj, _, _ = case
    name = "friction.gel_sheet"
    _, dX, dF = parameter_sensitivities(sim, None, [name], trajectory=traj, contact_force=True)
    obs = observation_sensitivities(sim.model, traj, dX, dF)
    value = sim.get_parameter(name)
    h = 1e-3 * value
    readings = []
    for sign in (1, -1):
        s = _make()
        s.set_parameter(name, value + sign * h)
        rollout(s, _controls(), record=False)
        readings.append(s.observe().tactile["tactile"])
    for key, channel in (("markers_uv", "markers_uv"), ("markers_xyz", "markers_xyz"), ("wrench", "wrench")):
        fd = (getattr(readings[0], channel) - getattr(readings[1], channel)) / (2 * h)
        got = obs[key][-1][..., 0]
        assert np.max(np.abs(fd)) > 0
        assert np.max(np.abs(got - fd)) < 1e-3 * np.max(np.abs(fd)), key


def test_unknown_parameter_and_stale_trajectory_are_refused(case):
    sim, traj, C, _ = case
    with pytest.raises(ConfigError, match="unknown parameter 'sheet.colour'"):
        rollout_gradient(sim, traj, C, ["sheet.colour"])
    with pytest.raises(ConfigError, match=r"dL_dx has shape"):
        rollout_gradient(sim, traj, C[:-1], [])
    other = _make()
    t2 = rollout(other, _controls()[:1])
    other.set_parameter("damping", 1.0)
    with pytest.raises(ConfigError, match="model parameters changed since the rollout"):
        rollout_gradient(other, t2, np.zeros((2, other.model.vertex_count, 3)), [])


def test_fixed_row_product_equals_the_assembled_hessian_on_the_fixed_rows(case):
    """StepLinearization.fixed_row_product (the batched reverse pass's Dirichlet pullback, from the element
    blocks touching a fixed vertex) against the assembled exact Hessian's product, on every step."""
    sim, traj, _, _ = case
    model = sim.model
    rng = np.random.default_rng(1)
    for rec, state in zip(traj.records, traj.states[:-1]):
        lin = StepLinearization(model, rec, state, ElasticTerms(model), ContactSet(model), model.vertex_mass(),
                                factorize=False)
        assert np.any(lin.static) and np.any(lin.driven)  # the clamped edge and the gel's driven vertices
        w = rng.normal(size=(model.vertex_count, 3))
        got = lin.fixed_row_product(w)
        want = lin.hessian_product(w[:, :, None])[:, :, 0]
        scale = np.abs(want[lin.fixed]).max()
        np.testing.assert_allclose(got[lin.fixed], want[lin.fixed], rtol=1e-12, atol=1e-12 * scale)
        assert not np.any(got[~lin.fixed])


def test_rebuilt_friction_rows_accept_the_rounding_of_positions_far_from_the_origin(case):
    """The adjoint's check of its rebuilt lagged-friction rows against the step's (the normal forces
    ``k_c (eps - d)``) allows the rounding of ``d`` at the positions' magnitude: a lockstep batch's copies
    sit up to metres from the origin. Here the step's start is moved 10 km along x (the table plane keeps its
    distances): the rows rebuilt there are the step's; a normal force changed by 1e-6 is refused."""
    from sim_core.adjoint_friction import friction_rows
    from sim_core.energies.friction.reference import LaggedFriction
    from sim_core.errors import ThinShellError

    sim, traj, _, _ = case
    model = sim.model
    rec, state = traj.records[-1], traj.states[-2]
    friction = next(p for p in rec.terms if isinstance(p, LaggedFriction))
    moved = state.copy()
    moved.x = state.x + np.array([1e4, 0.0, 0.0])
    rows = friction_rows(model, ContactSet(model), moved, friction)
    np.testing.assert_array_equal(rows.vertices, friction.vertices)
    lam = friction.lam.copy()
    try:
        friction.lam = lam * (1.0 + 1e-6)
        with pytest.raises(ThinShellError, match="do not match"):
            friction_rows(model, ContactSet(model), state, friction)
    finally:
        friction.lam = lam
