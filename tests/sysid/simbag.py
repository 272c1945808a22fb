"""Recordings made with this project's own simulator, for the fitting tests.

A card (clamped edge x0) lies on the table; the gel presses near its free end, slides toward the
clamp (the gel slips on the card: the sliding force is set by the gel-card friction), presses
deeper and slides on (the card between clamp and gel is compressed and buckles: force and buckle
height are set by its bending stiffness). Marker displacements per unit force are set by the gel's
modulus. The simulated streams get white noise at the levels of the reference bags and are written
with :class:`sysid.bagio.BagWriter` on the INTERFACES.md topics.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from sim_core.control import Control
from sim_core.series_drive import SeriesSpringDrive
from sim_core.transforms import quat_to_matrix
from sim_core.scenes import load_scene
from sim_core.simulation import Simulation
from sysid.bagio import BagWriter, codec
from benchmarks.diagnose_bench import load_bench_scene

NS = "/thinshell"
DT = 0.01
TRUE_PARAMS = {"sheet.bending_stiffness": 0.008, "gel.youngs_modulus": 3.0e5, "friction.gel_sheet": 0.8}
NOISE = {"markers_xy": 15e-6, "markers_z": 20e-6, "uv": 0.15, "force_xy": 0.1, "force_z": 0.2, "torque": 4e-4,
         "pose": 5e-6, "sheet": 50e-6}

CARD_SCENE = {**load_bench_scene(), "name": "small_card_press_slide"}
"""The benchmark's card scene (benchmarks/bench_card.yaml)."""


PRESS_ONLY = (((0.0, 0.0, -0.00105), 3), ((0.0, 0.0, -0.0001), 1))
"""Segments ``(displacement (m), steps)`` of a short press (0.15 mm past first contact, then 0.25 mm)."""

PRESS_SLIDE = (((0.0, 0.0, -0.00105), 3), ((-0.002, 0.0, 0.0), 8), ((0.0, 0.0, -0.0001), 1),
               ((-0.004, 0.0, 0.0), 16))
"""Press, slide 2 mm toward the clamp (slip), press deeper, slide 4 mm (the card buckles)."""


def targets_from_segments(start: np.ndarray, segments=PRESS_SLIDE) -> np.ndarray:
    """Effector targets ``(steps, 7)``: straight-line segments ``(displacement, steps)`` from ``start``."""
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


def simulate_streams(scene: dict, params: dict, targets: np.ndarray,
                     drive: tuple[float, float] | None = None) -> dict[str, np.ndarray]:
    """Noise-free streams of a replay: stamps (ns), poses, markers xyz / uv, wrench, sheet points.

    ``drive``: ``(k_s N/m, c N s/m)`` of an impedance-controlled arm (:class:`sim_core.series_drive.SeriesSpringDrive`
    along the sensor's +z, solved to 1e-6 N): the targets are its commands (``pose_cmd``) and ``pose`` is where
    the pad went; None: a kinematic arm (``pose`` = ``pose_cmd``).
    """
    sim = Simulation(load_scene(scene), dt=scene["dt"])
    for k, v in params.items():
        sim.set_parameter(k, v)
    spring = None
    if drive is not None:
        sensor = sim.model.sensors["tactile"]
        spring = SeriesSpringDrive("ee", drive[0], sim.model.bodies[sensor.gel_body].vertices, force_tolerance=1e-6,
                                   damping=drive[1], max_evaluations=40)
        axis = quat_to_matrix(targets[0][3:7]) @ quat_to_matrix(sensor.mount[3:7]) @ np.array([0.0, 0.0, 1.0])
        carried = (0.0, 0.0)
    rows = []

    def observe() -> None:
        o = sim.observe()
        r = o.tactile["tactile"]
        rows.append((o.effector_pose["ee"], r.markers_xyz, r.markers_uv, r.wrench, o.sheet_points))

    observe()
    for target in targets:
        if spring is None:
            sim.step(Control({"ee": target}))
        else:
            step = spring.step(sim, Control({"ee": target}), axis, start=carried[0], contact_slope=carried[1])
            carried = (step.compression, step.contact_slope)
        observe()
    n = len(rows)
    t_ns = np.arange(n, dtype=np.int64) * int(round(scene["dt"] * 1e9))
    pose_cmd = np.concatenate([np.asarray(sim.model.effectors["ee"].initial_pose, dtype=float)[None], targets])
    return {"t_ns": t_ns, "pose_cmd": pose_cmd, **{key: np.stack([row[i] for row in rows]) for i, key in
                             enumerate(("pose", "markers_xyz", "markers_uv", "wrench", "sheet_points"))}}


def add_noise(streams: dict, seed: int = 0) -> dict:
    """White noise at the reference-bag levels (README of shared/data/reference_bags)."""
    rng = np.random.default_rng(seed)
    out = dict(streams)
    pose = streams["pose"].copy()
    pose[:, :3] += rng.normal(0.0, NOISE["pose"], pose[:, :3].shape)
    out["pose"] = pose
    m = streams["markers_xyz"].copy()
    m[..., :2] += rng.normal(0.0, NOISE["markers_xy"], m[..., :2].shape)
    m[..., 2] += rng.normal(0.0, NOISE["markers_z"], m[..., 2].shape)
    out["markers_xyz"] = m
    out["markers_uv"] = streams["markers_uv"] + rng.normal(0.0, NOISE["uv"], streams["markers_uv"].shape)
    w = streams["wrench"].copy()
    w[:, :2] += rng.normal(0.0, NOISE["force_xy"], w[:, :2].shape)
    w[:, 2] += rng.normal(0.0, NOISE["force_z"], w[:, 2].shape)
    w[:, 3:] += rng.normal(0.0, NOISE["torque"], w[:, 3:].shape)
    out["wrench"] = w
    out["sheet_points"] = streams["sheet_points"] + rng.normal(0.0, NOISE["sheet"], streams["sheet_points"].shape)
    return out


