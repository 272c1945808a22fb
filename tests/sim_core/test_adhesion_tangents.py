"""Forward tangents of a card carried by the gel's tack (:class:`sim_core.candidates.adhesion.LaggedAdhesion` with the
compliant layer) against central differences of rollouts: the layer's ``k_t`` column (its ``parameter_gradient``) and
a material's column, through the bonds' lagged normals (:meth:`LaggedAdhesion.normal_state_product`). Before session 55
the tangents held each bond's normal at ``x^n`` fixed: the positions' tangents were 26 % (``k_t``) and 40 % (the
card's bending stiffness) off the differences after two steps of lift, the contact force's 6 %."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.adjoint import rollout
from sim_core.candidates.adhesion import LaggedAdhesion, _anchored_geometry, anchored_after, no_anchors
from sim_core.control import Control
from sim_core.sensitivity import rollout_sensitivities
from sim_core.simulation import Simulation
from tests.sim_core.test_adjoint import CONFIG, _scene
from tests.support.fd import relative_error

K_T = "candidate.adhesion.shear_stiffness"
PARAMS = [K_T, "sheet.bending_stiffness"]
VALUES = {K_T: 2.0, "sheet.bending_stiffness": 2e-4}
TOLERANCE = {K_T: 1e-5, "sheet.bending_stiffness": 1e-3}
"""Relative error of each checked column (measured 4e-7 and 9e-5). The tangents hold what a bond's formation step
fixes: the closest-point weights of a new pair and the anchor's barycentric weights (of the positions where it
formed). Where a parameter moves those (the contact stiffness: how deep the gel presses when the bonds form) its
column is 1e-3 off in the step they form and 3 % after the lift (2e-7 without the tack); it is propagated in the
fixture (the bonds are no term of the contact stiffness) but not checked here."""
SPRING_TOLERANCE = {K_T: 5e-4, "sheet.bending_stiffness": 1e-3}
"""The same with the layer's normal spring: the rollouts' differences resolve the k_t column to 2.7e-6-7e-5 at
h = 1 % of k_t, 2e-4 at 0.1 % and 1e-3 at 0.01 % (the solver's stopping error over a softer bond's larger
response), so the bound is that resolution; a tangent without the spring's terms is off by tens of percent."""
BETA = 0.05  # N a pair: holds the card's corner (0.04 x 0.03 x 0.3 mm at 700 kg/m^3 weighs 2.5 mN) up to the end


RATIOS = [None, 20.0]
"""The layer's normal law: the cohesive one (None) or its normal spring ``k_n = 20 k_t`` (40 N/m a pair: at ``k_n = k_t``
the tiny card's corner, 2.5 mN on a few bonds, hangs 0.3 mm below the gel and is not carried off the table)."""


def _sim(ratio: float | None = None, **changed) -> Simulation:
    """The tiny press-slide card of ``test_adjoint`` with the tack's bonds and the compliant layer (its normal spring
    ``ratio * k_t``, None: the cohesive normal law)."""
    sim = Simulation.from_scene(_scene(), solver_config=CONFIG)
    sim.set_parameter("candidate.adhesion", BETA)
    if ratio is not None:
        sim.set_parameter("candidate.adhesion.normal_ratio", ratio)
    for name, value in {**VALUES, **changed}.items():
        sim.set_parameter(name, value)
    return sim


