"""Observation-level candidate signatures vs finite differences; latency recovery; the contract check."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest

from sim_core.errors import CalibrationError
from sim_core.sensors.camera import PinholeCamera
from sysid.diagnose.candidates import (DiagnosisContext, ForceBiasCandidate, LatencyCandidate,
                                       LensDistortionCandidate)
from sysid.diagnose.locate import marker_attribution, windows_from_energy, xcorr_lag
from sysid.diagnose.schema import validate_report

CAMERA = {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240, "distance": 0.025}
DT_NS = 5_000_000


def _signal(t):
    """Smooth marker motion (k = 4 markers, m) and wrench (N)."""
    base = np.array([[-0.004, -0.002], [0.004, -0.002], [-0.004, 0.003], [0.006, 0.004]])
    xy = base[None] + 0.001 * np.sin(2 * np.pi * 1.3 * t)[:, None, None]
    z = -0.0008 * (1 - np.cos(2 * np.pi * 0.7 * t))[:, None] * np.ones((1, 4))
    xyz = np.concatenate([xy, z[..., None]], axis=2)
    wrench = np.stack([np.sin(2 * np.pi * f * t) for f in (0.5, 0.8, 1.1, 1.4, 1.7, 2.0)], axis=1)
    return xyz, wrench


def make_ctx(n_steps=400, data=None, tau=0.0):
    """A context on a fake observation model: per-step trace at 5 ms, stamps at 10 ms (markers) / 5 ms (wrench)."""
    steps = np.arange(n_steps + 1, dtype=np.int64) * DT_NS
    ts = steps * 1e-9
    cam = PinholeCamera.from_dict(CAMERA)
    xyz, wrench = _signal(ts)
    uv = np.stack([cam.project(p) for p in xyz])
    trace = SimpleNamespace(markers_xyz=xyz, markers_uv=uv, wrench=wrench,
                            channel=lambda name: {"markers_xyz": xyz, "markers_uv": uv, "wrench": wrench}[name])
    t_ns = {"markers_xyz": steps[::2][2:-2], "markers_uv": steps[::2][2:-2], "wrench": steps[4:-4]}
    idx = {"markers_xyz": np.arange(0, n_steps + 1, 2)[2:-2], "markers_uv": np.arange(0, n_steps + 1, 2)[2:-2],
           "wrench": np.arange(4, n_steps - 3)}
    pred = {ch: trace.channel(ch)[idx[ch]] for ch in t_ns}
    evidence = SimpleNamespace(t_ns=t_ns, channels_present=tuple(t_ns))
    model = SimpleNamespace(step_times_ns=steps, evidence=evidence, scene={"sensors": {"tactile": {"camera": CAMERA}}},
                            sensor="tactile", data=lambda ch: data[ch] if data else pred[ch],
                            sigma={"markers_xyz": np.full(3, 15e-6), "markers_uv": np.full(2, 0.15),
                                   "wrench": np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4])},
                            residual_weight_root=lambda ch: 1.0)
    return DiagnosisContext(model, {}, trace, pred, ("markers_xyz", "markers_uv", "wrench"))


def test_latency_signature_is_the_derivative_of_a_time_shift():
    ctx = make_ctx()
    sig = LatencyCandidate().signature(ctx)
    h = 1e-4
    for ch in ("markers_xyz", "wrench"):
        fd = (ctx.shifted(ch, h) - ctx.shifted(ch, -h)) / (2 * h)
        J = sig[ch][..., 0]
        scale = np.max(np.abs(J))
        assert np.max(np.abs(J - fd)) < 0.02 * scale, ch


def test_lens_distortion_signature_matches_finite_differences_of_k1():
    ctx = make_ctx()
    J = LensDistortionCandidate().signature(ctx)["markers_uv"][..., 0]
    h = 1e-3
    xyz = ctx.prediction["markers_xyz"]
    plus = np.stack([PinholeCamera.from_dict({**CAMERA, "k1": h}).project(p) for p in xyz])
    minus = np.stack([PinholeCamera.from_dict({**CAMERA, "k1": -h}).project(p) for p in xyz])
    fd = (plus - minus) / (2 * h)
    assert np.allclose(J, fd, rtol=1e-6, atol=1e-9)
    # grows like r^3 from the optical centre: the outer marker moves most
    r = np.linalg.norm(xyz[0, :, :2], axis=1)
    assert np.argmax(np.linalg.norm(J[0], axis=1)) == np.argmax(r)


def test_force_bias_signature_and_exact_refit():
    ctx = make_ctx()
    J = ForceBiasCandidate().signature(ctx)["wrench"]
    assert J.shape[1:] == (6, 12)
    beta = np.arange(12) * 0.01
    data = {**ctx.prediction, "wrench": ctx.prediction["wrench"] + J @ beta}
    ctx2 = make_ctx(data=data)
    rf = ForceBiasCandidate().refit(ctx2, ["wrench"], objective=None)
    assert np.allclose(rf.beta, beta, atol=1e-10)
    assert rf.params["bias_fz"] == pytest.approx(beta[4])


def test_force_bias_refit_keeps_only_the_axes_that_carry_a_bias():
    rng = np.random.default_rng(1)
    ctx = make_ctx()
    sigma = np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4])
    noisy = ctx.prediction["wrench"] + rng.normal(size=ctx.prediction["wrench"].shape) * sigma
    noisy[:, 2] += 0.5  # a 0.5 N offset on fz only (2.5 sigma)
    rf = ForceBiasCandidate().refit(make_ctx(data={**ctx.prediction, "wrench": noisy}), ["wrench"], objective=None)
    assert rf.beta.shape == (2,)  # offset + drift of fz: 2 parameters for the BIC, not 12
    assert rf.params["bias_fz"] == pytest.approx(0.5, abs=0.05)
    assert all(rf.params[f"bias_{a}"] == 0.0 for a in ("fx", "fy", "tx", "ty", "tz"))
    shift = rf.prediction["wrench"] - ctx.prediction["wrench"]
    assert np.all(shift[:, [0, 1, 3, 4, 5]] == 0.0)


def test_latency_of_40ms_recovered_by_cross_correlation_and_refit():
    rng = np.random.default_rng(0)
    ctx = make_ctx()
    tau, period = 0.040, 0.005
    t = ctx.stamps_s("wrench")
    xyz, wrench = _signal(t - tau)
    noisy = wrench + rng.normal(scale=[0.1, 0.1, 0.2, 0.1, 0.1, 0.1], size=wrench.shape)
    lag = xcorr_lag(ctx.prediction["wrench"], noisy, period, 0.1)
    assert abs(lag - tau) < period
    data = {**ctx.prediction, "wrench": noisy}
    ctx2 = make_ctx(data=data)

    def objective(pred):
        return float(np.sum(((noisy - pred["wrench"]) / ctx2.model.sigma["wrench"]) ** 2))

    rf = LatencyCandidate().refit(ctx2, ["wrench"], objective)
    assert abs(rf.params["latency_s"] - tau) < 0.002
    # the explained energy locates the mismatch where the signal moves, and its windows are ordered
    r = (noisy - ctx.prediction["wrench"]) / ctx2.model.sigma["wrench"]
    d = (rf.prediction["wrench"] - ctx.prediction["wrench"]) / ctx2.model.sigma["wrench"]
    from sysid.diagnose.locate import explained_energy

    wins = windows_from_energy(t, explained_energy(r, d))
    assert wins and all(a <= b for a, b in wins)


def test_xcorr_lag_errors():
    with pytest.raises(ValueError, match="differ in shape"):
        xcorr_lag(np.zeros(10), np.zeros(11), 0.01, 0.02)
    with pytest.raises(ValueError, match="fewer than 3"):
        xcorr_lag(np.zeros(10), np.zeros(10), 0.01, 0.09)


def test_marker_attribution_names_the_markers_that_carry_the_effect():
    rng = np.random.default_rng(1)
    r = rng.normal(size=(50, 20, 3))
    d = np.zeros_like(r)
    d[:, [3, 4, 12], :] = 2.0
    r = r + d
    assert marker_attribution(r, d) == [3, 4, 12]


VALID = {
    "schema_version": 2,
    "bag": "path",
    "baseline": {"params": {"bending_stiffness": 0.008}, "rms": {"markers_px": 0.9, "wrench_N": 0.05}},
    "mismatch": {"detected": True, "windows_s": [[1.2, 2.8]], "channels": ["tactile/markers"], "markers": [3, 4, 12]},
    "candidates": [{"effect": "latency", "statistic": 412.0, "p_value": 1e-12}],
    "explained_by": ["latency"],
    "refit": {"params": {"latency_s": 0.041}, "rms": {"markers_px": 0.21},
              "heldout_rms_before": 0.95, "heldout_rms_after": 0.24},
    "extra": {"pipeline": {"stage": "score", "drive": {"decision": "kinematic"}, "why": "the pose is its command",
                           "not_applied": []}},
}


def test_contract_example_validates_and_violations_are_named():
    validate_report(VALID)
    validate_report({**VALID, "extra": {**VALID["extra"], "anything": 1}})
    cases = [
        (lambda d: d.pop("refit"), "missing top-level key 'refit'"),
        (lambda d: d.update(score=1), "unknown top-level key 'score'"),
        (lambda d: d["mismatch"].pop("markers"), r"missing key 'mismatch.markers'"),
        (lambda d: d["candidates"][0].update(effect="gravity"), "not in the vocabulary"),
        (lambda d: d["candidates"][0].update(p_value=2.0), r"p_value' must be in \[0, 1\]"),
        (lambda d: d.update(explained_by=["unexplained", "latency"]), "neither an effect"),
        (lambda d: d["mismatch"].update(windows_s=[[2.0, 1.0]]), "start <= end"),
        (lambda d: (d["mismatch"].update(detected=False)), "detected' is false"),
        (lambda d: d.update(explained_by=[]), "use \\[\"unexplained\"\\]"),
        (lambda d: d.update(schema_version=1), "'schema_version' is 1; this version of thinshell reads 2"),
        (lambda d: d.pop("extra"), "missing object 'extra.pipeline'"),
        (lambda d: d["extra"]["pipeline"].pop("why"), "missing key 'extra.pipeline.why'"),
        (lambda d: d["extra"]["pipeline"].update(stage="engine"), "is none of score, signatures"),
    ]
    for mutate, msg in cases:
        d = copy.deepcopy(VALID)
        mutate(d)
        with pytest.raises(CalibrationError, match=msg):
            validate_report(d)


def test_cli_refuses_a_non_empty_output_directory(tmp_path, capsys):
    from sysid.diagnose_cli import diagnose_main

    out = tmp_path / "report"
    out.mkdir()
    (out / "old.txt").write_text("x")
    assert diagnose_main([str(tmp_path / "bag"), "--out", str(out)]) == 2
    assert "not empty" in capsys.readouterr().err


def test_force_bias_refit_applies_to_a_heldout_recording_when_some_axes_are_dropped():
    """The refit keeps only the axes its data support (beta holds those); applied to another
    recording the kept axes' offset and drift are added and the dropped axes are left unchanged."""
    from types import SimpleNamespace

    from sysid.diagnose.candidates import ForceBiasCandidate, Refit, apply_observation_refit

    t = np.linspace(0.0, 1.0, 11)
    params = {f"{k}_{a}": 0.0 for k in ("bias", "drift") for a in ("fx", "fy", "fz", "tx", "ty", "tz")}
    params.update({"bias_fz": 0.3, "drift_fz": 0.1})
    rf = Refit(np.array([0.3, 0.1]), params, {"wrench": np.zeros((11, 6))})
    hctx = SimpleNamespace(channels=("wrench",), stamps_s=lambda ch: t)
    pred = {"wrench": np.zeros((11, 6))}
    apply_observation_refit(hctx, rf, pred)
    B = ForceBiasCandidate.basis(t)
    assert np.allclose(pred["wrench"][:, 2], 0.3 * B[:, 0] + 0.1 * B[:, 1])
    assert np.allclose(np.delete(pred["wrench"], 2, axis=1), 0.0)


