"""Signature tests on synthetic recordings with known answers (no replay)."""

from __future__ import annotations

import numpy as np
import pytest

from sysid.diagnose.signature_engine import Prepared, refit_timing
from sysid.diagnose.signatures import Recording, run_signature_tests
from sysid.diagnose.signatures.damping import damping_test, kelvin_voigt
from sysid.diagnose.signatures.null import SHAPE_Z, Thresholds, calibrated_thresholds, decide, default_thresholds
from sysid.diagnose.signatures.sensor import apply_lens, force_bias_test, lens_test
from sysid.diagnose.signatures.sheet import adhesion_test, plasticity_test
from sysid.diagnose.signatures.timing import contact_events, delayed, first_order, low_pass, timing_tests

CAMERA = (300.0, 300.0, 160.0, 120.0, 0.025)
SIGMA = {"markers_xyz": np.array([15e-6, 15e-6, 20e-6]), "markers_uv": np.array([0.15, 0.15]),
         "wrench": np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4]), "sheet_points": np.array([5e-5, 5e-5, 5e-5]),
         "pose": np.array([5e-6] * 3 + [0.0] * 4)}


def press_profile(t: np.ndarray, t_on: float = 1.0, t_off: float = 2.5, ramp: float = 0.15) -> np.ndarray:
    """0 -> 1 -> 0 trapezoid (press, dwell, release)."""
    up = np.clip((t - t_on) / ramp, 0.0, 1.0)
    down = np.clip((t_off - t) / ramp, 0.0, 1.0)
    return np.minimum(up, down)


def synthetic(rng: np.random.Generator, *, latency: float = 0.0, lag_tau: float = 0.0, k1: float = 0.0,
              bias: float = 0.0, set_height: float = 0.0, carried: bool = False, duration: float = 3.5,
              damping: float = 0.0, ramp: float = 0.15, rough: float = 0.0) -> Recording:
    """A press-and-release recording and its exact 'replay', with one effect applied to the data
    (``damping``: a Kelvin-Voigt gel of that time constant, ``F = max(k (x + tau dx/dt), 0)`` on the
    force, the markers keep the elastic deformation ``x``). ``ramp``: press and release time, s;
    ``rough``: step-to-step roughness of the replay's force while it ramps, a fraction of its peak
    (alternating sign every 0.01 s replay step, as the contact solve leaves it)."""
    tw = np.arange(0.0, duration, 0.005)
    tm = np.arange(0.0, duration, 0.01)
    # with a carried sheet the replay lets go when the effector lifts (1.6 s); the recorded gel
    # stays loaded until the sheet drops off (2.5 s)
    t_off_pred = 1.6 if carried else 2.5
    prof_w, prof_m = press_profile(tw, t_off=t_off_pred, ramp=ramp), press_profile(tm, t_off=t_off_pred, ramp=ramp)
    rec_w, rec_m = press_profile(tw, ramp=ramp), press_profile(tm, ramp=ramp)
    # markers: 9 x 7 grid, pressed 200 um at the dwell
    gx, gy = np.meshgrid(np.arange(9) * 0.002 - 0.008, np.arange(7) * 0.002 - 0.006)
    rest = np.stack([gx.ravel(), gy.ravel(), np.zeros(63)], axis=1)
    bowl = np.exp(-(rest[:, 0] ** 2 + rest[:, 1] ** 2) / (2 * 0.006 ** 2))
    xyz_pred = rest[None] + np.stack([np.zeros_like(bowl), np.zeros_like(bowl), -2e-4 * bowl], 1)[None] * prof_m[:, None, None]
    wrench_pred = np.zeros((len(tw), 6))
    ramping = (prof_w > 0.0) & (prof_w < 1.0)
    wrench_pred[:, 2] = -5.0 * (prof_w + rough * ramping * (-1.0) ** np.floor(tw / 0.01 + 1e-9))
    # sheet: 21 x 13 flat grid, rises under the gel only if carried
    sx, sy = np.meshgrid(np.linspace(0, 0.1, 21), np.linspace(-0.03, 0.03, 13))
    sheet0 = np.stack([sx.ravel(), sy.ravel(), np.full(sx.size, 1.5e-4)], axis=1)
    sheet_pred = np.repeat(sheet0[None], len(tm), axis=0)
    pose = np.tile([0.07, 0.0, 0.003, 1.0, 0.0, 0.0, 0.0], (len(tw), 1))
    pose[:, 2] -= 0.0025 * prof_w
    # the recording: effects, then noise
    xyz = rest[None] + np.stack([np.zeros_like(bowl), np.zeros_like(bowl), -2e-4 * bowl], 1)[None] * rec_m[:, None, None]
    w = np.zeros((len(tw), 6))
    # a Kelvin-Voigt contact pushes only: where the damping force exceeds the elastic one on the
    # release the gel's surface parts from the sheet (sysid.diagnose.signatures.damping.contact_force)
    w[:, 2] = -5.0 * np.maximum(rec_w + damping * np.gradient(rec_w, tw), 0.0)
    if latency:
        xyz, w = delayed(tm, xyz, latency), delayed(tw, w, latency)
    if lag_tau:
        xyz, w = first_order(tm, xyz, lag_tau, 1.0), first_order(tw, w, lag_tau, 1.0)
    uv = apply_lens(xyz, CAMERA, {"k1": k1})
    if bias:
        w = w + bias * SIGMA["wrench"] * (1.0 + 0.1 * tw[:, None])
    sheet = sheet_pred.copy()
    if carried:
        lift = np.clip((tm - 1.6) / 0.5, 0.0, 1.0) * (tm < 2.45) * 0.01
        pose_lift = np.interp(tw, tm, lift)
        pose[:, 2] += pose_lift
        near = (np.abs(sheet0[:, 0] - 0.07) < 0.01)
        sheet[:, near, 2] += lift[:, None]
    if set_height:
        final = tm > 2.7
        fold = np.abs(sheet0[:, 0] - 0.07) < 0.015
        sheet[np.ix_(final, fold, [2])] += set_height
    noise = lambda a, s: a + rng.normal(size=a.shape) * s  # noqa: E731
    data = {"markers_xyz": noise(xyz, SIGMA["markers_xyz"]), "markers_uv": noise(uv, SIGMA["markers_uv"]),
            "wrench": noise(w, SIGMA["wrench"]), "sheet_points": noise(sheet, SIGMA["sheet_points"]),
            "pose": pose, "pose_cmd": pose}
    pred = {"markers_xyz": xyz_pred, "markers_uv": apply_lens(xyz_pred, CAMERA, {}), "wrench": wrench_pred,
            "sheet_points": sheet_pred}
    t = {"markers_xyz": tm, "markers_uv": tm, "sheet_points": tm, "wrench": tw, "pose": tw, "pose_cmd": tw}
    return Recording(t=t, data=data, prediction=pred, sigma=SIGMA, camera=CAMERA, name="synthetic")


