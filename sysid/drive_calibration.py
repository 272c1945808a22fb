"""Closed-form calibration of the effector's drive along the sensor normal (no replay).

An impedance-controlled arm's measured pose lags its command by the load over its stiffness, and its
damper holds the moving tool back (Hogan 1985, "Impedance Control: An Approach to Manipulation", J.
Dyn. Syst. Meas. Control 107(1)). Along the sensor normal ``n`` (into the contact, at the recorded pose)
the recorded normal load on the gel ``F_n = -F_z`` (sensor frame) then follows the recorded lag
``l = (c - p) . n`` of the command ``c`` past the measured position ``p`` and the measured velocity
``v = dp/dt . n``:

    ``F_n = k_s l - c_d v + F_0``,

``F_0`` an offset of the force sensor; the tool's mass is left out (an arm's tool of 0.1 kg at the
press's accelerations carries under a hundredth of a newton). In free motion the load is zero and the
lag is the damper's, ``tau_d v`` with ``tau_d = c_d / k_s``. The fit reads the damper where no load acts,
from the arm's own streams: ``tau_d`` by least squares of the lag on the velocity (central differences of
the measured position) and a constant over the samples in free motion (:data:`KEEP_UP`,
:data:`FREE_LOAD_SIGMAS`), so that a delay or a lag of the tactile streams (latency, a creeping gel) does
not enter it; then ``k_s`` and ``F_0`` by least squares of the load on ``l - tau_d v``, at the wrench's
stamps, with their standard errors (``c_d = tau_d k_s``).

The data choose between the two drives by the Bayesian information criterion (Schwarz 1978, "Estimating
the dimension of a model", Ann. Stat. 6(2)) of the load's two Gaussian models: a kinematic (rigid) arm, whose
load no lag can tell (``F_n = F_0``: one parameter), against the compliant one (``k_s``, ``tau_d``, ``F_0``):
``delta_BIC = n ln(RSS_0 / RSS_1) - 2 ln n`` over the ``n`` wrench samples (:attr:`DriveCalibration.delta_bic`).
The drive counts as compliant (:attr:`DriveCalibration.compliant`) when ``delta_BIC`` exceeds
:data:`DRIVE_MIN_DELTA_BIC` (SYSID.md's threshold for an added term), the spring law describes the load (the
lag explains at least :data:`DRIVE_MIN_EXPLAINED` of its variance: a model that wins the criterion but leaves
a tenth of the load's variance is not the arm's), ``k_s`` is positive and the load lasts
:data:`DRIVE_MIN_LOADED_SAMPLES` samples. A kinematic drive (the pose equal
to its command, as in this simulator's own recordings) leaves the lag at the pose noise, explains nothing, and
keeps the replay kinematic (``inf``). Every motion takes it, lifts included: the lag explains 0.94-0.99 of
the load on the nine reference recordings, press-slides and lift-and-folds alike, at 2,856-3,017 N/m (the
reference engine's arm: 3,000 N/m; docs/benchmarks_log.md, 2026-11-27, session 50).

On a recording made through such a drive the replay then loads the gel as the recording does
(:meth:`sysid.observation.ObservationModel.set_drive_stiffness`). The recorded wrench enters only this
fit, as it enters the sensor's gain: the replay itself takes no recorded force.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sysid.command_path import anchor_path
from sysid.evidence import resample_pose

DRIVE_MIN_EXPLAINED = 0.9
"""Smallest fraction of the recorded normal load's variance the lag must explain (the coefficient of
determination) for the drive to count as compliant: nine tenths, a load set by the lag, not by noise."""

KEEP_UP = 0.5
"""A sample counts as free motion only where the tool keeps at least this share of its command's speed
along the normal: in free motion it follows the command (the damper only delays it), in contact it moves at
``k_s / (k_s + k_c)`` of it, about a tenth for a 3 N/mm arm on a 35-40 N/mm contact."""

FREE_LOAD_SIGMAS = 2.0
"""... and where the load lies within this many noise levels of its free level (no contact load)."""

LOADED_FRACTION = 0.2
"""The pad counts as loaded above this fraction of the peak normal load (the contact events' level of
:mod:`sysid.diagnose.signatures.timing`)."""

DRIVE_MIN_LOADED_SAMPLES = 20
"""Fewest wrench samples under load (above :data:`LOADED_FRACTION` of the peak) for the data to choose the
drive: 0.1 s at 200 Hz. On a handful of samples (a recording of a few steps) a press's own lag of the pose
behind its command correlates with the load as a spring's would, and the criterion cannot tell them apart."""

