"""The effector's drive along the sensor normal: fitted in closed form (sysid.drive_calibration) and
replayed through a series spring anchored at the command and a damper (sysid.replay_drive).

The reference recordings are made by an arm that is a 3000 N/m Cartesian impedance (their README):
the fit must find that stiffness, and a replay through it must load the gel as the recording does.
A recording whose pose is its command (this simulator's own, kinematic) keeps the kinematic replay, and so
does a stiff arm whose lag is pose noise: the data choose the drive by delta-BIC.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from sim_core.errors import CalibrationError
from sysid.drive_calibration import DRIVE_MIN_DELTA_BIC, fit_drive
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel
from tests.sysid.conftest import SCENE, reference_bag, synthetic_streams, write_synthetic
from tests.sysid.simbag import (NOISE, PRESS_SLIDE, TRUE_PARAMS, add_noise, lagged_streams, lagging_commander,
                                scene_with, targets_from_segments, write_bag)

REFERENCE_IMPEDANCE = 3000.0  # N/m, the reference world's arm (shared/data/reference_bags/README.md)


def _model(bag, **kwargs) -> ObservationModel:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObservationModel(load_evidence(bag), **kwargs)


def test_the_reference_arm_is_fitted_as_its_documented_impedance():
    """The spring is the README's 3000 N/m; with the damper read in free motion (about 11 ms of lag per
    unit speed) the spring and damper leave the recorded normal load at the force sensor's noise."""
    model = _model(reference_bag("nominal_s101"))
    fit = fit_drive(model)
    assert fit.compliant and fit.why == ""
    assert fit.delta_bic > 100 * DRIVE_MIN_DELTA_BIC and fit.summary()["decision"] == "compliant"
    assert fit.stiffness == pytest.approx(REFERENCE_IMPEDANCE, rel=0.03)
    assert fit.stiffness_sigma < 0.01 * fit.stiffness
    assert fit.explained > 0.95
    assert fit.replay_stiffness == fit.stiffness
    assert 0.0 < fit.damping == fit.replay_damping
    assert fit.residual_rms < 1.05 * float(model.sigma["wrench"][2])


def test_the_damper_is_read_where_no_load_acts_so_a_tactile_delay_does_not_enter_it():
    """latency_s103's tactile streams lag its poses by 40 ms: a damper fitted to the load would take part of
    that delay (the load then trails the lag); read from the arm's own streams in free motion its time
    constant is nominal_s101's. The tactile delay is left in the load's residual, for the diagnosis."""
    nominal, late = fit_drive(_model(reference_bag("nominal_s101"))), fit_drive(_model(reference_bag("latency_s103")))
    tau_nominal, tau_late = nominal.damping / nominal.stiffness, late.damping / late.stiffness
    assert tau_late == pytest.approx(tau_nominal, rel=0.02)
    assert late.residual_rms > 2.0 * nominal.residual_rms


def test_a_press_and_lift_takes_the_same_arm():
    """nominal_s109 presses and lifts the card without sliding (under 2 mm across the normal while loaded): the
    arm is the same 3000 N/m impedance, and the data choose it there as on a press-and-slide."""
    fit = fit_drive(_model(reference_bag("nominal_s109")))
    assert fit.slide < 0.002
    assert fit.compliant and fit.delta_bic > 100 * DRIVE_MIN_DELTA_BIC
    assert fit.stiffness == pytest.approx(REFERENCE_IMPEDANCE, rel=0.05)
    assert fit.replay_stiffness == fit.stiffness and fit.replay_damping == fit.damping > 0.0


def _press(lag_of_load, seed: int = 5) -> dict:
    """Synthetic streams of a press (3 s at 100 Hz, a smooth 0-4 N load, 0.2 N force noise, 5 um pose noise)
    whose commanded pose leads the measured one along the sensor normal by ``lag_of_load(load)`` (m)."""
    rng = np.random.default_rng(seed)
    streams = synthetic_streams(n=300, seed=seed)
    t = np.arange(300) / 100.0
    load = 4.0 * np.sin(np.pi * np.clip((t - 0.5) / 2.0, 0.0, 1.0)) ** 2
    pose = streams["pose"]
    pose[:, 0] = 0.05
    pose[:, 2] = 0.004 - 0.001 * np.clip((t - 0.3) / 0.5, 0.0, 1.0)  # an approach, then held
    normal = np.array([0.0, 0.0, -1.0])  # the sensor's z (out of the gel) in world: the quaternion (1 0 0 0)
    command = pose.copy()
    command[:, :3] += lag_of_load(load)[:, None] * normal + rng.normal(scale=5e-6, size=(300, 3))
    streams["pose"][:, :3] += rng.normal(scale=5e-6, size=(300, 3))
    streams["pose_cmd"] = command
    streams["wrench"][:, :3] *= 0.2
    streams["wrench"][:, 2] -= load
    return streams


def test_the_data_choose_the_drive_by_delta_bic(tmp_path):
    """Known answer: a 2000 N/m arm whose commanded pose leads the measured one by load / k_s is found compliant
    at its stiffness; a stiff arm whose lag is pose noise alone (5 um, no load in it) keeps the kinematic
    replay, by delta-BIC, and says so."""
    compliant = fit_drive(_model(write_synthetic(tmp_path / "compliant", _press(lambda f: f / 2000.0), scene=SCENE)))
    assert compliant.compliant and compliant.delta_bic > DRIVE_MIN_DELTA_BIC
    assert compliant.stiffness == pytest.approx(2000.0, abs=3 * compliant.stiffness_sigma)
    stiff = fit_drive(_model(write_synthetic(tmp_path / "stiff", _press(lambda f: 0.0 * f), scene=SCENE)))
    assert not stiff.compliant and stiff.replay_stiffness == math.inf
    assert stiff.delta_bic < DRIVE_MIN_DELTA_BIC and "delta-BIC" in stiff.why
    assert stiff.summary()["decision"] == "kinematic"


