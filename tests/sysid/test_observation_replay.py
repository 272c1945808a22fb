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


def test_a_replay_fitted_on_some_channels_spans_every_channel_the_recording_has():
    """nominal_s101's wrench (200 Hz) ends after its markers and sheet points: a model that fits only those still
    replays to the wrench's last sample, which its calibration predicts, as the model of every channel does
    (``thinshell sysid BAG --channels markers_xyz,sheet_points``)."""
    from sysid.replay_trace import PREDICTABLE_CHANNELS
    from tests.sysid.conftest import reference_bag

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ev = load_evidence(reference_bag("nominal_s101"), include_image=False)
        assert ev.t_ns["wrench"][-1] > max(ev.t_ns[ch][-1] for ch in ("markers_xyz", "sheet_points"))
        some = ObservationModel(ev, channels=("markers_xyz", "sheet_points"))
        every = ObservationModel(ev)
    assert some.channels == ("markers_xyz", "sheet_points")
    assert (some.step_times_ns == every.step_times_ns).all()
    for ch in PREDICTABLE_CHANNELS:
        assert some.step_times_ns[0] <= ev.t_ns[ch][0] and ev.t_ns[ch][-1] <= some.step_times_ns[-1], ch
