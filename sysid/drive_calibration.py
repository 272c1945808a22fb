"""Closed-form calibration of the effector's drive along the sensor normal (no replay).

An impedance-controlled arm's measured pose lags its command by the load over its stiffness. Along
the sensor normal ``n`` (into the contact, at the recorded pose) the recorded normal load on the gel
``F_n = -F_z`` (sensor frame) then follows the recorded lag ``l = (c - p) . n`` of the command ``c`` past
the measured position ``p``:

    ``F_n = k_s l + F_0``,

``F_0`` an offset of the force sensor. Ordinary least squares of the recorded load on the recorded lag,
both at the wrench's stamps, gives the drive's stiffness ``k_s`` (N/m) and its standard error; the
drive counts as compliant (:attr:`DriveCalibration.compliant`) when the lag explains at least
:data:`DRIVE_MIN_EXPLAINED` of the load's variance and ``k_s`` is positive. A kinematic drive (the
pose equal to its command, as in this simulator's own recordings) leaves the lag at the pose noise,
explains nothing, and keeps the replay kinematic (``inf``).

On a recording made through such a drive the replay then loads the gel as the recording does
(:meth:`sysid.observation.ObservationModel.set_drive_stiffness`). The recorded wrench enters only this
fit, as it enters the sensor's gain: the replay itself takes no recorded force.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sysid.evidence import resample_pose

DRIVE_MIN_EXPLAINED = 0.9
"""Smallest fraction of the recorded normal load's variance the lag must explain (the coefficient of
determination) for the drive to count as compliant: nine tenths, a load set by the lag, not by noise."""


@dataclass(frozen=True)
class DriveCalibration:
    """The fitted drive.

    Attributes:
        stiffness: ``k_s`` (N/m) of the least-squares fit (nan when it could not be fitted).
        stiffness_sigma: its standard error, N/m.
        offset: ``F_0``, N.
        explained: coefficient of determination of the fit (-).
        samples: wrench samples used.
        compliant: whether the replay takes the drive (``explained >= DRIVE_MIN_EXPLAINED``, ``k_s > 0``).
        why: why the drive is kept kinematic ("" when compliant).
    """

    stiffness: float
    stiffness_sigma: float
    offset: float
    explained: float
    samples: int
    compliant: bool
    why: str = ""

    @property
    def replay_stiffness(self) -> float:
        """The stiffness a replay takes: :attr:`stiffness` when compliant, else ``inf`` (kinematic)."""
        return self.stiffness if self.compliant else math.inf

    def summary(self) -> dict:
        """JSON-ready."""
        return {"stiffness": float(self.stiffness), "stiffness_sigma": float(self.stiffness_sigma),
                "offset": float(self.offset), "explained": float(self.explained), "samples": int(self.samples),
                "compliant": bool(self.compliant), "replay_stiffness": float(self.replay_stiffness), "why": self.why}


def fit_drive(model) -> DriveCalibration:
    """Fit the drive of ``model``'s recording (module docstring).

    Args:
        model: the :class:`~sysid.observation.ObservationModel` (its evidence and sensor normal).

    Returns:
        the :class:`DriveCalibration`; kinematic, with the reason, when the recording has no commanded
        pose or no wrench, or the lag does not explain the load.
    """
    ev = model.evidence
    missing = [ch for ch in ("pose", "pose_cmd", "wrench") if ch not in ev.channels_present]
    if missing or model.sensor is None:
        why = f"no {', '.join(missing)} recorded" if missing else "no tactile sensor"
        return DriveCalibration(math.nan, math.nan, math.nan, 0.0, 0, False, why)
    t = np.asarray(ev.t_ns["wrench"], dtype=np.int64)
    load = -np.asarray(ev.values("wrench"), dtype=float)[:, 2]
    pose = resample_pose(ev.t_ns["pose"], ev.pose, t, outside="clamp")
    command = resample_pose(ev.t_ns["pose_cmd"], ev.pose_cmd, t, outside="clamp")
    normal = np.stack([model.sensor_normal(p) for p in pose])
    lag = np.einsum("ij,ij->i", command[:, :3] - pose[:, :3], normal)
    design = np.column_stack([lag, np.ones_like(lag)])
    coef, _, rank, _ = np.linalg.lstsq(design, load, rcond=None)
    residual = load - design @ coef
    spread = float(np.sum((load - load.mean()) ** 2))
    n = int(load.size)
    if rank < 2 or n < 3 or spread <= 0.0:
        return DriveCalibration(math.nan, math.nan, math.nan, 0.0, n, False, "the lag does not vary")
    explained = 1.0 - float(np.sum(residual ** 2)) / spread
    cov = np.linalg.inv(design.T @ design) * float(np.sum(residual ** 2)) / (n - 2)
    k, f0 = float(coef[0]), float(coef[1])
    compliant = explained >= DRIVE_MIN_EXPLAINED and k > 0.0
    why = "" if compliant else (f"the lag explains {explained:.2f} of the load's variance "
                                f"(< {DRIVE_MIN_EXPLAINED}) or k_s = {k:.3g} N/m <= 0")
    return DriveCalibration(k, float(math.sqrt(cov[0, 0])), f0, explained, n, compliant, why)
