"""The lockstep loop's lumped-mass quadratic (sim_core.batch.lumped): the inertia, gravity and damping terms' energy
and gradient to round-off, its gradient against finite differences of its energy, and the loop terms it replaces."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.batch.lumped import LumpedQuadratic, lumped_loop_terms
from sim_core.energies.damping.reference import ViscousDamping
from sim_core.energies.gravity.reference import GravityPotential
from sim_core.energies.inertia.reference import InertiaPotential
from sim_core.errors import ConfigError


def _terms(rng, n=40, dt=5e-3, damping=2.5):
    mass = rng.uniform(1e-5, 1e-3, n)
    mass[::7] = 0.0  # massless vertices (e.g. a kinematic body's): no term
    x_n = rng.normal(scale=0.05, size=(n, 3))
    x_hat = x_n + dt * rng.normal(scale=0.2, size=(n, 3))
    inertia = InertiaPotential(mass, x_hat, dt)
    gravity = GravityPotential(mass * rng.uniform(0.5, 1.5, n), np.array([0.3, -0.2, -9.81]))
    damp = ViscousDamping(mass, x_n, damping, dt) if damping else None
    return inertia, gravity, damp, x_n


@pytest.mark.parametrize("with_gravity, damping", [(True, 2.5), (True, 0.0), (False, 2.5), (False, 0.0)])
def test_lumped_quadratic_is_the_sum_of_the_three_terms(with_gravity, damping):
    rng = np.random.default_rng(3)
    inertia, gravity, damp, x_n = _terms(rng, damping=damping)
    terms = [t for t in (inertia, gravity if with_gravity else None, damp) if t is not None]
    lumped = LumpedQuadratic(inertia, gravity if with_gravity else None, damp)
    scale = sum(abs(t.energy(x_n)) for t in terms)
    for x in (x_n, x_n + rng.normal(scale=1e-3, size=x_n.shape), inertia.x_hat):
        assert lumped.energy(x) == pytest.approx(sum(t.energy(x) for t in terms), rel=0, abs=1e-13 * scale)
        want = sum(t.gradient(x) for t in terms)
        # a difference of terms of the size w |x| (the inertia's m x / dt^2): round-off relative to those
        np.testing.assert_allclose(lumped.gradient(x), want, rtol=0,
                                   atol=1e-14 * np.abs(lumped.weight[:, None] * x).max())
    # energy differences (what the line search compares) to round-off of the differences themselves
    x0 = x_n + rng.normal(scale=1e-3, size=x_n.shape)
    x1 = x0 + rng.normal(scale=1e-6, size=x_n.shape)
    want = sum(t.energy(x1) - t.energy(x0) for t in terms)
    assert lumped.energy(x1) - lumped.energy(x0) == pytest.approx(want, rel=1e-6)


@pytest.mark.parametrize("with_gravity, damping", [(True, 2.5), (False, 0.0)])
def test_lumped_energy_split_by_copy_is_each_copys_terms(with_gravity, damping):
    """Per copy (CopyEnergies): the three terms' energies over that copy's vertices (the others' masses zero)."""
    rng = np.random.default_rng(5)
    inertia, gravity, damp, x_n = _terms(rng, damping=damping)
    copy_of_vertex = rng.integers(0, 3, len(x_n))
    lumped = LumpedQuadratic(inertia, gravity if with_gravity else None, damp)
    x = x_n + rng.normal(scale=1e-3, size=x_n.shape)
    split = lumped.copy_energies(x, copy_of_vertex, 4)
    assert split.shape == (4,) and split[3] == 0.0  # copy 3 has no vertex
    for c in range(3):
        own = copy_of_vertex == c
        terms = [InertiaPotential(np.where(own, inertia.vertex_mass, 0.0), inertia.x_hat, inertia.dt)]
        if with_gravity:
            terms.append(GravityPotential(np.where(own, gravity.vertex_mass, 0.0), gravity.gravity))
        if damp is not None:
            terms.append(ViscousDamping(np.where(own, damp.vertex_mass, 0.0), damp.x_prev, damp.damping, damp.dt))
        scale = sum(abs(t.energy(x)) for t in terms)
        assert split[c] == pytest.approx(sum(t.energy(x) for t in terms), rel=0, abs=1e-13 * scale)
    assert np.sum(split) == pytest.approx(lumped.energy(x), rel=1e-13)


def test_lumped_gradient_matches_finite_differences_of_its_energy():
    rng = np.random.default_rng(4)
    inertia, gravity, damp, x_n = _terms(rng)
    lumped = LumpedQuadratic(inertia, gravity, damp)
    x = x_n + rng.normal(scale=1e-3, size=x_n.shape)
    g = lumped.gradient(x)
    h = 1e-7
    for v, k in [(1, 0), (2, 2), (11, 1), (39, 2)]:
        xp, xm = x.copy(), x.copy()
        xp[v, k] += h
        xm[v, k] -= h
        assert (lumped.energy(xp) - lumped.energy(xm)) / (2 * h) == pytest.approx(g[v, k], rel=1e-6, abs=1e-9)
    assert np.all(g[::7] == 0.0)  # massless vertices: no force


def test_lumped_loop_terms_replace_the_three_terms_at_the_inertias_place():
    rng = np.random.default_rng(5)
    inertia, gravity, damp, _ = _terms(rng)
    other = object()
    out = lumped_loop_terms([inertia, gravity, damp, other])
    assert len(out) == 2 and isinstance(out[0], LumpedQuadratic) and out[1] is other
    out = lumped_loop_terms([inertia, other])  # zero gravity leaves the gravity term out of the loop
    assert isinstance(out[0], LumpedQuadratic) and out[1] is other
    assert out[0].energy(inertia.x_hat) == pytest.approx(0.0, abs=1e-18)
    assert lumped_loop_terms([gravity, other]) == [gravity, other]  # no inertia: unchanged
    with pytest.raises(ConfigError, match="damping over other vertices"):
        LumpedQuadratic(inertia, gravity, ViscousDamping(inertia.vertex_mass, inertia.x_hat, 1.0, 1e-3))


def test_the_lockstep_step_evaluates_the_lumped_term_with_the_step_energy_of_its_terms():
    from sim_core.batch import BatchedSimulation
    from sim_core.scenes.task_scene import task_initial_state
    from sim_core.solver_config import SolverConfig
    from sim_core.step_info import StepInfo
    from tests.support.batch_copies import MOTIONS, PARAMS, control, pad_model

    model = pad_model()
    batch = BatchedSimulation.from_model(model, 3, params=PARAMS, state=task_initial_state(model),
                                         solver_config=SolverConfig(lockstep=True))
    batch.step([control(batch.states[i].effector_pose["pad"], MOTIONS[i], 0) for i in range(3)])
    engine = batch.lockstep
    solver, state = engine.solver, engine.state
    state.v = np.random.default_rng(6).normal(scale=1e-2, size=state.v.shape)  # x_hat away from x^n (a new array)
    pose0 = [s.effector_pose["pad"] for s in batch.states]
    stacked = engine.scene.stack_controls([control(pose0[i], MOTIONS[i], 1) for i in range(3)])
    step, x = solver._set_up_step(state, stacked, batch.sims[0].dt, None, StepInfo())
    lumped = [p for p in step.loop_terms if isinstance(p, LumpedQuadratic)]
    kinds = (InertiaPotential, GravityPotential, ViscousDamping)
    assert len(lumped) == 1 and not any(type(p) in kinds for p in step.loop_terms)
    replaced = [p for p in step.fixed_terms if type(p) in kinds]  # the record keeps the terms themselves
    assert [type(p) for p in replaced] == [InertiaPotential, GravityPotential]
    x1 = x + np.random.default_rng(7).normal(scale=1e-4, size=x.shape)
    for y in (x, x1):
        want = sum(p.energy(y) for p in replaced)
        assert lumped[0].energy(y) == pytest.approx(want, rel=1e-12)
        np.testing.assert_allclose(lumped[0].gradient(y), sum(p.gradient(y) for p in replaced), rtol=1e-9,
                                   atol=1e-12)
