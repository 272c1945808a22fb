"""Work a default ``thinshell sysid`` no longer does twice (issue 49's time goal; docs/benchmarks_log.md, session 55,
s55-49time), each reuse checked against the work it replaces:

- the calibration's secant step made with the fit's first tangents (:class:`sysid.jacobians.TangentReplay`): the
  fit's first evaluation takes it, and its residual and Jacobian equal a fresh joint replay's;
- a drive step's support product skips the static terms whose blocks touch no driven vertex
  (:class:`sim_core.adjoint.SupportTerms`): the tangents are bit for bit those that evaluate every term.

On this simulator's own press-slide through a compliant arm (the card scene of ``tests/sysid/simbag.py``, 45 steps).
"""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest

import sysid.jacobians as jacobians
from sim_core.adjoint import SupportTerms
from sim_core.energies.kirchhoff_bending.reference import KirchhoffBending
from sim_core.energies.membrane.reference import StVKMembrane
from sim_core.energies.neohookean.reference import StableNeoHookean
from sysid.evidence import load_evidence
from sysid.fit import DEFAULT_NUISANCE, FitProblem, SensitivityJacobian, joint_tangent_names, parameter_spec
from sysid.fit_recording import FitOptions, fit_recording
from sysid.jacobians import TangentReplay
from sysid.observation import ObservationModel
from sysid.replay_drive import drive_sensitivities
from tests.sysid.simbag import TRUE_PARAMS, add_noise, scene_with, simulate_streams, targets_from_segments, write_bag
from tests.sysid.test_sysid_drive import ARM, SEGMENTS, arm_bag  # noqa: F401 (the arm's recording, a fixture)

STICK_SPEED = 0.002
"""The stick speed ``contact.eps_v`` of ``sticky_bag``'s recording, m/s."""

FITTED = ("sheet.bending_stiffness", "gel.youngs_modulus", "friction.gel_sheet", "contact.eps_v")


@pytest.fixture(scope="module")
def sticky_bag(tmp_path_factory):
    """As ``arm_bag``, the recording made with a stick speed of 2 mm/s, its ``scene.yaml`` stating the default
    10 mm/s: the calibration's secant stage moves it (and the fit starts from its step)."""
    scene = scene_with(TRUE_PARAMS)
    recorded = copy.deepcopy(scene)
    recorded.setdefault("simulation", {})["contact_eps_v"] = STICK_SPEED
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), SEGMENTS)
    streams = add_noise(simulate_streams(recorded, TRUE_PARAMS, targets, drive=ARM), seed=11)
    return write_bag(tmp_path_factory.mktemp("sticky") / "bag", scene, streams)


def _model(bag) -> ObservationModel:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(bag), dt=0.01)
    model.set_drive_stiffness(*ARM)
    return model


def _problem(model, made=None) -> FitProblem:
    nuisance = {n: p for n, p in DEFAULT_NUISANCE.items() if n not in FITTED}
    extra = [parameter_spec(n, model.parameter_value(n)) for n in nuisance]
    specs = [parameter_spec(n, model.parameter_value(n)) for n in FITTED]
    return FitProblem(model, specs, joint=SensitivityJacobian().joint, extra=extra, made=made)


def test_the_fits_first_evaluation_takes_the_replay_made_before_it_and_equals_a_fresh_joint_replay(arm_bag):
    """The replay handed on gives the residual, Jacobian and nuisance columns of a fresh joint replay at the same
    values to 1e-9 (noise units; measured: bit for bit), its plain trace is a plain replay's, and a replay made at
    other values, or with other columns, is not taken."""
    model = _model(arm_bag)
    nuisance = {n: p for n, p in DEFAULT_NUISANCE.items() if n not in FITTED}
    names = joint_tangent_names(FITTED, nuisance, robust="hac", warm_start=False)
    assert names == (*FITTED, *nuisance)
    start = {n: model.parameter_value(n) for n in FITTED}
    made, trace = TangentReplay.make(model, {"contact.eps_v": start["contact.eps_v"]}, names)
    plain = model.simulate({"contact.eps_v": start["contact.eps_v"]})
    for ch, raw in model.predict_raw(plain).items():
        assert np.max(np.abs(model.predict_raw(trace)[ch] - raw)) <= 1e-12 * max(1.0, np.max(np.abs(raw))), ch

    fresh = _problem(model)
    u0 = np.zeros(len(FITTED))
    r_fresh = fresh.residual(u0, phase="initial")
    J_fresh, extra_fresh = fresh.cached_jacobian(u0), fresh.extra_jacobian(u0)
    taken = _problem(model, made=made)
    r = taken.residual(u0, phase="initial")
    assert taken.made is None  # taken, not replayed
    assert np.max(np.abs(r - r_fresh)) <= 1e-9
    assert np.max(np.abs(taken.cached_jacobian(u0) - J_fresh)) <= 1e-9 * np.max(np.abs(J_fresh))
    assert np.max(np.abs(taken.extra_jacobian(u0) - extra_fresh)) <= 1e-9 * np.max(np.abs(extra_fresh))
    assert np.linalg.norm(J_fresh, axis=0).min() > 0.5  # every column seen (bending 0.97): not a comparison of zeros

    other = _problem(model, made=made)
    other.residual(np.array([0.0, 0.1, 0.0, 0.0]), phase="initial")  # another modulus: replayed
    assert other.made is made
    assert not made.matches(model, start, names[:-1])  # other columns
    model.set_drive_stiffness(ARM[0] * 1.5, ARM[1])
    assert not made.matches(model, start, names)  # another drive


