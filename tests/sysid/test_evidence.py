"""sysid.evidence and sysid.noise: the evidence bundle, noise estimation, resampling."""

from __future__ import annotations

import hashlib
import time

import numpy as np
import pytest

from sim_core.errors import BagReadError, ConfigError
from sysid.bagio import BagWriter
from sysid.evidence import align, common_time_base, load_evidence, resample, resample_pose
from sysid.noise import estimate_noise, noise_config
from tests.sysid.conftest import NS, REFERENCE_BAGS, reference_bag, synthetic_streams, write_synthetic

pytestmark = pytest.mark.filterwarnings("ignore::sysid.bagio.errors.BagWarning")

# Documented 1-sigma noise of the reference bags (shared/data/reference_bags/README.md).
DOCUMENTED_NOISE = {
    "markers_xyz": [15e-6, 15e-6, 20e-6],
    "markers_uv": [0.15, 0.15],
    "wrench": [0.10, 0.10, 0.20, 4e-4, 4e-4, 4e-4],
    "sheet_points": [50e-6, 50e-6, 50e-6],
}


@pytest.mark.parametrize("name", REFERENCE_BAGS)
def test_noise_estimates_recover_the_documented_noise(name):
    ev = load_evidence(reference_bag(name))
    for channel, sigma in DOCUMENTED_NOISE.items():
        ratio = ev.noise[channel] / np.asarray(sigma)
        assert np.all((ratio > 1 / 1.25) & (ratio < 1.25)), f"{channel}: estimated/documented = {ratio}"
    ratio = ev.noise["pose"][:3] / 5e-6  # ee position noise 5 um
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio


def test_reference_evidence_contents_and_provenance():
    path = reference_bag("nominal_s101")
    t0 = time.perf_counter()
    ev = load_evidence(path)
    elapsed = time.perf_counter() - t0
    print(f"load_evidence(nominal_s101): {elapsed:.3f} s")
    assert elapsed < 5.0
    assert ev.channels_present == ("pose", "pose_cmd", "markers_xyz", "markers_uv", "wrench", "sheet_points")
    assert ev.channels_missing == {"image": f"topic {NS}/tactile/image not in the recording"}
    assert ev.pose.shape == (722, 7) and ev.wrench.shape == (722, 6)
    assert ev.markers_xyz.shape == (361, 63, 3) and ev.markers_uv.shape == (361, 63, 2)
    assert ev.sheet_points.shape == (361, 273, 3) and ev.image is None
    assert ev.t_ns["markers_xyz"] is ev.t_ns["markers_uv"]
    assert ev.t_ns["pose"].dtype == np.int64 and ev.t_ns["pose"][1] == 5_000_000
    assert ev.source.sha256 == hashlib.sha256((path / "nominal_s101.mcap").read_bytes()).hexdigest()
    assert ev.source.topics["wrench"] == f"{NS}/tactile/wrench"
    assert ev.scene.sheet.resolution == (21, 13) and ev.source.scene_path == path / "scene.yaml"
    assert (ev.start_ns, ev.end_ns) == (0, 3_605_000_000)
    with pytest.raises(ValueError, match="read-only"):
        ev.wrench[0, 0] = 1.0
    # Pressing gives F_z < 0 on the gel (INTERFACES.md); markers move to z < 0 while pressed.
    press = np.argmin(ev.wrench[:, 2])
    assert ev.wrench[press, 2] < -3.0
    assert ev.summary()["samples"]["markers_xyz"] == 361


def test_missing_markers_channel_is_named(tmp_path, scene_dict):
    write_synthetic(tmp_path / "b", synthetic_streams(n=8), scene=scene_dict, skip=("markers",))
    ev = load_evidence(tmp_path / "b")
    assert "markers_xyz" not in ev.channels_present and ev.markers_xyz is None
    assert ev.channels_missing["markers_xyz"] == f"topic {NS}/tactile/markers not in the recording"
    assert any(f"{NS}/tactile/markers" in n for n in ev.notes)
    with pytest.raises(KeyError, match="no markers_uv channel \\(topic /thinshell/tactile/markers not in"):
        ev.values("markers_uv")
    assert "markers_xyz" not in ev.noise and ev.noise["wrench"].shape == (6,)


def test_image_channel_is_carried_without_a_noise_entry(tmp_path):
    frames = np.random.default_rng(0).integers(0, 255, size=(3, 24, 32), dtype=np.uint8)
    with BagWriter(tmp_path / "b") as bag:
        for i, frame in enumerate(frames):
            bag.write_image(f"{NS}/tactile/image", 10 * i, frame, "tactile")
            bag.write_wrench(f"{NS}/tactile/wrench", 10 * i, np.full(6, float(i)), "tactile")
    ev = load_evidence(tmp_path / "b")
    assert "image" in ev.channels_present and ev.t_ns["image"].tolist() == [0, 10, 20]
    np.testing.assert_array_equal(ev.image, frames)
    assert "image" not in ev.noise
    skipped = load_evidence(tmp_path / "b", include_image=False)
    assert skipped.image is None and skipped.channels_missing["image"] == "not decoded (include_image=False)"


def test_bag_without_any_output_topic(tmp_path):
    with BagWriter(tmp_path / "b") as bag:
        bag.write_clock(1)
    with pytest.raises(BagReadError, match="nothing to identify from"):
        load_evidence(tmp_path / "b")


def test_point_counts_must_match_the_scene(tmp_path, scene_dict):
    write_synthetic(tmp_path / "b", synthetic_streams(n=4), scene=scene_dict)
    assert load_evidence(tmp_path / "b").markers_xyz.shape == (4, 6, 3)
    scene_dict["sensors"]["tactile"]["marker_grid"] = [4, 2]
    other = tmp_path / "other_scene.yaml"
    import yaml

    other.write_text(yaml.safe_dump(scene_dict))
    with pytest.raises(BagReadError, match=f"topic {NS}/tactile/markers has 6 points but sensor tactile of {other} "
                                           "has a 4x2 marker grid"):
        load_evidence(tmp_path / "b", scene_path=other)


