"""Effector trajectories for headless runs: files (YAML / CSV) and scripted ones derived from a scene.

File formats (poses ``x y z qx qy qz qw`` in ``world``, m; t in s, increasing; between waypoints the
position is interpolated linearly and the orientation by slerp; before the first / after the last
waypoint the pose is held):

YAML::

    version: 1
    effector: ee                 # optional; default: the scene's first effector
    waypoints:
      - {t: 0.0, pose: [0.06, 0.0, 0.004, 1.0, 0.0, 0.0, 0.0]}
      - {t: 0.5, pose: [0.06, 0.0, -0.0005, 1.0, 0.0, 0.0, 0.0], gripper: 0.02}   # gripper optional (m)

CSV (header required, ``gripper`` column optional; ``#`` lines are comments)::

    t,x,y,z,qx,qy,qz,qw
    0.0,0.06,0.0,0.004,1,0,0,0

Scripted (``press_slide``, ``press_slide_lift``): from the initial effector/sensor pose, approach the
sheet along the sensor's outward normal until the gel surface touches the top of the sheet, press
``depth`` further, hold, slide ``slide`` along world +x, and (``_lift``) return to the start height.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sim_core.errors import ConfigError
from sim_core.trajectory_file import read_trajectory
from sim_core.transforms import quat_from_rotvec, quat_multiply, quat_to_matrix, quat_to_rotvec

SCRIPTED = ("press_slide", "press_slide_lift")
_CSV_COLUMNS = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")


@dataclass(frozen=True)
class Trajectory:
    """Waypoints of one effector.

    Attributes:
        effector: effector name (None: the scene's first effector).
        t: waypoint times in s, strictly increasing, shape ``(n,)``.
        poses: waypoint poses ``[x y z qx qy qz qw]``, shape ``(n, 7)``, unit quaternions.
        gripper: finger openings in m, shape ``(n,)``, or None.
    """

    effector: str | None
    t: np.ndarray
    poses: np.ndarray
    gripper: np.ndarray | None = None

    @property
    def duration(self) -> float:
        """Time of the last waypoint in s."""
        return float(self.t[-1])

    def sample(self, t: float) -> np.ndarray:
        """Pose at time ``t`` (s): linear in position, slerp in orientation, held outside the range."""
        if t <= self.t[0]:
            return self.poses[0].copy()
        if t >= self.t[-1]:
            return self.poses[-1].copy()
        i = int(np.searchsorted(self.t, t, side="right")) - 1
        a = (t - self.t[i]) / (self.t[i + 1] - self.t[i])
        p0, p1 = self.poses[i], self.poses[i + 1]
        q0, q1 = p0[3:], p1[3:] if np.dot(p0[3:], p1[3:]) >= 0 else -p1[3:]
        rel = quat_to_rotvec(quat_multiply(q1, q0 * np.array([-1, -1, -1, 1])))
        q = quat_multiply(quat_from_rotvec(a * rel), q0)
        return np.concatenate([(1 - a) * p0[:3] + a * p1[:3], q / np.linalg.norm(q)])

    def sample_gripper(self, t: float) -> float | None:
        """Finger opening at ``t`` (linear interpolation), or None when the trajectory has none."""
        return None if self.gripper is None else float(np.interp(t, self.t, self.gripper))


def _validated(effector: str | None, t: Any, poses: Any, gripper: Any, where: str) -> Trajectory:
    t = np.asarray(t, dtype=float)
    poses = np.asarray(poses, dtype=float)
    if t.ndim != 1 or t.size < 1 or poses.shape != (t.size, 7):
        raise ConfigError(f"{where}: need n times and n poses of 7 numbers, got {t.shape} and {poses.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(poses))):
        raise ConfigError(f"{where}: non-finite time or pose")
    if np.any(np.diff(t) <= 0) or t[0] < 0:
        raise ConfigError(f"{where}: times must be >= 0 and strictly increasing, got {t.tolist()}")
    norms = np.linalg.norm(poses[:, 3:], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1) > 1e-3)
    if bad.size:
        raise ConfigError(f"{where}: waypoint {int(bad[0])} has quaternion norm {norms[bad[0]]:.6g}, not 1")
    poses[:, 3:] /= norms[:, None]
    if gripper is not None:
        gripper = np.asarray(gripper, dtype=float)
        if gripper.shape != t.shape or not np.all(np.isfinite(gripper)) or np.any(gripper < 0):
            raise ConfigError(f"{where}: gripper openings must be n finite values >= 0")
    return Trajectory(effector, t, poses, gripper)


def _from_trajectory_file(path: Path) -> Trajectory:
    """A one-effector ``thinshell-trajectory`` file (``docs/trajectory_format.md``) as a :class:`Trajectory`."""
    traj = read_trajectory(path)
    if len(traj.effectors) != 1:
        raise ConfigError(f"{path}: a headless run plays one effector; the file has {traj.effectors}")
    (effector,) = traj.effectors
    return Trajectory(effector, traj.t, traj.poses[effector], traj.gripper.get(effector))


def load_trajectory(path: str | Path) -> Trajectory:
    """Read a YAML (``.yaml``/``.yml``) or CSV (``.csv``) trajectory file (module docstring), or a
    one-effector ``thinshell-trajectory`` file (``docs/trajectory_format.md``, what ``thinshell deploy`` plays).

    Raises:
        ConfigError: missing file, unknown keys, bad values (the message names the file).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: trajectory file not found")
    if path.suffix.lower() == ".csv":
        rows = [r for r in csv.reader(line for line in path.read_text().splitlines() if line.strip()
                                      and not line.lstrip().startswith("#"))]
        if not rows:
            raise ConfigError(f"{path}: empty CSV trajectory")
        header = [h.strip() for h in rows[0]]
        missing = [c for c in _CSV_COLUMNS if c not in header]
        unknown = [c for c in header if c not in (*_CSV_COLUMNS, "gripper")]
        if missing or unknown:
            raise ConfigError(f"{path}: CSV header must be {','.join(_CSV_COLUMNS)}[,gripper]; missing {missing}, "
                              f"unknown {unknown}")
        try:
            data = np.array([[float(v) for v in r] for r in rows[1:]], dtype=float).reshape(-1, len(header))
        except ValueError as err:
            raise ConfigError(f"{path}: non-numeric CSV value ({err})") from err
        col = {h: data[:, i] for i, h in enumerate(header)}
        poses = np.stack([col[c] for c in _CSV_COLUMNS[1:]], axis=1)
        return _validated(None, col["t"], poses, col.get("gripper"), str(path))
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: invalid YAML ({err})") from err
    if isinstance(doc, dict) and doc.get("format") == "thinshell-trajectory":
        return _from_trajectory_file(path)
    if not isinstance(doc, dict) or doc.get("version") != 1:
        raise ConfigError(f"{path}: trajectory must be a mapping with 'version: 1'")
    unknown = set(doc) - {"version", "effector", "waypoints"}
    if unknown:
        raise ConfigError(f"{path}: unknown keys {sorted(unknown)}")
    wps = doc.get("waypoints")
    if not isinstance(wps, list) or not wps:
        raise ConfigError(f"{path}: 'waypoints' must be a non-empty list")
    for i, wp in enumerate(wps):
        if not isinstance(wp, dict) or not {"t", "pose"} <= set(wp) or set(wp) - {"t", "pose", "gripper"}:
            raise ConfigError(f"{path}: waypoints[{i}] must have keys t, pose and optionally gripper, got {wp!r}")
    has_grip = [("gripper" in wp) for wp in wps]
    if any(has_grip) and not all(has_grip):
        raise ConfigError(f"{path}: 'gripper' must be given for every waypoint or none")
    try:
        return _validated(doc.get("effector"), [wp["t"] for wp in wps], [wp["pose"] for wp in wps],
                          [wp["gripper"] for wp in wps] if all(has_grip) else None, str(path))
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{path}: bad waypoint values ({err})") from err


def scripted_trajectory(name: str, effector_pose: np.ndarray, sensor_pose: np.ndarray, sheet_top: float,
                        depth: float = 1.0e-3, slide: float = 0.015, approach_speed: float = 0.02,
                        press_speed: float = 0.005, slide_speed: float = 0.02, hold: float = 0.05,
                        effector: str | None = None) -> Trajectory:
    """A press-and-slide trajectory computed from the scene geometry (module docstring).

    Args:
        name: ``press_slide`` or ``press_slide_lift``.
        effector_pose: initial effector pose ``(7,)`` in ``world``.
        sensor_pose: initial sensor-frame pose ``(7,)`` (its z axis is the gel's outward normal).
        sheet_top: world z of the sheet's upper surface, m.
        depth: press depth beyond first contact, m.
        slide: slide distance along world +x, m.
        approach_speed, press_speed, slide_speed: m/s; hold: s.
        effector: effector name.

    Raises:
        ConfigError: unknown name, or a sensor that does not face down onto the sheet.
    """
    if name not in SCRIPTED:
        raise ConfigError(f"unknown scripted trajectory {name!r} (known: {list(SCRIPTED)})")
    n = quat_to_matrix(np.asarray(sensor_pose[3:7], float))[:, 2]
    if n[2] > -0.5:
        raise ConfigError(f"{name}: the sensor's normal {n.round(3).tolist()} does not face down onto the sheet")
    gap = (sheet_top - sensor_pose[2]) / n[2]
    if gap < 0:
        raise ConfigError(f"{name}: the gel surface starts {-gap * 1e3:.3g} mm inside the sheet")
    start = np.asarray(effector_pose, dtype=float)
    touch = start.copy()
    touch[:3] += gap * n
    pressed = touch.copy()
    pressed[:3] += depth * n
    slid = pressed.copy()
    slid[0] += slide
    t = [0.0, gap / approach_speed]
    poses = [start, touch]
    t += [t[-1] + depth / press_speed, t[-1] + depth / press_speed + hold]
    poses += [pressed, pressed]
    t.append(t[-1] + slide / slide_speed)
    poses.append(slid)
    if name == "press_slide_lift":
        lifted = slid.copy()
        lifted[2] = start[2]
        t.append(t[-1] + (start[2] - slid[2]) / approach_speed)
        poses.append(lifted)
    keep = [0] + [i for i in range(1, len(t)) if t[i] - t[i - 1] > 1e-9]  # e.g. no approach when already touching
    return _validated(effector, [t[i] for i in keep], [poses[i] for i in keep], None, name)
