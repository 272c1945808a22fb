"""A Newton step that ends with its last update applied (``SolverConfig.apply_last_update``) is second-order exact.

The default stopping test measures the update ``d_k`` at ``x_k`` and stops at ``x_k``: the result is off the step's
minimiser by about ``|d_k|`` (up to ``tol_velocity * dt``). Applied, the error is ``O(|d_k|^2)`` (a full Newton step
with the exact Hessian). Checked on the press-slide card of ``test_adjoint`` (penalty contact with the table and the
gel, lagged friction, damping): every step started from the converged trajectory's state and
solved at the simulator's default 1e-4 m/s, with and without the update, against the same step solved to
1e-9 m/s (its own error below 5e-12 m).
The distance to that minimiser is ``H^{-1} g`` of the result: the step's gradient in the metric of its Hessian.

The step's tangents are then the implicit-function tangents at the result ``x_k + d_k``: its Newton matrix is that of
``x_k``, so the forward sensitivities take the exact Hessian assembled at the result (``NewtonSolver.exact_factorization``,
the lagged friction's stick stiffness there). Checked against the tangents of the trajectory solved to 1e-9 m/s.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.sensitivity import rollout_sensitivities
from sim_core.simulation import Simulation
from sim_core.solver import STRICT_STOPS, SolverConfig
from tests.sim_core.test_adjoint import _scene
from tests.sim_core.test_simplified_newton import _controls

TOL = 1e-4
"""The simulator's default Newton tolerance (m/s), at which the stopping error shows."""


def _errors():
    """Per step, the largest vertex distance (m) from the step's converged result of the step solved at ``TOL`` as
    it stops by default and with its last update applied, each from the converged trajectory's state; the step (s)
    and the applied steps' stop reasons."""
    ref = Simulation.from_scene(_scene(), solver_config=SolverConfig(tol_velocity=1e-9))
    plain = Simulation.from_scene(_scene(), solver_config=SolverConfig(tol_velocity=TOL))
    applied = Simulation.from_scene(_scene(), solver_config=SolverConfig(tol_velocity=TOL, apply_last_update=True))
    out = []
    for control in _controls():
        start = ref.state.copy()
        ref.step(control)
        row = []
        for sim in (plain, applied):
            sim.state = start.copy()
            info = sim.step(control)
            row.append(float(np.max(np.linalg.norm(sim.state.x - ref.state.x, axis=1))))
        out.append((row[0], row[1], info.stop_reason, info.iterations))
    return out, ref.dt


@pytest.fixture(scope="module")
def errors():
    return _errors()


def test_the_applied_update_brings_every_step_to_its_minimiser_to_second_order(errors):
    rows, dt = errors
    bound = TOL * dt  # the default stop's error bound, m
    # strict stops, none by the simplified test (its correction, from the previous matrix, is not applied)
    assert all(reason in STRICT_STOPS and reason != "simplified" for _, _, reason, _ in rows)
    for plain, applied, _, _ in rows:
        assert plain < bound
        # second order: measured <= 4.2e-12 m against the default stop's up to 2.0e-7 m (bound 5e-7 m)
        assert applied < 0.01 * bound
    # the default stop's error is the update it leaves: the applied one removes it (at least 10x on the whole run)
    assert max(a for _, a, _, _ in rows) < 0.1 * max(p for p, _, _, _ in rows)


TANGENT_PARAMETERS = ["contact.eps_v", "friction.gel_sheet", "gel.youngs_modulus", "contact.stiffness"]
"""Parameters whose tangents the press-slide rollout checks: the stick regularisation and friction coefficient (the
lagged friction's stick stiffness), the gel's modulus, the penalty's stiffness."""


def test_the_tangents_of_applied_steps_are_those_of_the_converged_trajectory():
    """Forward tangents of the six-step press-slide, every step solved at ``TOL`` with its update applied, against those
    of the trajectory solved to 1e-9 m/s: each column within 1e-6 of its norm over the rollout (measured 3.5e-7 for
    contact.eps_v, 1.6e-8 ... 2.8e-8 for the rest; 3.9e-5 ... 5.6e-5 with the matrix of the iterate before the result;
    the default unapplied stop 8e-4 ... 6.8e-3)."""

    def tangents(config: SolverConfig) -> np.ndarray:
        sim = Simulation.from_scene(_scene(), solver_config=config)
        return rollout_sensitivities(sim, _controls(), TANGENT_PARAMETERS)[1]

    applied = tangents(SolverConfig(tol_velocity=TOL, apply_last_update=True))
    converged = tangents(SolverConfig(tol_velocity=1e-9))
    for j, name in enumerate(TANGENT_PARAMETERS):
        norm = np.linalg.norm(converged[..., j])
        assert norm > 0.0, name
        assert np.linalg.norm(applied[..., j] - converged[..., j]) < 1e-6 * norm, name


def test_off_by_default():
    assert SolverConfig().apply_last_update is False
