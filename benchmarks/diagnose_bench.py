"""``python -m benchmarks.diagnose_bench``: a labelled set of recordings with concealed effects, and its score.

SYSID.md "Benchmark protocol". Every recording replays one card press-slide-dwell-lift
(:data:`SEGMENTS`; coarse gel, dt 10 ms) and is written as a rosbag2 bag plus the
*nominal* ``scene.yaml``; the effect is produced by code independent of the candidate models of ``sim_core.candidates`` and
``sysid.diagnose``:

- physics, through a solver hook (:class:`~sim_core.candidates.hook.StepHook`, given to the solver
  with :meth:`~sim_core.solver.NewtonSolver.set_hook`; the terms and rules of :mod:`benchmarks.bench_effects`): ``bending_plasticity`` (rate-dependent Perzyna-type yield,
  not the library's instantaneous return), ``damping`` (drag on the sheet only),
  ``stiction`` (a driver-level Stribeck law: the gel-sheet coefficient is set before each step from
  the previous step's slip speed), ``gel_viscoelasticity`` (a two-term Prony series of small-strain
  linear branches, not the finite-strain SLS), ``adhesion`` (cohesive-zone point bonds that form on
  contact: Needleman's polynomial traction-separation law with irreversible damage, no re-healing
  in contact, formed again on the next touch), ``anisotropic_bending``
  (orthotropic hinges with the grain 15 degrees off x) and, NOT in the library, ``thickness_step`` (the far 40 % of the card is thicker: stiffer hinges);
- data, on the recorded streams: ``latency`` (tactile streams late by tau), ``lens_distortion``
  (radial k1 on the marker pixels), ``force_bias`` (slow offset drift on the wrench).

Strength: ``max over channels of the RMS of the whitened noise-free change inside the effect's
window`` (window: samples where the change exceeds a quarter of its peak). Each effect is scaled,
from one calibration rollout (plus one power-law correction when the response is nonlinear), to
about 1, 2 and 4, and the strength actually reached is recorded (a saturating effect such as
``thickness_step`` may stay below its target).
Nominal recordings differ by their noise only. Each recording's noise is seeded by the set's seed and the
recording's name (:func:`recording_rng`), so a set can be generated per effect in parallel processes
(``--generate-only --effects E --nominal 0``, the nominal recordings with ``--effects --nominal N``) and merged
(``--merge PART... --out DIR``) into the bytes one process writes. With ``--heldout-companions`` each recording also
gets a held-out companion (``heldout/<name>``: the same effect at the same magnitude on a motion
whose slides are :data:`COMPANION_SLIDE_SCALE` as long, with independent noise) that the diagnosis
validates its refits on (``thinshell diagnose BAG --heldout COMPANION``) instead of held-out time
blocks; not the default: measured worse on the set (docs/benchmarks_log.md, 2026-11-22). Scores: confusion matrix of the top-1 name (``none``
when nothing is reported), top-1 accuracy per strength (``unexplained`` is the right answer for
``thickness_step``), false-alarm rate on nominal recordings, IoU of the located windows, held-out
RMS reduction ``1 - after / before``.
"""

from __future__ import annotations

import argparse
import copy
import importlib
import json
import math
import multiprocessing
import sys
import tempfile
import time
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import yaml

from sim_core.control import Control
from sim_core.errors import ThinShellError
from sim_core.scenes import load_scene
from sim_core.scenes.scene_file import load_yaml
from sim_core.simulation import Simulation
from sysid.bagio import BagWriter
from benchmarks.bench_effects import (BondAdhesion, HingeStiffness, PronyGel, RatePlasticity, SheetDrag,
                                 StribeckFriction)
from benchmarks.reference_bench import bench_reference, format_reference
from benchmarks.diagnose_scoring import (Recording, format_score, heldout_excess_reduction, interval_iou, score,  # noqa: F401
                                    top1)
from sysid.diagnose.signature_engine import SignatureSettings

NS = "/thinshell"
DT = 0.01
NOISE = {"markers_xyz": np.array([15e-6, 15e-6, 20e-6]), "markers_uv": np.array([0.15, 0.15]),
         "wrench": np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4]), "pose": np.array([5e-6] * 3),
         "sheet_points": np.array([50e-6] * 3)}
"""1-sigma white noise per channel axis (the reference bags' levels)."""

SCENE_PATH = Path(__file__).resolve().with_name("bench_card.yaml")
"""The benchmark's scene file (scene v1, ``benchmarks/bench_card.yaml``): a small card and a coarse
tactile pad."""


