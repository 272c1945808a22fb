"""The simplified Newton test (``SolverConfig.simplified_newton_check``): a step may end on the
correction solved with the previous iteration's factorisation instead of assembling and
factorising the Newton matrix once more only to find its update below the tolerance.

Checked on the press-slide card of ``test_adjoint`` (penalty contact with the table and the gel,
lagged friction, damping): the steps it ends reach the same positions as the ordinary test, with
fewer factorisations; the record of such a step is marked inexact, so that the adjoint assembles
the exact Hessian at ``x``; and the guard on the touching contacts.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.adjoint import rollout
from sim_core.contact_set import active_contacts, same_active_contacts
from sim_core.control import Control
from sim_core.energies.contact.reference import PlaneContact
from sim_core.sensitivity import parameter_sensitivities, rollout_sensitivities
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from tests.sim_core.test_adjoint import PARAMS, _scene
from tests.sim_core.test_sensitivity_joint import assert_tangents_equal, relinearised


def _controls() -> list[Control]:
    """Press the gel into the card, then drag it 0.5 mm per step along x."""
    zs = [0.00026, 0.00022, 0.00022, 0.00022, 0.00022, 0.00022]
    xs = [0.025, 0.025, 0.0255, 0.026, 0.0265, 0.027]
    return [Control({"ee": np.array([x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}) for x, z in zip(xs, zs)]


def _run(config: SolverConfig):
    sim = Simulation.from_scene(_scene(), solver_config=config)
    infos, states = [], []
    for control in _controls():
        infos.append(sim.step(control))
        states.append(sim.state.x.copy())
    return sim, infos, states


@pytest.fixture(scope="module")
def runs():
    return _run(SolverConfig()), _run(SolverConfig(simplified_newton_check=0.0))


def test_simplified_stops_reach_the_ordinary_result_with_fewer_factorisations(runs):
    (_, infos, states), (_, ref_infos, ref_states) = runs
    tol_dx = SolverConfig().tol_velocity * 0.005  # the Newton tolerance as a displacement per step, m
    assert sum(i.simplified_stops for i in infos) >= 2
    assert all(i.simplified_stops == 0 for i in ref_infos)
    for info, ref in zip(infos, ref_infos):
        # a simplified stop saves the factorisation that only tested convergence
        assert info.factorizations == info.iterations - info.simplified_stops + info.projected_iterations
        assert info.residual_velocity < SolverConfig().tol_velocity
        if info.simplified_stops:
            assert info.residual_velocity < SolverConfig().simplified_newton_check * SolverConfig().tol_velocity
    assert sum(i.factorizations for i in infos) < sum(i.factorizations for i in ref_infos)
    for x, x_ref in zip(states, ref_states):
        assert np.max(np.abs(x - x_ref)) < tol_dx


def _recording_infos(sim: Simulation) -> list:
    """Make ``sim.step`` also append each step's StepInfo to the returned list."""
    infos, step = [], sim.step
    sim.step = lambda control=None: infos.append(step(control)) or infos[-1]
    return infos


def test_simplified_stop_keeps_no_exact_factorisation_and_the_tangents_stay_exact():
    """A step ended by the simplified test holds the factorisation of the iterate before ``x``:
    it is not offered as the exact Hessian at ``x`` (``hessian_exact`` False, no
    ``last_factorization``), so the sensitivities have the solver assemble the Hessian at ``x`` and
    Cholesky-factorise it (``exact_factorization``, by an assembler and a solver of its own: no general
    LU is made) and equal those of the re-linearised recorded trajectory; the positions are bit for bit
    those of a rollout without tangents (the Newton loop's pattern and ordering untouched)."""
    config = SolverConfig(tol_velocity=1e-9, tol_force=5e-8)
    sim = Simulation.from_scene(_scene(), solver_config=config)
    infos = _recording_infos(sim)
    held = []
    traj_a, dX_a = rollout_sensitivities(sim, _controls()[:4], PARAMS, on_step=lambda k, T: held.append(
        (sim.solver.last_record.hessian_exact, sim.solver.last_factorization is not None,
         sim.solver.exact_factorization())))
    assert any(i.simplified_stops for i in infos)
    for info, (exact, factorization, refactorised) in zip(infos, held):
        if info.simplified_stops:
            assert not exact and not factorization
            assert refactorised is not None and refactorised is not sim.solver.linear_solver
    assert sim.solver._general_solver is None  # every step's tangents solved with a Cholesky factorisation
    sim_b = Simulation.from_scene(_scene(), solver_config=config)
    traj_b = rollout(sim_b, _controls()[:4])
    for rec in traj_b.records:
        rec.hessian_exact = False  # reference: every step's exact Hessian assembled again
    _, dX_b = parameter_sensitivities(sim_b, None, PARAMS, trajectory=traj_b)
    np.testing.assert_array_equal(traj_a.x, traj_b.x)
    scale = np.abs(dX_b).reshape(-1, len(PARAMS)).max(axis=0)
    assert np.max(np.abs(dX_a - dX_b).reshape(-1, len(PARAMS)) / scale) < 1e-8