def test_sysid_hands_the_calibrations_secant_step_to_the_fit(sticky_bag, tmp_path, monkeypatch):
    """``fit_recording`` (``thinshell sysid``'s defaults) makes the calibration's secant step with the fit's
    tangents, and the fit's first evaluation takes it: one rollout with tangents fewer than evaluations with them."""
    rollouts, taken = [], []
    rollout = jacobians.rollout_with_tangents
    matches = TangentReplay.matches

    def counted(model, sim, names):
        rollouts.append(tuple(names))
        return rollout(model, sim, names)

    def checked(self, model, values, names):
        taken.append(matches(self, model, values, names))
        return taken[-1]

    monkeypatch.setattr(jacobians, "rollout_with_tangents", counted)
    monkeypatch.setattr(TangentReplay, "matches", checked)
    out = fit_recording(sticky_bag, tmp_path / "fit", FitOptions(max_nfev=2))
    stage = out.sensor.secant
    assert stage is not None and stage.accepted
    assert "contact.eps_v" in out.result.values
    assert taken == [True]  # the fit's first evaluation, at the stage's values
    fit_joint = sum(1 for e in out.result.history if e.phase in ("initial", "local"))
    assert len(rollouts) == fit_joint  # the secant step's rollout and the fit's later ones: none for its start
    assert out.result.history[0].phase == "initial"


def test_a_drive_steps_support_product_skips_the_terms_away_from_the_drive_bit_for_bit(arm_bag, monkeypatch):
    """The tangents through the drive with :class:`SupportTerms` equal those that evaluate every term's Hessian
    whole bit for bit, while the support products evaluate the card's membrane and Kirchhoff bending (no vertex on the
    pad) only at the steps that confirm their elements (two), and the gel's law on the tets under the pad only
    (``restricted``) from then on."""
    model = _model(arm_bag)
    names = ["gel.youngs_modulus", "friction.gel_sheet"]
    calls = {KirchhoffBending: 0, StVKMembrane: 0}
    for cls in calls:
        original = cls.hessian

        def counting(self, x, projection="clamp", _cls=cls, _original=original):
            calls[_cls] += 1
            return _original(self, x, projection)

        monkeypatch.setattr(cls, "hessian", counting)
    restricted = []
    original_restricted = StableNeoHookean.restricted

    def restricting(self, elements):
        restricted.append((len(elements), len(self.tets)))
        return original_restricted(self, elements)

    monkeypatch.setattr(StableNeoHookean, "restricted", restricting)
    _, dX, dF, dQ = drive_sensitivities(model, model.prepare({}), names)
    kept = dict(calls)
    assert len(restricted) == model.step_count - SupportTerms.CONFIRMING_STEPS  # the gel's law, once a product
    assert all(0 < j <= k for j, k in restricted), restricted[:3]  # the tets under the pad (this small gel: each one)
    monkeypatch.setattr(SupportTerms, "touching", lambda self, p, support: None)  # no term trusted: each one whole
    _, dX_all, dF_all, dQ_all = drive_sensitivities(model, model.prepare({}), names)
    assert len(restricted) == model.step_count - SupportTerms.CONFIRMING_STEPS
    for cls, n in kept.items():  # the same forward steps; the support products skipped the card's terms
        assert calls[cls] - 2 * n == model.step_count - SupportTerms.CONFIRMING_STEPS, cls
    assert np.array_equal(dX, dX_all) and np.array_equal(dF, dF_all) and np.array_equal(dQ, dQ_all)
    assert np.abs(dQ).max() > 0.0


def test_the_joint_replays_columns_follow_one_rule():
    """:func:`sysid.fit.joint_tangent_names` is :func:`sysid.jacobians.tangent_columns` of the fit's parameters and
    of the nuisance it hands its joint replays: the sensor offset (a difference parameter) has no tangent column,
    a nuisance parameter fitted is not a nuisance column, a difference parameter among the nuisance drops them all,
    and warm or non-robust fits hand none."""
    offset = "sensor.normal_offset"
    nuisance = dict(DEFAULT_NUISANCE)
    fitted = (FITTED[1], offset, "contact.stiffness")
    names = joint_tangent_names(fitted, nuisance, robust="hac", warm_start=False)
    assert names == (FITTED[1], "contact.stiffness", "friction.sheet_table", "gel.poisson_ratio")
    assert names == sum(jacobians.tangent_columns(fitted, ["friction.sheet_table", "gel.poisson_ratio"]), ())
    assert joint_tangent_names(fitted[:1], {**nuisance, offset: 1e-3}, robust="hac", warm_start=False) == names[:1]
    assert joint_tangent_names(fitted, nuisance, robust="hac", warm_start=True) == names[:2]
    assert joint_tangent_names(fitted, nuisance, robust=None, warm_start=False) == names[:2]