def load_bench_scene(path: Path = SCENE_PATH) -> dict[str, Any]:
    """The benchmark scene as a dict (a fresh copy per call).

    Raises:
        ThinShellError: the file is missing or not YAML (named).
    """
    try:
        return load_yaml(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        raise ThinShellError(f"{path}: cannot read the benchmark scene ({err})") from err


SCENE: dict[str, Any] = load_bench_scene()

SEGMENTS = (((0.0, 0.0, -0.00105), 3), ((-0.002, 0.0, 0.0), 8), ((0.0, 0.0, -0.0001), 1),
            ((-0.004, 0.0, 0.0), 16), ((0.0, 0.0, 0.0), 12), ((0.0, 0.0, 0.0012), 6))
"""Press, slide 2 mm (slip), press deeper, slide 4 mm (the card buckles), dwell 0.12 s, lift 1.2 mm.

Two taps on the flat card after the lift (every contact event then happens more than once, so
that adhesion at lift-off can be fitted on one and validated on another, ``sysid.diagnose.events``)
were tried on the 36-recording set and dropped: top-1 at 2 sigma fell from 0.9 to 0.4 and a
nominal recording was flagged (docs/benchmarks_log.md, 2026-11-22)."""

CHANNELS = ("markers_xyz", "markers_uv", "wrench", "sheet_points")

COMPANION_SLIDE_SCALE = 0.85
"""The held-out companion's slides are this fraction of :data:`SEGMENTS`' (same presses, dwell, lift
and duration): a refit must then hold on a motion it was not fitted to, not only on new noise."""


def companion_segments(segments=SEGMENTS, slide_scale: float = COMPANION_SLIDE_SCALE) -> tuple:
    """``segments`` with every horizontal displacement scaled by ``slide_scale`` (vertical ones kept)."""
    return tuple(((dp[0] * slide_scale, dp[1] * slide_scale, dp[2]), n) for dp, n in segments)


# ============================================================================ motion and rollouts
def effector_targets(start: Sequence[float], segments=SEGMENTS) -> np.ndarray:
    """Effector targets ``(steps, 7)``: straight segments ``(displacement m, steps)`` from ``start``."""
    pose = np.asarray(start, dtype=float).copy()
    out = []
    for dp, n in segments:
        begin = pose.copy()
        for k in range(1, n + 1):
            p = begin.copy()
            p[:3] += np.asarray(dp, dtype=float) * k / n
            out.append(p)
        pose = out[-1].copy()
    return np.array(out)


def rollout(scene: Mapping[str, Any], targets: np.ndarray, hook: Any | None = None) -> dict[str, np.ndarray]:
    """Noise-free streams of one replay (one sample per step, step 0 = initial state).

    Args:
        scene: scene dict.
        targets: effector targets ``(K, 7)``.
        hook: effect hook (a :class:`~sim_core.candidates.hook.StepHook`: ``terms`` /
            ``update_state``, see :class:`~benchmarks.bench_effects.PhysicsEffect`), or None for the
            nominal model.

    Returns:
        ``t_ns (K+1,)``, ``pose``, ``pose_cmd`` ``(K+1, 7)``, ``markers_xyz``, ``markers_uv``,
        ``wrench (K+1, 6)``, ``sheet_points``.
    """
    sim = Simulation(load_scene(copy.deepcopy(dict(scene))), dt=DT)
    if hook is not None:
        hook.attach(sim)
        sim.solver.set_hook(hook)
    rows = []

    def observe() -> None:
        o = sim.observe()
        r = o.tactile["tactile"]
        rows.append((o.effector_pose["ee"], r.markers_xyz, r.markers_uv, r.wrench, o.sheet_points))

    observe()
    for target in targets:
        sim.step(Control({"ee": target}))
        observe()
    keys = ("pose", "markers_xyz", "markers_uv", "wrench", "sheet_points")
    out = {k: np.stack([np.asarray(row[i], dtype=float) for row in rows]) for i, k in enumerate(keys)}
    out["t_ns"] = np.arange(len(rows), dtype=np.int64) * int(round(DT * 1e9))
    out["pose_cmd"] = np.concatenate([np.asarray(scene["effectors"]["ee"]["initial_pose"], float)[None], targets])
    return out


# ============================================================================ data effects
def shift_latency(streams: dict, tau: float) -> dict:
    """Tactile streams observed ``tau`` s late: ``y_rec(t) = y(t - tau)`` (linear interpolation, held at 0)."""
    out = dict(streams)
    t = streams["t_ns"] * 1e-9
    for ch in ("markers_xyz", "markers_uv", "wrench"):
        a = streams[ch].reshape(len(t), -1)
        out[ch] = np.stack([np.interp(t - tau, t, a[:, j]) for j in range(a.shape[1])], axis=1).reshape(streams[ch].shape)
    return out


def distort_lens(streams: dict, k1: float, scene: Mapping[str, Any] = SCENE) -> dict:
    """Radial distortion ``(u, v) - c <- (1 + k1 r^2) ((u, v) - c)``, ``r`` in normalised image coordinates."""
    cam = scene["sensors"]["tactile"]["camera"]
    c = np.array([cam["cx"], cam["cy"]])
    f = np.array([cam["fx"], cam["fy"]])
    n = (streams["markers_uv"] - c) / f
    r2 = np.sum(n * n, axis=-1, keepdims=True)
    out = dict(streams)
    out["markers_uv"] = c + f * n * (1 + k1 * r2)
    return out


def drift_force(streams: dict, b: float) -> dict:
    """Wrench offset drifting as ``b (t / T)^2 (0.6, -0.3, 1, 0, 0, 0)`` N (slow, quadratic in time)."""
    t = streams["t_ns"] * 1e-9
    out = dict(streams)
    out["wrench"] = streams["wrench"] + b * (t / t[-1])[:, None] ** 2 * np.array([0.6, -0.3, 1.0, 0, 0, 0])[None]
    return out


# ============================================================================ effect table
@dataclass(frozen=True)
class EffectSpec:
    """One effect of the benchmark: label, how it is made, its reference magnitude."""

    label: str
    make: Callable[[float], Any]
    reference: float
    data: bool = False
    in_library: bool = True


EFFECTS: tuple[EffectSpec, ...] = (
    EffectSpec("bending_plasticity", lambda m: RatePlasticity(m), 0.5),
    EffectSpec("damping", lambda m: SheetDrag(m), 20.0),
    EffectSpec("stiction", lambda m: StribeckFriction(m), 0.3),
    EffectSpec("gel_viscoelasticity", lambda m: PronyGel((0.6 * m, 0.4 * m)), 0.3),
    EffectSpec("adhesion", lambda m: BondAdhesion(m), 0.004),
    EffectSpec("anisotropic_bending", lambda m: HingeStiffness(m, "orthotropic"), 0.3),
    EffectSpec("thickness_step", lambda m: HingeStiffness(m, "thickness_step"), 1.0, in_library=False),
    EffectSpec("latency", lambda m: (lambda s: shift_latency(s, m)), 0.01, data=True),
    EffectSpec("lens_distortion", lambda m: (lambda s: distort_lens(s, m)), 0.05, data=True),
    EffectSpec("force_bias", lambda m: (lambda s: drift_force(s, m)), 0.2, data=True),
)
QUICK_EFFECTS = ("latency", "gel_viscoelasticity", "thickness_step")


def whitened_change(a: dict, b: dict) -> dict[str, np.ndarray]:
    """Per channel, per sample RMS over components of ``(a - b) / sigma``, shape ``(K+1,)``."""
    out = {}
    for ch in CHANNELS:
        d = (a[ch] - b[ch]) / NOISE[ch]
        out[ch] = np.sqrt(np.mean(d.reshape(d.shape[0], -1) ** 2, axis=1))
    return out


def effect_strength(a: dict, b: dict) -> tuple[float, list[tuple[float, float]]]:
    """Strength (module docstring) and true windows ``[(t0, t1)]`` in s from the recording start."""
    change = whitened_change(a, b)
    t = a["t_ns"] * 1e-9
    best, windows = 0.0, []
    e = np.max(np.stack(list(change.values())), axis=0)
    if e.max() <= 0:
        return 0.0, []
    for ch, c in change.items():
        inside = c > 0.25 * c.max() if c.max() > 0 else np.zeros_like(c, bool)
        if inside.any():
            best = max(best, float(np.sqrt(np.mean(c[inside] ** 2))))
    inside = e > 0.25 * e.max()
    start = None
    for i, flag in enumerate(inside):
        if flag and start is None:
            start = t[i]
        if not flag and start is not None:
            windows.append((start, t[i - 1]))
            start = None
    if start is not None:
        windows.append((start, t[-1]))
    merged: list[tuple[float, float]] = []
    for w in windows:
        if merged and w[0] - merged[-1][1] <= 0.1:
            merged[-1] = (merged[-1][0], w[1])
        else:
            merged.append(w)
    return best, merged


CALIBRATION_TOLERANCE = 0.15
"""Relative strength error accepted by the calibration (was 0.3: damping x2 and stiction x2 of the
36-recording set stayed at 1.42 and 1.41 for a target of 2)."""

REFERENCE_RETRIES = 3
"""A reference rollout the simulator cannot finish is retried at half the magnitude up to this many
times before the effect is left out of the set (the orthotropic hinges at 0.3 fail a Newton line
search on the released card right after the first lift-off; at 0.15 they run)."""

CALIBRATION_STEPS = 6
"""Largest number of correcting rollouts per recording."""


def strength_error(s: float, target: float) -> float:
    """``|ln(s / target)|``: distance of a strength from its target (infinite for no visible change)."""
    return abs(math.log(s / target)) if s > 0 else math.inf


def next_magnitude(tried: Sequence[tuple[float, float]], target: float) -> float | None:
    """Next magnitude to try when calibrating an effect's strength (safeguarded regula falsi in log-log).

    Once the target is bracketed (a try below it, one above), the log-log secant through the closest
    pair is used when it lands in the middle 80 % of the bracket (in log magnitude), else the bracket's
    geometric midpoint: a threshold effect (bonds that lift the card or not) has a strength that jumps
    from ~0 to above the target, where the secant crawls along one end (the adhesion x1 recording of
    the 36-recording set kept strength 0.065 for a target of 1). Unbracketed, the log-log secant of the
    two tries closest to the target extrapolates (factor at most 10), or the magnitude is doubled /
    halved towards the target when no secant is defined (no visible change yet, equal strengths).

    Args:
        tried: ``(magnitude > 0, strength >= 0)`` pairs already rolled out.
        target: target strength > 0.

    Returns:
        the next magnitude, or None when the bracket has collapsed (nothing left to refine).
    """
    pts = [(float(m), float(s)) for m, s in tried if m > 0]
    below = [p for p in pts if p[1] < target]
    above = [p for p in pts if p[1] > target]
    if below and above:
        (m_a, s_a) = max(below, key=lambda p: (p[1], p[0]))
        (m_b, s_b) = min(above, key=lambda p: (p[1], -p[0]))
        la, lb = math.log(m_a), math.log(m_b)
        if abs(lb - la) < 1e-3:
            return None
        mid = 0.5 * (la + lb)
        if s_a > 0 and s_b > s_a:
            x = la + (math.log(target / s_a)) * (lb - la) / math.log(s_b / s_a)
            lo, hi = min(la, lb), max(la, lb)
            if lo + 0.1 * (hi - lo) <= x <= hi - 0.1 * (hi - lo):
                return math.exp(x)
        return math.exp(mid)
    ranked = sorted(pts, key=lambda p: strength_error(p[1], target))
    (m_a, s_a) = ranked[0]
    if len(ranked) > 1:
        (m_b, s_b) = ranked[1]
        if s_a > 0 and s_b > 0 and not math.isclose(s_a, s_b) and not math.isclose(m_a, m_b):
            slope = math.log(s_b / s_a) / math.log(m_b / m_a)
            if slope > 0.05:
                return m_a * float(np.clip((target / s_a) ** (1.0 / slope), 0.1, 10.0))
    return m_a * (2.0 if s_a < target else 0.5)


def add_noise(streams: dict, rng: np.random.Generator) -> dict:
    """White noise at :data:`NOISE` on every recorded channel."""
    out = dict(streams)
    for ch in CHANNELS:
        out[ch] = streams[ch] + rng.normal(size=streams[ch].shape) * NOISE[ch]
    pose = streams["pose"].copy()
    pose[:, :3] += rng.normal(size=pose[:, :3].shape) * NOISE["pose"]
    out["pose"] = pose
    return out


def write_recording(out_dir: Path, streams: dict, scene: Mapping[str, Any] = SCENE) -> Path:
    """Write streams as a rosbag2 MCAP bag plus the nominal ``scene.yaml`` (INTERFACES.md topics)."""
    with BagWriter(out_dir, scene=dict(scene)) as bag:
        for i, t in enumerate(streams["t_ns"]):
            t = int(t)
            bag.write_pose(f"{NS}/ee/pose", t, streams["pose"][i], "world")
            bag.write_pose(f"{NS}/ee/pose_cmd", t, streams["pose_cmd"][i], "world")
            bag.write_wrench(f"{NS}/tactile/wrench", t, streams["wrench"][i], "tactile")
            uv = streams["markers_uv"][i]
            bag.write_points(f"{NS}/tactile/markers", t, streams["markers_xyz"][i], "tactile",
                             extra_fields={"u": uv[:, 0], "v": uv[:, 1]})
            bag.write_points(f"{NS}/sheet/points", t, streams["sheet_points"][i], "world")
            bag.write_clock(t)
    return out_dir


HELDOUT_DIR = "heldout"
"""Sub-directory of a set that holds the held-out companion of each recording (same name)."""


def recording_rng(seed: int, name: str) -> np.random.Generator:
    """Noise generator of one primary recording: seeded by the set's seed and the recording's name only,
    so that a recording's bytes do not depend on which other recordings are generated, nor in which
    process or order (a set generated per effect in parallel, ``--effects``, equals the one-process set).

    Args:
        seed: the set's noise seed.
        name: the recording's name (e.g. ``damping_x2``).
    """
    return np.random.default_rng([seed, zlib.crc32(name.encode("utf-8"))])


def companion_rng(seed: int, name: str) -> np.random.Generator:
    """Noise generator of one held-out companion: independent of its recording's
    (:func:`recording_rng`), so that adding companions leaves the primary recordings of a seed
    unchanged, and, like it, a function of the seed and the recording's name only."""
    return np.random.default_rng([seed, 1, zlib.crc32(name.encode("utf-8"))])


def write_companion(out_dir: Path, rec: Recording, streams: dict, seed: int) -> Path:
    """Write the held-out companion of ``rec``: its noise-free ``streams`` with new noise
    (:func:`companion_rng`), as ``out_dir/heldout/<name>``; appends the path to ``rec.heldout``."""
    path = write_recording(Path(out_dir) / HELDOUT_DIR / rec.name, add_noise(streams, companion_rng(seed, rec.name)))
    rec.heldout.append(path)
    return path


def generate_set(out_dir: Path, quick: bool = False, seed: int = 0, strengths: Sequence[float] = (1.0, 2.0, 4.0),
                 nominal_count: int = 6, effects: Sequence[str] | None = None,
                 log: Callable[[str], None] = lambda s: None, heldout: bool = False) -> list[Recording]:
    """Simulate, perturb, add noise and write the labelled set (module docstring).

    Args:
        out_dir: directory for the bags (one sub-directory per recording; must not hold them already).
        quick: :data:`QUICK_EFFECTS` at strength 4 only, one nominal recording.
        seed: noise seed.
        strengths: target strengths in noise units.
        nominal_count: nominal recordings (noise only).
        effects: restrict to these labels.
        log: progress callback.
        heldout: also write each recording's held-out companion (:func:`add_companions`: the same
            effect at the same magnitude on a motion with shorter slides, independent noise), so that
            the diagnosis validates its refits on another recording; an effect confined to one event
            (adhesion's single lift-off) cannot be validated on held-out time blocks.
    """
    if quick:
        strengths, nominal_count, effects = (4.0,), 1, effects or QUICK_EFFECTS
    specs = [e for e in EFFECTS if effects is None or e.label in effects]
    targets = effector_targets(SCENE["effectors"]["ee"]["initial_pose"])
    t0 = time.perf_counter()
    base = rollout(SCENE, targets)
    log(f"nominal rollout: {len(targets)} steps in {time.perf_counter() - t0:.1f} s")
    recs: list[Recording] = []
    for i in range(nominal_count):
        recs.append(Recording(f"nominal_{i}", "none", True, 0.0, 0.0, 0.0, [], streams=base))
    for spec in specs:
        run = (lambda m: spec.make(m)(base)) if spec.data else (lambda m: rollout(SCENE, targets, spec.make(m)))
        reference, probe = spec.reference, None
        for _ in range(REFERENCE_RETRIES + 1):
            try:
                probe = run(reference)
                break
            except ThinShellError as err:  # a rollout the simulator cannot finish: retried at half the magnitude
                log(f"{spec.label}: reference rollout at magnitude {reference:g} failed ({err})")
                reference *= 0.5
        if probe is None:
            log(f"{spec.label}: no reference rollout finished, effect left out of the set")
            continue
        s0, _ = effect_strength(probe, base)
        log(f"{spec.label}: reference magnitude {reference:g} -> strength {s0:.2f}")
        if not s0 > 0:  # invisible in this scenario: a recording labelled with it would be nominal
            log(f"{spec.label}: no visible change at the reference magnitude, effect left out of the set")
            continue
        for k in strengths:
            m = reference * k / s0 if s0 > 0 else reference
            try:
                streams = run(m) if not math.isclose(m, reference) else probe
            except ThinShellError as err:
                log(f"  x{k:g}: rollout at magnitude {m:.4g} failed, recording left out ({err})")
                continue
            s, windows = effect_strength(streams, base)
            # nonlinear response (stiction, damping of a quasi-static card; adhesion, a threshold
            # effect): safeguarded corrections (next_magnitude), keeping the try closest to the
            # target in log strength
            tried = [(reference, s0), (m, s)]
            for _ in range(CALIBRATION_STEPS):
                if strength_error(s, k) <= math.log1p(CALIBRATION_TOLERANCE):
                    break
                m2 = next_magnitude(tried, k)
                if m2 is None:
                    break
                try:
                    streams2 = run(m2)
                except Exception as err:  # a diverged rollout keeps the best try so far
                    log(f"  x{k:g}: correction to magnitude {m2:.4g} failed ({err})")
                    break
                s2, w2 = effect_strength(streams2, base)
                tried.append((m2, s2))
                if strength_error(s2, k) < strength_error(s, k):
                    m, streams, s, windows = m2, streams2, s2, w2
            recs.append(Recording(f"{spec.label}_x{k:g}", spec.label, spec.in_library, k, s, m, windows, streams=streams))
            log(f"  x{k:g}: magnitude {m:.4g}, strength {s:.2f}, windows {[(round(a, 2), round(b, 2)) for a, b in windows]}")
    for rec in recs:
        rec.path = write_recording(out_dir / rec.name, add_noise(rec.streams, recording_rng(seed, rec.name)))
        rec.streams = {}
    if heldout:
        add_companions(out_dir, recs, seed=seed, log=log)
    return recs


def add_companions(directory: Path, recs: Sequence[Recording], seed: int = 0,
                   log: Callable[[str], None] = lambda s: None) -> list[Recording]:
    """Write the held-out companion of every recording (also for a set written without them).

    Each effect is simulated at its recording's labelled magnitude on the companion motion
    (:func:`companion_segments`: slides shortened to :data:`COMPANION_SLIDE_SCALE`), a nominal
    recording's companion is the nominal rollout of that motion, and both get noise from
    :func:`companion_rng`. A companion whose rollout fails is left out (that recording is then
    validated on held-out time blocks).

    Raises:
        ValueError: a recording's label is not an effect of :data:`EFFECTS` (names it).
    """
    specs = {e.label: e for e in EFFECTS}
    targets = effector_targets(SCENE["effectors"]["ee"]["initial_pose"], companion_segments())
    base = rollout(SCENE, targets)
    for rec in recs:
        if rec.label != "none" and rec.label not in specs:
            raise ValueError(f"{rec.name}: label {rec.label!r} is not a benchmark effect")
        spec = specs.get(rec.label)
        try:
            if spec is None:
                streams = base
            else:
                streams = spec.make(rec.magnitude)(base) if spec.data else rollout(SCENE, targets, spec.make(rec.magnitude))
        except ThinShellError as err:
            log(f"{rec.name}: companion rollout failed, validated on held-out time blocks ({err})")
            continue
        write_companion(directory, rec, streams, seed)
        log(f"{rec.name}: held-out companion written")
    return recs


def load_labelled_set(directory: Path) -> list[Recording]:
    """The recordings of a set written by :func:`generate_set` (its ``labels.json``).

    Raises:
        FileNotFoundError: no ``labels.json`` or a listed recording missing (names the path).
    """
    directory = Path(directory)
    index = directory / "labels.json"
    recs = []
    for item in json.loads(_labels_text(directory)):
        path = directory / item["name"]
        if not path.exists():
            raise FileNotFoundError(f"{index}: recording {item['name']!r} not found at {path}")
        heldout = [directory / h for h in item.get("heldout", [])]
        missing = [h for h in heldout if not h.exists()]
        if missing:
            raise FileNotFoundError(f"{index}: held-out companion of {item['name']!r} not found at {missing[0]}")
        recs.append(Recording(item["name"], item["label"], bool(item["in_library"]), float(item["target_strength"]),
                              float(item["strength"]), float(item["magnitude"]),
                              [tuple(w) for w in item["windows_s"]], path=path, heldout=heldout))
    return recs


def merge_sets(parts: Sequence[Path], out_dir: Path) -> int:
    """Move the recordings of sets generated in parts (e.g. one ``--effects E`` process each) into one set.

    The recordings' noise depends on the seed and their names only (:func:`recording_rng`), so parts of one
    seed merge into the set one process would have written. ``labels.json`` of ``out_dir`` lists the parts'
    recordings in the order the parts are given.

    Args:
        parts: directories written by :func:`generate_set` (each with its ``labels.json``).
        out_dir: the merged set's directory (created; must not hold a ``labels.json`` yet).

    Returns:
        the number of recordings merged.

    Raises:
        FileNotFoundError: a part without ``labels.json`` or a listed recording missing (names it).
        FileExistsError: ``out_dir`` already holds a set, or two parts hold recordings of one name.
    """
    out_dir = Path(out_dir)
    if (out_dir / "labels.json").exists():
        raise FileExistsError(f"{out_dir}: already holds a labelled set (labels.json)")
    items = [(Path(part), item) for part in parts for item in json.loads(_labels_text(Path(part)))]
    names = [item["name"] for _, item in items]
    if len(set(names)) != len(names):
        raise FileExistsError(f"{out_dir}: recordings of one name in two parts: "
                              f"{sorted({n for n in names if names.count(n) > 1})}")
    for part, item in items:
        if item.get("heldout"):
            raise ValueError(f"{part}: {item['name']!r} has held-out companions; merge sets without them")
        if not (part / item["name"]).exists():
            raise FileNotFoundError(f"{part / 'labels.json'}: recording {item['name']!r} not found")
    out_dir.mkdir(parents=True, exist_ok=True)
    for part, item in items:
        (part / item["name"]).rename(out_dir / item["name"])
    (out_dir / "labels.json").write_text(json.dumps([item for _, item in items], indent=1))
    return len(items)


def _labels_text(directory: Path) -> str:
    index = directory / "labels.json"
    if not index.is_file():
        raise FileNotFoundError(f"{index}: no labels.json (write a set with --generate-only --out DIR)")
    return index.read_text()


def _engine(spec: str) -> Callable[..., Mapping[str, Any]]:
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name or "diagnose")


