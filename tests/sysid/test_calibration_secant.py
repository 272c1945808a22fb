"""The calibration's secant stage (sysid.calibration_secant): its later replays start from its first
replay's state before the gel's first contact force, and a first replay made elsewhere is taken only
for its own parameters. On the reference recording nominal_s101 (first second, coarse gel)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sysid.calibration_secant import (CONTACT_MARGIN_STEPS, SECANT_FIRST_FACTOR, FirstReplay, first_probe_values,
                                      resume_before_contact)

CHANNELS = ("markers_xyz", "markers_uv", "wrench", "sheet_points")


@pytest.fixture(scope="module")
def press():
    """nominal_s101's first second (the pad's approach, then the press from 0.63 s), coarse gel."""
    from sysid.evidence import load_evidence
    from sysid.observation import ObservationModel
    from tests.sysid.conftest import reference_bag

    ev = load_evidence(reference_bag("nominal_s101"))
    model = ObservationModel(ev, dt=0.01, t_max=1.0, simulation={"gel_resolution": [4, 3, 2]}, arch="cpu")
    return model, model.simulate({}, keep_states=True)


def _close(a, b, rtol):
    for ch in CHANNELS:
        x, y = np.asarray(getattr(a, ch)), np.asarray(getattr(b, ch))
        assert x.shape == y.shape
        assert np.max(np.abs(x - y)) <= rtol * max(float(np.max(np.abs(x))), 1e-30), ch


def test_a_stick_regularisation_replay_resumed_before_the_gel_touches_is_the_full_replay(press):
    """Known answer: the friction's stick regularisation acts only on a loaded contact that slips, so a
    replay at a third of ``contact.eps_v`` takes the scene-value replay's steps until the gel's first
    force; resumed from the state two steps before it, it equals the full replay to round-off."""
    model, trace = press
    loaded = np.flatnonzero(np.any(trace.wrench != 0.0, axis=1))
    assert loaded.size and 20 < loaded[0] < model.step_count  # an approach in the air, then a press
    resume = resume_before_contact(trace)
    assert resume.step == loaded[0] - 1 - CONTACT_MARGIN_STEPS
    assert resume.prefix.wrench.shape[0] == resume.step + 1 and not np.any(resume.prefix.wrench)
    values = {"contact.eps_v": SECANT_FIRST_FACTOR * model.parameter_value("contact.eps_v")}
    full = model.simulate(values)
    resumed = model.simulate(values, resume=resume)
    _close(full, resumed, 1e-9)
    # the regularisation changes the press: the resumed replay is not the scene-value one
    assert np.max(np.abs(full.wrench - trace.wrench)) > 1e-6


def test_no_resume_where_the_gel_is_loaded_from_the_start(press):
    model, trace = press
    pressed = dataclasses.replace(trace, wrench=np.ones_like(trace.wrench))
    assert resume_before_contact(pressed) is None
    with pytest.raises(ValueError, match="no states"):
        resume_before_contact(dataclasses.replace(trace, states=None))


def test_secant_stage_takes_a_first_replay_made_elsewhere_only_for_its_parameters(press):
    """The stage with its first replay given (as a probe worker gives it) fits what the stage fits
    alone; a given replay of other parameters is not taken."""
    from sysid.calibration import calibrate

    model, _ = press
    alone = calibrate(model, (), secant_replays=2).summary()["secant"]
    values = first_probe_values(model, {}, ("contact.eps_v",))
    made = model.simulate(values, keep_states=True)
    first = FirstReplay(values, dataclasses.replace(made, states=None), resume_before_contact(made))
    calls = []

    def given():
        calls.append(1)
        return first

    taken = calibrate(model, (), secant_replays=2, secant_first=given).summary()["secant"]
    assert len(calls) == 1
    for key in ("values", "replays", "cost_initial", "cost_final", "accepted"):
        assert taken[key] == pytest.approx(alone[key], rel=1e-9), key
    # a replay of other parameters (here: a wrench the simulator never made) is ignored
    other = FirstReplay({"contact.eps_v": 1.0}, dataclasses.replace(first.trace, wrench=first.trace.wrench + 1.0), None)
    ignored = calibrate(model, (), secant_replays=2, secant_first=lambda: other).summary()["secant"]
    assert ignored["values"] == pytest.approx(alone["values"], rel=1e-9)
    assert ignored["cost_final"] == pytest.approx(alone["cost_final"], rel=1e-9)
