"""The diagnosis benchmark: data-level effects, strengths and windows, scoring, and (slow) the whole run."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from benchmarks import diagnose_bench as db


def _streams(n=101):
    t = np.arange(n) * 10_000_000
    rng = np.random.default_rng(0)
    s = {"t_ns": t, "pose": np.zeros((n, 7)), "pose_cmd": np.zeros((n, 7)),
         "markers_xyz": rng.normal(scale=1e-3, size=(n, 4, 3)),
         "markers_uv": 160 + rng.normal(scale=30, size=(n, 4, 2)),
         "wrench": np.zeros((n, 6)), "sheet_points": np.zeros((n, 5, 3))}
    s["wrench"][:, 2] = np.sin(np.linspace(0, 3, n))
    return s


def test_latency_delays_the_tactile_streams_only():
    s = _streams()
    late = db.shift_latency(s, 0.05)
    assert np.allclose(late["wrench"][5:, 2], s["wrench"][:-5, 2])
    assert late["sheet_points"] is s["sheet_points"]


def test_lens_distortion_is_radial_and_grows_like_r_cubed():
    s = _streams()
    s["markers_uv"] = np.array([[[160.0, 120.0], [190.0, 120.0], [220.0, 120.0], [160.0, 60.0]]] * 3)
    d = db.distort_lens(s, 0.1)["markers_uv"][0] - s["markers_uv"][0]
    assert np.allclose(d[0], 0.0)
    assert d[2, 0] / d[1, 0] == pytest.approx(8.0)  # r doubles -> shift x 8
    assert d[3, 0] == 0.0 and d[3, 1] < 0  # towards the centre's direction, radially


def test_force_drift_touches_the_wrench_only_and_grows_slowly():
    s = _streams()
    b = db.drift_force(s, 0.4)
    off = b["wrench"] - s["wrench"]
    assert off[0, 2] == 0.0 and off[-1, 2] == pytest.approx(0.4)
    assert np.all(np.diff(off[:, 2]) >= 0) and np.array_equal(b["markers_uv"], s["markers_uv"])


def test_strength_and_window_of_a_known_change():
    s = _streams()
    a = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in s.items()}
    a["wrench"][40:61, 2] += 3 * db.NOISE["wrench"][2] * np.sqrt(6)  # whitened RMS over 6 axes = 3
    strength, windows = db.effect_strength(a, s)
    assert strength == pytest.approx(3.0)
    assert windows == [(pytest.approx(0.40), pytest.approx(0.60))]


def test_interval_iou():
    assert db.interval_iou([(0, 1)], [(0, 1)]) == 1.0
    assert db.interval_iou([(0, 1)], [(0.5, 1.5)]) == pytest.approx(1 / 3)
    assert db.interval_iou([(0, 1), (0.5, 2)], [(0, 2)]) == 1.0
    assert db.interval_iou([], [(0, 1)]) == 0.0


def _recs():
    mk = lambda name, label, lib, k, w: db.Recording(name, label, lib, k, k, 1.0, w)
    return [mk("n0", "none", True, 0.0, []), mk("n1", "none", True, 0.0, []),
            mk("lat2", "latency", True, 2.0, [(0.0, 1.0)]), mk("lat4", "latency", True, 4.0, [(0.0, 1.0)]),
            mk("step4", "thickness_step", False, 4.0, [(0.5, 1.0)])]


def test_score_of_an_oracle_and_of_a_silent_engine():
    recs = _recs()
    oracle = []
    for r in recs:
        name = [] if r.label == "none" else (["unexplained"] if not r.in_library else [r.label])
        oracle.append({"mismatch": {"detected": bool(name), "windows_s": r.windows_s}, "explained_by": name,
                       "refit": {"heldout_rms_before": 2.0, "heldout_rms_after": 0.5}})
    res = db.score(recs, oracle)
    assert res["top1_accuracy"]["2"]["accuracy"] == 1.0 and res["top1_accuracy"]["4"]["accuracy"] == 1.0
    assert res["false_alarm_rate"] == 0.0 and res["window_iou_mean"] == 1.0
    assert res["heldout_rms_reduction_mean"] == pytest.approx(0.75)
    assert res["confusion"]["unexplained"]["unexplained"] == 1
    silent = db.score(recs, [{"explained_by": [], "mismatch": {"detected": False}}] * len(recs))
    assert silent["top1_accuracy"]["4"]["accuracy"] == 0.0 and silent["false_alarm_rate"] == 0.0
    assert silent["confusion"]["latency"]["none"] == 2
    alarmist = db.score(recs, [{"explained_by": ["damping"], "mismatch": {"detected": True}}] * len(recs))
    assert alarmist["false_alarm_rate"] == 1.0
    assert "confusion (rows: truth" in db.format_score(res)


def test_missing_engine_is_reported(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(db, "generate_set", lambda out, **kw: _recs())
    assert db.bench_diagnose_main(["--quick", "--out", str(tmp_path), "--engine", "no_such_module:diagnose"]) == 2
    assert "cannot import the diagnosis engine" in capsys.readouterr().err


def test_main_scores_with_a_given_engine(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(db, "generate_set", lambda out, **kw: _recs())
    monkeypatch.setattr(db, "_engine", lambda spec: (lambda bags, **kw: {"explained_by": [], "mismatch": {}}))
    assert db.bench_diagnose_main(["--quick", "--json", "--out", str(tmp_path)]) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["false_alarm_rate"] == 0.0 and doc["recordings"] == 5
    assert json.loads((tmp_path / "labels.json").read_text())[2]["label"] == "latency"
    # the written set can be diagnosed again later (e.g. on another machine) from its labels.json
    assert db.bench_diagnose_main(["--labelled", str(tmp_path), "--json"]) == 2
    assert "not found" in capsys.readouterr().err
    for item in json.loads((tmp_path / "labels.json").read_text()):
        (tmp_path / item["name"]).mkdir()
    assert db.bench_diagnose_main(["--labelled", str(tmp_path), "--json"]) == 0
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert again["recordings"] == 5 and again["labels"] == doc["labels"]


@pytest.mark.slow
def test_quick_benchmark_end_to_end(tmp_path, capsys):
    """Generates the quick set, runs the score stage alone on it, uncalibrated (the scene states the truth), and
    prints the scores (minutes). The pipeline's defaults calibrate, and on this 0.46 s set they miss the gel's
    Maxwell branch at 4 sigma (docs/benchmarks_log.md, 2026-11-27, session 51, 51pipeline)."""
    pytest.importorskip("sysid.diagnose.engine")
    assert db.bench_diagnose_main(["--quick", "--json", "--out", str(tmp_path),
                                   "--engine", "sysid.diagnose.engine:diagnose"]) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["recordings"] == 4
    # in-library effects reach their target strength; thickness_step saturates (a stiffer far part of
    # the card changes the recording only so much), so only its presence is asserted
    assert all(abs(l["strength"] - 4.0) < 2.0 for l in doc["labels"] if l["in_library"] and l["label"] != "none")
    assert all(l["strength"] > 0.5 for l in doc["labels"] if not l["in_library"])
    # the engine names the in-library effects at 4 sigma and raises no alarm on the nominal recording
    assert doc["confusion"]["latency"]["latency"] == 1
    assert doc["confusion"]["gel_viscoelasticity"]["gel_viscoelasticity"] == 1
    assert doc["false_alarm_rate"] == 0.0


def test_heldout_excess_reduction_counts_the_part_above_the_noise():
    from benchmarks.diagnose_bench import heldout_excess_reduction

    assert heldout_excess_reduction(2.0, 1.0) == pytest.approx(1.0)
    assert heldout_excess_reduction(2.0, 2.0) == pytest.approx(0.0)
    assert 0.0 < heldout_excess_reduction(2.0, 1.5) < 1.0


def test_benchmark_effect_hooks_run_in_the_candidate_solver():
    # the benchmark's effects are hooks without the library's damping_terms (regression: a62d1bc)
    from benchmarks.bench_effects import SheetDrag

    targets = db.effector_targets(db.SCENE["effectors"]["ee"]["initial_pose"])[:3]
    out = db.rollout(db.SCENE, targets, SheetDrag(10.0))
    assert out["sheet_points"].shape[0] == 4 and np.all(np.isfinite(out["wrench"]))


def _cohesive_case(openings, s_max, f_max=0.004, delta_c=1e-4):
    from benchmarks.bench_effects import _CohesiveBonds

    rng = np.random.default_rng(3)
    k = len(openings)
    x = rng.normal(scale=1e-3, size=(4 * k, 3))
    v = np.arange(4 * k).reshape(k, 4)
    w = np.column_stack([np.ones(k), -rng.dirichlet(np.ones(3), size=k)])
    n = rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    r = np.einsum("kj,kjd->kd", w, x[v])
    return x, _CohesiveBonds(v, w, n, r - np.asarray(openings)[:, None] * n, np.asarray(s_max), f_max, delta_c)


def test_cohesive_bonds_fd_gradient_hessian_and_psd_projection():
    """Bench adhesion bonds (code separate from the candidate): exact gradient and Hessian by central
    finite differences on every branch (undamaged rising, damaged secant, damaged envelope rising and
    softening, failed), and the clamped Hessian has no negative eigenvalue."""
    from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

    openings = [2e-5, 1e-5, 3e-5, 6e-5, 1.5e-4, -2e-5]  # the last one pressed: no force
    s_max = [0.0, 2e-5, 2e-5, 4e-5, 5e-5, 3e-5]
    x, bonds = _cohesive_case(openings, s_max)
    assert np.allclose(bonds.opening(x), np.maximum(openings, 0.0))
    g = bonds.gradient(x)
    assert relative_error(g, fd_gradient(bonds.energy, x, h=1e-10)) < 1e-5
    H = dense_hessian(bonds.hessian(x, projection="none"), x.shape[0])
    assert relative_error(H, fd_hessian(bonds.gradient, x, h=1e-10)) < 1e-5
    assert np.linalg.eigvalsh(H).min() < -1.0  # the softening bond (u = 0.6) is not convex
    Hc = dense_hessian(bonds.hessian(x), x.shape[0])
    assert np.linalg.eigvalsh(0.5 * (Hc + Hc.T)).min() > -1e-9 * np.abs(Hc).max()
    with pytest.raises(ValueError):
        bonds.hessian(x, projection="bogus")


def test_cohesive_law_peak_softening_fracture_energy_and_damage():
    """Needleman's law: peak traction f_max at delta_c / 3, zero traction and the fracture energy
    9/16 f_max delta_c past delta_c; a damaged bond unloads along the secant to the origin (force
    proportional to the opening), and sliding along the sheet loads no bond."""
    f, dc = 0.004, 1e-4
    x, peak = _cohesive_case([dc / 3], [0.0], f, dc)
    assert np.linalg.norm(peak.gradient(x)[0]) == pytest.approx(f)
    x, gone = _cohesive_case([1.5 * dc], [0.0], f, dc)
    assert np.abs(gone.gradient(x)).max() == 0.0
    assert gone.energy(x) == pytest.approx(9 / 16 * f * dc)
    u = 0.5
    t_max = 6.75 * f * u * (1 - u) ** 2
    for frac in (0.25, 0.5, 1.0):
        x, d = _cohesive_case([frac * u * dc], [u * dc], f, dc)
        assert np.linalg.norm(d.gradient(x)[0]) == pytest.approx(frac * t_max)
    x, d = _cohesive_case([2e-5], [0.0], f, dc)
    slid = x.copy()
    e = np.cross(d.normal[0], [1.0, 0.0, 0.0])
    slid[0] += 1e-4 * e / np.linalg.norm(e)
    assert d.opening(slid)[0] == pytest.approx(2e-5)
    with pytest.raises(ValueError):
        _cohesive_case([1e-5], [0.0], -1.0, dc)


def test_bench_adhesion_signature_grows_with_the_peak_traction():
    """Below the magnitude at which the bonds carry the card away, the bench adhesion's recorded
    signature (the generator's whitened strength) grows monotonically and smoothly with the peak
    traction (measured 0.016 / 0.027 / 0.060 at 0.5 / 0.75 / 1.1 mN, docs/benchmarks_log.md)."""
    from benchmarks.diagnose_bench import SCENE, effect_strength, effector_targets, rollout
    from benchmarks.bench_effects import BondAdhesion

    targets = effector_targets(SCENE["effectors"]["ee"]["initial_pose"])
    base = rollout(SCENE, targets)
    s = [effect_strength(base, rollout(SCENE, targets, BondAdhesion(m)))[0] for m in (0.0005, 0.001)]
    assert 0.0 < s[0] < s[1] < 6.0 * s[0]


def test_bench_adhesion_acts_through_the_candidate_solver():
    """A hook's contact terms reach the Newton step (they were dropped unless they were the
    library's adhesion): on lift-off the bonds pull the sheet, so the wrench changes."""
    from benchmarks.diagnose_bench import SCENE, effector_targets, rollout
    from benchmarks.bench_effects import BondAdhesion

    targets = effector_targets(SCENE["effectors"]["ee"]["initial_pose"])
    base = rollout(SCENE, targets)
    glued = rollout(SCENE, targets, BondAdhesion(0.004))
    lift = slice(-6, None)
    assert np.allclose(glued["wrench"][:3], base["wrench"][:3])
    # dropped terms leave the wrench unchanged to round-off; the bonds pull by ~0.01 N (measured
    # 0.011 N with the cohesive-zone bonds, which carry the card at this peak traction)
    assert np.max(np.abs(glued["wrench"][lift, 2] - base["wrench"][lift, 2])) > 2e-3


def test_calibration_reaches_a_power_law_and_brackets_a_threshold():
    """Calibration of the strength: a sublinear response (sheet drag: strength ~ m^0.6) is reached
    within the tolerance; a threshold response (no change below m = 1, then strength 0.5 + 2 m) is
    bisected towards the jump instead of crawling along the secant, and a try of strength 0 is never
    taken as the closest one."""
    from benchmarks.diagnose_bench import CALIBRATION_STEPS, CALIBRATION_TOLERANCE, next_magnitude, strength_error

    def calibrate(response, k, m0):
        tried = [(m0, response(m0))]
        m = m0 * k / tried[0][1] if tried[0][1] > 0 else 2 * m0
        tried.append((m, response(m)))
        for _ in range(CALIBRATION_STEPS):
            best = min(tried, key=lambda p: strength_error(p[1], k))
            if strength_error(best[1], k) <= math.log1p(CALIBRATION_TOLERANCE):
                break
            m2 = next_magnitude(tried, k)
            if m2 is None:
                break
            tried.append((m2, response(m2)))
        return min(tried, key=lambda p: strength_error(p[1], k)), tried

    (m, s), _ = calibrate(lambda m: m ** 0.6, 4.0, 1.0)
    assert abs(s / 4.0 - 1.0) <= CALIBRATION_TOLERANCE
    step = lambda m: 0.0 if m < 1.0 else 0.5 + 2.0 * m  # noqa: E731
    (m, s), tried = calibrate(step, 3.0, 4.0)  # reference far above the jump
    assert s > 0 and abs(s / 3.0 - 1.0) <= CALIBRATION_TOLERANCE
    # below the jump: the next try doubles instead of dividing by a zero strength
    assert next_magnitude([(0.5, 0.0)], 3.0) == pytest.approx(1.0)
    # bracketed by a zero strength and a large one: geometric midpoint, not an end of the bracket
    assert next_magnitude([(0.25, 0.0), (4.0, 8.5)], 3.0) == pytest.approx(1.0)
    assert next_magnitude([(1.0, 1.0), (1.0 + 1e-9, 9.0)], 3.0) is None
    assert strength_error(0.0, 1.0) == math.inf


def test_each_recording_is_diagnosed_with_its_heldout_companion(tmp_path, capsys, monkeypatch):
    """With --heldout-companions a generated set lists each recording's companion in labels.json; the
    engine receives it as ``heldout`` (generated and re-read with --labelled); --no-heldout falls back
    to time blocks."""
    asked = []

    def recs_with_companions(out, **kw):
        asked.append(kw["heldout"])
        recs = _recs()
        for r in recs:
            r.path = out / r.name
            r.heldout = [out / db.HELDOUT_DIR / r.name]
            r.heldout[0].mkdir(parents=True)
        return recs

    calls = []
    monkeypatch.setattr(db, "generate_set", recs_with_companions)
    monkeypatch.setattr(db, "_engine", lambda spec: (lambda bags, **kw: calls.append((bags, kw)) or
                                                     {"explained_by": [], "mismatch": {}}))
    assert db.bench_diagnose_main(["--quick", "--json", "--out", str(tmp_path), "--heldout-companions"]) == 0
    assert asked == [True]  # opt-in: the default validates on held-out time blocks
    assert all(kw["heldout"] == [str(tmp_path / db.HELDOUT_DIR / Path(b[0]).name)] for b, kw in calls)
    labels = json.loads((tmp_path / "labels.json").read_text())
    assert labels[0]["heldout"] == [f"{db.HELDOUT_DIR}/n0"]
    for item in labels:
        (tmp_path / item["name"]).mkdir()
    calls.clear()
    assert db.bench_diagnose_main(["--labelled", str(tmp_path), "--json"]) == 0
    assert len(calls) == 5 and all(kw["heldout"][0].endswith(Path(b[0]).name) for b, kw in calls)
    calls.clear()
    assert db.bench_diagnose_main(["--labelled", str(tmp_path), "--json", "--no-heldout"]) == 0
    assert len(calls) == 5 and all("heldout" not in kw for _, kw in calls)
    capsys.readouterr()
    (tmp_path / db.HELDOUT_DIR / "n1").rmdir()
    assert db.bench_diagnose_main(["--labelled", str(tmp_path), "--json"]) == 2
    assert "held-out companion of 'n1' not found" in capsys.readouterr().err


def test_companion_noise_leaves_the_primary_noise_of_a_seed_unchanged():
    a, b = db.recording_rng(3, "damping_x2"), db.companion_rng(3, "damping_x2")
    assert not np.allclose(a.normal(size=5), b.normal(size=5))
    assert np.array_equal(db.recording_rng(3, "damping_x2").normal(size=5),
                          db.recording_rng(3, "damping_x2").normal(size=5))
    assert not np.allclose(db.recording_rng(3, "damping_x2").normal(size=5),
                           db.recording_rng(3, "damping_x4").normal(size=5))


def test_a_set_generated_per_effect_has_the_bytes_of_the_one_process_set(tmp_path, monkeypatch):
    """A recording's noise depends on the seed and its name only: generating one effect alone (as the
    per-effect parallel generation does) writes the same bag files as generating it with the others."""
    base = _streams(n=21)

    def fake_rollout(scene, targets, hook=None):
        out = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in base.items()}
        if hook is not None:
            out["wrench"][5:15, 2] += hook * db.NOISE["wrench"][2] * np.sqrt(6)
        return out

    monkeypatch.setattr(db, "rollout", fake_rollout)
    monkeypatch.setattr(db, "EFFECTS", (db.EffectSpec("fake_a", lambda m: m, 1.0),
                                        db.EffectSpec("fake_b", lambda m: 2 * m, 1.0)))
    together = db.generate_set(tmp_path / "one", nominal_count=2, strengths=(2.0,))
    alone = db.generate_set(tmp_path / "part", nominal_count=0, strengths=(2.0,), effects=["fake_b"])
    assert [r.name for r in together] == ["nominal_0", "nominal_1", "fake_a_x2", "fake_b_x2"]
    assert [r.name for r in alone] == ["fake_b_x2"]

    def files(path):
        return {p.relative_to(path): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}

    one, part = files(tmp_path / "one" / "fake_b_x2"), files(tmp_path / "part" / "fake_b_x2")
    assert one and one == part
    assert files(tmp_path / "one" / "fake_a_x2") != one
    assert files(tmp_path / "one" / "nominal_0") != files(tmp_path / "one" / "nominal_1")

    # the CLI: parts generated one effect each (nominal recordings in a part of their own), merged
    for name, argv in (("n", ["--effects", "--nominal", "2"]), ("a", ["--effects", "fake_a", "--nominal", "0"]),
                       ("b", ["--effects", "fake_b", "--nominal", "0"])):
        assert db.bench_diagnose_main(["--generate-only", "--json", "--strengths", "2", "--out", str(tmp_path / name),
                                       *argv]) == 0
    parts = [str(tmp_path / n) for n in ("n", "a", "b")]
    assert db.bench_diagnose_main(["--merge", *parts, "--out", str(tmp_path / "merged")]) == 0
    merged = {r.name: r for r in db.load_labelled_set(tmp_path / "merged")}
    assert list(merged) == ["nominal_0", "nominal_1", "fake_a_x2", "fake_b_x2"]
    for name in merged:
        assert files(tmp_path / "merged" / name) == files(tmp_path / "one" / name)
    assert db.bench_diagnose_main(["--merge", *parts, "--out", str(tmp_path / "merged")]) == 2  # a set is there


