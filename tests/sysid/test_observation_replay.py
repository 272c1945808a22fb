"""The replay of a recording (sysid.observation.ObservationModel): failed steps retried in substeps,
and the retries counted."""

from __future__ import annotations

import warnings

import pytest

from sysid.evidence import load_evidence
from sysid.observation import REPLAY_DT_HALVINGS, ObservationModel
from tests.sysid.simbag import DT, PRESS_ONLY, make_recording


@pytest.fixture(scope="module")
def press_model(tmp_path_factory):
    bag = make_recording(tmp_path_factory.mktemp("press") / "bag", segments=PRESS_ONLY, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObservationModel(load_evidence(bag), dt=DT)


def test_replays_retry_a_failed_step_in_substeps_and_count_the_steps(press_model):
    sim = press_model.simulation()
    assert REPLAY_DT_HALVINGS >= 1 and sim.solver.config.dt_halvings_on_failure == REPLAY_DT_HALVINGS
    press_model.simulate({})
    totals = sim.step_totals
    assert totals.steps == press_model.step_count
    assert totals.substeps >= totals.steps and totals.retries >= totals.retried_steps
    press_model.simulate({})  # each replay starts its counts again (Simulation.reset)
    assert sim.step_totals.steps == press_model.step_count
