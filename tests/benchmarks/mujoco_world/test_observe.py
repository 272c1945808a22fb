"""Streams of the contract from a run's true signals (pure numpy; MuJoCo is not imported)."""

from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks.mujoco_world import observe as ob

CAM = {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "distance": 0.025}
SCENE = {"sensors": {"tactile": {"marker_grid": [9, 7], "marker_pitch": 0.002, "camera": CAM}}}


def _gel_rest(nx=10, ny=8, gx=0.0186, gy=0.0143):
    return np.array([(x, y) for y in np.linspace(-gy / 2, gy / 2, ny) for x in np.linspace(-gx / 2, gx / 2, nx)])


def test_marker_weights_interpolate_an_affine_field_exactly():
    rest = _gel_rest()
    w, mrest = ob.marker_weights(rest, (10, 8), (9, 7), 0.002)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    field = 0.3 * rest[:, 0] - 1.7 * rest[:, 1] + 0.01
    np.testing.assert_allclose(w @ field, 0.3 * mrest[:, 0] - 1.7 * mrest[:, 1] + 0.01, atol=1e-15)
    # marker 0 is at sensor (-8, -6) mm = effector/world-aligned (-8, +6) mm (sensor y = -world y)
    np.testing.assert_allclose(mrest[0], [-0.008, 0.006])
    np.testing.assert_allclose(mrest[9], [-0.008, 0.004])


def test_exposure_mean_averages_the_last_5_ms():
    t = np.arange(30) * 0.001
    y = np.arange(30.0)
    np.testing.assert_allclose(ob._exposure_mean(t, y, np.array([0.0, 0.005, 0.02])), [0.0, 3.0, 18.0])


def test_pixels_pinhole_and_radial_distortion():
    xyz = np.array([[0.0, 0.0, 0.0], [0.005, -0.0025, -0.0002]])
    uv = ob.pixels(xyz, CAM)
    np.testing.assert_allclose(uv[0], [160.0, 120.0])
    np.testing.assert_allclose(uv[1], [160 + 300 * 0.005 / 0.0248, 120 - 300 * 0.0025 / 0.0248])
    k1 = -0.08
    uvd = ob.pixels(xyz, CAM, k1)
    r2 = (0.005 / 0.0248) ** 2 + (0.0025 / 0.0248) ** 2
    np.testing.assert_allclose(uvd[1] - [160, 120], (uv[1] - [160, 120]) * (1 + k1 * r2))


def _recording(n=101, shear=np.zeros(3)):
    t = np.arange(n) * 0.001
    ee = np.c_[0.05 + 0.01 * t, np.zeros(n), 0.004 - 0.002 * t]
    rest = np.c_[_gel_rest(), np.full(80, 1e-4)]
    ramp = np.clip(t / 0.05, 0, 1)[:, None, None]
    gel = ee[:, None, :] + rest[None] + ramp * shear
    wrench = np.tile([1.0, 2.0, 3.0, 0.1, 0.2, 0.3], (n, 1))
    return SimpleNamespace(t=t, cmd=ee.copy(), ee=ee, wrench=wrench, gel_bottom=gel,
                           sheet=np.zeros((n, 273, 3)), gel_bottom_rest=np.c_[_gel_rest(), np.zeros(80)])


def test_observe_frames_rates_and_a_rigid_shear():
    rng = np.random.default_rng(0)
    rec = _recording(shear=np.array([2e-4, 1e-4, -5e-5]))
    s = ob.observe(rec, SCENE, 0.1, {}, rng)
    assert s.t_fast_ns.tolist() == [i * 5_000_000 for i in range(21)]
    assert s.t_slow_ns.tolist() == [i * 10_000_000 for i in range(11)]
    # world -> sensor: x kept, y and z flipped (sensor z out of the gel, pointing down)
    np.testing.assert_allclose(s.wrench.mean(axis=0)[:3], [1.0, -2.0, -3.0], atol=0.1)
    _, mrest = ob.marker_weights(_gel_rest(), (10, 8), (9, 7), 0.002)
    late = s.markers[-1]
    np.testing.assert_allclose(late[:, 0] - mrest[:, 0], 2e-4, atol=8e-5)
    np.testing.assert_allclose(late[:, 1] + mrest[:, 1], -1e-4, atol=8e-5)
    np.testing.assert_allclose(late[:, 2], 5e-5, atol=1e-4)
    assert np.std(s.markers[:, :, 0] - s.markers[:1, :, 0]) < 3 * ob.NOISE["marker_xy"] + 1e-4


def test_latency_delays_the_tactile_streams_only():
    rec = _recording()
    rec.wrench = np.c_[np.arange(101.0), np.zeros((101, 5))]
    a = ob.observe(rec, SCENE, 0.1, {}, np.random.default_rng(1))
    b = ob.observe(rec, SCENE, 0.1, {"tactile_latency_s": 0.02}, np.random.default_rng(1))
    i = np.arange(5, 21)
    # true F_x = step index (ms); a 5 ms exposure mean at stamp 5 i ms is 5 i - 2; noise sigma 0.1 N
    np.testing.assert_allclose(a.wrench[5:, 0], 5 * i - 2, atol=0.6)
    np.testing.assert_allclose(b.wrench[5:, 0], 5 * i - 22, atol=0.6)
    np.testing.assert_allclose(b.pose, a.pose)
    with pytest.raises(KeyError):
        ob.observe(rec, {"sensors": {}}, 0.1, {}, np.random.default_rng(1))