def named(rec: Recording, th: Thresholds | None = None) -> list[str]:
    results = run_signature_tests(rec)
    return decide(results, th or default_thresholds(rec)).explained_by


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def test_nothing_concealed_names_nothing(rng):
    rec = synthetic(rng)
    assert named(rec) == []
    results = run_signature_tests(rec)
    # noise only: the lens statistic follows chi-square(2), the force-bias one chi-square(12)
    assert results["lens_distortion"].statistic < 20.0
    assert results["force_bias"].statistic < 40.0


def test_latency_named_with_its_delay(rng):
    rec = synthetic(rng, latency=0.04)
    assert named(rec) == ["latency"]
    lat, _ = timing_tests(rec)
    assert lat.estimate["latency_s"] == pytest.approx(0.04, abs=0.006)


def test_contact_events_ignore_roughness_near_the_level():
    t = np.arange(0.0, 3.0, 0.005)
    y = press_profile(t, ramp=0.6) * (1.0 + 0.3 * (-1.0) ** np.floor(t / 0.01 + 1e-9))
    # the rough ramp crosses 20 % of the peak several times on the way up and down: one press
    assert [d for _, d in contact_events(t, y)] == [1, -1]
    # each where the rough ramp is at the level (20 % of the 1.3 peak): the smooth ramp between 0.2 and 0.37
    (t_on, _), (t_off, _) = contact_events(t, y)
    assert 1.0 + 0.2 * 0.6 - 0.01 <= t_on <= 1.0 + 0.26 / 0.7 * 0.6 + 0.01
    assert 2.5 - 0.26 / 0.7 * 0.6 - 0.01 <= t_off <= 2.5 - 0.2 * 0.6 + 0.01
    # two presses with a release between them stay four events
    two = press_profile(t, 0.5, 1.2, 0.1) + press_profile(t, 1.8, 2.6, 0.1)
    assert [d for _, d in contact_events(t, two)] == [1, -1, 1, -1]


@pytest.mark.parametrize("rough", [0.0, 0.05])
def test_latency_on_a_slow_rough_press_is_named_latency(rng, rough):
    # a slower press (0.3 s ramps) seen by a replay with step-to-step roughness (5 % of the peak, as
    # nominal_s109's replay has near the event level): one event per ramp, a pure delay, not a
    # first-order lag with an unphysical share above one
    rec = synthetic(rng, latency=0.04, ramp=0.3, rough=rough)
    assert named(rec) == ["latency"]
    lat, visco = timing_tests(rec)
    assert len(lat.detail["events"]) == 2
    assert 0.0 <= visco.estimate["fraction"] <= 1.0


def test_first_order_lag_named_as_gel_viscoelasticity(rng):
    rec = synthetic(rng, lag_tau=0.12)
    assert named(rec) == ["gel_viscoelasticity"]
    _, visco = timing_tests(rec)
    assert visco.estimate["tau_s"] == pytest.approx(0.12, rel=0.25)


