"""The semi-synthetic validation generator (:mod:`benchmarks.synthetic_effects`) applies the effect it
says: a delay of whole samples, a radial pattern about the principal point, the stated bias values,
a first-order creep that keeps the recorded noise; and writes bags of the same contract."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml

from sysid.bagio import open_bag
from sysid.noise import estimate_noise
from benchmarks.synthetic_effects import (Item, apply_effect, creep, delayed, force_bias, force_bias_params, make_set,
                                          radial_distortion, write_like)
from tests.sysid.conftest import SCENE, synthetic_streams, write_synthetic

CAMERA = {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0}


@pytest.fixture
def bag(tmp_path):
    return write_synthetic(tmp_path / "src", synthetic_streams(n=60), scene=copy.deepcopy(SCENE))


def test_delay_is_a_shift_of_whole_samples_at_multiples_of_the_period():
    t_ns = np.arange(50, dtype=np.int64) * 10_000_000 + 7
    y = np.random.default_rng(0).normal(size=(50, 4, 2))
    out = delayed(t_ns, y, 0.03)
    np.testing.assert_allclose(out[3:], y[:-3], atol=1e-12)
    np.testing.assert_allclose(out[:3], np.broadcast_to(y[0], (3, 4, 2)))
    # half a period: the mean of the two neighbours
    np.testing.assert_allclose(delayed(t_ns, y, 0.005)[1:], 0.5 * (y[1:] + y[:-1]), atol=1e-12)
    with pytest.raises(ValueError, match="latency"):
        delayed(t_ns, y, -0.01)


def test_radial_distortion_moves_pixels_along_the_radius_by_k1_r_cubed():
    rng = np.random.default_rng(1)
    uv = np.stack([rng.uniform(60, 260, 200), rng.uniform(40, 200, 200)], axis=-1)
    k1 = -0.08
    out = radial_distortion(uv, CAMERA, k1)
    d = out - uv
    rel = (uv - [160.0, 120.0]) / 300.0
    r2 = np.sum(rel ** 2, axis=-1)
    # along the radius (cross product zero), of length f r k1 r^2, and toward the centre for k1 < 0
    np.testing.assert_allclose(d[:, 0] * rel[:, 1] - d[:, 1] * rel[:, 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 300.0 * np.sqrt(r2) * abs(k1) * r2, rtol=1e-9, atol=1e-12)
    assert np.all(np.sum(d * rel, axis=-1) <= 0.0)
    np.testing.assert_allclose(radial_distortion([[160.0, 120.0]], CAMERA, k1), [[160.0, 120.0]])
    np.testing.assert_allclose(radial_distortion(uv, CAMERA, 0.0), uv)


def test_force_bias_has_the_stated_offset_drift_and_wobble():
    sigma = np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4])
    p = force_bias_params(3.0, sigma, np.random.default_rng(2))
    off = np.abs(np.array(p["offset"])) / sigma
    assert np.all((off >= 1.5 - 1e-9) & (off <= 3.0 + 1e-9))
    assert np.all(np.abs(np.array(p["drift_per_s"])) / sigma <= 1.5 + 1e-9)
    t = np.array([0.0, p["wobble_period_s"]])
    b = force_bias(t, p)
    wob = np.array(p["wobble_amp"]) * np.sin(np.array(p["wobble_phase"]))
    np.testing.assert_allclose(b[0], np.array(p["offset"]) + wob, rtol=1e-12)
    # one wobble period later only the drift has changed it
    np.testing.assert_allclose(b[1] - b[0], np.array(p["drift_per_s"]) * p["wobble_period_s"], rtol=1e-9, atol=1e-15)
    with pytest.raises(ValueError, match="6 values"):
        force_bias(t, dict(p, offset=[0.0, 1.0]))


def test_creep_lags_a_ramp_by_tau_and_keeps_the_noise():
    t_ns = np.arange(600, dtype=np.int64) * 5_000_000
    t = t_ns * 1e-9
    clean = np.clip((t - 0.5) / 1.0, 0.0, 1.0)[:, None] * 10.0          # ramp 10 / s from 0.5 s to 1.5 s, hold
    noise = np.random.default_rng(3).normal(scale=0.2, size=clean.shape)
    tau = 0.1
    lag = (clean - creep(t_ns, clean, tau, 1.0))[:, 0]
    # on the ramp, after a few tau, a first-order low-pass lags by rate * tau = 1.0
    on_ramp = (t > 1.0) & (t < 1.5)
    np.testing.assert_allclose(lag[on_ramp], 1.0, rtol=0.01)
    # in the hold it relaxes as exp(-(t - 1.5) / tau)
    hold = (t > 1.55) & (t < 2.0)
    np.testing.assert_allclose(lag[hold], np.exp(-(t[hold] - 1.5) / tau), atol=0.01)
    # half the response creeping: half the lag
    np.testing.assert_allclose((clean - creep(t_ns, clean, tau, 0.5))[:, 0], 0.5 * lag, atol=1e-12)
    # the recorded noise passes: the increment is computed on the smoothed recording, so it carries
    # under half a sigma of smoothed noise and the stream's noise level stays within 15 %
    noisy = creep(t_ns, clean + noise, tau, 1.0)
    extra = noisy - noise - creep(t_ns, clean, tau, 1.0)
    assert np.std(extra) < 0.5 * 0.2
    assert estimate_noise(t_ns, noisy)[0] == pytest.approx(estimate_noise(t_ns, clean + noise)[0], rel=0.15)
    with pytest.raises(ValueError, match="fraction"):
        creep(t_ns, clean, tau, 1.5)


def test_effects_written_as_bags_read_back_as_applied(bag, tmp_path):
    c = open_bag(bag)
    m0, w0 = c.series["markers"].values, c.series["wrench"].values
    lat = apply_effect(c, "latency", {"latency_s": 0.02})
    write_like(c, lat.values, tmp_path / "lat")
    r = open_bag(tmp_path / "lat")
    assert set(r.series) == set(c.series) and r.scene is not None
    np.testing.assert_array_equal(r.series["wrench"].t_ns, c.series["wrench"].t_ns)
    np.testing.assert_allclose(r.series["wrench"].values[2:], w0[:-2], rtol=1e-12)
    np.testing.assert_allclose(r.series["markers"].values[2:], m0[:-2], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(r.series["pose"].values, c.series["pose"].values)
    np.testing.assert_array_equal(r.series["sheet_points"].values, c.series["sheet_points"].values)

    lens = apply_effect(c, "lens", {"k1": 0.1})
    write_like(c, lens.values, tmp_path / "lens")
    r = open_bag(tmp_path / "lens")
    uv0 = np.stack([c.series["markers"].field("u"), c.series["markers"].field("v")], -1)
    uv1 = np.stack([r.series["markers"].field("u"), r.series["markers"].field("v")], -1)
    np.testing.assert_allclose(uv1, radial_distortion(uv0, CAMERA, 0.1), atol=1e-3)  # float32 pixels
    np.testing.assert_array_equal(r.series["markers"].field("z"), c.series["markers"].field("z"))
    assert lens.visibility["markers_uv"] > 0.0 and lens.visibility["wrench"] == 0.0

    bias = apply_effect(c, "force_bias", {"scale_sigma": 3.0}, np.random.default_rng(0))
    t = (c.series["wrench"].t_ns - c.start_ns) * 1e-9
    np.testing.assert_allclose(bias.values["wrench"] - w0, force_bias(t, bias.params), atol=1e-12)
    np.testing.assert_array_equal(bias.values["markers"], m0)

    with pytest.raises(ValueError, match="unknown effect"):
        apply_effect(c, "wobble")
    with pytest.raises(ValueError, match="tau_s"):
        apply_effect(c, "gel_creep", {"fraction": 1.0})


def test_make_set_writes_bags_and_reference_style_labels(bag, tmp_path):
    src = bag.parent
    plan = (Item("lat_src", "src", "latency", {"latency_s": 0.01}), Item("ctl_src", "src", "none", {}))
    labels = make_set(src, tmp_path / "set", plan)
    doc = yaml.safe_load((tmp_path / "set" / "labels.yaml").read_text())
    assert doc == labels
    assert doc["lat_src"]["variant"] == "latency" and doc["lat_src"]["magnitude"] == {"latency_s": 0.01}
    assert doc["ctl_src"]["variant"] == "nominal" and doc["ctl_src"]["magnitude"] is None
    ctl = open_bag(tmp_path / "set" / "ctl_src")
    for role, s in open_bag(bag).series.items():
        np.testing.assert_array_equal(ctl.series[role].values, s.values)


def test_make_set_reads_each_source_from_the_first_directory_that_holds_it(bag, tmp_path):
    src = bag.parent
    other = tmp_path / "other"
    other.mkdir()
    (other / "labels.yaml").write_text(yaml.safe_dump({"src": {"variant": "plastic", "motion": {"kind": "lift_fold"}}}))
    plan = (Item("ctl_src", "src", "none", {}),)
    # the source is only in the second directory: read from there, without the first's labels
    labels = make_set([other, src], tmp_path / "set", plan)
    assert labels["ctl_src"]["source_variant"] is None
    with pytest.raises(FileNotFoundError, match="missing_s1 in none of"):
        make_set([other, src], tmp_path / "set2", (Item("x", "missing_s1", "none", {}),))