def lagging_commander(lags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """When a robot that steps back to back takes the commands of a commander that falls behind it.

    As the sim node and the commander run over DDS (``thinshell_ros.commander``): the commander sends
    command ``j`` when it sees the clock at ``t_j`` (the start of step ``j``; header stamp ``t_j``), for
    the end of that step; on a loaded machine it reaches the robot ``lags[j]`` steps late. Commands arrive
    in order (one reliable publisher), so command ``j`` is taken at the start of step
    ``a_j = max(a_{j-1}, j + lags[j])``, with every other command queued since (several at one time),
    and logged then; the newest command taken controls the step, the last one before stays in force
    while none arrives.

    Args:
        lags: steps each command arrives late, int ``(J,)`` >= 0 (all 0: the node's timing when idle).

    Returns:
        ``(taken (J,) the step at whose start each command is taken, in_force (J,) the command controlling
        each step j, -1 before the first)``.
    """
    lags = np.asarray(lags, dtype=np.int64)
    taken = np.maximum.accumulate(np.arange(lags.size) + lags)
    in_force = np.searchsorted(taken, np.arange(lags.size), side="right") - 1
    return taken, in_force


def lagged_streams(scene: dict, params: dict, targets: np.ndarray, lags: np.ndarray,
                   drive: tuple[float, float] | None = None) -> dict[str, np.ndarray]:
    """:func:`simulate_streams` of an arm (kinematic, or ``drive``: an impedance-controlled one) driven as
    :func:`lagging_commander` says: step ``j`` goes to the target of the command in force (the initial pose before
    the first), and ``pose_cmd`` is the sim node's command log: command ``j`` (``targets[j]``) stamped ``t_j`` and
    logged when taken (``"pose_cmd_log_ns"``), several at one log time."""
    taken, in_force = lagging_commander(lags)
    start = np.asarray(scene["effectors"]["ee"]["initial_pose"], dtype=float)
    held = np.array([targets[j] if j >= 0 else start for j in in_force])
    out = simulate_streams(scene, params, held, drive=drive)
    dt_ns = int(round(scene["dt"] * 1e9))
    cut = taken < len(targets)  # commands taken after the last step are not in the recording
    out["pose_cmd_t_ns"] = np.arange(len(targets), dtype=np.int64)[cut] * dt_ns
    out["pose_cmd"] = np.asarray(targets, dtype=float)[cut]
    out["pose_cmd_log_ns"] = taken[cut] * dt_ns
    return out


def write_bag(out_dir: Path, scene: dict, streams: dict, skip: tuple[str, ...] = ()) -> Path:
    """Write ``streams`` as a rosbag2 MCAP bag with ``scene.yaml`` (topics of INTERFACES.md); the commands
    at the sample stamps, or, with ``"pose_cmd_log_ns"`` (:func:`lagged_streams`), stamped
    ``"pose_cmd_t_ns"`` and logged at those times."""
    with BagWriter(out_dir, scene=scene) as bag:
        if "pose_cmd_log_ns" in streams:
            for h, log, pose in zip(streams["pose_cmd_t_ns"], streams["pose_cmd_log_ns"], streams["pose_cmd"]):
                bag.write_message(f"{NS}/ee/pose_cmd", codec.POSE_STAMPED, int(log), codec.pose_stamped(int(h), pose, "world"))
        for i, t in enumerate(streams["t_ns"]):
            t = int(t)
            bag.write_pose(f"{NS}/ee/pose", t, streams["pose"][i], "world")
            if "pose_cmd_log_ns" not in streams:
                bag.write_pose(f"{NS}/ee/pose_cmd", t, streams["pose_cmd"][i], "world")
            if "wrench" not in skip:
                bag.write_wrench(f"{NS}/tactile/wrench", t, streams["wrench"][i], "tactile")
            if "markers" not in skip:
                uv = streams["markers_uv"][i]
                bag.write_points(f"{NS}/tactile/markers", t, streams["markers_xyz"][i], "tactile",
                                 extra_fields={"u": uv[:, 0], "v": uv[:, 1]})
            if "sheet_points" not in skip:
                bag.write_points(f"{NS}/sheet/points", t, streams["sheet_points"][i], "world")
            bag.write_clock(t)
    return out_dir


SCENE_KEYS = {
    "sheet.bending_stiffness": ("sheet", "material", "bending_stiffness"),
    "gel.youngs_modulus": ("sensors", "tactile", "gel_material", "youngs_modulus"),
    "friction.gel_sheet": ("sensors", "tactile", "friction"),
}


def scene_with(values: dict) -> dict:
    """:data:`CARD_SCENE` with the nominal values of some parameters (:data:`SCENE_KEYS`) replaced."""
    scene = copy.deepcopy(CARD_SCENE)
    for name, value in values.items():
        *path, key = SCENE_KEYS[name]
        block = scene
        for k in path:
            block = block[k]
        block[key] = float(value)
    return scene


def make_recording(out_dir: Path, params: dict | None = None, seed: int = 0, skip: tuple[str, ...] = (),
                   segments=PRESS_SLIDE, nominal: dict | None = None) -> Path:
    """Simulate the card scene with ``params`` (default :data:`TRUE_PARAMS`), add noise, write a bag.

    ``scene.yaml`` holds ``nominal`` values (default: the true ones) like a real cell's nominal guesses.
    """
    params = dict(TRUE_PARAMS if params is None else params)
    scene = scene_with(params)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), segments)
    streams = add_noise(simulate_streams(scene, params, targets), seed)
    return write_bag(out_dir, scene_with(nominal if nominal is not None else params), streams, skip)