DRIVE_MIN_DELTA_BIC = 10.0
"""Smallest ``delta_BIC`` of the compliant drive over the kinematic one (module docstring) for the replay to
take the drive: "very strong" evidence on Kass and Raftery's scale (1995, J. Am. Stat. Assoc. 90(430)), the
threshold SYSID.md sets for accepting an added term."""


@dataclass(frozen=True)
class DriveCalibration:
    """The fitted drive.

    Attributes:
        stiffness: ``k_s`` (N/m) of the least-squares fit (nan when it could not be fitted).
        stiffness_sigma: its standard error, N/m.
        damping: ``c_d`` (N s/m) of the same fit (nan when it could not be fitted).
        damping_sigma: its standard error, N s/m.
        offset: ``F_0``, N.
        explained: coefficient of determination of the fit (-).
        residual_rms: root mean square of the load the fit leaves, N (nan when it could not be fitted).
        samples: wrench samples used.
        compliant: whether the replay takes the drive (``delta_bic > DRIVE_MIN_DELTA_BIC``,
            ``explained >= DRIVE_MIN_EXPLAINED``, ``k_s > 0``).
        why: why the drive is kept kinematic ("" when compliant).
        delta_bic: ``delta_BIC`` of the compliant drive over the kinematic one (module docstring; nan when the
            drive could not be fitted).
        slide: path length the pad travels across the sensor normal under load, m (reported, not a criterion).
    """

    stiffness: float
    stiffness_sigma: float
    damping: float
    damping_sigma: float
    offset: float
    explained: float
    samples: int
    compliant: bool
    why: str = ""
    residual_rms: float = math.nan
    delta_bic: float = math.nan
    slide: float = math.nan

    @property
    def replay_stiffness(self) -> float:
        """The stiffness a replay takes: :attr:`stiffness` when compliant, else ``inf`` (kinematic)."""
        return self.stiffness if self.compliant else math.inf

    @property
    def replay_damping(self) -> float:
        """The damping a replay takes, N s/m: :attr:`damping` when compliant and positive, else 0 (a damper
        that feeds energy in is no arm's)."""
        return max(self.damping, 0.0) if self.compliant else 0.0

    def summary(self) -> dict:
        """JSON-ready (strict JSON: a value not fitted, nan or infinite, is None)."""
        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {"stiffness": num(self.stiffness), "stiffness_sigma": num(self.stiffness_sigma),
                "damping": num(self.damping), "damping_sigma": num(self.damping_sigma),
                "replay_damping": num(self.replay_damping),
                "offset": num(self.offset), "explained": num(self.explained), "samples": int(self.samples),
                "residual_rms": num(self.residual_rms), "delta_bic": num(self.delta_bic),
                "min_delta_bic": DRIVE_MIN_DELTA_BIC, "slide_m": num(self.slide),
                "decision": "compliant" if self.compliant else "kinematic",
                "compliant": bool(self.compliant),
                "replay_stiffness": num(self.replay_stiffness),  # None: kinematic
                "why": self.why}


def _free_motion_time_constant(lag: np.ndarray, velocity: np.ndarray, command_velocity: np.ndarray,
                               load: np.ndarray, sigma: float) -> float:
    """The damper's time constant ``c_d / k_s`` (s) from the samples in free motion (module docstring): where
    the command advances into the contact, the tool keeps at least :data:`KEEP_UP` of its speed along ``n``
    and the load lies within :data:`FREE_LOAD_SIGMAS` noise levels of its median there, least squares of the
    lag on the velocity and a constant; 0 with fewer than three such samples or no speed among them. (On a
    retreat a decompressing gel lets a loaded tool keep up with its command: only the approach is read.)"""
    moving = (command_velocity > 0.0) & (velocity >= KEEP_UP * command_velocity)
    if moving.sum() < 3:
        return 0.0
    free = moving & (np.abs(load - np.median(load[moving])) <= FREE_LOAD_SIGMAS * sigma)
    if free.sum() < 3 or np.ptp(velocity[free]) <= 0.0:
        return 0.0
    coef, *_ = np.linalg.lstsq(np.column_stack([velocity[free], np.ones(int(free.sum()))]), lag[free], rcond=None)
    return float(coef[0])


def loaded_slide(pose: np.ndarray, normal: np.ndarray, load: np.ndarray) -> float:
    """Path length (m) the tool travels across the sensor normal while the normal load exceeds
    :data:`LOADED_FRACTION` of its peak: the slide of a press-and-slide.

    Args:
        pose: measured poses ``(n, 7)`` at the load's stamps, m.
        normal: unit sensor normals ``(n, 3)`` there.
        load: normal load ``(n,)``, N.
    """
    if load.size < 2 or not np.max(load) > 0.0:
        return 0.0
    step = np.diff(pose[:, :3], axis=0)
    across = step - np.einsum("ij,ij->i", step, normal[1:])[:, None] * normal[1:]
    loaded = load[1:] > LOADED_FRACTION * float(np.max(load))
    return float(np.linalg.norm(across[loaded], axis=1).sum())


