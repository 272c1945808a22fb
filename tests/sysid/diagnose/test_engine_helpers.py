"""Engine pieces that need no replay: noise from the residual, pose denoising, effect size, the latency
cross-correlation test, candidate switching and the reset of a cached simulation between replays."""

from __future__ import annotations

import functools
import math
from types import SimpleNamespace

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sysid.diagnose import engine, latency, noise
from sysid.diagnose.residuals import explained_fraction
from sysid.diagnose.candidates import PhysicsParameterCandidate, _known_parameter, yield_angle_for
from sysid.diagnose.parallel import _reset_candidates
from tests.sysid.diagnose.test_candidates import _signal, make_ctx


def _bare(model, **settings) -> engine.BagDiagnosis:
    d = engine.BagDiagnosis.__new__(engine.BagDiagnosis)
    d.model, d.settings, d.notes = model, engine.Settings(**settings), []
    d.tested = tuple(model.sigma)
    return d


def test_noise_from_residual_takes_the_white_part_and_ignores_a_smooth_error():
    rng = np.random.default_rng(0)
    T = 400
    t = np.linspace(0.0, 2.0, T)
    declared = np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4])
    smooth = 5.0 * declared * np.sin(2 * np.pi * 0.7 * t)[:, None]      # model error: 5 sigma, smooth
    white = rng.normal(size=(T, 6)) * declared * np.array([2.0, 1.0, 1.0, 1.0, 1.0, 3.0])
    data = smooth + white
    model = SimpleNamespace(sigma={"wrench": declared.copy()}, data=lambda ch: data)
    noise.raise_to_white_residual(model, ("wrench",), {"wrench": np.zeros((T, 6))})
    ratio = model.sigma["wrench"] / declared
    # axes 0 and 5 carry 2x and 3x the declared white noise; the others keep the declared level,
    # and the 5-sigma smooth error is not taken for noise
    assert ratio[0] == pytest.approx(2.0, rel=0.12) and ratio[5] == pytest.approx(3.0, rel=0.12)
    assert np.all(ratio[1:5] < 1.15) and np.all(ratio >= 1.0)


def _pose_model(noise_m=5e-6, seed=1):
    rng = np.random.default_rng(seed)
    t_ns = np.arange(0, 1_000_000_000, 5_000_000, dtype=np.int64)       # 200 Hz, 1 s
    t = t_ns * 1e-9
    cmd = np.zeros((t.shape[0], 7))
    cmd[:, 6] = 1.0
    cmd[:, 0] = np.interp(t, [0.0, 0.3, 0.6, 1.0], [0.0, 0.0, 0.006, 0.006])   # sharp corners
    cmd[:, 2] = np.interp(t, [0.0, 0.2, 1.0], [0.001, -0.001, -0.001])
    lag = 2e-4 * (1.0 - np.exp(-np.clip(t - 0.2, 0.0, None) / 0.05))        # smooth tracking error
    truth = cmd.copy()
    truth[:, 2] += lag
    pose = truth.copy()
    pose[:, :3] += rng.normal(size=(t.shape[0], 3)) * noise_m
    steps = np.arange(0, 990_000_001, 10_000_000, dtype=np.int64)
    ev = SimpleNamespace(channels_present=("pose", "pose_cmd"), t_ns={"pose": t_ns, "pose_cmd": t_ns},
                         pose=pose, pose_cmd=cmd, pose_cmd_taken=None)
    model = SimpleNamespace(evidence=ev, step_times_ns=steps, controls=None, scene={"effectors": {"ee": {}}},
                            effector="ee", _sim=object(), sigma={})
    return model, t_ns, truth, pose


def test_denoised_controls_keep_the_command_corners_and_the_tracking_lag():
    from sysid.evidence import resample_pose

    model, t_ns, truth, pose = _pose_model()
    noise.denoise_controls(model, engine.Settings().denoise_window)
    want = resample_pose(t_ns, truth, model.step_times_ns)
    raw = resample_pose(t_ns, pose, model.step_times_ns)
    err = np.sqrt(np.mean((model.controls[:, :3] - want[:, :3]) ** 2))
    raw_err = np.sqrt(np.mean((raw[:, :3] - want[:, :3]) ** 2))
    assert raw_err == pytest.approx(5e-6, rel=0.2)
    assert err < 0.6 * raw_err                               # the noise is reduced ...
    assert np.max(np.abs(model.controls[:, :3] - want[:, :3])) < 2.5e-5   # ... and no corner is rounded
    assert model._sim is None and model.scene["effectors"]["ee"]["initial_pose"][0] == pytest.approx(0.0, abs=2e-5)


