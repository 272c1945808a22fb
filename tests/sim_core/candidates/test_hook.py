"""Candidates in the Newton step (a CandidateHook given to the solver): parameters, neutrality at beta = 0,
signatures; the solver's one hook path."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from sim_core.candidates import CandidateHook, validate_candidate_parameters
from sim_core.contact_set import ContactSet
from sim_core.control import Control
from sim_core.elastic import ElasticTerms
from sim_core.errors import ConfigError
from sim_core.scenes import load_scene
from sim_core.simulation import Simulation
from sim_core.solver import NewtonSolver, SolverConfig
from benchmarks.diagnose_bench import load_bench_scene

DT = 0.01


def _tiny_press_scene() -> dict:
    """The benchmark card scene made smaller: 5 x 4 sheet vertices, 3 x 3 markers, 3 x 3 x 2 gel."""
    scene = load_bench_scene()
    scene["name"] = "tiny_press"
    scene["sheet"].update(size=[0.04, 0.03], resolution=[5, 4])
    scene["sensors"]["tactile"]["marker_grid"] = [3, 3]
    scene["effectors"]["ee"]["initial_pose"] = [0.025, 0.0, 0.0012, 1.0, 0.0, 0.0, 0.0]
    scene["simulation"]["gel_resolution"] = [3, 3, 2]
    return scene


SCENE = _tiny_press_scene()


def candidate_terms(model, state, x_prev: np.ndarray, dt: float, params) -> list:
    """All candidate potentials of one step built from scratch (fresh elastic terms and contact set,
    the lagged friction at ``x_prev``), contact-like first."""
    contact = ContactSet(model)
    memory = contact.begin_step(x_prev, state.contact_memory)
    friction = contact.friction(x_prev, dt, memory)
    contact_like, body_like = CandidateHook(params).terms(model, state, x_prev, dt, ElasticTerms(model), friction)
    return contact_like + body_like


def _press_and_hold(candidates, hold=6, lift=0, tol_velocity=None):
    """Press 0.25 mm past contact in 3 steps, hold, then optionally lift; returns Fz per step (N).

    ``tol_velocity``: Newton tolerance in m/s (None: the default, 1e-4 m/s, i.e. 1 um per step,
    which resolves the gel's force to about 0.02 N only: its stiffness is about 2e4 N/m)."""
    config = None if tol_velocity is None else SolverConfig(tol_velocity=tol_velocity)
    sim = Simulation(load_scene(copy.deepcopy(SCENE)), dt=DT, solver_config=config)
    if candidates is not None:
        sim.solver.set_hook(CandidateHook(candidates))
    pose = np.array(SCENE["effectors"]["ee"]["initial_pose"], dtype=float)
    path = [pose[2] - 0.00115 * k / 3 for k in range(1, 4)] + [pose[2] - 0.00115] * hold
    path += [pose[2] - 0.00115 + 0.0002 * k for k in range(1, lift + 1)]
    fz = []
    for z in path:
        target = pose.copy()
        target[2] = z
        sim.step(Control({"ee": target}))
        fz.append(sim.observe().tactile["tactile"].wrench[2])
    return np.array(fz), sim


def test_parameter_validation_names_the_problem():
    with pytest.raises(ConfigError, match="unknown candidate parameter 'latency'"):
        validate_candidate_parameters({"latency": 0.1})
    with pytest.raises(ConfigError, match="'stiction' must be >= 0"):
        validate_candidate_parameters({"stiction": -0.2})
    with pytest.raises(ConfigError, match="anisotropic_bending"):
        CandidateHook({"anisotropic_bending": 1.5})
    assert CandidateHook({"adhesion": 0.1}).setting("adhesion.reach") == pytest.approx(0.01 * 2.5e-4)


def test_zero_betas_leave_the_rollout_unchanged_and_viscoelastic_force_relaxes():
    base, _ = _press_and_hold(None)
    off, sim = _press_and_hold({"gel_viscoelasticity": 0.0, "stiction": 0.0, "adhesion": 0.0,
                                "anisotropic_bending": 0.0})
    assert np.allclose(off, base, rtol=1e-6, atol=1e-9)
    terms = candidate_terms(sim.model, sim.state, sim.state.x, DT, {"gel_viscoelasticity": 0.0, "adhesion": 0.0})
    assert {type(t).__name__ for t in terms} == {"MaxwellBranch", "LaggedAdhesion"}
    visco, sim = _press_and_hold({"gel_viscoelasticity": 1.0, "gel_viscoelasticity.tau": 0.05})
    pressing = base[3:] < -0.05
    assert pressing.all()
    # stiffer at the end of the press, then the extra force relaxes towards the elastic one
    assert visco[2] < base[2] * 1.2
    excess = visco[3:] - base[3:]
    assert np.all(np.diff(np.abs(excess)) < 0)
    assert abs(excess[-1]) < 0.6 * abs(excess[0])  # series contact stiffness slows the relaxation
    assert "gel_viscoelasticity" in sim.state.candidate_state


def test_adhesion_pulls_on_lift_off():
    """Pressing then lifting 0.2 mm per step: without bonds the gel comes free (Fz <= 0); with bonds it
    is pulled back (Fz > 0, tension) at the step it leaves the card, never beyond the bonds' total
    strength, and no bond acts before the gel touches the card (pairs form only in contact)."""
    beta = 0.05
    # forces of 1e-3 N are asserted: converge to 1e-6 m/s (10 nm per step, ~2e-4 N)
    base, _ = _press_and_hold(None, hold=1, lift=4, tol_velocity=1e-6)
    tacky, sim = _press_and_hold({"adhesion": beta}, hold=1, lift=4, tol_velocity=1e-6)
    assert base[-1] == pytest.approx(0.0, abs=1e-9) and base[-3] <= 0.0
    # before contact: nothing (a reach of 5 delta pulled 0.040 and 0.010 N across the gap)
    assert np.allclose(tacky[:2], base[:2], atol=1e-9)
    # lift-off: tension (measured 0.0125 N against the bare gel's -0.0004 N), and the bonded vertices
    # keep pulling while the gel rises (bond memory; before it, the pairs were gone after one step)
    assert tacky[-3] > 1e-3 and np.all(tacky[-2:] > 1e-3)
    face_vertices = np.unique(sim.model.sensors["tactile"].contact_triangles).size
    assert tacky.max() < beta * face_vertices


def test_adhesion_bonds_carry_the_card_while_the_gel_rises():
    """Bond memory (state ``candidate_state["adhesion"]``, gel face vertices that touched): lifting
    2 mm, weak bonds (2 mN per pair) keep pulling on the card after the lift-off step, past the
    cohesive peak and down its softening branch (measured 3.1, 5.5, 6.0, 5.9 ... 3.5 mN); the release
    beyond 5 delta is tested on a single pair (test_adhesion.py)."""
    beta = 0.002
    assert CandidateHook({"adhesion": beta}).setting("adhesion.release") == pytest.approx(5 * 2.5e-4)
    tacky, sim = _press_and_hold({"adhesion": beta}, hold=1, lift=10, tol_velocity=1e-6)
    lift = tacky[-9:]  # the first lift step still presses (-0.68 N)
    assert np.all(lift > 1e-3)  # pulled at every step after the lift-off
    k = int(np.argmax(lift))
    assert 0 < k < 8 and np.all(np.diff(lift[k:]) < 0)  # rises to the peak, then softens
    face = set(np.unique(sim.model.sensors["tactile"].contact_triangles).tolist())
    bonded = set(sim.state.candidate_state["adhesion"].tolist())
    assert bonded and bonded <= face


def test_one_hook_path_model_candidates_and_a_given_hook_step_alike():
    """The model's candidate parameters and the same CandidateHook given to the solver take the one
    path of the step: the same states bit for bit; both at once, or a hook without the StepHook
    methods, are refused with a message naming them."""
    params = {"stiction": 0.5, "gel_viscoelasticity": 1.0, "gel_viscoelasticity.tau": 0.05}
    _, by_hook = _press_and_hold(params, hold=1)
    sim = Simulation(load_scene(copy.deepcopy(SCENE)), dt=DT)
    for name, value in params.items():
        sim.set_parameter(f"candidate.{name}", value)
    pose = np.array(SCENE["effectors"]["ee"]["initial_pose"], dtype=float)
    for z in [pose[2] - 0.00115 * k / 3 for k in range(1, 4)] + [pose[2] - 0.00115]:
        target = pose.copy()
        target[2] = z
        sim.step(Control({"ee": target}))
    np.testing.assert_array_equal(sim.state.x, by_hook.state.x)
    with pytest.raises(ConfigError, match=r"a step hook \(CandidateHook\) and the model's candidate parameters"):
        sim.solver.set_hook(CandidateHook({"stiction": 0.1}))
    with pytest.raises(ConfigError, match="hook object is not a StepHook .missing terms, update_state"):
        NewtonSolver(sim.model, hook=object())


def test_adhesion_bonds_break_at_the_release_time():
    """``adhesion.release_time``: the bonds act as without it in every step that starts before it, and
    from it on none acts (the gel rising off the card is free: Fz 0, as without adhesion) and the
    bonded set is empty."""
    beta, release = 0.002, 0.07  # the lift starts with step 5 (t 0.04 -> 0.05); bonds pull from step 6 on
    base, _ = _press_and_hold(None, hold=1, lift=10, tol_velocity=1e-6)
    tacky, _ = _press_and_hold({"adhesion": beta}, hold=1, lift=10, tol_velocity=1e-6)
    peeled, sim = _press_and_hold({"adhesion": beta, "adhesion.release_time": release}, hold=1, lift=10,
                                  tol_velocity=1e-6)
    n_before = int(round(release / DT))  # steps 0..6 start before 0.07 s
    assert np.allclose(peeled[:n_before], tacky[:n_before], rtol=1e-9, atol=1e-12)
    assert np.all(tacky[n_before:] > 1e-3)  # still pulled without the release
    # free after it, as the bare gel (1e-6 N at the first step: the card, pulled up, touches as it falls back)
    assert np.allclose(peeled[n_before:], base[n_before:], atol=1e-5)
    assert sim.state.candidate_state["adhesion"].size == 0
    with pytest.raises(ConfigError, match="release_time"):
        validate_candidate_parameters({"adhesion.release_time": -1.0})
