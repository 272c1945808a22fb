"""The series spring's compression as an unknown of the step's Newton solve (sim_core.drive_compression).

A gel pad pressed onto a rigid table through a series spring and damper (the scene of test_series_drive.py).
Checked: the joint potential's gradient and bordered Newton matrix in ``(x_free, b)`` against central
differences of its energy and gradient at a step in contact; the joint step against the secant's converged
root (``SeriesSpringDrive(solve="secant")``) on the press and the dwell; free motion's damper lag ``b = c v /
k_s`` exactly; and forward tangents carried through joint drive steps (``DriveStep.inertial``) against central
differences of the rollout in the gel's modulus.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from sim_core.control import Control
from sim_core.drive_compression import CompressionUnknown
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.sensitivity import DriveStep, TangentPropagation
from sim_core.series_drive import SeriesSpringDrive
from sim_core.step_info import StepInfo
from sim_core.scenes import load_scene
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from tests.sim_core.test_series_drive import DOWN, START_Z, _gel_vertices, _pose
from tests.sim_core.test_sliding_normal_force import _scene

DEPTH = 4.0e-4  # m: the anchor's depth past first contact
STIFFNESS, DAMPING = 3000.0, 2.0  # N/m, N s/m: an arm's impedance of the reference engine's order
TANGENT_STEPS = 13
"""The tangent's rollout: the approach, the touch and the press's stop (the gel's inertia is in the balance there:
the tangent with the contact load alone is 3e-4 off in the load, 2e-5 in the compression; measured 8e-7 with it)."""


def _simulation() -> Simulation:
    """The pad above the table, each step solved to a replay's 1e-7 m/s (the joint balance's force is resolved to
    the Newton tolerance times the contact's and spring's stiffness: ~1e-9 m of compression, ~3 uN here)."""
    return Simulation(load_scene(_scene(0.8)), dt=0.01, solver_config=SolverConfig(tol_velocity=1e-7))


def _path() -> list[float]:
    """Approach in 12 steps to :data:`DEPTH` past first contact, then 6 steps of dwell."""
    return [START_Z - (START_Z + DEPTH) * k / 12 for k in range(1, 13)] + [-DEPTH] * 6


def _press(solve: str, steps: int | None = None, modulus: float | None = None, joint_fails: bool = False):
    """The pad pressed along :func:`_path` (its first ``steps`` steps) through the drive solved by ``solve``:
    the simulation and each step's :class:`~sim_core.series_drive.SeriesDriveStep`. ``joint_fails``: every
    step with the compression among the unknowns raises the solver's divergence (a forced failure)."""
    sim = _simulation()
    if joint_fails:
        step = sim.step

        def failing(control):
            if control.compression is not None:
                raise SimulationDivergedError("forced: the joint Newton solve did not converge")
            return step(control)

        sim.step = failing
    if modulus is not None:
        sim.model.set_parameter("gel.youngs_modulus", modulus)
    drive = SeriesSpringDrive("ee", STIFFNESS, _gel_vertices(sim), force_tolerance=1.0e-5, damping=DAMPING,
                              solve=solve, max_evaluations=30)
    b, slope, results = 0.0, 0.0, []
    for z in _path()[:steps]:
        result = drive.step(sim, Control({"ee": _pose(z)}), DOWN, start=b, contact_slope=slope)
        b, slope = result.compression, result.contact_slope
        results.append(result)
    return sim, drive, results


def _unknown(sim, drive: SeriesSpringDrive, anchor: np.ndarray, start: float) -> CompressionUnknown:
    rate = drive.damping / sim.dt
    reach = float(np.dot(anchor[:3] - sim.state.effector_pose["ee"][:3], DOWN))
    return CompressionUnknown("ee", DOWN, drive.stiffness, rate, reach, start, drive.load_vertices)