def test_lens_distortion_named_and_k1_recovered(rng):
    rec = synthetic(rng, k1=-0.08)
    assert named(rec) == ["lens_distortion"]
    r = lens_test(rec)
    assert r.estimate["k1"] == pytest.approx(-0.08, abs=0.02)


def test_force_bias_named_and_offset_recovered(rng):
    rec = synthetic(rng, bias=3.0)
    assert named(rec) == ["force_bias"]
    r = force_bias_test(rec)
    assert r.estimate["offset_Fz"] == pytest.approx(3.0 * 0.2 * (1.0 + 0.1 * r.estimate["t_ref_s"]), rel=0.15)


def test_permanent_set_named_as_plasticity(rng):
    rec = synthetic(rng, set_height=0.004)
    assert named(rec) == ["bending_plasticity"]
    assert plasticity_test(rec).effect_size == pytest.approx(0.004, rel=0.1)


def test_adhesion_alone_is_a_contact_property_and_named_beside_plasticity(rng):
    rec = synthetic(rng, carried=True)
    results = run_signature_tests(rec)
    d = decide(results, default_thresholds(rec))
    assert results["adhesion"].detected and d.explained_by == [] and d.contact_properties == ["adhesion"]
    rec2 = synthetic(np.random.default_rng(8), carried=True, set_height=0.004)
    assert named(rec2) == ["bending_plasticity", "adhesion"]
    assert adhesion_test(rec2).effect_size > 0.005


def test_baseline_null_raises_thresholds(rng):
    base = synthetic(rng, latency=0.04)
    rec = synthetic(np.random.default_rng(9), latency=0.04)
    th = calibrated_thresholds(default_thresholds(rec), [run_signature_tests(base)], baseline_factor=2.0)
    # the same delay on the cell's normal recordings is the usual gap: not named
    assert th.source["latency"] == "baseline"
    assert named(rec, th) == []


def test_low_pass_step_response():
    t = np.arange(0.0, 1.0, 0.001)
    y = low_pass(t, (t >= 0.1).astype(float), 0.1)
    assert y[np.searchsorted(t, 0.2)] == pytest.approx(1.0 - np.exp(-1.0), abs=0.01)


def test_tests_say_what_they_need():
    rec = Recording(t={"wrench": np.arange(10) * 0.005}, data={"wrench": np.zeros((10, 6))}, prediction=None,
                    sigma=SIGMA, camera=CAMERA)
    results = run_signature_tests(rec)
    assert not results["lens_distortion"].applicable and "marker positions" in results["lens_distortion"].reason
    assert not results["latency"].applicable and "replay" in results["latency"].reason
    assert not results["bending_plasticity"].applicable


def test_a_shape_the_replay_also_keeps_is_not_a_set(rng):
    rec = synthetic(rng, set_height=0.004)
    # the replay keeps most of the same deformation after release (a held buckle): not plasticity
    pred = dict(rec.prediction)
    sheet = pred["sheet_points"].copy()
    final = rec.t["sheet_points"] > 2.7
    fold = np.abs(sheet[0, :, 0] - 0.07) < 0.015
    sheet[np.ix_(final, fold, [2])] += 0.003
    pred["sheet_points"] = sheet
    held = Recording(t=rec.t, data=rec.data, prediction=pred, sigma=rec.sigma, camera=rec.camera)
    r = plasticity_test(held)
    assert r.effect_size == 0.0 and "replay itself" in r.reason
    assert "bending_plasticity" not in named(held)


def test_gel_damping_named_with_its_time_constant(rng):
    # Kelvin-Voigt gel, tau = 30 ms: the force leads the markers' elastic deformation at both events
    rec = synthetic(rng, damping=0.03)
    assert named(rec) == ["damping"]
    r = damping_test(rec)
    assert r.estimate["tau_s"] == pytest.approx(0.03, abs=0.005)
    assert min(r.detail["leads_s"]) == pytest.approx(0.03, abs=0.0051)
    # the timing effects read the same windows with the other sign: no delay, no lag
    lat, visco = timing_tests(rec)
    assert not lat.detected and not visco.detected


def test_gel_damping_refit_lowers_heldout_residual(rng):
    rec = synthetic(rng, damping=0.03)
    results = run_signature_tests(rec)
    decide(results, default_thresholds(rec))
    p = Prepared("synthetic", None, None, dict(rec.prediction), rec, results)
    fit = refit_timing(p, results["damping"])
    assert fit["params"]["tau_s"] == pytest.approx(0.03, abs=0.005)
    # each event predicted with the lead fitted on the other one: back to the noise level
    assert fit["heldout_rms_before"] > 2.0 and fit["heldout_rms_after"] < 1.2