LAGGED_ARM = (2000.0, 5.0)
"""An impedance-controlled arm (k_s N/m, c N s/m along the sensor normal), as tests/sysid/test_sysid_drive.py's."""

LAGGED_ARM_SEGMENTS = (((0.0, 0.0, -0.0025), 8), *PRESS_SLIDE[1:], ((0.0, 0.0, 0.0), 4), ((0.0, 0.0, 0.0025), 8))
"""The card pressed 2.5 mm down through the arm (about 3 N on the gel), slid, held and released: 45 steps of 10 ms."""


def test_under_a_lagging_commander_the_drive_is_read_from_the_commands_the_robot_took(tmp_path):
    """Known answer: the card pressed and slid by :data:`LAGGED_ARM` whose commands come 0, 1 or 2 steps late
    (p 0.6 / 0.3 / 0.1; the sim node's log: stamped when meant, logged when taken, several at once). The spring is
    anchored at the command in force, so the lag ``pose - command`` is read about the commands held from when the
    robot took them: the fit finds the arm's stiffness, the load left at the force sensor's noise, and the replay's
    anchor is the command in force at every step. (Read between the commands' header stamps the lag runs up to two
    steps ahead of the arm: k_s 1,840 +- 134 N/m, explaining 0.81 of the load, the arm kept kinematic.)"""
    scene = scene_with(TRUE_PARAMS)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), LAGGED_ARM_SEGMENTS)
    lags = np.random.default_rng(1).choice(3, size=len(targets), p=(0.6, 0.3, 0.1))
    streams = lagged_streams(scene, TRUE_PARAMS, targets, lags, drive=LAGGED_ARM)
    bag = write_bag(tmp_path / "bag", scene, add_noise(streams, seed=7))
    model = _model(bag, dt=0.01)
    fit = fit_drive(model)
    assert fit.compliant and fit.delta_bic > DRIVE_MIN_DELTA_BIC
    assert fit.stiffness == pytest.approx(LAGGED_ARM[0], abs=2 * fit.stiffness_sigma, rel=0.03)
    assert fit.residual_rms < 1.1 * NOISE["force_z"]
    _, in_force = lagging_commander(lags)
    start = np.asarray(scene["effectors"]["ee"]["initial_pose"], dtype=float)
    want = np.array([targets[j] if j >= 0 else start for j in in_force])  # row k + 1: the end of step k
    assert np.max(np.abs(model.commands[1:, :3] - want[:model.step_count, :3])) < 1e-15


def test_a_pose_equal_to_its_command_keeps_the_kinematic_drive(tmp_path):
    fit = fit_drive(_model(write_synthetic(tmp_path / "bag", synthetic_streams(), scene=SCENE)))
    assert not fit.compliant and fit.replay_stiffness == math.inf
    assert "the lag does not vary" in fit.why


def test_a_recording_without_commands_keeps_the_kinematic_drive(tmp_path):
    fit = fit_drive(_model(write_synthetic(tmp_path / "bag", synthetic_streams(), scene=SCENE, skip=("pose_cmd",))))
    assert not fit.compliant and fit.why == "no pose_cmd recorded"


def test_drive_stiffness_is_validated_and_has_no_tangent_controls(tmp_path):
    model = _model(write_synthetic(tmp_path / "bag", synthetic_streams(), scene=SCENE))
    with pytest.raises(CalibrationError, match="drive stiffness must be > 0"):
        model.set_drive_stiffness(0.0)
    model.set_drive_stiffness(3000.0)
    with pytest.raises(CalibrationError, match="no kinematic controls"):
        model.controls_list()
    model.set_drive_stiffness(math.inf)
    assert len(model.controls_list()) == model.step_count


def test_a_replay_through_the_fitted_drive_loads_the_gel_as_the_recording():
    model = _model(reference_bag("nominal_s101"), dt=0.01, t_max=1.6, simulation={"gel_resolution": [5, 4, 2]},
                   arch="cpu")
    recorded = -model.data("wrench")[:, 2]
    pressed = recorded > 2.0  # N: the press and its dwell
    kinematic = -model.predict_raw(model.simulate({}))["wrench"][:, 2]
    fit = fit_drive(model)  # its first 1.6 s hold the press but not the slide: the data choose the drive there too
    assert fit.compliant
    model.set_drive_stiffness(fit.stiffness, fit.damping)
    trace = model.simulate({})
    driven = -model.predict_raw(trace)["wrench"][:, 2]
    assert trace.drive["unconverged"] == 0 and trace.drive["anchored_at_command"]
    assert trace.drive["evaluations"] < 3 * model.step_count
    # the kinematic replay presses harder than the recording; the drive's load is about the recording's
    # (on this coarse gel, 1.6 s of the recording; within 1 % at the scene's resolution, the whole press-slide)
    rec, kin, drv = (float(np.mean(f[pressed])) for f in (recorded, kinematic, driven))
    assert kin > 1.15 * rec
    assert abs(drv - rec) < 0.1 * rec and abs(drv - rec) < 0.5 * abs(kin - rec)
