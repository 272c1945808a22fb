"""A plain replay lets the card at rest sleep (``sysid.observation.REPLAY_SLEEPING``) and stays the replay it was.

The bundled recording (nominal_s101's press-slide) through its series drive, the fit's 10 ms step: in its first
0.6 s the pad comes down in the air while the card lies on the table, at rest to round-off (its Newton update after
a step's first iteration ~1e-15 m/s: docs/benchmarks_log.md, session 64, 64step), so the card falls asleep; the
sleeping replay must then equal the replay with every body awake to within the sleep's own bound, ``sleep_velocity *
dt`` a step it sleeps (the drive's guessed first iterate and the joint compression step, which sleeping used to
exclude, included). A replay with the fit's tangents after it keeps every body awake (a sleeping step's record is not
differentiable: :func:`sim_core.adjoint.rollout_step` refuses it).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import sysid.observation as observation
from sysid.evidence import load_evidence
from sysid.fit import DEFAULT_PARAMETERS
from sysid.observation import ObservationModel
from sysid.replay_drive import drive_sensitivities

BAG = Path(__file__).resolve().parents[2] / "bags" / "nominal_s101"

T_MAX = 0.6
"""Seconds replayed (60 steps of 10 ms): the pad's approach in the air, the card at rest on the table."""


@pytest.fixture(scope="module")
def model() -> ObservationModel:
    """The bundled recording's first 0.6 s through a series drive (3,000 N/m, 10 N s/m)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(BAG, include_image="auto"), dt=0.01, t_max=T_MAX, arch="cpu")
    model.set_drive_stiffness(3000.0, 10.0)
    return model


def _replay(model: ObservationModel, sleeping: bool, monkeypatch) -> tuple[np.ndarray, list[tuple[str, ...]]]:
    """The replay's positions ``(K + 1, n, 3)`` m and the bodies asleep at each step, with REPLAY_SLEEPING set."""
    monkeypatch.setattr(observation, "REPLAY_SLEEPING", sleeping)
    asleep: list[tuple[str, ...]] = []
    params = {name: model.parameter_value(name) for name in DEFAULT_PARAMETERS}
    trace = model.simulate(params, keep_positions=True,
                           on_step=lambda k, K: asleep.append(tuple(model.simulation().last_info.sleeping)))
    return trace.positions, asleep


def test_the_resting_card_sleeps_and_the_replay_is_the_awake_one(model, monkeypatch):
    awake, none_asleep = _replay(model, False, monkeypatch)
    slept, asleep = _replay(model, True, monkeypatch)
    assert not any(none_asleep)
    sleeping_steps = sum("sheet" in names for names in asleep)
    assert sleeping_steps >= 20, f"the card slept in {sleeping_steps} of {len(asleep)} steps"
    config = model.simulation().solver.config
    assert not config.sleeping  # restored after the replay
    bound = config.sleep_velocity * model.dt * sleeping_steps
    assert np.abs(slept - awake).max() <= bound
    # every step solved: the positions move (the pad comes down), the card's asleep are its awake ones to the bound
    assert np.abs(awake[-1] - awake[0]).max() > 1e-4


def test_a_replay_with_tangents_after_a_sleeping_replay_keeps_every_body_awake(model, monkeypatch):
    _, asleep = _replay(model, True, monkeypatch)
    assert any(asleep)
    params = {name: model.parameter_value(name) for name in DEFAULT_PARAMETERS}
    sim = model.prepare(params)
    trajectory, dX, _, _ = drive_sensitivities(model, sim, list(params))  # raises on a sleeping step's record
    assert len(trajectory.states) == model.step_count + 1
    assert np.all(np.isfinite(dX))
    assert not sim.last_info.sleeping