def _write_report(directory: Path, name: str, report: Mapping[str, Any]) -> None:
    """Write one diagnosis as ``<directory>/<name>.json`` (temporary file, then rename)."""
    directory.mkdir(parents=True, exist_ok=True)
    tmp = directory / f".{name}.json.tmp"
    tmp.write_text(json.dumps(report, default=float))
    tmp.replace(directory / f"{name}.json")


def _diagnose_one(engine: str, path: str, heldout: Sequence[str] = ()) -> Mapping[str, Any]:
    """Diagnose one recording in a worker process (engine given as ``module:function``), validated
    on its held-out companions when it has any (else on held-out time blocks)."""
    return _engine(engine)([path], dt=DT, **({"heldout": list(heldout)} if heldout else {}))


def bench_diagnose_main(argv: Sequence[str] | None = None) -> int:
    """``python -m benchmarks.diagnose_bench [--quick] [--json] [--out DIR] [--seed N] [--generate-only]``.

    Returns:
        0 on success, 2 when the diagnosis engine cannot be imported.
    """
    ap = argparse.ArgumentParser(prog="python -m benchmarks.diagnose_bench", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="three effects at 4 sigma and one nominal recording")
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    ap.add_argument("--out", type=Path, default=None, help="directory for the bags (default: a temporary one)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--nominal", type=int, default=6, help="nominal recordings")
    ap.add_argument("--effects", nargs="*", default=None, help="restrict to these labels")
    ap.add_argument("--engine", default="sysid.diagnose.cli:diagnose",
                    help="module:function of the diagnosis (default: thinshell diagnose's pipeline with its defaults; "
                         "sysid.diagnose.engine:diagnose: the score stage alone, uncalibrated)")
    ap.add_argument("--generate-only", action="store_true", help="write the labelled set, do not diagnose")
    ap.add_argument("--strengths", type=float, nargs="+", default=[1.0, 2.0, 4.0],
                    help="target strengths in noise units (default: 1 2 4)")
    ap.add_argument("--jobs", type=int, default=1, help="recordings diagnosed in parallel (processes)")
    ap.add_argument("--reports", type=Path, default=None,
                    help="write each recording's diagnosis JSON here as soon as it is done")
    ap.add_argument("--labelled", type=Path, default=None,
                    help="diagnose a set written earlier (its labels.json) instead of generating one")
    ap.add_argument("--heldout-companions", action="store_true",
                    help="also write a held-out companion per recording (other motion, same effect) and "
                         "validate on it (default: held-out time blocks; see docs/benchmarks_log.md 2026-11-22)")
    ap.add_argument("--no-heldout", action="store_true",
                    help="ignore the companions a labelled set lists (validate on held-out time blocks)")
    ap.add_argument("--add-heldout", action="store_true",
                    help="with --labelled: write held-out companions for a set that has none (seed --seed)")
    ap.add_argument("--merge", type=Path, nargs="+", default=None, metavar="PART",
                    help="move the recordings of sets generated in parts (e.g. one --effects E process each, same "
                         "--seed) into --out, with one labels.json, and stop")
    args = ap.parse_args(argv)
    if args.merge is not None:
        if args.out is None:
            print("python -m benchmarks.diagnose_bench: --merge needs --out DIR", file=sys.stderr)
            return 2
        try:
            count = merge_sets(args.merge, args.out)
        except (OSError, ValueError) as err:
            print(f"python -m benchmarks.diagnose_bench: {err}", file=sys.stderr)
            return 2
        print(f"merged {count} recordings into {args.out} (labels.json)")
        return 0
    if args.jobs < 1 or any(not k > 0 for k in args.strengths):
        print("python -m benchmarks.diagnose_bench: --jobs must be >= 1 and --strengths > 0", file=sys.stderr)
        return 2
    log = (lambda s: None) if args.json else (lambda s: print(s, file=sys.stderr, flush=True))
    t0 = time.perf_counter()
    if args.labelled is not None and (args.labelled / "labels.yaml").is_file():
        return _reference_main(args)
    if args.labelled is not None:
        out = args.labelled
        try:
            recs = load_labelled_set(out)
        except FileNotFoundError as err:
            print(f"python -m benchmarks.diagnose_bench: {err}", file=sys.stderr)
            return 2
        if args.add_heldout:
            if any(r.heldout for r in recs) or (out / HELDOUT_DIR).exists():
                print(f"python -m benchmarks.diagnose_bench: {out} already has held-out companions", file=sys.stderr)
                return 2
            add_companions(out, recs, seed=args.seed, log=log)
    else:
        out = args.out or Path(tempfile.mkdtemp(prefix="thinshell_bench_diagnose_"))
        out.mkdir(parents=True, exist_ok=True)
        recs = generate_set(out, quick=args.quick, seed=args.seed, strengths=tuple(args.strengths),
                            nominal_count=args.nominal, effects=args.effects, log=log, heldout=args.heldout_companions and not args.no_heldout)
    if args.no_heldout:
        for r in recs:
            r.heldout = []
    gen_s = time.perf_counter() - t0
    labels = [{"name": r.name, "label": r.label, "in_library": r.in_library, "target_strength": r.target_strength,
               "strength": r.strength, "magnitude": r.magnitude, "windows_s": r.windows_s,
               **({"heldout": [str(Path(h).relative_to(out)) for h in r.heldout]} if r.heldout else {})}
              for r in recs]
    if args.labelled is None or args.add_heldout:
        (out / "labels.json").write_text(json.dumps(labels, indent=1))
    result: dict[str, Any] = {"out": str(out), "generation_s": round(gen_s, 1), "labels": labels}
    if not args.generate_only:
        try:
            diagnose = _engine(args.engine)
        except (ImportError, AttributeError) as err:
            print(f"python -m benchmarks.diagnose_bench: cannot import the diagnosis engine {args.engine!r}: {err}", file=sys.stderr)
            return 2
        t1 = time.perf_counter()
        if args.jobs == 1:
            reports = []
            for r in recs:
                log(f"diagnosing {r.name} ...")
                reports.append(diagnose([str(r.path)], dt=DT, **({"heldout": [str(h) for h in r.heldout]}
                                                                 if r.heldout else {})))
                if args.reports is not None:
                    _write_report(args.reports, r.name, reports[-1])
        else:
            log(f"diagnosing {len(recs)} recordings, {args.jobs} at a time ...")
            reports = [None] * len(recs)
            # spawned, not forked: this process may have run Taichi (generating the set), and a kernel a
            # forked child compiles hangs it (Taichi's compile thread pool does not survive fork)
            with ProcessPoolExecutor(max_workers=args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
                futures = {pool.submit(_diagnose_one, args.engine, str(r.path), [str(h) for h in r.heldout]): i for i, r in enumerate(recs)}
                for fut in as_completed(futures):
                    i = futures[fut]
                    reports[i] = fut.result()
                    log(f"diagnosed {recs[i].name}: {top1(reports[i])}")
                    if args.reports is not None:
                        _write_report(args.reports, recs[i].name, reports[i])
        result["diagnosis_s"] = round(time.perf_counter() - t1, 1)
        scored = score(recs, reports)
        # keep the per-recording "labels" of the set; the score's label names go under "label_names"
        scored["label_names"] = scored.pop("labels")
        result.update(scored)
    if args.json:
        print(json.dumps(result, default=float))
    elif "confusion" in result:
        print(format_score(result))
    else:
        print(f"wrote {len(recs)} recordings to {out} (labels.json)")
    return 0


def _reference_main(args: argparse.Namespace) -> int:
    """``--labelled DIR`` on a reference set (``labels.yaml``): :mod:`benchmarks.reference_bench`."""
    log = (lambda s: None) if args.json else (lambda s: print(s, file=sys.stderr, flush=True))
    try:
        result = bench_reference(args.labelled, SignatureSettings(dt=DT), log=log)
    except (FileNotFoundError, ValueError) as err:
        print(f"python -m benchmarks.diagnose_bench: {err}", file=sys.stderr)
        return 2
    print(json.dumps(result, default=float) if args.json else format_reference(result))
    return 0


if __name__ == "__main__":
    sys.exit(bench_diagnose_main())
