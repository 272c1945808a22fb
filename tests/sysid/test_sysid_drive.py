"""``thinshell sysid`` through the effector's series drive (on by default): the Jacobian's tangents are carried
through the spring's compression (sim_core.sensitivity.DriveStep, sysid.replay_drive.drive_sensitivities),
and a recording of this simulator made by an impedance-controlled arm (a concealed compliant drive; the
scene states nothing of it) gives back its materials and its arm.

The recording: the benchmark card (tests/sysid/simbag.py), pressed and slid by a 2,000 N/m arm with a 5 N s/m
damper (the reference engine's arm is 3,000 N/m with about 34 N s/m), noise at the reference bags' levels.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import sysid.replay_drive as replay_drive
from sysid.cli import sysid_main
from sysid.drive_calibration import fit_drive
from sysid.evidence import load_evidence
from sysid.fit import FitProblem, FiniteDifferenceJacobian, SensitivityJacobian, parameter_spec
from sysid.observation import ObservationModel
from tests.sysid.simbag import (PRESS_SLIDE, TRUE_PARAMS, add_noise, scene_with, simulate_streams,
                                targets_from_segments, write_bag)

ARM = (2000.0, 5.0)
"""The concealed arm: stiffness k_s (N/m) and damping (N s/m) along the sensor normal."""

SEGMENTS = (((0.0, 0.0, -0.0025), 8), *PRESS_SLIDE[1:], ((0.0, 0.0, 0.0), 4), ((0.0, 0.0, 0.0025), 8))
"""PRESS_SLIDE's press commanded 2.5 mm down (the arm gives way by 1.5 mm: about 3 N on the gel, 15 noise levels
of the normal force), its slides, a hold and the release: 45 steps of 10 ms."""

FITTED = ("sheet.bending_stiffness", "gel.youngs_modulus", "friction.gel_sheet")


@pytest.fixture(scope="module")
def arm_bag(tmp_path_factory):
    """The card pressed and slid through :data:`ARM`; ``scene.yaml`` states the true materials."""
    scene = scene_with(TRUE_PARAMS)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), SEGMENTS)
    streams = add_noise(simulate_streams(scene, TRUE_PARAMS, targets, drive=ARM), seed=7)
    return write_bag(tmp_path_factory.mktemp("arm") / "bag", scene, streams)


def _model(bag, t_max: float | None = None) -> ObservationModel:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObservationModel(load_evidence(bag), dt=0.01, t_max=t_max)


def test_the_jacobian_through_the_drive_is_the_derivative_of_the_drive_replay(arm_bag, monkeypatch):
    """Analytic Jacobian through the drive against central differences of replays whose drive steps are solved
    jointly with the step (``DRIVE_SOLVE``'s default; a secant replay's to 1e-6 N: a finite-difference column of the
    default 0.5-sigma tolerance measures that tolerance over the step instead). Over the whole recording: at the step
    where contact begins the spring's balance has a kink, and a difference across it is not the one-sided tangent. The wrench column of the gel modulus is the drive's own: a kinematic tangent (compression
    held) is far from it, since the arm, not the gel, sets most of the load."""
    monkeypatch.setattr(replay_drive, "DRIVE_FORCE_TOLERANCE", 5e-6)  # in noise levels of the normal force
    model = _model(arm_bag)
    drive = fit_drive(model)
    assert drive.compliant
    model.set_drive_stiffness(drive.replay_stiffness, drive.replay_damping)
    names = ["gel.youngs_modulus", "friction.gel_sheet"]
    problem = FitProblem(model, [parameter_spec(n, TRUE_PARAMS[n]) for n in names])
    u = np.array([0.2, -0.15])
    J_fd = FiniteDifferenceJacobian(step=1e-3)(problem, u)
    J_s = SensitivityJacobian()(problem, u)
    rows = model.channel_slices()
    for j, name in enumerate(names):
        err = np.linalg.norm(J_s[:, j] - J_fd[:, j]) / np.linalg.norm(J_fd[:, j])
        assert err < 0.05, (name, err)
    wrench = rows["wrench"]
    err = np.linalg.norm(J_s[wrench, 0] - J_fd[wrench, 0]) / np.linalg.norm(J_fd[wrench, 0])
    assert err < 0.1, err
    # the same replay's tangent with the compression held (a kinematic replay of where the pad went)
    advance = replay_drive.TangentPropagation.advance
    monkeypatch.setattr(replay_drive.TangentPropagation, "advance", lambda self, lin, drive=None: advance(self, lin))
    J_held = SensitivityJacobian()(problem, u)
    far = np.linalg.norm(J_held[wrench, 0] - J_fd[wrench, 0]) / np.linalg.norm(J_fd[wrench, 0])
    assert far > 3.0 * max(err, 0.05), far


def test_the_stick_speed_column_through_the_drive_is_the_derivative_of_the_drive_replay(arm_bag, monkeypatch):
    """``contact.eps_v``'s column (the lagged friction's mollifier tangent, carried through the spring's compression
    like the materials') against central differences of replays solved to 1e-8 m/s and 1e-6 N (at the defaults a
    replay is rough in eps_v at the 5-15 % level of its column); measured: relative error 8e-5 at 1 % steps."""
    import functools

    import sysid.observation as observation
    from sim_core.solver import SolverConfig

    monkeypatch.setattr(replay_drive, "DRIVE_FORCE_TOLERANCE", 5e-6)
    monkeypatch.setattr(observation, "SolverConfig", functools.partial(SolverConfig, tol_velocity=1e-8))
    model = _model(arm_bag)
    drive = fit_drive(model)
    model.set_drive_stiffness(drive.replay_stiffness, drive.replay_damping)
    names = ["contact.eps_v", "gel.youngs_modulus"]
    problem = FitProblem(model, [parameter_spec(n, model.parameter_value(n)) for n in names])
    u, h = np.array([-0.6, 0.2]), np.array([1e-2, 0.0])
    J = SensitivityJacobian()(problem, u)
    central = (problem.residual(u + h) - problem.residual(u - h)) / (2.0 * h[0])
    assert np.linalg.norm(central) > 10.0
    for channel, rows in model.channel_slices().items():
        err = np.linalg.norm(J[rows, 0] - central[rows]) / np.linalg.norm(central[rows])
        assert err < 1e-2, (channel, err)


def test_sysid_defaults_find_the_arm_and_recover_the_materials_from_starts_20_percent_off(arm_bag, tmp_path, capsys):
    """Defaults, started 20 % off on all three materials (``scene.yaml`` rewritten): the drive is chosen by
    delta-BIC and its stiffness found within 5 %; the gel-sheet friction comes back within 5 %, the gel modulus
    within 8 % (0.945: the 0.05 % RMS stop ends the fit in a flat valley), and every truth lies inside the
    robust 2-sigma interval. The bending stiffness, which the slide does not load, is held at its start and
    reported not identified. The drive is in fit.json (decision, k_s and damping with sigma) and in the report."""
    off = {name: TRUE_PARAMS[name] * f for name, f in zip(FITTED, (1.2, 0.8, 1.2))}
    bag = tmp_path / "bag"
    bag.mkdir()
    for f in arm_bag.iterdir():
        (bag / f.name).write_bytes(f.read_bytes())
    import yaml

    (bag / "scene.yaml").write_text(yaml.safe_dump(scene_with(off)))
    out = tmp_path / "fit"
    rc = sysid_main([str(bag), "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    doc = json.loads((out / "fit.json").read_text())
    drive = doc["diagnostics"]["drive"]
    assert drive["decision"] == "compliant" and drive["delta_bic"] > drive["min_delta_bic"]
    assert drive["stiffness"] == pytest.approx(ARM[0], rel=0.05) and 0.0 < drive["stiffness_sigma"] < 0.05 * ARM[0]
    assert drive["damping_sigma"] > 0.0 and drive["replay_stiffness"] == drive["stiffness"]
    assert "effector drive: compliant" in (out / "report.md").read_text()
    assert "drive: compliant" in captured.err
    params = doc["fit"]["parameters"]
    for name in FITTED:
        p = params[name]
        assert abs(p["value"] - TRUE_PARAMS[name]) < 2.0 * p["sigma_robust"], (name, p)
        if name == "friction.gel_sheet":
            assert p["value"] == pytest.approx(TRUE_PARAMS[name], rel=0.05), (name, p)
        elif name == "gel.youngs_modulus":
            # 0.945 x the truth in 6 replays (0.967 in 11 with the held column zeroed, session 52's 49fit: cost 4102.66
            # against 4103.40 here, both ended by the 0.05 % RMS stop); the modulus' robust sigma is 0.098 x
            assert p["value"] == pytest.approx(TRUE_PARAMS[name], rel=0.08), (name, p)
    # the bending stiffness: its Jacobian column is about 1/400 of the modulus' here (a 6 mm slide that does not
    # buckle the card), so the recording does not tell it; the fit says so by an interval wider than the value
    assert params["sheet.bending_stiffness"]["sigma_robust"] > 0.5 * TRUE_PARAMS["sheet.bending_stiffness"]
    # ... and names it: not identified (its robust 2-sigma interval reaches zero), with a warning; the others are
    assert params["sheet.bending_stiffness"]["identified"] is False
    # the fit took no step along it (sysid.fit.fit hold_unidentified): it ends at its start, 20 % above the truth,
    # exactly, and says so; without the hold it wandered 0.99-1.34 x the truth in the same fit, and on
    # nominal_s101 a first step of x13.8 decided where it landed
    assert params["sheet.bending_stiffness"]["held"] is True
    assert params["sheet.bending_stiffness"]["value"] == pytest.approx(off["sheet.bending_stiffness"], rel=1e-9)
    assert any(w.startswith("sheet.bending_stiffness was held at its start value") for w in doc["diagnostics"]["warnings"])
    assert all(params[n]["held"] is False for n in FITTED if n != "sheet.bending_stiffness")
    # with the held coordinate's column orthogonal rather than zero (sysid.fit_region.held_jacobian) the trust region's
    # steps are Gauss-Newton's, not the region's boundary: 6 replays (11 with the column zeroed, two trials rejected)
    assert doc["diagnostics"]["sim_runs"] - doc["diagnostics"]["profile_runs"] <= 8, doc["diagnostics"]
    assert any(w.startswith("sheet.bending_stiffness is not identified") for w in doc["diagnostics"]["warnings"])
    assert "NOT IDENTIFIED" in next(l for l in captured.out.splitlines() if "sheet.bending_stiffness:" in l)
    assert all(params[n]["identified"] is True for n in FITTED if n != "sheet.bending_stiffness")