def test_damping_below_two_wrench_periods_not_named(rng):
    rec = synthetic(rng, damping=0.004)
    r = run_signature_tests(rec)["damping"]
    assert default_thresholds(rec).effect_size["damping"] == pytest.approx(0.01)
    assert named(rec) == []
    assert r.effect_size < 0.01


@pytest.mark.parametrize("kwargs", [{"latency": 0.04}, {"lag_tau": 0.12}])
def test_delay_and_lag_give_no_lead(rng, kwargs):
    r = damping_test(synthetic(rng, **kwargs))
    assert r.effect_size == 0.0 and r.estimate["tau_s"] == 0.0


def test_baseline_null_raises_damping_threshold(rng):
    base = synthetic(rng, damping=0.03)
    rec = synthetic(np.random.default_rng(9), damping=0.03)
    th = calibrated_thresholds(default_thresholds(rec), [run_signature_tests(base)], baseline_factor=2.0)
    assert th.source["damping"] == "baseline"
    assert named(rec, th) == []


def test_kelvin_voigt_is_value_plus_tau_times_rate():
    t = np.arange(0.0, 2.0, 0.005)
    y = np.sin(2 * np.pi * 1.5 * t)
    kv = kelvin_voigt(t, y, 0.02)
    exact = y + 0.02 * 2 * np.pi * 1.5 * np.cos(2 * np.pi * 1.5 * t)
    inner = slice(20, -20)  # the filter's edges fit a shorter span
    assert np.max(np.abs(kv[inner] - exact[inner])) < 0.01


def _timing_pair(delay_s: float, lag_delay_s: float, shape_z: float) -> dict:
    from sysid.diagnose.signatures.base import SignatureResult

    detail = {"explained_delay": 0.9, "explained_lag": 0.9, "shape_z": shape_z}
    return {"latency": SignatureResult("latency", statistic=200.0, effect_size=delay_s, detail=detail),
            "gel_viscoelasticity": SignatureResult("gel_viscoelasticity", statistic=210.0, effect_size=lag_delay_s,
                                                   estimate={"tau_s": lag_delay_s / 0.9, "fraction": 0.9},
                                                   detail=detail)}


@pytest.mark.parametrize("delay, lag, z, expected", [
    (0.005, 0.025, -2.0, []),                                      # a delay's shape, too small: not a lag
    (0.025, 0.005, 3.0, []),                                       # a lag's shape, too small: not a delay
    (0.005, 0.025, 1.0, []),                                       # the lag not significantly better: not named
    (0.030, 0.035, 1.0, ["latency"]),                              # both pass, lag not significant: the delay
    (0.030, 0.035, 1.7, ["gel_viscoelasticity"]),                  # both pass, lag significant: the lag alone
    (0.01 - 1e-17, 0.0, -0.5, ["latency"]),                        # two wrench periods read off the grid
])
def test_the_timing_shape_decides_also_when_one_effect_alone_passes(delay, lag, z, expected):
    rec = Recording(t={"wrench": np.arange(100) * 0.005, "markers_xyz": np.arange(50) * 0.01},
                    data={"wrench": np.zeros((100, 6)), "markers_xyz": np.zeros((50, 63, 3))}, prediction=None,
                    sigma=SIGMA, camera=CAMERA)
    d = decide(_timing_pair(delay, lag, z), default_thresholds(rec))
    assert d.explained_by == expected
    assert d.ties == []


def test_a_delay_that_explains_too_little_is_not_named_and_the_result_says_why():
    from sysid.diagnose.signatures.base import SignatureResult
    from sysid.diagnose.signatures.null import MIN_EXPLAINED

    rec = Recording(t={"wrench": np.arange(100) * 0.005, "markers_xyz": np.arange(50) * 0.01},
                    data={"wrench": np.zeros((100, 6)), "markers_xyz": np.zeros((50, 63, 3))}, prediction=None,
                    sigma=SIGMA, camera=CAMERA)
    for explained, named in ((MIN_EXPLAINED - 0.12, []), (MIN_EXPLAINED + 0.1, ["latency"])):
        r = SignatureResult("latency", statistic=337.0, effect_size=0.021, detail={"explained_delay": explained})
        d = decide({"latency": r}, default_thresholds(rec))
        assert d.explained_by == named
        if named:
            assert r.reason == ""
        else:  # statistic and size pass: the report says which condition withdrew the name
            assert "delay removes 38%" in r.reason and "50%" in r.reason


def test_both_timing_effects_are_sized_by_their_smallest_press_in_mean_delay(rng):
    lat, visco = timing_tests(synthetic(rng, lag_tau=0.12))
    ev, delays = visco.detail["events"], lat.detail["delays_s"]
    assert len(ev) == 2  # one press: its rising and its falling event
    # the lag is sized by its mean delay a tau, the unit of the delay
    mean_delays = [e["lag_fraction"] * e["lag_tau_s"] for e in ev]
    assert visco.effect_size == pytest.approx(0.5 * sum(mean_delays)) and lat.effect_size == pytest.approx(0.5 * sum(delays))
    assert visco.detail["press_lag_delays_s"] == [pytest.approx(visco.effect_size)]