def test_a_white_tracking_error_replays_the_command_exactly():
    """An effector that follows its command (the own-simulator benchmark's kinematic pad): the
    tracking error is the pose noise alone, and the replay takes the command itself rather than the
    command plus a smoothed noise (which would leave a correlated error of about 2 um)."""
    from sysid.evidence import resample_pose

    model, t_ns, truth, pose = _pose_model()
    ev = model.evidence
    ev.pose = ev.pose_cmd + np.concatenate([pose[:, :3] - truth[:, :3], np.zeros((len(t_ns), 4))], axis=1)
    note = noise.denoise_controls(model, engine.Settings().denoise_window)
    assert "tracking error is white" in note
    assert np.array_equal(model.controls, resample_pose(t_ns, ev.pose_cmd, model.step_times_ns, outside="clamp"))


def test_whiteness_of_the_tracking_error():
    """Von Neumann's ratio: white noise passes at every seed tried; a lag, an offset or a slow drift of
    a fraction of the noise's size over the whole recording does not."""
    t = np.linspace(0.0, 1.0, 47)[:, None]
    passed = [noise.tracking_error_is_white(np.random.default_rng(k).normal(size=(47, 3)) * 5e-6)
              for k in range(200)]
    assert sum(passed) >= 198  # one-sided p = 0.001 per seed
    rng = np.random.default_rng(7)
    white = rng.normal(size=(47, 3)) * 5e-6
    assert not noise.tracking_error_is_white(white + 1e-5)                        # offset of 2 sigma
    assert not noise.tracking_error_is_white(white + 2e-5 * np.sin(np.pi * t))    # smooth lag
    assert not noise.tracking_error_is_white(np.zeros((2, 3)))                    # too short to test
    assert noise.tracking_error_is_white(np.zeros((47, 3)))


def test_an_arm_that_lags_its_command_keeps_the_smoothed_tracking_error():
    """The reference recordings' arm (a 3000 N/m impedance about ``ee/pose_cmd``) lags its command by
    0.2-1.1 mm: far from white, so the replay adds the smoothed tracking error as before."""
    from sysid.evidence import load_evidence, resample_pose
    from tests.sysid.conftest import reference_bag

    ev = load_evidence(reference_bag("nominal_s101"))
    cmd = resample_pose(np.asarray(ev.t_ns["pose_cmd"]), ev.pose_cmd, np.asarray(ev.t_ns["pose"]), outside="clamp")
    err = np.asarray(ev.pose, dtype=float)[:, :3] - cmd[:, :3]
    assert np.sqrt(np.mean(err ** 2)) > 1e-4 and not noise.tracking_error_is_white(err)


def test_without_a_command_the_measured_poses_are_replayed():
    model, *_ = _pose_model()
    model.evidence.channels_present = ("pose",)
    noise.denoise_controls(model, engine.Settings().denoise_window)
    assert model.controls is None


def test_explained_fraction_is_relative_to_the_excess_over_noise():
    assert explained_fraction(2.0, 1.0) == pytest.approx(1.0)          # all of 4 - 1 removed
    assert explained_fraction(2.0, math.sqrt(2.5)) == pytest.approx(0.5)
    assert explained_fraction(1.0, 0.99) < 1.0                          # floor: 5 % of 1
    assert explained_fraction(1.5, 1.6) < 0.0


def test_cross_correlation_lag_matches_a_delay_of_the_recording():
    tau = 0.03
    ctx0 = make_ctx()
    xyz, wrench = _signal(ctx0.stamps_s("wrench") - tau)
    data = {**ctx0.prediction, "wrench": wrench}
    ctx = make_ctx(data=data)
    d = _bare(ctx.model)
    d.tested = ("wrench",)
    lags = latency.xcorr_lags(d.model, ctx, ["wrench"], d.notes)
    assert lags["wrench"] == pytest.approx(tau, abs=0.005)
    same = make_ctx()
    assert latency.xcorr_lags(same.model, same, ["wrench"], [])["wrench"] == pytest.approx(0.0, abs=0.003)