def test_adhesion_probe_scale_is_the_sheet_weight_per_face_vertex():
    """``adhesion_weight_scale``: g m_sheet / n_face (the per-pair strength at which the face's bonds
    together bear the card); nan without gravity, sheet or contact face. On the benchmark card
    (0.315 g, 20 face vertices) it is 0.155 mN, so the probe (4 weights) is 0.62 mN per pair."""
    from types import SimpleNamespace

    from sysid.diagnose.candidates import ADHESION_PROBE_WEIGHTS, adhesion_weight_scale

    masses = np.array([1e-4, 2e-4, 3e-4, 4e-4, 5.0, 5.0, 5.0, 5.0])
    model = SimpleNamespace(vertex_mass=lambda: masses, gravity=np.array([0.0, 0.0, -9.81]),
                            bodies={"sheet": SimpleNamespace(kind="sheet", vertices=np.arange(4)),
                                    "gel": SimpleNamespace(kind="solid", vertices=np.arange(4, 8))},
                            sensors={"tactile": SimpleNamespace(contact_triangles=np.array([[4, 5, 6], [5, 6, 7]]))})
    assert adhesion_weight_scale(model) == pytest.approx(9.81 * 1e-3 / 4)
    model.gravity = np.zeros(3)
    assert np.isnan(adhesion_weight_scale(model))
    model.gravity = np.array([0.0, 0.0, -9.81])
    model.sensors = {}
    assert np.isnan(adhesion_weight_scale(model))

    from sim_core.scenes import load_scene
    from benchmarks.diagnose_bench import load_bench_scene

    w = adhesion_weight_scale(load_scene(load_bench_scene()))
    assert w == pytest.approx(9.81 * 700.0 * 0.0003 * 0.05 * 0.03 / 20, rel=1e-6)
    assert ADHESION_PROBE_WEIGHTS * w < 0.05 / 50  # far below the old fixed probe