def test_press_size_needs_every_event_delayed():
    from sysid.diagnose.signatures.timing import press_sizes, timing_size

    ev = [{"t_s": 1.0, "direction": "rising", "d": 0.05}, {"t_s": 2.0, "direction": "falling", "d": 0.0},
          {"t_s": 3.0, "direction": "rising", "d": 0.03}]
    assert press_sizes(ev, "d") == [0.025, 0.03]  # the last rise has no fall: a press of its own
    assert timing_size(ev, "d") == 0.0  # one event not delayed: not an effect of the stream
    ev[1]["d"] = 0.01
    assert timing_size(ev, "d") == pytest.approx(0.03)


def _with_depth_gap(rec: Recording, gap: float) -> Recording:
    """``rec`` with a replay whose contact begins ``gap`` s late and ends ``gap`` s early (a shallower
    mount or a softer contact, as a calibration fitted to the recording may leave it)."""
    tw, tm = rec.t["wrench"], rec.t["markers_xyz"]
    prof_w = press_profile(tw, t_on=1.0 + gap, t_off=2.5 - gap, ramp=0.3)
    prof_m = press_profile(tm, t_on=1.0 + gap, t_off=2.5 - gap, ramp=0.3)
    rec.prediction["wrench"] = rec.prediction["wrench"].copy()
    rec.prediction["wrench"][:, 2] = -5.0 * prof_w
    rest = rec.prediction["markers_xyz"][0]
    depth = rec.prediction["markers_xyz"][int(np.argmax(press_profile(tm, ramp=0.3)))] - rest
    rec.prediction["markers_xyz"] = rest[None] + depth[None] * prof_m[:, None, None]
    return rec


def test_latency_read_through_a_replay_with_a_depth_gap_is_named_latency(rng):
    """Through a replay whose contact begins 25 ms late and ends 25 ms early, a 40 ms latency delays
    the rise by 15 ms only (under the two-period size) and the fall by 65 ms; the press's mean is the
    latency."""
    rec = _with_depth_gap(synthetic(rng, latency=0.04, ramp=0.3), 0.025)
    lat, _ = timing_tests(rec)
    assert min(lat.detail["delays_s"]) < 0.02 < max(lat.detail["delays_s"])
    assert lat.effect_size == pytest.approx(0.04, abs=0.005)
    assert named(rec)[0] == "latency"


def test_gel_damping_read_through_a_replay_with_a_depth_gap_is_named_damping(rng):
    """Through the same shallower replay a 30 ms Kelvin-Voigt lead is 5 ms at one event (under the
    10 ms size) and about 55 ms at the other; the press's mean is the time constant. Without damping
    the gap alone leads one event only, and names nothing."""
    rec = _with_depth_gap(synthetic(rng, damping=0.03, ramp=0.3), 0.025)
    r = damping_test(rec)
    assert min(r.detail["leads_s"]) < 0.01 < max(r.detail["leads_s"])
    assert r.effect_size == pytest.approx(0.03, abs=0.006)
    assert named(rec) == ["damping"]
    plain = _with_depth_gap(synthetic(np.random.default_rng(5), ramp=0.3), 0.025)
    assert damping_test(plain).effect_size == 0.0 and named(plain) == []


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_short_latency_is_named_latency_not_a_lag(seed):
    """A 15 ms delay (three wrench periods, under two marker periods): the first-order lag fits it
    about as well (the two shapes agree to first order in tau d/dt), so the lag, the richer model,
    is not named; the delay is resolved on the 200 Hz wrench and named."""
    rec = synthetic(np.random.default_rng(seed), latency=0.015)
    lat, visco = timing_tests(rec)
    assert lat.effect_size == pytest.approx(0.015, abs=0.0025)
    assert lat.detail["shape_z"] < SHAPE_Z
    assert named(rec) == ["latency"]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_first_order_lag_is_named_alone(seed):
    """A first-order lag of 65 ms on a 0.15 s press: its rounded step fits significantly better
    than any delay (Vuong z >= SHAPE_Z), so gel viscoelasticity is named and the latency is not
    named beside it."""
    rec = synthetic(np.random.default_rng(seed), lag_tau=0.065)
    lat, visco = timing_tests(rec)
    assert lat.detail["shape_z"] >= SHAPE_Z
    assert named(rec) == ["gel_viscoelasticity"]
    assert visco.effect_size == pytest.approx(0.065, abs=0.01)  # mean delay a tau of a full lag


def test_shape_z_is_vuongs_statistic():
    from sysid.diagnose.signatures.timing import shape_z

    rng = np.random.default_rng(3)
    # equal fits: the block differences are centred, z about standard normal
    zs = [shape_z(rng.normal(size=40)) for _ in range(400)]
    assert abs(np.mean(zs)) < 0.15 and np.std(zs) == pytest.approx(1.0, abs=0.12)
    # a consistent difference: z = mean / (std / sqrt(B))
    d = 1.0 + 0.5 * rng.normal(size=25)
    assert shape_z(d) == pytest.approx(d.mean() / (d.std(ddof=1) / 5.0))
    assert shape_z(np.array([3.0])) == 0.0 and shape_z(np.zeros(5)) == 0.0