def test_physics_candidate_off_means_no_parameter_and_unknown_candidates_are_skipped():
    # beta = theta_max / theta_yield - 1: yield at the largest bend at the onset, half of it at beta 1
    plastic = PhysicsParameterCandidate("bending_plasticity", "sheet.yield_angle", 2.0, True,
                                        to_parameter=functools.partial(yield_angle_for, theta_max=0.3))
    assert plastic.sim_parameters(0.0) == {} and plastic.sim_parameters(-3.0) == {}
    assert plastic.sim_parameters(1e-9)["sheet.yield_angle"] == pytest.approx(0.3)
    assert plastic.sim_parameters(1.0) == {"sheet.yield_angle": pytest.approx(0.15)}
    aniso = PhysicsParameterCandidate("anisotropic_bending", "candidate.anisotropic_bending", 0.3, False)
    assert aniso.sim_parameters(-0.2) == {"candidate.anisotropic_bending": -0.2}
    assert aniso.bound == pytest.approx(0.95) and plastic.bound == pytest.approx(8.0)   # |anisotropy| < 1
    plastic.shrink_probe(0.25)  # a probe that diverged is retried smaller, and the refit bound follows
    assert plastic.probe_beta == pytest.approx(0.5) and plastic.bound == pytest.approx(2.0)
    with pytest.raises(ValueError, match="shrink factor"):
        plastic.shrink_probe(1.5)

    def get(name):
        if name != "candidate.stiction":
            raise ConfigError(f"unknown parameter {name!r}")
        return 0.0

    model = SimpleNamespace(simulation=lambda: SimpleNamespace(get_parameter=get))
    assert _known_parameter(model, "candidate.stiction", set())
    assert not _known_parameter(model, "candidate.magic", set())
    assert _known_parameter(model, "damping", {"damping"})


def test_reset_switches_candidates_off_and_restores_an_infinite_yield_angle():
    material = {"yield_angle": 0.3, "bending_stiffness": 0.008}
    inner = SimpleNamespace(candidates={"stiction": 0.5}, revision=3, bodies={"sheet": SimpleNamespace(material=material)})
    sim = SimpleNamespace(model=inner, get_parameter=lambda n: material[n.split(".")[1]])
    model = SimpleNamespace(_sim=sim, _nominal={"sheet.yield_angle": math.inf, "sheet.bending_stiffness": 0.008})
    _reset_candidates(model)
    assert inner.candidates == {} and math.isinf(material["yield_angle"]) and inner.revision == 5
    _reset_candidates(model)                      # nothing to do: no revision bump
    assert inner.revision == 5


def _wrench_model(T=40, seed=0):
    rng = np.random.default_rng(seed)
    steps = np.arange(T, dtype=np.int64) * 10_000_000
    sigma = np.full(6, 0.1)
    data = rng.normal(size=(T, 6)) * sigma
    model = SimpleNamespace(sigma={"wrench": sigma}, data=lambda ch: data, step_times_ns=steps,
                            evidence=SimpleNamespace(t_ns={"wrench": steps}))
    return model, data


def test_probes_are_rescaled_towards_the_target_change():
    model, _ = _wrench_model()
    d = _bare(model)
    base = np.zeros((40, 6))
    ctx = SimpleNamespace(prediction={"wrench": base}, params={})
    weak = PhysicsParameterCandidate("damping", "candidate.damping", 1.0)     # change 1e-4 noise units per beta
    strong = PhysicsParameterCandidate("stiction", "candidate.stiction", 0.5)  # change 40 noise units per beta
    gain = {"damping": 1e-5, "stiction": 8.0}

    def replay(sets):
        out = []
        for p in sets:
            name = "damping" if "candidate.damping" in p else "stiction"
            beta = p[f"candidate.{name}"]
            out.append((None, {"wrench": base + gain[name] * beta}))
        return out

    d._replays = replay
    probe_out = dict(zip(["damping", "stiction"], replay([weak.probe(ctx), strong.probe(ctx)])))
    d._calibrate_probes(ctx, [weak, strong], probe_out)
    for c in (weak, strong):
        change = d._probe_change(ctx, probe_out[c.name][1])
        assert 0.5 <= change <= 8.0, (c.name, change)
    assert weak.probe_beta > 1.0 and strong.probe_beta < 0.5
    assert strong.bound == pytest.approx(2.0)  # a shrunk probe keeps the first probe's refit range