def test_crop_keeps_a_window():
    ev = load_evidence(reference_bag("nominal_s101"))
    part = ev.crop(1_000_000_000, 2_000_000_000)
    assert part.t_ns["pose"][0] == 1_000_000_000 and part.t_ns["pose"][-1] == 2_000_000_000
    assert part.pose.shape == (201, 7) and part.markers_uv.shape == (101, 63, 2)
    np.testing.assert_array_equal(part.wrench, ev.wrench[200:401])
    with pytest.raises(ValueError, match="holds no pose sample"):
        ev.crop(10_000_000_000, 11_000_000_000)


# --------------------------------------------------------------------------------- noise
def test_noise_estimator_on_smooth_motion_plus_white_noise():
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.integers(8_000_000, 12_000_000, size=2000)).astype(np.int64)  # irregular ~100 Hz
    ts = t * 1e-9
    clean = np.stack([0.01 * np.sin(2 * np.pi * 0.5 * ts), 0.003 * ts, np.where(ts > 10, 0.002, 0.0)], axis=1)
    sigma = np.array([1e-5, 2e-5, 4e-5])
    est = estimate_noise(t, clean + rng.normal(size=clean.shape) * sigma)
    np.testing.assert_allclose(est, sigma, rtol=0.06)
    # a linear trend is removed exactly by second differences, even with irregular spacing
    assert np.all(estimate_noise(t, np.stack([3.0 * ts, -ts], axis=1)) < 1e-12)
    # an accelerating drift: first differences see it, second ones hardly
    drift = 0.001 * ts[:, None] ** 2 + rng.normal(size=(t.size, 1)) * 1e-6
    assert estimate_noise(t, drift, order=1)[0] > 10 * estimate_noise(t, drift, order=2)[0]
    assert estimate_noise(t, drift, order=2)[0] == pytest.approx(1e-6, rel=0.1)
    with pytest.raises(ValueError, match="difference order must be 1 or 2"):
        estimate_noise(t, clean, order=3)


def test_noise_config_rejects_unknown_keys(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("noise: {difference_order: 1}\n")
    assert noise_config(cfg) == {"difference_order": 1}
    cfg.write_text("noise: {order: 1}\n")
    with pytest.raises(ConfigError, match=f"{cfg}: unknown key noise.order"):
        noise_config(cfg)


# ----------------------------------------------------------------------------- alignment
def test_resample_is_exact_on_linear_signals_with_large_stamps():
    t0 = 1_700_000_000_000_000_000  # wall-clock stamps: float64 seconds would lose ~100 ns
    t_src = t0 + np.array([0, 10_000_000, 25_000_000, 40_000_000], dtype=np.int64)
    values = np.stack([(t_src - t0) * 1e-9 * 2.0 + 1.0, -(t_src - t0) * 1e-9], axis=1)[:, None, :]  # (4, 1, 2)
    t_dst = t0 + np.array([0, 1, 5_000_001, 33_333_333, 40_000_000], dtype=np.int64)
    out = resample(t_src, values, t_dst)
    expected = np.stack([(t_dst - t0) * 1e-9 * 2.0 + 1.0, -(t_dst - t0) * 1e-9], axis=1)[:, None, :]
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="1 target stamps lie outside"):
        resample(t_src, values, np.array([t0 - 1]))
    np.testing.assert_array_equal(resample(t_src, values, np.array([t0 - 1, t0 + 50_000_000]), outside="clamp"),
                                  values[[0, -1]])
    assert np.isnan(resample(t_src, values, np.array([t0 + 50_000_000]), outside="nan")).all()
    with pytest.raises(ValueError, match="strictly increasing"):
        resample(t_src[::-1], values, t_dst)


def test_resample_pose_interpolates_rotation_on_the_short_arc():
    half = np.pi / 4  # 90 degrees about z, stored with a sign flip at the second sample
    q0 = np.array([0, 0, 0, 1.0])
    q1 = -np.array([0, 0, np.sin(half), np.cos(half)])
    pose = np.array([np.r_[0, 0, 0, q0], np.r_[2, 0, 0, q1]])
    out = resample_pose(np.array([0, 100]), pose, np.array([50]))
    np.testing.assert_allclose(out[0, :3], [1, 0, 0])
    np.testing.assert_allclose(np.abs(out[0, 3:]), [0, 0, np.sin(half / 2), np.cos(half / 2)], atol=1e-12)


def test_common_time_base_and_align_on_a_reference_bag():
    ev = load_evidence(reference_bag("latency_s103"))
    t = common_time_base(ev)
    assert np.all(np.diff(t) == 10_000_000)  # the slowest stream (markers, sheet) is 100 Hz
    assert t[0] >= max(v[0] for v in ev.t_ns.values()) and t[-1] <= min(v[-1] for v in ev.t_ns.values())
    aligned = align(ev, t)
    assert aligned["pose"].shape == (t.size, 7) and aligned["markers_uv"].shape == (t.size, 63, 2)
    # markers are sampled on the grid itself: resampling returns them unchanged
    np.testing.assert_array_equal(aligned["markers_xyz"], ev.markers_xyz[np.searchsorted(ev.t_ns["markers_xyz"], t)])
    fast = common_time_base(ev, channels=["pose", "wrench"])
    assert np.all(np.diff(fast) == 5_000_000)
    with pytest.raises(KeyError, match="no image channel"):
        common_time_base(ev, channels=["image"])
