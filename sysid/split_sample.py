"""Whether a fitted parameter is one constant over the recording: the split-sample test over the motion's phases.

A least-squares fit reports one value per parameter and an interval from the cost's curvature (the robust sandwich,
:mod:`sysid.covariance`; the profile, :mod:`sysid.identifiability`). Both judge how *steep* the cost is at the fit, and
neither sees a cost that is steep but biased: where the model lacks a piece of physics, a parameter that shares a
balance with the missing piece takes whatever value makes up for it, and how much it must make up differs between the
parts of the motion that load it differently. That is the classic sign of misspecification a split-sample (Chow)
test reads (Chow 1960, Econometrica 28(3); Hansen 1992, J. Policy Modeling 14(4): parameter stability): fit the
parameter on one part of the data and on the rest, and compare.

**The phases** (:func:`motion_phases`) are the recording's own: the effector's recorded path, binned at the
residual's time bin, split where it changes between still and moving or where the moving direction's dominant axis or
sign changes (a press, a lift, a fold, a hold: the segments of the commanded motion); a run shorter than
:data:`MIN_PHASE_BINS` bins joins the one before it. Still means slower than :data:`STILL_FRACTION` of the path's
fastest speed. Nothing is read from a fit.

**The statistic** (:func:`split_test`), linearised at the fit, no replay. With the whitened Jacobian ``J`` and
residual ``r`` at the fit, ``B = J^T J``, the rows of phase ``k`` (``J_k``, ``r_k``, ``B_k``) and the rest (``-k``):

- the fit's one Gauss-Newton point ``u_all = u_hat - B^-1 J^T r`` (``u_hat`` where the fit reached its minimum);
- the rest's, leaving phase ``k`` out: ``u_-k = u_hat - B_-k^-1 J_-k^T r_-k``;
- ``D_k = u_-k - u_all``. Under the model (the residual noise ``n``, ``r`` linear in ``u``) ``D_k = sum_t A_t g_t`` over
  the time bins' scores ``g_t = J_t^T n_t`` with ``A_t = B^-1`` in phase ``k`` and ``B^-1 - B_-k^-1`` elsewhere, so its
  covariance is the Newey-West long-run covariance of ``A_t g_t`` (:func:`sysid.covariance.hac_meat`, the fit's lag
  window: the residual's time correlation counted), at least the white noise's ``B_-k^-1 - B^-1`` (Hausman 1978,
  Econometrica 46(6): the variance of an efficient and an inefficient estimate's difference; the floor of
  :meth:`sysid.covariance.RobustCovariance.floored`);
- ``z_kj = D_kj / sd(D_kj)``, ``N(0, 1)``-like under the model for each phase.

**The rule**: parameter ``j`` is not one constant over the recording where ``max_k |z_kj|`` exceeds
:func:`split_threshold` (the one-sided 2.3 % of :data:`sysid.identifiability.NULL_SIGMAS`, family-wise over the
phases and both signs: Bonferroni). Such a parameter is reported NOT IDENTIFIED
(:func:`sysid.identifiability.judge`'s interval widened to hold every phase's ``u_-k +- 2 sd``, clipped to the prior
range), with the phases' values in the report: the recording carries a value per phase, not the constant the
model assumes, and the interval of the whole fit would hold only the compromise. A phase whose removal leaves
``B_-k`` singular (it alone informs a parameter) is not tested.

Chosen on this simulator's own lift-and-fold (``tests/sysid/test_split_sample.py``: the tack's layer law concealed
as the model's own, and as another law), never on the reference recordings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.stats import norm

from sim_core.errors import CalibrationError
from sysid.covariance import bin_scores, hac_meat, time_bins

STILL_FRACTION = 0.1
"""The effector is still where its binned speed is below this fraction of the path's fastest (a hold between moves)."""
MIN_PHASE_BINS = 3
"""A run of the path shorter than this many residual time bins joins the phase before it (a turn's few bins are no
phase of their own)."""
SPEED_HALF_WINDOW = 2
"""The path's velocity in a bin is the central difference over this many bins on each side (the pose's noise)."""
SINGULAR = 1e-10
"""``B_-k`` counts as singular where its smallest eigenvalue is below this fraction of ``B``'s largest."""


def split_threshold(phases: int, null_sigmas: float | None = None) -> float:
    """The ``|z|`` above which :func:`split_test` excludes one constant: the one-sided tail of ``null_sigmas``
    (default :data:`sysid.identifiability.NULL_SIGMAS`, 2.3 %) spread over ``phases`` phases and both signs
    (Bonferroni). ``phases`` < 1: inf."""
    from sysid.identifiability import NULL_SIGMAS

    if phases < 1:
        return math.inf
    tail = float(norm.sf(NULL_SIGMAS if null_sigmas is None else null_sigmas))
    return float(norm.isf(tail / (2.0 * phases)))