def test_a_rescaled_probe_that_diverges_is_kept_and_not_replayed_again():
    """A too-strong probe whose smaller rescale diverges keeps its first size; the second round does
    not repeat that (deterministic) replay."""
    model, _ = _wrench_model()
    d = _bare(model)
    base = np.zeros((40, 6))
    ctx = SimpleNamespace(prediction={"wrench": base}, params={})
    strong = PhysicsParameterCandidate("stiction", "candidate.stiction", 0.5)  # 20 noise units at the probe
    calls = []

    def replay(sets):
        calls.extend(p["candidate.stiction"] for p in sets)
        return [None if p["candidate.stiction"] < 0.5 else (None, {"wrench": base + 8.0 * p["candidate.stiction"]})
                for p in sets]

    probe_out = {"stiction": replay([strong.probe(ctx)])[0]}
    calls.clear()
    d._replays = replay
    d._calibrate_probes(ctx, [strong], probe_out)
    assert len(calls) == 1                                  # one rescale tried, not one per round
    assert strong.probe_beta == pytest.approx(0.5) and strong.bound == pytest.approx(2.0)
    assert sum("rescaled probe diverged" in n for n in d.notes) == 1

def test_heldout_products_sum_channels_per_time_sample():
    from sysid.diagnose.residuals import heldout_products

    model, data = _wrench_model(T=10)
    before = {"wrench": np.zeros((10, 6))}
    after = {"wrench": data * 0.5}
    rows = {"wrench": np.arange(10) % 2 == 1}
    a, b, c, n = heldout_products(model, before, after, ["wrench"], rows)
    r = data / 0.1
    assert a.shape == (5,) and np.allclose(a, np.sum(r[1::2] * 0.5 * r[1::2], axis=1))
    assert np.allclose(b, np.sum((0.5 * r[1::2]) ** 2, axis=1)) and np.allclose(c, np.sum(r[1::2] ** 2, axis=1))
    assert np.all(n == 6)


def test_latency_is_shared_only_by_streams_whose_own_delay_agrees():
    """The wrench stream is 30 ms late, the markers are on time: even when the markers' test is the
    strongest, the delay is the wrench's (confirmed by its cross-correlation lag, largest SSE gain)
    and the markers are left out of it, with a note."""
    ctx0 = make_ctx()
    _, wrench = _signal(ctx0.stamps_s("wrench") - 0.03)
    ctx = make_ctx(data={**ctx0.prediction, "wrench": wrench})
    d = _bare(ctx.model)
    train = {ch: np.ones(ctx.stamps_s(ch).shape[0], dtype=bool) for ch in d.tested}
    for strongest in ("markers_xyz", "wrench"):
        d.notes = []
        chans = latency.streams_sharing_delay(d.model, ctx, train, strongest, ["markers_uv", "markers_xyz", "wrench"], d.notes)
        assert chans == ["wrench"], strongest
        assert "tactile/markers" in d.notes[0] and "confirmed" in d.notes[0]


def _sheet_model(D=0.008, density=700.0, thickness=3e-4, size=(0.05, 0.03), resolution=(9, 5)):
    """A bare sim_core Model with one grid sheet (lumped masses from the builder's rule)."""
    from sim_core.mesh.sheet import grid_sheet

    mesh = grid_sheet(size, resolution, (0.0, 0.0, 0.0))
    n = mesh.x.shape[0]
    area = size[0] * size[1]
    body = SimpleNamespace(kind="sheet", vertices=np.arange(n), triangles=mesh.triangles,
                           material={"bending_stiffness": D})
    gel = SimpleNamespace(kind="solid", vertices=np.arange(n, n + 4), triangles=np.zeros((0, 3), int), material={})
    masses = np.concatenate([np.full(n, density * thickness * area / n), np.full(4, 1.0)])
    return SimpleNamespace(bodies={"sheet": body, "gel": gel}, x_rest=np.concatenate([mesh.x, np.zeros((4, 3))]),
                           vertex_mass=lambda: masses)


def test_sheet_drag_scale_is_bending_stiffness_per_vertex_over_mass_per_step():
    """c_ref = D dt / (m_v A_v): the drag coefficient whose per-step spring c m_v / dt equals the
    bending stiffness per vertex D / A_v (benchmark card: 3.4e5 1/s); it scales with D, dt and
    1 / (density thickness) and ignores the gel."""
    from sysid.diagnose.candidates import sheet_drag_scale

    c = sheet_drag_scale(_sheet_model(), 0.01)
    n = 45
    m_v, a_v = 700.0 * 3e-4 * 0.05 * 0.03 / n, 0.05 * 0.03 / n
    assert c == pytest.approx(0.008 * 0.01 / (m_v * a_v))
    assert c == pytest.approx(3.43e5, rel=0.01)
    assert sheet_drag_scale(_sheet_model(D=0.016), 0.01) == pytest.approx(2 * c)
    assert sheet_drag_scale(_sheet_model(density=1400.0), 0.02) == pytest.approx(c)
    assert math.isnan(sheet_drag_scale(_sheet_model(D=0.0), 0.01))