def test_companion_motion_shortens_the_slides_only():
    seg = db.companion_segments(slide_scale=0.5)
    assert [n for _, n in seg] == [n for _, n in db.SEGMENTS]
    for (dp, _), (dp0, _) in zip(seg, db.SEGMENTS):
        assert dp[0] == pytest.approx(0.5 * dp0[0]) and dp[2] == dp0[2]
    start = db.SCENE["effectors"]["ee"]["initial_pose"]
    a, b = db.effector_targets(start), db.effector_targets(start, db.companion_segments())
    assert a.shape == b.shape and np.allclose(a[:, 2], b[:, 2]) and not np.allclose(a[:, 0], b[:, 0])


def test_bench_bonds_damage_fail_and_reform_only_after_leaving_contact():
    """Bench adhesion (tacky gel): a vertex in contact bonds; the bond keeps its largest opening as
    damage; a bond opened past the critical opening fails and does not re-heal while the vertex stays
    within the contact offset; once the vertex has left contact it bonds again on its next touch."""
    from types import SimpleNamespace

    from benchmarks.bench_effects import BondAdhesion

    eps = 4e-4
    model = SimpleNamespace(sensors={"tactile": SimpleNamespace(contact_triangles=np.array([[0, 0, 0]]))},
                            bodies={"sheet": SimpleNamespace(triangles=np.array([[1, 2, 3]]))},
                            contact=SimpleNamespace(eps=eps))
    effect = BondAdhesion(0.004, delta_c=1e-4)  # fails at 0.1 mm opening

    def at(height):
        return np.array([[0.2e-2, 0.2e-2, height], [0, 0, 0], [1e-2, 0, 0], [0, 1e-2, 0]], dtype=float)

    def step(state, height):
        return SimpleNamespace(candidate_state=effect.update_state(model, state, at(height), 0.01, None))

    h0 = 0.5 * eps
    s = step(SimpleNamespace(candidate_state={}), h0)
    assert list(s.candidate_state["bonds"]) == [0] and s.candidate_state["broken"] == ()
    s = step(s, h0 + 5e-5)  # opened, not failed: damage 50 um
    assert s.candidate_state["bonds"][0][4] == pytest.approx(5e-5)
    s = step(s, h0 + 1e-5)  # unloaded: the damage stays
    assert s.candidate_state["bonds"][0][4] == pytest.approx(5e-5)
    s = step(s, h0 + 1.2e-4)  # past the critical opening, still within the contact offset: failed
    assert s.candidate_state["bonds"] == {} and s.candidate_state["broken"] == (0,)
    s = step(s, h0)  # back down while still in contact: no new bond
    assert s.candidate_state["bonds"] == {}
    s = step(s, 2 * eps)  # left contact
    assert s.candidate_state["bonds"] == {} and s.candidate_state["broken"] == ()
    s = step(s, h0)  # next touch: bonds again, undamaged
    assert list(s.candidate_state["bonds"]) == [0] and s.candidate_state["bonds"][0][4] == 0.0