def motion_phases(t_pose_s: np.ndarray, position: np.ndarray, bin_s: float) -> list[tuple[float, float]]:
    """The recording's phases from the effector's recorded path (module docstring).

    Args:
        t_pose_s: pose stamps ``(n,)``, s (the residual times' origin).
        position: the effector's recorded position ``(n, 3)``, m.
        bin_s: the residual's time bin, s (> 0).

    Returns:
        ``[(start_s, end_s), ...]`` covering ``[t_pose_s[0], t_pose_s[-1] + bin_s)``, in time order (one phase where the
        path never moves).

    Raises:
        CalibrationError: shapes that do not match, or fewer than two pose samples.
    """
    t = np.asarray(t_pose_s, dtype=float)
    p = np.asarray(position, dtype=float)
    if t.ndim != 1 or p.shape != (t.size, 3) or t.size < 2:
        raise CalibrationError(f"motion phases need pose stamps (n,) and positions (n, 3), n >= 2; got {t.shape}, "
                               f"{p.shape}")
    if not (math.isfinite(bin_s) and bin_s > 0.0):
        raise CalibrationError(f"motion phases need a time bin > 0 s, got {bin_s!r}")
    edges = np.arange(t[0], t[-1] + bin_s, bin_s)
    centres = edges + 0.5 * bin_s
    path = np.stack([np.interp(centres, t, p[:, a]) for a in range(3)], axis=1)
    h = SPEED_HALF_WINDOW
    n = path.shape[0]
    vel = np.zeros_like(path)
    for i in range(n):
        lo, hi = max(i - h, 0), min(i + h, n - 1)
        if hi > lo:
            vel[i] = (path[hi] - path[lo]) / ((hi - lo) * bin_s)
    speed = np.linalg.norm(vel, axis=1)
    top = float(speed.max()) if speed.size else 0.0
    if not top > 0.0:
        return [(float(edges[0]), float(edges[-1] + bin_s))]
    axis = np.argmax(np.abs(vel), axis=1)
    label = np.where(speed < STILL_FRACTION * top, -1, 2 * axis + (vel[np.arange(n), axis] > 0.0))
    runs: list[list[int]] = []  # [label, first bin, last bin]
    for i, lab in enumerate(label):
        if runs and runs[-1][0] == lab:
            runs[-1][2] = i
        else:
            runs.append([int(lab), i, i])
    merged: list[list[int]] = []
    for run in runs:
        if merged and (run[2] - run[1] + 1 < MIN_PHASE_BINS or merged[-1][0] == run[0]):
            merged[-1][2] = run[2]
        else:
            merged.append(list(run))
    if len(merged) > 1 and merged[0][2] - merged[0][1] + 1 < MIN_PHASE_BINS:
        merged[1][1] = merged[0][1]
        merged.pop(0)
    return [(float(edges[a]), float(edges[b] + bin_s)) for _, a, b in merged]


@dataclass(frozen=True)
class SplitTest:
    """:func:`split_test` for one parameter.

    Attributes:
        name: parameter name.
        phases: ``(start_s, end_s)`` of each tested phase.
        leave_out_du: the estimate without each phase ``(K,)``, search coordinate, relative to the fit.
        leave_out_sd: its 1-sigma ``(K,)`` (the robust sandwich of the rest's rows, floored at the white noise's).
        z: ``(K,)`` the difference from the whole fit in its null standard deviations.
        threshold: :func:`split_threshold` for the phases tested.
        stable: ``max |z| <= threshold``.
    """

    name: str
    phases: tuple[tuple[float, float], ...]
    leave_out_du: tuple[float, ...]
    leave_out_sd: tuple[float, ...]
    z: tuple[float, ...]
    threshold: float
    stable: bool

    def summary(self, u_hat: float = 0.0, to_value=None) -> dict[str, Any]:
        """fit.json's ``parameters.<name>.interval.split`` (``u_hat``: the fit's coordinate; ``to_value``: search
        coordinate -> parameter units)."""
        f = (lambda u: u) if to_value is None else to_value
        return {"phases_s": [list(p) for p in self.phases],
                "leave_out": [float(f(u_hat + du)) for du in self.leave_out_du],
                "z": [float(z) for z in self.z], "threshold": self.threshold, "stable": self.stable}


def _inverse(B: np.ndarray, scale: float) -> np.ndarray | None:
    w, V = np.linalg.eigh(0.5 * (B + B.T))
    if w.size == 0 or w[0] <= SINGULAR * scale:
        return None
    return (V / w) @ V.T