def test_damping_probe_starts_where_the_drag_acts():
    """The library's sheet drag is probed at c_ref (not at the spec's 100 1/s, three decades below where
    the drag moves a quasi-static card), and a fitted density moves it as 1 / density."""
    from sysid.diagnose import candidates as cands

    sim_model = _sheet_model()
    names = ["sheet.bending_stiffness", "sheet.density", "sheet.thickness"]
    scene_values = {"sheet.bending_stiffness": 0.008, "sheet.density": 700.0, "sheet.thickness": 3e-4}
    obs = SimpleNamespace(dt=0.01, parameter_value=lambda n: scene_values[n],
                          simulation=lambda: SimpleNamespace(parameter_names=names, model=sim_model,
                                                             get_parameter=lambda n: 0.0))
    spec = {"damping": {"parameter": "candidate.damping", "probe": 100.0, "one_sided": True}}
    c_ref = cands.sheet_drag_scale(sim_model, 0.01)
    lib = cands.default_candidates(cands.DiagnosisContext(obs, {}, None, {}, ()), extra=spec)
    damping = next(c for c in lib if c.name == "damping")
    assert damping.probe_beta == pytest.approx(cands.DRAG_PROBE_FRACTION * c_ref)
    lib = cands.default_candidates(cands.DiagnosisContext(obs, {"sheet.density": 1400.0}, None, {}, ()), extra=spec)
    assert next(c for c in lib if c.name == "damping").probe_beta == pytest.approx(0.5 * cands.DRAG_PROBE_FRACTION * c_ref)
    # without a sheet the spec's probe stays
    bare = SimpleNamespace(dt=0.01, parameter_value=lambda n: 1.0,
                           simulation=lambda: SimpleNamespace(parameter_names=[], model=SimpleNamespace(bodies={}),
                                                              get_parameter=lambda n: 0.0))
    lib = cands.default_candidates(cands.DiagnosisContext(bare, {}, None, {}, ()), extra=spec)
    assert next(c for c in lib if c.name == "damping").probe_beta == pytest.approx(100.0)


def test_relaxation_grid_spans_what_the_recording_resolves():
    from sysid.diagnose.candidates import relaxation_times

    assert relaxation_times(0.01, 0.46) == pytest.approx([0.05, 0.15, 0.45])
    assert relaxation_times(0.01, 0.03) == pytest.approx([0.05])  # always at least one member
    assert relaxation_times(0.005, 2.0, ratio=10.0) == pytest.approx([0.025, 0.25])
    with pytest.raises(ValueError, match="ratio > 1"):
        relaxation_times(0.01, 1.0, ratio=1.0)


def test_family_members_carry_their_settings_only_when_on():
    c = PhysicsParameterCandidate("gel_viscoelasticity", "candidate.gel_viscoelasticity", 0.5,
                                  settings={"candidate.gel_viscoelasticity.tau": 0.05}, family_size=3)
    assert c.key == "gel_viscoelasticity[tau=0.05]"
    assert c.sim_parameters(0.0) == {}
    assert c.sim_parameters(0.2) == {"candidate.gel_viscoelasticity": 0.2, "candidate.gel_viscoelasticity.tau": 0.05}
    assert c.probe(SimpleNamespace(params={"gel.youngs_modulus": 1.0}))["candidate.gel_viscoelasticity.tau"] == 0.05
    assert PhysicsParameterCandidate("stiction", "candidate.stiction", 0.5).key == "stiction"
    with pytest.raises(ValueError, match="family size"):
        PhysicsParameterCandidate("x", "y", 1.0, family_size=0)


def _test_entry(member, effect, statistic, p, channel="wrench"):
    return {"effect": effect, "key": member, "channel": channel,
            "result": SimpleNamespace(statistic=statistic, p_value=p)}