def test_paired_shape_z_is_standard_normal_when_both_fits_are_equally_far():
    """Two fixed curves and a truth midway between them: the paired z (noise-model variance) is
    about standard normal over noise draws."""
    from sysid.diagnose.signatures.timing import paired_shape_z

    rng = np.random.default_rng(4)
    t = np.linspace(0.0, 1.0, 240)
    f1, f2 = np.sin(6.0 * t), np.sin(6.0 * t) + 0.3 * np.exp(-((t - 0.6) / 0.1) ** 2)
    zs = []
    for _ in range(400):
        y = 0.5 * (f1 + f2) + rng.normal(size=t.size)
        zs.append(paired_shape_z(float(np.sum((y - f1) ** 2) - np.sum((y - f2) ** 2)),
                                 float(np.sum((f2 - f1) ** 2)), 1.0, 0))
    assert abs(np.mean(zs)) < 0.15 and np.std(zs) == pytest.approx(1.0, abs=0.12)
    # curves within the noise of the extra parameter: observationally equivalent, no preference
    assert paired_shape_z(5.0, 0.0, 1.0, 1) == 0.0 and paired_shape_z(-0.5, 0.9, 1.0, 1) == 0.0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_shape_difference_in_few_blocks_is_resolved_by_the_paired_z(seed):
    """The second fit differs from the first only over 20 samples (two 10-sample blocks, as a lag's
    exponential tail past a release), and the data follow it: Vuong's block estimate counts that
    difference as spread and stays near the square root of the two blocks, under SHAPE_Z, while
    the paired z, whose variance is the noise model's, resolves it."""
    from sysid.diagnose.signatures.timing import paired_shape_z, shape_z

    rng = np.random.default_rng(seed)
    f1 = np.zeros(240)
    f2 = f1.copy()
    f2[150:170] = 2.0
    y = f2 + rng.normal(size=240)
    d = (y - f1) ** 2 - (y - f2) ** 2
    assert shape_z(np.add.reduceat(d, np.arange(0, 240, 10))) < SHAPE_Z
    assert paired_shape_z(float(d.sum()), float(np.sum((f2 - f1) ** 2)), 1.0, 1) > SHAPE_Z + 1.0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_release_that_still_relaxes_is_not_read_as_a_force_bias(seed):
    """A first-order lag of the slowest time constant searched (TAU_MAX_S) on the whole tactile
    stream: after the release the wrench relaxes for a few tenths of a second more, beyond where the
    markers' whole-grid displacement is back at rest. Those rows are not free gel (RELAXATION_S
    after the release), so the lag is named and no force bias beside it (main named both)."""
    from sysid.diagnose.signatures.base import marker_displacement
    from sysid.diagnose.signatures.sensor import RELAXATION_S, REST_DISPLACEMENT, free_gel_rows
    from sysid.diagnose.signatures.timing import TAU_MAX_S

    rec = synthetic(np.random.default_rng(seed), lag_tau=TAU_MAX_S)
    tw, tm = rec.t["wrench"], rec.t["markers_xyz"]
    back = tm[np.flatnonzero(marker_displacement(rec) > REST_DISPLACEMENT)[-1]]
    free = free_gel_rows(rec)
    assert RELAXATION_S == TAU_MAX_S
    # the markers' last off-rest sample reaches the wrench's time base through one marker period
    assert not free[(tw > back) & (tw <= back + RELAXATION_S)].any()
    assert free[tw > back + RELAXATION_S + rec.sample_period("markers_xyz")].all()
    assert named(rec) == ["gel_viscoelasticity"]


def test_baselines_raise_the_statistic_not_the_resolvable_size():
    """The cell's normal recordings lead their replay by 12 ms (a gap of the model, as a nominal lift
    of the reference set leads by 11 ms); a recording of the same cell with a 20 ms Kelvin-Voigt
    damping leads by less than twice that, but its lead explains far more than the gap's: named.
    A second normal recording of the cell is not."""
    base = synthetic(np.random.default_rng(11), damping=0.012)
    th_of = lambda rec: calibrated_thresholds(default_thresholds(rec), [run_signature_tests(base)])  # noqa: E731
    rec = synthetic(np.random.default_rng(12), damping=0.02)
    r = damping_test(rec)
    assert r.effect_size < 2.0 * damping_test(base).effect_size  # the size rule "twice the baseline's" would miss it
    th = th_of(rec)
    assert th.source["damping"] == "baseline" and th.effect_size["damping"] == default_thresholds(rec).effect_size["damping"]
    assert named(rec, th) == ["damping"]
    normal = synthetic(np.random.default_rng(13), damping=0.012)
    assert named(normal, th_of(normal)) == []
    # a baseline never lowers a threshold
    for effect, s in default_thresholds(rec).statistic.items():
        assert th.statistic[effect] >= s