def split_test(names: Sequence[str], J: np.ndarray, r: np.ndarray, times_s: np.ndarray, bin_s: float, lag: int,
               phases: Sequence[tuple[float, float]] = (),
               groups: Sequence[tuple[Any, np.ndarray]] = ()) -> dict[str, SplitTest]:
    """The split-sample test of every fitted parameter over ``phases`` and ``groups`` (module docstring).

    Args:
        names: the parameters, ``(p,)`` in the columns' order.
        J: whitened Jacobian at the fit ``(m, p)``, search coordinates; r: whitened residual at the fit ``(m,)``.
        times_s: each residual's time ``(m,)``, s; bin_s: the time bin, s; lag: the lag window, bins (the fit's).
        phases: ``(start_s, end_s)`` in the residual times' origin (:func:`motion_phases`).
        groups: further ``(label, rows)`` to leave out, ``rows`` bool ``(m,)`` (e.g. a channel's residuals).

    Returns:
        name -> :class:`SplitTest` (every parameter stable where fewer than two parts hold residuals).

    Raises:
        CalibrationError: shapes that do not match, or a singular ``J^T J``.
    """
    J, r, times = np.asarray(J, dtype=float), np.asarray(r, dtype=float), np.asarray(times_s, dtype=float)
    if J.ndim != 2 or J.shape != (r.size, len(names)) or times.shape != r.shape:
        raise CalibrationError(f"split test needs J (m, p), r (m,), times (m,) for {len(names)} parameters; got "
                               f"{J.shape}, {r.shape}, {times.shape}")
    B = J.T @ J
    scale = float(np.linalg.eigvalsh(B)[-1]) if B.size else 0.0
    Binv = _inverse(B, scale)
    if Binv is None:
        raise CalibrationError("J^T W J is singular: no split-sample test")
    u_all = -Binv @ (J.T @ r)  # the whole fit's Gauss-Newton point, relative to the fit
    bins = time_bins(times, bin_s)
    parts = [((float(a), float(b)), (times >= a) & (times < b)) for a, b in phases]
    parts += [(label, np.asarray(rows, bool)) for label, rows in groups]
    tested, D, V, u_rests, sd_rest = [], [], [], [], []
    for label, mk in parts:
        if mk.shape != r.shape:
            raise CalibrationError(f"split test: group {label!r} has {mk.shape} rows for {r.size} residuals")
        if not mk.any() or mk.all():
            continue
        Br = J[~mk].T @ J[~mk]
        Brinv = _inverse(Br, scale)
        if Brinv is None:
            continue
        u_rest = -Brinv @ (J[~mk].T @ r[~mk])  # the rest's Gauss-Newton point, relative to the fit
        g_in = bin_scores(J * mk[:, None], r, bins)
        g_out = bin_scores(J * ~mk[:, None], r, bins)
        h = g_in @ Binv.T + g_out @ (Binv - Brinv).T  # A g per time bin
        var = np.maximum(np.diag(hac_meat(h, lag)), np.diag(Brinv - Binv))
        rest = np.diag(Brinv @ hac_meat(g_out, lag) @ Brinv)
        tested.append(label)
        D.append(u_rest - u_all)
        V.append(var)
        u_rests.append(u_rest)
        sd_rest.append(np.sqrt(np.maximum(rest, np.diag(Brinv))))
    threshold = split_threshold(len(tested))
    out = {}
    for j, name in enumerate(names):
        if len(tested) < 2:
            out[name] = SplitTest(name, tuple(tested), (), (), (), threshold, True)
            continue
        z = tuple(float(d[j] / math.sqrt(v[j])) if v[j] > 0.0 else 0.0 for d, v in zip(D, V))
        out[name] = SplitTest(name, tuple(tested), tuple(float(u[j]) for u in u_rests),
                              tuple(float(s[j]) for s in sd_rest), z, threshold,
                              bool(max(abs(x) for x in z) <= threshold))
    return out


def model_phases(model: Any, bin_s: float) -> list[tuple[float, float]]:
    """:func:`motion_phases` of ``model``'s recording (:class:`~sysid.observation.ObservationModel`), in its residual
    times' origin (:func:`sysid.covariance.model_residual_times`: the earliest stamp of the fitted channels).

    Raises:
        CalibrationError: no recorded pose, or a fitted channel without stamps.
    """
    ev = model.evidence
    if "pose" not in ev.t_ns or ev.pose is None:
        raise CalibrationError("the recording has no effector pose: no motion phases")
    missing = [ch for ch in model.channels if ch not in ev.t_ns]
    if missing:
        raise CalibrationError(f"no stamps for fitted channel(s) {', '.join(missing)}: no motion phases")
    t0 = min(int(np.asarray(ev.t_ns[ch])[0]) for ch in model.channels)
    t = (np.asarray(ev.t_ns["pose"], dtype=np.int64) - t0) * 1e-9
    return motion_phases(t, np.asarray(ev.pose, dtype=float)[:, :3], bin_s)
