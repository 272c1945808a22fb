"""A replay's steps start their Newton iterations at the inertia's prediction ``x^n + dt v^n``
(:data:`sysid.observation.REPLAY_INERTIAL_START`, ``SolverConfig.inertial_start``) and end at the same minimiser.

Each step minimises the same incremental potential from either first iterate and stops within
:data:`sysid.observation.REPLAY_TOL_VELOCITY` of its minimiser, so the two replays may differ by the stopping error
only; where the card slides on the table under the gel such an error is carried on from step to step
(tests/sysid/test_replay_convergence.py), so nominal_s101's first 2 s (the press, the dwell and the slide's start)
are replayed kinematically both ways and compared in noise units. The prediction saves Newton iterations wherever
the pad moves (docs/benchmarks_log.md, session 57, s57-49time).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.solver_config import SolverConfig
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel
from tests.sysid.conftest import reference_bag

SCENE = {"sheet.bending_stiffness": 0.007418, "gel.youngs_modulus": 3.0e5, "friction.gel_sheet": 0.8}
"""nominal_s101's scene values (its engine's)."""

T_MAX = 2.0
"""Seconds replayed (kinematic, 200 steps of 10 ms)."""

BOUND = 1e-3
"""Largest whitened RMS difference per channel between the two replays (noise units): the bound within which
replays a hair apart in the gel modulus stay at the replay tolerance (tests/sysid/test_replay_convergence.py), 8-10x
below the jumps of a replay stopped at the simulator's default 1e-4 m/s."""


@pytest.fixture(scope="module")
def replays():
    """nominal_s101's first 2 s at the scene's values, each step from ``x^n + dt v^n`` and from ``x^n``: the model,
    the whitened residuals and the Newton iterations of every step, per first iterate."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(reference_bag("nominal_s101"), include_image="auto"), dt=0.01,
                                 t_max=T_MAX, arch="cpu")
    config = model.simulation().solver.config
    out = {}
    for inertial in (True, False):
        config.inertial_start = inertial
        iterations = []
        sim = model.prepare(SCENE)
        observed = [model.observe_step(sim)]
        for k in range(1, model.step_count + 1):
            iterations.append(sim.step(model.control(k)).iterations)
            observed.append(model.observe_step(sim))
        trace = model.trace_from(observed, 0.0)
        out[inertial] = (model.residuals(model.predict(trace)), np.array(iterations))
    config.inertial_start = True
    return model, out


def test_replays_start_at_the_inertia_prediction():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(reference_bag("nominal_s101"), include_image="auto"), dt=0.01,
                                 t_max=0.05, arch="numpy")
    assert model.simulation().solver.config.inertial_start is True


def test_the_inertia_prediction_ends_each_step_at_the_same_minimiser(replays):
    """Every channel within 1e-3 whitened RMS of the replay whose steps start at ``x^n``."""
    model, out = replays
    a, b = out[True][0], out[False][0]
    diff = {ch: float(np.sqrt(np.mean((a[s] - b[s]) ** 2))) for ch, s in model.channel_slices().items()}
    assert max(diff.values()) < BOUND, diff


def test_the_inertia_prediction_saves_newton_iterations(replays):
    """Fewer Newton iterations in all; the pad's approach in the air (the first 20 steps: no contact, the gel carried
    at the pad's speed) takes at most as many from the prediction as from ``x^n`` at every step."""
    _, out = replays
    inertial, rest = out[True][1], out[False][1]
    assert inertial.sum() < 0.9 * rest.sum(), (inertial.sum(), rest.sum())
    assert np.all(inertial[:20] <= rest[:20]), (inertial[:20], rest[:20])


def test_a_lockstep_batch_has_no_inertial_start():
    with pytest.raises(ConfigError, match="inertial_start is not available with lockstep"):
        SolverConfig(inertial_start=True, lockstep=True)