def test_family_keeps_its_strongest_member_with_bonferroni_p_values():
    members = [PhysicsParameterCandidate("gel_viscoelasticity", "candidate.gel_viscoelasticity", 0.5,
                                         settings={"candidate.gel_viscoelasticity.tau": tau}, family_size=3)
               for tau in (0.05, 0.15, 0.45)]
    single = PhysicsParameterCandidate("stiction", "candidate.stiction", 0.5)
    tests = [_test_entry(members[0].key, "gel_viscoelasticity", 5.0, 0.02),
             _test_entry(members[1].key, "gel_viscoelasticity", 30.0, 1e-6),
             _test_entry(members[1].key, "gel_viscoelasticity", 2.0, 0.4, "markers_uv"),
             _test_entry(members[2].key, "gel_viscoelasticity", 9.0, 0.003),
             _test_entry("stiction", "stiction", 4.0, 0.04)]
    from sysid.diagnose.candidates import select_family_members

    notes = []
    lib, kept = select_family_members(members + [single], tests, notes)
    assert [c.key for c in lib] == [members[1].key, "stiction"]
    assert [t["key"] for t in kept] == [members[1].key, members[1].key, "stiction"]
    assert [t["p_family"] for t in kept] == pytest.approx([3e-6, 1.0, 0.04])
    assert any("kept gel_viscoelasticity[tau=0.15]" in n for n in notes)


def test_best_of_a_family_keeps_its_size_under_the_null():
    """Pure white noise, three candidate signatures (decays of three time constants; the classical
    variance, exact here, isolates the selection): picking the member with the
    largest statistic rejects far more often than alpha unless its p-value is multiplied by the family
    size; with the Bonferroni factor the family-wise rate stays at or below alpha."""
    from sysid.diagnose import stats

    rng = np.random.default_rng(11)
    T, S, alpha, reps = 40, 6, 0.1, 400
    t = np.linspace(0.0, 1.0, T)
    sigs = [np.exp(-t / tau)[:, None] * rng.normal(size=(1, S)) + 0.05 * rng.normal(size=(T, S)) for tau in (0.05, 0.15, 0.45)]
    raw = bonf = 0
    for _ in range(reps):
        r = rng.normal(size=(T, S))
        ps = [stats.score_test(r, J[..., None], None, prewhiten=False, robust=False).p_value for J in sigs]
        stat_best = int(np.argmin(ps))
        raw += ps[stat_best] <= alpha
        bonf += min(1.0, 3 * ps[stat_best]) <= alpha
    assert raw / reps > 1.3 * alpha
    assert bonf / reps <= alpha + 0.03


def test_a_mismatch_needs_its_excess_on_the_held_out_part_too():
    """In-sample excess with significant tests is declared only when the held-out blocks carry an
    excess above the floor as well; an accepted candidate is always declared."""
    from sysid.diagnose.residuals import mismatch_declared

    floor = 0.1
    assert mismatch_declared(True, [], 0.9, floor)
    assert not mismatch_declared(False, [], 2.0, floor)  # nothing loud in sample
    assert not mismatch_declared(False, ["markers_xyz"], 0.995, floor)  # the benchmark's nominal_4
    assert not mismatch_declared(False, ["markers_xyz"], 1.04, floor)  # 1.04^2 - 1 = 0.082 < 0.1
    assert mismatch_declared(False, ["sheet_points"], 1.18, floor)  # thickness step x2: 0.39
    assert mismatch_declared(False, ["wrench"], float("nan"), floor)  # no held-out part: in-sample only
    assert mismatch_declared(False, ["wrench"], None, floor)


def test_replay_arch_reaches_the_observation_model():
    """``Settings.arch`` (``thinshell diagnose --arch``, default cpu) builds the replays on the fused
    Taichi kernels; the engine API default stays numpy."""
    from tests.sysid.conftest import reference_bag

    bag = reference_bag("nominal_s101")
    assert engine.Settings().arch == "numpy"
    d = engine.BagDiagnosis(bag, settings=engine.Settings(arch="cpu", t_max=0.2))
    assert d.model.arch == "cpu"
    assert d.model.simulation().solver.backend == "taichi-cpu"
    from sysid.diagnose.cli import build_parser

    assert build_parser().parse_args([str(bag)]).arch == "cpu"