def fit_drive(model) -> DriveCalibration:
    """Fit the drive of ``model``'s recording (module docstring).

    Args:
        model: the :class:`~sysid.observation.ObservationModel` (its evidence, noise levels and sensor normal).

    Returns:
        the :class:`DriveCalibration`; kinematic, with the reason, when the recording has no commanded
        pose or no wrench, or the data do not choose the compliant drive (module docstring).
    """
    ev = model.evidence
    missing = [ch for ch in ("pose", "pose_cmd", "wrench") if ch not in ev.channels_present]
    if missing or model.sensor is None:
        why = f"no {', '.join(missing)} recorded" if missing else "no tactile sensor"
        return DriveCalibration(math.nan, math.nan, math.nan, math.nan, math.nan, 0.0, 0, False, why)
    t = np.asarray(ev.t_ns["wrench"], dtype=np.int64)
    load = -np.asarray(ev.values("wrench"), dtype=float)[:, 2]
    pose = resample_pose(ev.t_ns["pose"], ev.pose, t, outside="clamp")
    command = anchor_path(ev, t)
    normal = np.stack([model.sensor_normal(p) for p in pose])
    lag = np.einsum("ij,ij->i", command[:, :3] - pose[:, :3], normal)
    n = int(load.size)
    if n < 4 or np.ptp(lag) <= 0.0:
        return DriveCalibration(math.nan, math.nan, math.nan, math.nan, math.nan, 0.0, n, False,
                                "the lag does not vary")
    seconds = (t - t[0]) * 1e-9
    velocity = np.einsum("ij,ij->i", np.gradient(pose[:, :3], seconds, axis=0), normal)
    command_velocity = np.einsum("ij,ij->i", np.gradient(command[:, :3], seconds, axis=0), normal)
    tau = _free_motion_time_constant(lag, velocity, command_velocity, load, float(model.sigma["wrench"][2]))
    design = np.column_stack([lag - tau * velocity, np.ones_like(lag)])
    coef, _, rank, _ = np.linalg.lstsq(design, load, rcond=None)
    residual = load - design @ coef
    spread = float(np.sum((load - load.mean()) ** 2))
    if rank < 2 or spread <= 0.0:
        return DriveCalibration(math.nan, math.nan, math.nan, math.nan, math.nan, 0.0, n, False,
                                "the lag does not vary")
    rss = float(np.sum(residual ** 2))
    explained = 1.0 - rss / spread
    cov = np.linalg.inv(design.T @ design) * rss / (n - 2)
    k, f0 = float(coef[0]), float(coef[1])
    k_sigma = float(math.sqrt(cov[0, 0]))
    # BIC of Gaussian models: n ln(RSS / n) + p ln n; the kinematic arm has F_0 alone (p = 1), the drive k_s,
    # tau_d and F_0 (p = 3)
    delta_bic = n * math.log(spread / max(rss, 1e-300)) - 2.0 * math.log(n)
    slide = loaded_slide(pose, normal, load)
    loaded = int(np.sum(load > LOADED_FRACTION * float(np.max(load)))) if np.max(load) > 0.0 else 0
    compliant = (delta_bic > DRIVE_MIN_DELTA_BIC and explained >= DRIVE_MIN_EXPLAINED and k > 0.0
                 and loaded >= DRIVE_MIN_LOADED_SAMPLES)
    if compliant:
        why = ""
    elif loaded < DRIVE_MIN_LOADED_SAMPLES:
        why = (f"{loaded} wrench samples under load (< {DRIVE_MIN_LOADED_SAMPLES}): too few to tell an arm's "
               "compliance from the press's own lag")
    elif not delta_bic > DRIVE_MIN_DELTA_BIC:
        why = (f"delta-BIC of the compliant drive over the kinematic one {delta_bic:.3g} <= {DRIVE_MIN_DELTA_BIC:g}: "
               "the lag of the measured pose behind its command does not tell the load")
    elif not k > 0.0:
        why = f"k_s = {k:.3g} N/m <= 0: the pose does not lag its command under load as a spring's would"
    else:
        why = f"the lag explains {explained:.2f} of the load's variance (< {DRIVE_MIN_EXPLAINED})"
    return DriveCalibration(k, k_sigma, tau * k, abs(tau) * k_sigma, f0, explained, n, compliant, why,
                            float(np.sqrt(rss / n)), float(delta_bic), slide)