def test_the_joint_gradient_and_bordered_matrix_are_the_derivatives_of_its_energy():
    """At a step's start in contact (the spring 2 um off its balance), along the joint Newton direction (a random
    direction kinks the penalty contacts' curvature: its differences converge at first order only)."""
    sim, drive, results = _press("joint", steps=15)
    assert results[-1].load > 0.5  # in contact
    solver, state = sim.solver, sim.state
    anchor = _pose(_path()[15])
    control = Control({"ee": anchor}, compression=_unknown(sim, drive, anchor, results[-1].compression + 2e-6))
    info = StepInfo()
    step, x = solver._set_up_step(state, control, sim.dt, None, info)
    joint = step.compression

    def energy_and_gradient(at: np.ndarray) -> tuple[float, np.ndarray, list]:
        terms, searched, g = solver._gradient(step, at, 1, info)
        return solver._energy(step, at, terms, searched), joint.reduced_gradient(g), terms

    _, g0, terms = energy_and_gradient(x)
    upper = solver._assemble_hessian(step, x, "none", terms + step.dynamic_terms)
    full = joint.bordered(upper).tocsc()
    direction = spla.spsolve(full, -g0)
    # the solver's elimination of the border is the reduced system's solution
    kinematic = joint.constrained(upper)
    lu = spla.splu((kinematic + sp.triu(kinematic, k=1).T).tocsc())
    eliminated = joint.direction(lu.solve, solver._gradient(step, x, 1, info)[2], *joint.border(upper)[1:])
    assert np.allclose(eliminated, joint.update(direction), rtol=0.0, atol=1e-9 * np.max(np.abs(direction)))
    assert abs(g0[-1]) > 1e-3 and abs(direction[-1]) > 1e-7  # the compression moves: a border that can fail
    direction *= 1e-7 / np.max(np.abs(direction))
    shift = joint.update(direction).reshape(-1, 3)
    assert np.max(np.abs(shift[joint.base] + direction[-1] * DOWN)) == 0.0  # the base tied rigidly
    (e_plus, g_plus, _), (e_minus, g_minus, _) = energy_and_gradient(x + shift), energy_and_gradient(x - shift)
    assert (e_plus - e_minus) / 2.0 == pytest.approx(float(g0 @ direction), rel=1e-6)
    product = full @ direction
    assert np.linalg.norm((g_plus - g_minus) / 2.0 - product) < 1e-5 * np.linalg.norm(product)
    # the compression's own row (the border and the corner) against its difference
    assert (g_plus[-1] - g_minus[-1]) / 2.0 == pytest.approx(product[-1], rel=1e-8)


def test_the_joint_step_is_the_secants_converged_root_and_one_newton_solve():
    """The joint balance is the secant's with the gel's inertia ``N`` (the joint step's ``-residual``) beside the
    contact load: the two loads differ by ``N`` within 0.1 mN (the free approach's lag is exact in the joint step,
    within the secant's 1e-5 N tolerance there, and the first touch's contact of ~6e5 N/m turns that into ~0.1 mN),
    ``N`` is a few tenths of a mN where the pad touches and stops, and zero at the dwell's rest."""
    _, _, secant = _press("secant")
    sim, _, joint = _press("joint")
    assert all(r.evaluations == 1 and r.converged and r.joint for r in joint)
    assert sum(r.evaluations for r in secant) > 2 * len(secant)
    pressed = [k for k, r in enumerate(secant) if r.load > 0.2]
    assert len(pressed) >= 10
    for k in pressed:
        assert secant[k].converged and abs(secant[k].residual) <= 1.0e-5
        inertia = -joint[k].residual
        assert abs(inertia) < 1.0e-3, k
        assert joint[k].load + inertia == pytest.approx(secant[k].load, abs=1.0e-4), k
        assert joint[k].compression == pytest.approx(secant[k].compression, abs=1.0e-4 / STIFFNESS), k
    assert max(abs(joint[k].residual) for k in pressed[:2]) > 1.0e-4  # the touch decelerates the gel
    assert abs(joint[-1].residual) < 1.0e-6  # at rest
    assert sim.state.effector_pose["ee"][2] == pytest.approx(-DEPTH + joint[-1].compression, abs=1e-12)
    # the base rigidly at the tool: the kinematic step's driven vertices at the pose found
    base = sim.model.effectors["ee"].vertices
    kinematic = _simulation()
    kinematic.step(Control({"ee": sim.state.effector_pose["ee"]}))
    assert np.max(np.abs(sim.state.x[base] - kinematic.state.x[base])) < 1e-12