def test_rollout_free_probes_are_the_library_probes_except_plasticity():
    """The probes prefetched while the nominal replay runs are exactly the parameter sets the library
    built from the nominal rollout asks for, bending plasticity's (sized from that rollout) aside."""
    from sysid.diagnose import candidates as cands
    from tests.sysid.conftest import reference_bag

    d = engine.BagDiagnosis(reference_bag("latency_s103"), settings=engine.Settings(arch="cpu", t_max=0.3))
    trace = d.model.simulate({})
    ctx = cands.DiagnosisContext(d.model, {}, trace, d.model.predict(trace), d.tested)
    library = cands.default_candidates(ctx)
    early = cands.rollout_free_probes(d.model, {}, d.tested)
    ranked = cands.in_start_order(library)
    later = [c.probe(ctx) for c in ranked if c.name != "bending_plasticity" and c.probe(ctx) is not None]
    assert early == later and len(early) >= 6
    # the probes sized from a scene scale (sheet drag, card weight) start first
    scaled = [c.name for c in ranked if getattr(c, "scaled_probe", False)]
    assert set(scaled) == {"damping", "adhesion"} & {c.name for c in library}
    assert [c.name for c in ranked[:len(scaled)]] == scaled
    assert {"stiction", "gel_viscoelasticity", "adhesion"} <= {c.name for c in library}
    assert cands.rollout_free_probes(d.model, {}, d.tested, ("stiction",)) == [
        c.probe(ctx) for c in library if c.name == "stiction"]


def test_rescale_stays_inside_the_bracket_of_the_chains_own_probes():
    from sysid.diagnose.probing import rescale_factor

    # the linear response: target / change, within the growth limit; a probe in range is kept
    assert rescale_factor([(1.0, 0.1)], 2.0, 1000.0) == pytest.approx(20.0)
    assert rescale_factor([(1.0, 80.0)], 2.0, 1000.0) == pytest.approx(0.025)
    assert rescale_factor([(1.0, 3.0)], 2.0, 1000.0) == 1.0
    # adhesion on the demo's recording: 1.03e-3 overshot (57.6 units), 3.58e-5 undershot (1.31e-3 units);
    # the grow lands inside that bracket, where the power law through its ends gives the target
    seen = [(1.03e-3, 57.6), (3.58e-5, 1.31e-3)]
    factor = rescale_factor(seen, 2.0, 1000.0)
    new = 3.58e-5 * factor
    assert 3.58e-5 < new < 1.03e-3
    slope = math.log(57.6 / 1.31e-3) / math.log(1.03e-3 / 3.58e-5)
    assert 1.31e-3 * (new / 3.58e-5) ** slope == pytest.approx(2.0)
    # and a shrink does not pass an earlier probe that undershot
    assert 0.3 < 0.855 * rescale_factor([(0.3, 0.3), (0.855, 292.0)], 2.0, 1000.0) < 0.855
    # anisotropic bending: 0.16 units at 0.3, its bound caps a grow at 0.855, where the linear response
    # gives 0.45 < target / 4: not grown; uncapped (or reaching the range at the cap) it is
    assert rescale_factor([(0.3, 0.159)], 2.0, 1000.0, largest=0.855) == 1.0
    assert rescale_factor([(0.3, 0.159)], 2.0, 1000.0) == pytest.approx(2.0 / 0.159)
    assert rescale_factor([(0.3, 0.2)], 2.0, 1000.0, largest=0.855) > 1.0


def test_a_probe_its_bound_keeps_out_of_range_is_not_grown_into_the_nonlinear_end():
    """The chain replays nothing more for a grow the parameter's bound caps short of the range."""
    model, _ = _wrench_model()
    d = _bare(model)
    base = np.zeros((40, 6))
    ctx = SimpleNamespace(prediction={"wrench": base}, params={})
    aniso = PhysicsParameterCandidate("anisotropic_bending", "candidate.anisotropic_bending", 0.3, False)
    calls = []

    def replay(sets):  # linear up to 0.5, then the card buckles: hundreds of noise units
        calls.extend(p["candidate.anisotropic_bending"] for p in sets)
        return [(None, {"wrench": base + (0.05 if b < 0.5 else 30.0) * b})
                for b in (p["candidate.anisotropic_bending"] for p in sets)]

    probe_out = {"anisotropic_bending": replay([aniso.probe(ctx)])[0]}
    calls.clear()
    d._replays = replay
    d._calibrate_probes(ctx, [aniso], probe_out)
    assert calls == [] and aniso.probe_beta == pytest.approx(0.3)
    assert d._probe_change(ctx, probe_out["anisotropic_bending"][1]) == pytest.approx(0.15)