def test_simplified_stop_record_is_inexact(runs):
    (sim, infos, _), _ = runs
    last = infos[-1]
    if last.simplified_stops:
        assert not sim.solver.last_record.hessian_exact and sim.solver.last_factorization is None
    else:
        assert sim.solver.last_record.hessian_exact == (sim.solver.last_factorization is not None)


def test_active_contacts_name_the_touching_vertices_and_refuse_unknown_terms():
    plane = PlaneContact(np.array([0, 1, 2]), np.array([0.0, 0.0, 1.0]), 0.0, 100.0, 1e-3)
    x = np.array([[0.0, 0.0, 5e-4], [1.0, 0.0, 2e-3], [0.0, 1.0, -1e-4]])
    a = active_contacts([plane], x)
    assert [v.tolist() for v in a] == [[0, 2]]
    assert same_active_contacts(a, active_contacts([plane], x + np.array([0.0, 0.0, 1e-4])))
    moved = x.copy()
    moved[1, 2] = 9e-4  # vertex 1 comes within eps: a contact switches on
    assert not same_active_contacts(a, active_contacts([plane], moved))
    assert not same_active_contacts(a, None) and not same_active_contacts(None, None)

    class Adhesion:  # a contact-like term without a penalty's active set
        vertices = np.array([0])

    assert active_contacts([plane, Adhesion()], x) is None


def test_switched_off_check_never_stops_early(runs):
    _, (_, ref_infos, _) = runs
    assert all(i.factorizations == i.iterations + i.projected_iterations for i in ref_infos)


def _adhesion_run(config: SolverConfig) -> list[tuple]:
    """The card of ``test_adjoint`` pressed by a tacky gel (candidate adhesion, 2 mN per pair) that then
    lifts 0.2 mm: per step its StepInfo, the open adhesion pairs at the result and the positions."""
    from sim_core.candidates.adhesion import LaggedAdhesion

    sim = Simulation.from_scene(_scene(), solver_config=config)
    sim.set_parameter("candidate.adhesion", 0.002)
    out = []
    for z in (0.00026, 0.00022, 0.00022, 0.00024, 0.00027, 0.00030, 0.00034, 0.00038, 0.00042):
        info = sim.step(Control({"ee": np.array([0.025, 0.0, z, 1.0, 0.0, 0.0, 0.0])}))
        bonds = [t for t in sim.solver.last_record.terms if isinstance(t, LaggedAdhesion)]
        opened = sum(int(np.count_nonzero(t.active_mask(sim.state.x))) for t in bonds)
        out.append((info, len(bonds), opened, sim.state.x.copy()))
    return out


def test_simplified_stops_with_adhesion_pairs_reach_the_ordinary_result():
    """A candidate's adhesion declares its open pairs (``LaggedAdhesion.active_mask``), so the test runs on
    its steps too, and ends some where bonded pairs are open, at the positions the ordinary test reaches."""
    runs, ref = _adhesion_run(SolverConfig()), _adhesion_run(SolverConfig(simplified_newton_check=0.0))
    tol_dx = SolverConfig().tol_velocity * 0.005
    assert all(bonds == 1 for _, bonds, _, _ in runs)  # the candidate's term is in every step
    assert any(info.simplified_stops for info, _, opened, _ in runs if opened)
    assert all(info.simplified_stops == 0 for info, _, _, _ in ref)
    for (info, _, opened, x), (ref_info, _, ref_opened, x_ref) in zip(runs, ref):
        assert opened == ref_opened
        assert info.factorizations == info.iterations - info.simplified_stops + info.projected_iterations
        assert np.max(np.abs(x - x_ref)) < tol_dx
    assert sum(r[0].factorizations for r in runs) < sum(r[0].factorizations for r in ref)


def test_tangents_on_the_fused_taichi_path_solve_with_the_refactorised_exact_hessian():
    """On the Taichi CPU backend the step's elastic Hessian comes from the fused kernels, whose values sit in
    the slots of the Newton loop's static pattern: the refactorisation at ``x`` of a step ended by the
    simplified test assembles them with an assembler of its own (``HessianAssembler.use_pattern``). The
    positions are bit for bit those of a rollout without tangents, every step's tangents solve with a
    Cholesky factorisation, and they equal those of the recorded trajectory linearised again (its exact
    Hessian assembled element by element, a general LU) to round-off."""
    config = SolverConfig(backend="taichi-cpu", tol_velocity=1e-9, tol_force=5e-8)
    sim = Simulation.from_scene(_scene(), solver_config=config)
    infos = _recording_infos(sim)
    held = []
    traj_a, dX_a, dF_a = rollout_sensitivities(sim, _controls()[:4], PARAMS, contact_force=True,
                                               on_step=lambda k, T: held.append(sim.solver.exact_factorization()))
    assert sim.solver.backend == "taichi-cpu" and any(i.simplified_stops for i in infos)
    assert all(h is not None for h in held) and sim.solver._general_solver is None
    _, traj_b, dX_b, dF_b = relinearised(config, _controls()[:4])
    np.testing.assert_array_equal(traj_a.x, traj_b.x)
    assert_tangents_equal(((dX_a, dX_b), (dF_a, dF_b)))
