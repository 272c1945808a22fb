"""Forward tangents solved with each step's Newton factorisation during the rollout
(:func:`sim_core.sensitivity.rollout_sensitivities`) vs the reference path that linearises every
recorded step again (assembled exact Hessian, its own LU), on the press-slide card of
``test_adjoint``; and the record's exact Newton matrix vs the assembled exact Hessian."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from sim_core.adjoint import StepLinearization, rollout
from sim_core.contact_set import ContactSet
from sim_core.elastic import ElasticTerms
from sim_core.linsolve import make_linear_solver
from sim_core.sensitivity import observation_sensitivities, parameter_sensitivities, rollout_sensitivities
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from tests.sim_core.test_adjoint import CONFIG, PARAMS, _controls, _scene

CONFIGS = {"exact_first": SolverConfig(tol_velocity=1e-9, tol_force=5e-8),
           "projection_none": CONFIG}


def relinearised(config: SolverConfig, controls: list) -> tuple:
    """The reference of the joint tangents: ``controls`` rolled out on the card with ``config`` and every recorded
    step linearised again (exact Hessian assembled element by element, a general LU); ``(sim, trajectory, dX, dF)``."""
    sim_b = Simulation.from_scene(_scene(), solver_config=config)
    traj_b = rollout(sim_b, controls)
    for rec in traj_b.records:
        rec.hessian_exact = False
    _, dX_b, dF_b = parameter_sensitivities(sim_b, None, PARAMS, trajectory=traj_b, contact_force=True)
    return sim_b, traj_b, dX_b, dF_b


def assert_tangents_equal(pairs, rtol: float = 1e-8) -> None:
    """Each ``(got, ref)`` tangent pair ``(K + 1, n, 3, P)`` equal within ``rtol`` of the reference's largest entry
    per parameter (each parameter moving something)."""
    for got, ref in pairs:
        scale = np.abs(ref).reshape(-1, len(PARAMS)).max(axis=0)
        assert np.all(scale > 0)
        assert np.max(np.abs(got - ref).reshape(-1, len(PARAMS)) / scale) < rtol


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_joint_rollout_tangents_equal_recorded_linearisation(config):
    sim_a = Simulation.from_scene(_scene(), solver_config=CONFIGS[config])
    steps = []
    traj_a, dX_a, dF_a = rollout_sensitivities(sim_a, _controls(), PARAMS, contact_force=True,
                                               on_step=lambda k, T: steps.append((k, T)))
    assert steps == [(k, 4) for k in range(1, 5)] and traj_a.records is None
    sim_b, traj_b, dX_b, dF_b = relinearised(CONFIGS[config], _controls())
    np.testing.assert_array_equal(traj_a.x, traj_b.x)
    assert_tangents_equal(((dX_a, dX_b), (dF_a, dF_b)))
    obs_a = observation_sensitivities(sim_a.model, traj_a, dX_a, dF_a)
    obs_b = observation_sensitivities(sim_b.model, traj_b, dX_b, dF_b)
    for key in obs_b:
        np.testing.assert_allclose(obs_a[key], obs_b[key], rtol=1e-7, atol=1e-9 * np.abs(obs_b[key]).max())


def test_rate_stopping_tangents_match_the_recorded_linearisation_to_the_newton_tolerance():
    """With rate stopping (opt-in) a step may end on a Newton update whose matrix is not
    re-assembled: the tangents solved with that matrix differ from those of the Hessian at the
    final x by the size of the last update only (here < 1e-5 relative at tol 1e-9 m/s)."""
    config = SolverConfig(tol_velocity=1e-9, tol_force=5e-8, rate_stopping=True)
    sim_a = Simulation.from_scene(_scene(), solver_config=config)
    traj_a, dX_a, _ = rollout_sensitivities(sim_a, _controls(), PARAMS, contact_force=True)
    sim_b = Simulation.from_scene(_scene(), solver_config=config)
    traj_b = rollout(sim_b, _controls())
    for rec in traj_b.records:
        rec.hessian_exact = False
    _, dX_b, _ = parameter_sensitivities(sim_b, None, PARAMS, trajectory=traj_b, contact_force=True)
    np.testing.assert_array_equal(traj_a.x, traj_b.x)
    scale = np.abs(dX_b).reshape(-1, len(PARAMS)).max(axis=0)
    err = np.max(np.abs(dX_a - dX_b).reshape(-1, len(PARAMS)) / scale)
    assert 0.0 < err < 1e-5  # > 0: some step ended on a rate-stopped update


def test_recorded_exact_newton_matrix_is_the_assembled_exact_hessian():
    sim = Simulation.from_scene(_scene(), solver_config=SolverConfig(tol_velocity=1e-9, tol_force=5e-8))
    traj = rollout(sim, _controls())
    model = sim.model
    assert any(rec.hessian_exact for rec in traj.records)
    for rec, state in zip(traj.records, traj.states):
        if not rec.hessian_exact:
            continue
        lin = StepLinearization(model, rec, state, ElasticTerms(model), ContactSet(model), model.vertex_mass(),
                                make_linear_solver("pardiso"), factorize=False)
        D = sp.diags(lin.free.astype(float))
        assembled = (D @ lin.H @ D + sp.diags((~lin.free).astype(float))).toarray()
        assert np.max(np.abs(rec.hessian.toarray() - assembled)) < 1e-12 * np.abs(assembled).max()
        # the record's matrix factorised as it is solves like the re-assembled one
        b = np.random.default_rng(1).normal(size=(3 * model.vertex_count, 2))
        direct = StepLinearization(model, rec, state, ElasticTerms(model), ContactSet(model), model.vertex_mass())
        ref = StepLinearization(model, dataclasses.replace(rec, hessian_exact=False), state, ElasticTerms(model),
                                ContactSet(model), model.vertex_mass())
        np.testing.assert_allclose(direct.solve(b), ref.solve(b), rtol=1e-9, atol=1e-12 * np.abs(ref.solve(b)).max())


def test_contact_products_without_assembly_equal_the_assembled_ones():
    """The contact-force tangent's blockwise ``H_contact dx`` and the kept friction / parameter
    products equal the assembled matrix and fresh evaluations; a new argument is not served a
    kept result."""
    sim = Simulation.from_scene(_scene(), solver_config=CONFIG)
    traj = rollout(sim, _controls())
    model = sim.model
    rng = np.random.default_rng(1)
    checked = 0
    for rec, state in zip(traj.records, traj.states):
        lin = StepLinearization(model, rec, state, ElasticTerms(model), ContactSet(model), model.vertex_mass(),
                                factorize=False)
        if lin.friction is None:
            continue
        checked += 1
        dx = rng.normal(size=(model.vertex_count, 3, 3))
        blockwise = lin.contact_hessian_product(dx)
        assembled = (lin.H_contact @ dx.reshape(-1, 3)).reshape(dx.shape)
        np.testing.assert_allclose(blockwise, assembled, rtol=0, atol=1e-12 * np.abs(assembled).max())
        first = lin._friction_apply(dx)
        assert lin._friction_apply(dx) is first
        other = lin._friction_apply(2.0 * dx)
        np.testing.assert_allclose(other, 2.0 * first, rtol=1e-12, atol=1e-12 * np.abs(first).max())
        a = lin.contact_parameter_rhs("friction.gel_sheet")
        b = lin.contact_parameter_rhs("friction.sheet_table")
        assert np.abs(a).max() > 0 and np.abs(b).max() > 0 and not np.allclose(a, b)
        assert lin.contact_parameter_rhs("friction.gel_sheet") is a
        np.testing.assert_array_equal(a, lin._contact_parameter_rhs("friction.gel_sheet"))
    assert checked


def test_record_newton_matrix_expanded_on_use_equals_a_fresh_expansion():
    """A record keeps the upper triangle and expands it on first use: after the whole rollout
    (later steps assembled and expanded other matrices with the solver's shared expansion), every
    record's full matrix equals SciPy's expansion of its own upper triangle, is symmetric, and is
    kept (the same object on the next use); the solver's last_hessian is the last record's."""
    from sim_core.linsolve import full_from_upper

    sim = Simulation.from_scene(_scene(), solver_config=SolverConfig(tol_velocity=1e-9, tol_force=5e-8))
    traj = rollout(sim, _controls())
    assert len(traj.records) == 4
    for rec in reversed(traj.records):  # out of step order: the shared index map is rebuilt as needed
        assert "_hessian" not in rec.__dict__
        full = rec.hessian
        ref = full_from_upper(rec.hessian_upper)
        assert full.shape == ref.shape and abs(full - ref).max() == 0.0
        assert abs(full - full.T).max() == 0.0
        assert rec.hessian is full
    assert sim.solver.last_hessian is traj.records[-1].hessian