def _controls() -> list[Control]:
    """Press, slide 1 mm, then lift 0.38 mm while sliding on: the bonds open and shear."""
    zs = [0.00026, 0.00022, 0.00022, 0.00030, 0.00045, 0.0006]
    xs = [0.025, 0.025, 0.0255, 0.026, 0.0265, 0.027]
    return [Control({"ee": np.array([x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}) for x, z in zip(xs, zs)]


@pytest.fixture(scope="module", params=RATIOS)
def tangents(request):
    sim = _sim(request.param)
    traj, dX, dF = rollout_sensitivities(sim, _controls(), [*PARAMS, "contact.stiffness"], contact_force=True)
    return sim, traj, dX, dF, request.param


def test_the_scene_carries_the_card_on_open_sheared_bonds(tangents):
    sim, traj, _, _, _ = tangents
    anchors = traj.states[-1].candidate_state["adhesion_anchor_triangle"]
    assert len(anchors) >= 4
    gel = np.asarray(traj.states[-1].candidate_state["adhesion"])
    x = traj.states[-1].x
    sheet = sim.model.bodies["sheet"]
    assert np.max(x[gel, 2]) > 0.00045  # the gel lifted off the table ...
    assert np.max(x[sheet.vertex_start:sheet.vertex_stop, 2]) > 0.0004  # ... and the card with it


@pytest.mark.parametrize("name", PARAMS)
def test_positions_and_contact_force_tangents_match_central_differences(tangents, name):
    _, traj, dX, dF, ratio = tangents
    j = PARAMS.index(name)
    h = 1e-3 * VALUES[name]
    plus = rollout(_sim(ratio, **{name: VALUES[name] + h}), _controls(), record=False)
    minus = rollout(_sim(ratio, **{name: VALUES[name] - h}), _controls(), record=False)
    fd_x = (plus.x - minus.x) / (2 * h)
    force = lambda tr: np.stack([s.contact_force for s in tr.states])  # noqa: E731
    fd_f = (force(plus) - force(minus)) / (2 * h)
    assert np.abs(fd_x[-1]).max() > 0 and np.abs(fd_f[-1]).max() > 0
    tol = TOLERANCE[name] if ratio is None else SPRING_TOLERANCE[name]
    for t in range(1, len(fd_x)):
        assert relative_error(dX[t, :, :, j], fd_x[t]) < tol, (name, t)
    assert relative_error(dF[-1, :, :, j], fd_f[-1]) < tol


def _bonds(x_prev: np.ndarray, x: np.ndarray, ratio: float | None) -> tuple[LaggedAdhesion, tuple]:
    """Two gel vertices (0, 1) bonded to the sheet triangles (2, 3, 4) and (3, 5, 4) at ``x_prev``, the bonds at
    their anchors with the normals of ``x_prev`` (as a step builds them)."""
    gel, tri = np.array([0, 1]), np.array([[2, 3, 4], [3, 5, 4]])
    anchors = anchored_after(x_prev, gel, tri, 4e-4, 1e-3, 1e-2, 1e-2, no_anchors())
    v, w, n, _ = _anchored_geometry(x_prev, tri, anchors)
    return LaggedAdhesion(v, w, n, 4e-4, 0.2, 2.5e-4, k_shear=3.0, normal_ratio=ratio), (tri, anchors)


@pytest.mark.parametrize("ratio", RATIOS)
def test_normal_state_product_is_the_derivative_through_the_anchored_normals_and_its_transpose(ratio):
    """``d(grad E(x))/d(x^n) dxn`` against a central difference of the bonds rebuilt at ``x^n +- h dxn`` (their
    anchors held), one bond open and one pressed; and :meth:`normal_state_vjp` its transpose."""
    rng = np.random.default_rng(3)
    x_prev = np.array([[2e-3, 2e-3, 5e-4], [6e-3, 4e-3, 3e-4], [0, 0, 0], [1e-2, 0, 0], [0, 1e-2, 0],
                       [1e-2, 1e-2, 1e-4]], dtype=float)
    bonds, (tri, anchors) = _bonds(x_prev, x_prev, ratio)
    assert bonds.vertices.shape[0] == 2
    x = x_prev + rng.normal(scale=2e-4, size=x_prev.shape)
    dxn = rng.normal(size=(6, 3, 2))
    h = 1e-7

    def grad(xp: np.ndarray) -> np.ndarray:
        v, w, n, _ = _anchored_geometry(xp, tri, anchors)
        return LaggedAdhesion(v, w, n, 4e-4, 0.2, 2.5e-4, k_shear=3.0, normal_ratio=ratio).gradient(x)

    got = bonds.normal_state_product(x, x_prev, dxn)
    for r in range(2):
        fd = (grad(x_prev + h * dxn[:, :, r]) - grad(x_prev - h * dxn[:, :, r])) / (2 * h)
        assert np.abs(fd).max() > 0
        assert relative_error(got[:, :, r], fd) < 1e-6
    w = rng.normal(size=(6, 3))
    lhs = np.einsum("nd,ndr->r", w, got)
    rhs = np.einsum("nd,ndr->r", bonds.normal_state_vjp(x, x_prev, w), dxn)
    np.testing.assert_allclose(lhs, rhs, rtol=1e-12)
