"""The effector's drive along the sensor normal: fitted in closed form (sysid.drive_calibration) and
replayed through a series spring anchored at the command (sysid.replay_drive).

The reference recordings are made by an arm that is a 3000 N/m Cartesian impedance (their README):
the fit must find that stiffness, and a replay through it must load the gel as the recording does.
A recording whose pose is its command (this simulator's own, kinematic) keeps the kinematic replay.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from sim_core.errors import CalibrationError
from sysid.drive_calibration import fit_drive
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel
from tests.sysid.conftest import SCENE, reference_bag, synthetic_streams, write_synthetic

REFERENCE_IMPEDANCE = 3000.0  # N/m, the reference world's arm (shared/data/reference_bags/README.md)


def _model(bag, **kwargs) -> ObservationModel:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObservationModel(load_evidence(bag), **kwargs)


def test_the_reference_arm_is_fitted_as_its_documented_impedance():
    fit = fit_drive(_model(reference_bag("nominal_s101")))
    assert fit.compliant and fit.why == ""
    assert fit.stiffness == pytest.approx(REFERENCE_IMPEDANCE, rel=0.03)
    assert fit.stiffness_sigma < 0.01 * fit.stiffness
    assert fit.explained > 0.95
    assert fit.replay_stiffness == fit.stiffness


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
    model.set_drive_stiffness(fit_drive(model).replay_stiffness)
    trace = model.simulate({})
    driven = -model.predict_raw(trace)["wrench"][:, 2]
    assert trace.drive["unconverged"] == 0 and trace.drive["anchored_at_command"]
    assert trace.drive["evaluations"] < 3 * model.step_count
    # the kinematic replay presses harder than the recording; the drive's load is about the recording's
    # (on this coarse gel, 1.6 s of the recording; within 1 % at the scene's resolution, the whole press-slide)
    rec, kin, drv = (float(np.mean(f[pressed])) for f in (recorded, kinematic, driven))
    assert kin > 1.15 * rec
    assert abs(drv - rec) < 0.1 * rec and abs(drv - rec) < 0.5 * abs(kin - rec)