def test_a_failing_reference_rollout_is_retried_at_half_the_magnitude(tmp_path, monkeypatch):
    """Generator: a reference rollout the simulator cannot finish is retried at half the magnitude
    (the orthotropic hinges at 0.3 fail after the first lift-off of the two-tap motion, 0.15 runs)
    instead of leaving the effect out; the strengths are then calibrated from the reference that ran."""
    from sim_core.errors import ThinShellError

    base = _streams()

    def fake_rollout(scene, targets, hook=None):
        if hook is None:
            return base
        if hook > 0.25:
            raise ThinShellError("line search failed")
        out = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in base.items()}
        out["wrench"][40:61, 2] += 10.0 * hook * db.NOISE["wrench"][2] * np.sqrt(6)  # strength 10 m
        return out

    monkeypatch.setattr(db, "rollout", fake_rollout)
    monkeypatch.setattr(db, "write_recording", lambda out_dir, streams, scene=None: out_dir)
    monkeypatch.setattr(db, "EFFECTS", (db.EffectSpec("fake", lambda m: m, 0.8),))
    lines = []
    recs = db.generate_set(tmp_path, nominal_count=0, strengths=(2.0,), effects=["fake"], log=lines.append)
    assert sum("failed" in s for s in lines) == 2  # 0.8 and 0.4 fail, 0.2 runs
    assert any("reference magnitude 0.2 -> strength 2.00" in s for s in lines)
    assert len(recs) == 1 and recs[0].magnitude == pytest.approx(0.2) and recs[0].strength == pytest.approx(2.0)
    monkeypatch.setattr(db, "EFFECTS", (db.EffectSpec("fake", lambda m: m, 8.0),))  # 8, 4, 2, 1: all fail
    lines.clear()
    assert db.generate_set(tmp_path, nominal_count=0, strengths=(2.0,), effects=["fake"], log=lines.append) == []
    assert "left out of the set" in lines[-1]