@pytest.mark.parametrize("seed", [1, 3])
def test_a_long_lag_is_read_at_the_share_bound(seed):
    """A 0.26 s first-order lag: at the falling event the unconstrained share comes out a little
    above one at every time constant; read at the bound (share one) the event is lagged, so the lag
    is sized over the whole press and named first (not the latency its delay-like rise suggests)."""
    rec = synthetic(np.random.default_rng(seed), lag_tau=0.26)
    lat, visco = timing_tests(rec)
    assert all(e["lag_tau_s"] > 0.0 and 0.0 < e["lag_fraction"] <= 1.0 for e in visco.detail["events"])
    assert visco.effect_size > 0.15
    assert named(rec)[0] == "gel_viscoelasticity" and "latency" not in named(rec)


def _replay_still_pressing(rec: Recording) -> Recording:
    """``rec`` with a replay whose contact outlasts the recorded one: 1 N on the gel to the end (an
    elastic fold of the replay leaning on the pad after the recorded gel let go)."""
    pred = dict(rec.prediction)
    w = pred["wrench"].copy()
    w[rec.t["wrench"] > 2.5, 2] = -1.0
    pred["wrench"] = w
    return Recording(t=rec.t, data=rec.data, prediction=pred, sigma=rec.sigma, camera=rec.camera, name=rec.name)


def test_a_set_after_the_recorded_release_is_read_while_the_replay_still_presses(rng):
    rec = _replay_still_pressing(synthetic(rng, set_height=0.004))
    r = plasticity_test(rec)
    # the recorded markers are at rest: the gel let go, whatever the replay's contact says
    assert r.applicable and r.detail["replay_released"] is False and "initial shape" in r.reason
    assert r.effect_size == pytest.approx(0.004, rel=0.1)
    assert named(rec) == ["bending_plasticity"]
    flat = _replay_still_pressing(synthetic(np.random.default_rng(8)))
    r = plasticity_test(flat)
    assert r.applicable and r.effect_size < 5e-4 and "bending_plasticity" not in named(flat)


def test_a_gel_still_loaded_at_the_end_gives_no_final_window(rng):
    rec = synthetic(rng, set_height=0.004, duration=2.55)
    r = plasticity_test(rec)
    assert not r.applicable and "does not release" in r.reason


def test_a_brief_touch_after_the_release_does_not_hide_the_set(rng):
    rec = synthetic(rng, set_height=0.004)
    # the kept fold brushes the lifted pad for 50 ms near the end: every marker moves 100 um
    xyz = rec.data["markers_xyz"].copy()
    touch = (rec.t["markers_xyz"] > 3.3) & (rec.t["markers_xyz"] < 3.35)
    xyz[touch, :, 0] += 1e-4
    touched = Recording(t=rec.t, data=dict(rec.data, markers_xyz=xyz), prediction=rec.prediction, sigma=rec.sigma,
                        camera=rec.camera, name=rec.name)
    r = plasticity_test(touched)
    assert r.applicable and r.effect_size == pytest.approx(0.004, rel=0.1)
    # the window is the free run before the touch, its last 0.2 s
    assert r.detail["final_window_s"][1] < 3.3 - 0.1 and r.detail["final_window_s"][0] > 2.5
@pytest.mark.parametrize("tau, seed", [(0.1, 1), (0.25, 3)])
def test_a_lag_on_a_slow_release_is_read_in_its_tail_beyond_the_release(tau, seed):
    """A 0.4 s release ramp (the press-slides of the independent engine lift off over 0.3-0.4 s):
    on the ramp a first-order lag of time constant tau is a delay by tau, and the two shapes differ
    only in the lag's exponential tail after the force reaches zero, which lies up to a few tau
    beyond the crossing. The falling event's window reaches RELEASE_TAIL_S (the largest time
    constant searched) further into the free gel, so the tail is read and the lag is named, not
    the latency its ramp suggests (with the 0.15 s free side of the rising event the shapes tie)."""
    from sysid.diagnose.signatures.timing import RELEASE_TAIL_S, TAU_MAX_S, WINDOW_BEFORE_S

    rec = synthetic(np.random.default_rng(seed), lag_tau=tau, ramp=0.4)
    lat, visco = timing_tests(rec)
    fall = [e for e in lat.detail["events"] if e["direction"] == "falling"]
    assert RELEASE_TAIL_S == TAU_MAX_S
    assert fall and fall[0]["window_s"][1] - fall[0]["t_s"] == pytest.approx(WINDOW_BEFORE_S + RELEASE_TAIL_S)
    assert lat.detail["shape_z"] >= SHAPE_Z
    assert named(rec) == ["gel_viscoelasticity"]