def test_a_joint_solve_that_diverges_is_taken_again_by_the_secant():
    """Where the joint Newton solve fails (forced here at every step), the step is taken by the secant from the
    same start state: the press is the secant's bit for bit (compressions, loads, residuals, the state and the
    accepted steps' totals), each step counting the failed solve as one evaluation more and marked not joint."""
    plain_sim, _, plain = _press("secant")
    sim, _, retried = _press("joint", joint_fails=True)
    assert len(retried) == len(plain)
    for a, b in zip(retried, plain):
        assert not a.joint and not b.joint
        assert (a.compression, a.load, a.residual, a.converged) == (b.compression, b.load, b.residual, b.converged)
        assert a.evaluations == b.evaluations + 1
    assert np.array_equal(sim.state.x, plain_sim.state.x)
    assert sim.step_totals == plain_sim.step_totals


def test_free_motion_lags_by_the_dampers_c_v_over_k_s():
    _, _, results = _press("joint", steps=6)
    speed = (START_Z + DEPTH) / 12 / 0.01
    assert results[-1].load == 0.0
    assert results[-1].compression == pytest.approx(DAMPING * speed / STIFFNESS, rel=1e-6)


def _joint_tangent(modulus: float) -> tuple[float, float, float, float]:
    """The press's last compression (m) and load (N), and their tangents in the gel's modulus, carried through
    every joint drive step."""
    sim = _simulation()
    sim.model.set_parameter("gel.youngs_modulus", modulus)
    drive = SeriesSpringDrive("ee", STIFFNESS, _gel_vertices(sim), damping=DAMPING, solve="joint")
    tangents = TangentPropagation(sim.model, ["gel.youngs_modulus"], contact_force=True, backend=sim.solver.backend)
    base = np.asarray(sim.model.effectors["ee"].vertices)
    rate = DAMPING / sim.dt
    b, result, db, df = 0.0, None, 0.0, None
    for z in _path()[:TANGENT_STEPS]:
        before = sim.state.copy()
        result = drive.step(sim, Control({"ee": _pose(z)}), DOWN, start=b)
        b = result.compression
        lin = tangents.linearization(sim.solver.last_record, before, sim.solver.general_solver(),
                                     factorization=sim.solver.exact_factorization())
        _, df = tangents.advance(lin, DriveStep(base, drive.load_vertices, DOWN, STIFFNESS + rate, rate, inertial=True))
        db = float(tangents.db[0])
    dload = -float(np.dot(DOWN, df[drive.load_vertices, :, 0].sum(axis=0)))
    return result.compression, result.load, db, dload


def test_tangents_through_joint_drive_steps_are_the_derivatives_of_the_rollout():
    modulus = 3.0e5
    _, _, db, dload = _joint_tangent(modulus)
    h = 1e-3 * modulus
    (b_plus, f_plus, _, _), (b_minus, f_minus, _, _) = _joint_tangent(modulus + h), _joint_tangent(modulus - h)
    assert abs(db) > 1e-12 and abs(dload) > 1e-8  # the modulus moves the press's balance
    assert db == pytest.approx((b_plus - b_minus) / (2.0 * h), rel=1e-5)
    assert dload == pytest.approx((f_plus - f_minus) / (2.0 * h), rel=1e-5)


@pytest.mark.parametrize("field, value, match", [
    ("axis", np.array([0.0, 0.0, 2.0]), "unit 3-vector"),
    ("stiffness", np.inf, "finite and > 0"),
    ("rate", -1.0, "c/dt"),
    ("start", np.nan, "finite"),
])
def test_invalid_compression_unknowns_are_refused(field, value, match):
    good = CompressionUnknown("ee", DOWN, 1000.0, 0.0, 0.0, 0.0, np.arange(3))
    with pytest.raises(ConfigError, match=match):
        dataclasses.replace(good, **{field: value})


def test_an_unknown_solve_is_refused():
    with pytest.raises(ConfigError, match="solve must be one of"):
        SeriesSpringDrive("ee", 1000.0, np.arange(3), solve="newton")
