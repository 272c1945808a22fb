"""The trajectory file: timed effector poses (and gripper openings) for deployment, as pure data.

Format ``thinshell-trajectory`` version 1 (``docs/trajectory_format.md``)::

    format: thinshell-trajectory
    version: 1
    frame: world
    scene: {path: config/scenes/forming.yaml, name: forming, parameters: {sheet.youngs_modulus: 2.0e5}}
    effectors: [ee]
    waypoints:                       # strictly increasing t (s, from the start of the motion)
      - {t: 0.0, poses: {ee: [x, y, z, qx, qy, qz, qw]}, gripper: {ee: 0.02}}
    prediction: {reward: 0.8, wrench_peak_N: 1.2}
    provenance: {tool: thinshell optimise, created: 2026-01-01T00:00:00+00:00, git: abc123, seed: 0}

Poses are ``[x y z qx qy qz qw]`` in ``world`` (m, unit quaternion, scalar last, the ROS order).
Between waypoints the position is interpolated linearly and the orientation by slerp
(:meth:`Trajectory.sample`); the gripper opening (m) linearly. ``gripper`` is optional per
effector, but an effector that has one has it in every waypoint. ``prediction`` is a free mapping
of numbers (or null) the producer expects (reward, peak wrench, ...); ``provenance`` a free mapping
of scalars saying who made the file.

Both :func:`read_trajectory` and :func:`write_trajectory` validate with :func:`validate_trajectory`;
every error is a :class:`~sim_core.errors.ConfigError` naming the file and, for a waypoint's fault,
the waypoint index, the time and the effector.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from sim_core.errors import ConfigError
from sim_core.plain import plain
from sim_core.transforms import quat_from_rotvec, quat_multiply, quat_to_rotvec

FORMAT = "thinshell-trajectory"
VERSION = 1
QUATERNION_TOLERANCE = 1e-3
"""Accepted ``| |q| - 1 |`` of a waypoint quaternion (it is normalised on reading)."""

_TOP_KEYS = ("format", "version", "frame", "scene", "effectors", "waypoints", "prediction", "provenance")
_REQUIRED_KEYS = ("format", "version", "frame", "effectors", "waypoints")
_SCENE_KEYS = ("path", "name", "parameters")
_WAYPOINT_KEYS = ("t", "poses", "gripper")


@dataclass
class Trajectory:
    """Timed poses of one or more effectors (the file's content, validated).

    Attributes:
        t: waypoint times, s from the start of the motion, strictly increasing, ``>= 0``, shape ``(T,)``.
        poses: effector -> waypoint poses ``[x y z qx qy qz qw]`` in ``world``, shape ``(T, 7)``.
        gripper: effector -> finger opening in m, shape ``(T,)`` (only effectors that have one).
        scene_path: scene file the trajectory was optimised / predicted on, or None.
        scene_name: that scene's name ("" when unknown).
        parameters: global parameter name -> value used on that scene (SI units).
        prediction: what the producer predicts (numbers or None; e.g. ``reward``, ``wrench_peak_N``).
        provenance: who made it (``tool``, ``created`` ISO 8601, ``git``, ``seed``, ...).
        frame: pose frame; only ``world``.
    """

    t: np.ndarray
    poses: dict[str, np.ndarray]
    gripper: dict[str, np.ndarray] = field(default_factory=dict)
    scene_path: str | None = None
    scene_name: str = ""
    parameters: dict[str, float] = field(default_factory=dict)
    prediction: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    frame: str = "world"

    @property
    def effectors(self) -> list[str]:
        """Effector names, in file order."""
        return list(self.poses)

    @property
    def waypoint_count(self) -> int:
        """Number of waypoints ``T``."""
        return int(np.asarray(self.t).size)

    @property
    def duration(self) -> float:
        """Time of the last waypoint, s."""
        return float(self.t[-1])

    def sample_pose(self, effector: str, t: float) -> np.ndarray:
        """Pose of ``effector`` at time ``t`` (s): linear in position, slerp in orientation.

        Held at the first / last waypoint outside ``[t[0], t[-1]]``.

        Returns:
            ``[x y z qx qy qz qw]``, shape ``(7,)``, unit quaternion.
        """
        poses = self.poses[effector]
        if t <= self.t[0]:
            return poses[0].copy()
        if t >= self.t[-1]:
            return poses[-1].copy()
        i = int(np.searchsorted(self.t, t, side="right")) - 1
        a = (t - self.t[i]) / (self.t[i + 1] - self.t[i])
        return interpolate_pose(poses[i], poses[i + 1], float(a))

    def sample_gripper(self, effector: str, t: float) -> float | None:
        """Finger opening of ``effector`` at ``t`` (m, linear), or None when it has no gripper channel."""
        if effector not in self.gripper:
            return None
        return float(np.interp(t, self.t, self.gripper[effector]))


def interpolate_pose(p0: np.ndarray, p1: np.ndarray, a: float) -> np.ndarray:
    """Pose a fraction ``a`` (0..1) of the way from ``p0`` to ``p1``.

    Position linear, orientation by slerp along the shorter arc (``q(a) = exp(a log(q1 q0^-1)) q0``).

    Args:
        p0, p1: poses ``[x y z qx qy qz qw]``, shape ``(7,)``, unit quaternions.
        a: fraction.

    Returns:
        the pose, shape ``(7,)``.
    """
    q0 = np.asarray(p0[3:], dtype=float)
    q1 = np.asarray(p1[3:], dtype=float)
    if np.dot(q0, q1) < 0:
        q1 = -q1
    rel = quat_to_rotvec(quat_multiply(q1, q0 * np.array([-1.0, -1.0, -1.0, 1.0])))
    q = quat_multiply(quat_from_rotvec(a * rel), q0)
    return np.concatenate([(1 - a) * np.asarray(p0[:3], float) + a * np.asarray(p1[:3], float), q / np.linalg.norm(q)])


# ----------------------------------------------------------------------------------- validation
def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{what} must be a number, got {value!r}")
    return float(value)


def _check_free_mapping(doc: Any, what: str, numbers_only: bool) -> dict[str, Any]:
    if doc is None:
        return {}
    if not isinstance(doc, Mapping):
        raise ConfigError(f"{what} must be a mapping, got {type(doc).__name__}")
    out = {}
    for key, value in doc.items():
        if not isinstance(key, str):
            raise ConfigError(f"{what}: key {key!r} is not a string")
        ok_scalar = value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))
        if numbers_only:
            if not ok_scalar and not (isinstance(value, list) and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
                raise ConfigError(f"{what}.{key} must be a number, null or a list of numbers, got {value!r}")
        elif not (ok_scalar or isinstance(value, (str, bool))):
            raise ConfigError(f"{what}.{key} must be a scalar (number, string, bool, null), got {value!r}")
        out[key] = value
    return out


def validate_trajectory(traj: Trajectory, where: str = "trajectory") -> Trajectory:
    """Check a trajectory and return a copy with float arrays and normalised quaternions.

    Checks: frame ``world``; at least one effector; ``t`` finite, ``>= 0`` and strictly increasing;
    every pose finite with a quaternion of norm ``1 +- QUATERNION_TOLERANCE`` (a zero quaternion is
    refused); gripper openings finite and ``>= 0``; scene parameters finite numbers.

    Args:
        traj: the trajectory.
        where: prefix of error messages (the file).

    Raises:
        ConfigError: the first fault, naming ``where``, the waypoint index, its time and the effector.
    """
    if traj.frame != "world":
        raise ConfigError(f"{where}: frame must be 'world', got {traj.frame!r}")
    t = np.asarray(traj.t, dtype=float).reshape(-1)
    if t.size < 1:
        raise ConfigError(f"{where}: no waypoints")
    if not traj.poses:
        raise ConfigError(f"{where}: no effectors")
    for i, ti in enumerate(t):
        if not math.isfinite(ti):
            raise ConfigError(f"{where}: waypoint {i}: time t={ti} is not finite")
        if ti < 0:
            raise ConfigError(f"{where}: waypoint {i}: time t={ti:g} s is negative")
        if i and ti <= t[i - 1]:
            raise ConfigError(f"{where}: waypoint {i}: time t={ti:g} s is not after waypoint {i - 1}'s "
                              f"t={t[i - 1]:g} s (times must be strictly increasing)")
    poses: dict[str, np.ndarray] = {}
    for eff, arr in traj.poses.items():
        arr = np.array(arr, dtype=float)
        if arr.shape != (t.size, 7):
            raise ConfigError(f"{where}: effector {eff!r}: need {t.size} poses of 7 numbers, got shape {arr.shape}")
        for i in range(t.size):
            at = f"{where}: waypoint {i} (t={t[i]:g} s), effector {eff!r}"
            if not np.all(np.isfinite(arr[i])):
                raise ConfigError(f"{at}: pose has non-finite entries {arr[i].tolist()}")
            norm = float(np.linalg.norm(arr[i, 3:]))
            if abs(norm - 1.0) > QUATERNION_TOLERANCE:
                raise ConfigError(f"{at}: quaternion [qx qy qz qw] = {arr[i, 3:].tolist()} has norm {norm:.6g}, "
                                  f"not 1 (tolerance {QUATERNION_TOLERANCE:g})")
            arr[i, 3:] /= norm
        poses[str(eff)] = arr
    gripper: dict[str, np.ndarray] = {}
    for eff, arr in traj.gripper.items():
        if eff not in poses:
            raise ConfigError(f"{where}: gripper of unknown effector {eff!r} (effectors: {list(poses)})")
        arr = np.array(arr, dtype=float).reshape(-1)
        if arr.shape != t.shape:
            raise ConfigError(f"{where}: effector {eff!r}: need {t.size} gripper openings, got {arr.size}")
        for i, g in enumerate(arr):
            if not math.isfinite(g) or g < 0:
                raise ConfigError(f"{where}: waypoint {i} (t={t[i]:g} s), effector {eff!r}: gripper opening {g} m "
                                  "must be finite and >= 0")
        gripper[str(eff)] = arr
    params = {}
    for name, value in traj.parameters.items():
        v = _number(value, f"{where}: scene.parameters.{name}")
        if not math.isfinite(v):
            raise ConfigError(f"{where}: scene.parameters.{name} = {v} is not finite")
        params[str(name)] = v
    return Trajectory(t=t, poses=poses, gripper=gripper, scene_path=traj.scene_path, scene_name=str(traj.scene_name or ""),
                      parameters=params,
                      prediction=_check_free_mapping(traj.prediction, f"{where}: prediction", numbers_only=True),
                      provenance=_check_free_mapping(traj.provenance, f"{where}: provenance", numbers_only=False),
                      frame=traj.frame)


# ----------------------------------------------------------------------------------- reading
def trajectory_from_document(doc: Any, where: str = "trajectory") -> Trajectory:
    """Parse and validate a loaded YAML document of the trajectory format (module docstring).

    Raises:
        ConfigError: wrong format/version, unknown or missing keys, bad waypoint (named by index).
    """
    if not isinstance(doc, Mapping):
        raise ConfigError(f"{where}: a trajectory file must be a YAML mapping")
    if doc.get("format") != FORMAT:
        raise ConfigError(f"{where}: 'format' must be {FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != VERSION:
        raise ConfigError(f"{where}: unsupported version {doc.get('version')!r} (this reader knows {VERSION})")
    unknown = sorted(set(doc) - set(_TOP_KEYS))
    if unknown:
        raise ConfigError(f"{where}: unknown keys {unknown} (allowed: {list(_TOP_KEYS)})")
    missing = [k for k in _REQUIRED_KEYS if k not in doc]
    if missing:
        raise ConfigError(f"{where}: missing keys {missing}")
    effectors = doc["effectors"]
    if (not isinstance(effectors, list) or not effectors or not all(isinstance(e, str) and e for e in effectors)
            or len(set(effectors)) != len(effectors)):
        raise ConfigError(f"{where}: 'effectors' must be a non-empty list of distinct names, got {effectors!r}")
    scene = doc.get("scene") or {}
    if not isinstance(scene, Mapping) or set(scene) - set(_SCENE_KEYS):
        raise ConfigError(f"{where}: 'scene' must be a mapping with keys {list(_SCENE_KEYS)}, got {scene!r}")
    if scene.get("path") is not None and not isinstance(scene.get("path"), str):
        raise ConfigError(f"{where}: scene.path must be a string or null, got {scene.get('path')!r}")
    parameters = scene.get("parameters") or {}
    if not isinstance(parameters, Mapping):
        raise ConfigError(f"{where}: scene.parameters must be a mapping of name: value")
    wps = doc["waypoints"]
    if not isinstance(wps, list) or not wps:
        raise ConfigError(f"{where}: 'waypoints' must be a non-empty list")
    t = []
    poses = {e: [] for e in effectors}
    grip_eff = set()
    for i, wp in enumerate(wps):
        if not isinstance(wp, Mapping) or "t" not in wp or "poses" not in wp or set(wp) - set(_WAYPOINT_KEYS):
            raise ConfigError(f"{where}: waypoint {i} must be a mapping with keys t, poses and optionally gripper, "
                              f"got {wp!r}")
        t.append(_number(wp["t"], f"{where}: waypoint {i}: t"))
        wp_poses = wp["poses"]
        if not isinstance(wp_poses, Mapping) or set(wp_poses) != set(effectors):
            got = sorted(wp_poses) if isinstance(wp_poses, Mapping) else wp_poses
            raise ConfigError(f"{where}: waypoint {i} (t={wp['t']}): poses must give exactly the effectors "
                              f"{effectors}, got {got!r}")
        for e in effectors:
            p = wp_poses[e]
            if not isinstance(p, list) or len(p) != 7:
                raise ConfigError(f"{where}: waypoint {i} (t={wp['t']}), effector {e!r}: pose must be a list of 7 "
                                  f"numbers [x y z qx qy qz qw], got {p!r}")
            poses[e].append([_number(v, f"{where}: waypoint {i}, effector {e!r}: pose entry") for v in p])
        g = wp.get("gripper")
        if g is not None:
            if not isinstance(g, Mapping) or set(g) - set(effectors):
                raise ConfigError(f"{where}: waypoint {i}: gripper must map effectors {effectors} to openings, got {g!r}")
            if i == 0:
                grip_eff = set(g)
            elif set(g) != grip_eff:
                raise ConfigError(f"{where}: waypoint {i}: gripper given for {sorted(g)} but waypoint 0 gives it for "
                                  f"{sorted(grip_eff)} (an effector's gripper is in every waypoint or none)")
        elif grip_eff:
            raise ConfigError(f"{where}: waypoint {i}: gripper missing (waypoint 0 gives it for {sorted(grip_eff)})")
    gripper = {e: [_number(wp["gripper"][e], f"{where}: waypoint {i}, effector {e!r}: gripper")
                   for i, wp in enumerate(wps)] for e in effectors if e in grip_eff}
    traj = Trajectory(t=np.asarray(t), poses={e: np.asarray(v) for e, v in poses.items()},
                      gripper={e: np.asarray(v) for e, v in gripper.items()},
                      scene_path=scene.get("path"), scene_name=str(scene.get("name") or ""),
                      parameters=dict(parameters), prediction=doc.get("prediction") or {},
                      provenance=doc.get("provenance") or {}, frame=doc["frame"])
    return validate_trajectory(traj, where)


def read_trajectory(path: str | Path) -> Trajectory:
    """Read and validate a ``thinshell-trajectory`` YAML file.

    Raises:
        ConfigError: missing file, invalid YAML, or any fault of :func:`trajectory_from_document`
            (the message names the file and the waypoint).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: trajectory file not found")
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: invalid YAML ({err})") from err
    return trajectory_from_document(doc, str(path))


# ----------------------------------------------------------------------------------- writing
def trajectory_to_document(traj: Trajectory) -> dict[str, Any]:
    """The YAML document of a (validated) trajectory; floats keep full precision."""
    wps = []
    for i, ti in enumerate(traj.t):
        wp: dict[str, Any] = {"t": float(ti), "poses": {e: [float(v) for v in p[i]] for e, p in traj.poses.items()}}
        if traj.gripper:
            wp["gripper"] = {e: float(g[i]) for e, g in traj.gripper.items()}
        wps.append(wp)
    return {
        "format": FORMAT, "version": VERSION, "frame": traj.frame,
        "scene": {"path": traj.scene_path, "name": traj.scene_name,
                  "parameters": {k: float(v) for k, v in traj.parameters.items()}},
        "effectors": traj.effectors, "waypoints": wps,
        "prediction": plain(traj.prediction), "provenance": plain(traj.provenance),
    }




def write_trajectory(path: str | Path, traj: Trajectory, *, force: bool = False) -> Path:
    """Validate ``traj`` and write it atomically (a temporary file in the same folder, then rename).

    Args:
        path: output file (``.yaml``).
        traj: the trajectory.
        force: replace an existing file.

    Returns:
        the path written.

    Raises:
        ConfigError: an invalid trajectory (nothing is written), or an existing file without ``force``.
    """
    path = Path(path)
    checked = validate_trajectory(traj, str(path))
    if path.exists() and not force:
        raise ConfigError(f"{path}: exists; pass force=True (--force) to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    text = "# thinshell trajectory (docs/trajectory_format.md)\n" + yaml.safe_dump(
        trajectory_to_document(checked), sort_keys=False, default_flow_style=None, width=120)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