@pytest.mark.parametrize("seed", [1, 2])
def test_a_delay_on_a_slow_release_stays_a_latency(seed):
    """The same slow press delayed by 45 ms: after the release the delayed force is zero like the
    replay, no tail, so the longer free side gives the lag nothing to gain and the latency is
    named with its delay."""
    rec = synthetic(np.random.default_rng(seed), latency=0.045, ramp=0.4)
    lat, _ = timing_tests(rec)
    assert named(rec) == ["latency"]
    assert lat.effect_size == pytest.approx(0.045, abs=0.005)


def test_the_release_tail_stops_short_of_the_next_press():
    """Two presses 0.3 s apart: the first release's extended window ends where the next rising
    event's window begins (the same samples are not read by two events)."""
    from sysid.diagnose.signatures.timing import RELEASE_TAIL_S, WINDOW_BEFORE_S, event_windows

    t = np.arange(0.0, 4.0, 0.005)
    y = press_profile(t, t_on=1.0, t_off=2.0) + press_profile(t, t_on=2.3, t_off=3.3)
    ev = event_windows(t, y, RELEASE_TAIL_S)
    assert [d for _, d, *_ in ev] == [1, -1, 1, -1]
    (_, _, _, hi_fall, _), (t_rise, _, lo_rise, _, _) = ev[1], ev[2]
    assert hi_fall == pytest.approx(lo_rise) and lo_rise == pytest.approx(t_rise - WINDOW_BEFORE_S)
    # the last release has nothing after it: the full tail
    assert ev[3][3] - ev[3][0] == pytest.approx(WINDOW_BEFORE_S + RELEASE_TAIL_S)


@pytest.mark.parametrize("seed", [1, 2])
def test_force_bias_refit_holds_out_blocks_of_the_free_rows(seed):
    """A bias of the reference set's form (offset, drift and a slow wobble of a 4 s period) on a
    recording free of contact for 0.9 s before the press and only 0.35 s after the release has
    relaxed (``RELAXATION_S`` after it): blocks of the free rows themselves put training rows in both
    free stretches, so the offset and drift refitted on them bring the held-out wrench down to the
    noise (whitened RMS about 1). Blocks of the whole recording would leave the last stretch held
    out only, the drift extrapolated over the press."""
    from sysid.diagnose.signature_engine import refit_force_bias
    from sysid.diagnose.signatures.sensor import RELAXATION_S
    from benchmarks.synthetic_effects import force_bias

    rec = synthetic(np.random.default_rng(seed), duration=2.85 + RELAXATION_S)
    tw = rec.t["wrench"]
    s = SIGMA["wrench"]
    params = {"offset": (3.0 * s).tolist(), "drift_per_s": (-1.5 * s).tolist(), "wobble_amp": (0.8 * s).tolist(),
              "wobble_period_s": 4.0, "wobble_phase": [0.3, 1.0, 2.0, 0.5, 1.5, 2.5]}
    data = dict(rec.data, wrench=rec.data["wrench"] + force_bias(tw, params))
    rec = Recording(t=rec.t, data=data, prediction=rec.prediction, sigma=rec.sigma, camera=rec.camera, name="biased")
    results = run_signature_tests(rec)
    assert "force_bias" in decide(results, default_thresholds(rec)).explained_by
    p = Prepared("synthetic", None, None, dict(rec.prediction), rec, results)
    fit = refit_force_bias(p, results["force_bias"], 4)
    assert fit["heldout"] == "every other of 8 blocks of the free-gel rows"
    assert fit["heldout_rms_before"] > 2.0
    assert fit["heldout_rms_after"] < 1.3
    assert fit["params"]["offset_Fz"] + fit["params"]["drift_Fz_per_s"] * (0.0 - fit["params"]["t_ref_s"]) == \
        pytest.approx(3.0 * s[2] + 0.8 * s[2] * np.sin(1.0), abs=1.0 * s[2])


def test_the_explained_share_of_the_event_windows_excess_stays_a_share():
    """Session 51 (own MuJoCo world, 8 of 18 recordings without creep): where the windows' whitened SSE is below
    its sample count the share read 1e11-1e13 (the excess floored at 1e-12); it is a share in [0, 1]."""
    from sysid.diagnose.signatures.timing import explained_share

    assert explained_share(300.0, 200.0, 100.0) == pytest.approx(0.5)
    assert explained_share(300.0, 50.0, 100.0) == 1.0          # removes the noise's share too: all of the excess
    assert explained_share(90.0, 89.0, 100.0) == 1.0           # no excess: whatever it removes is all of it
    assert explained_share(90.0, 90.0, 100.0) == 0.0
    for seed in range(4):                                      # a recording without a timing effect
        lat, visco = timing_tests(synthetic(np.random.default_rng(seed)))
        for r, key in ((lat, "explained_delay"), (visco, "explained_lag")):
            assert 0.0 <= r.detail[key] <= 1.0
