"""Whether a recording identifies a fitted parameter: one rule, the cost's profile against the null's spread.

A fitted value is a measurement only where the recording's cost rises, along that parameter (the others re-fitted),
by more than a change of cost means by chance, before the parameter leaves the range its prior leaves open. Where it
does not, the parameter is **not identified**: the report gives the interval the data can honestly give (up to the
prior's bound on the open side), never a tight sigma.

**The statistic.** Let ``e`` be the whitened residual at the fit ``u_hat`` and ``r_d`` the residual at a point of the
parameter's profile, ``u_hat + d v`` with ``v = H^-1 e_j / (H^-1)_jj`` (``H = J^T J``: the others moved to their
first-order optimum for the parameter's shift ``d``, the Schur complement's direction), after which the residual's
part the others' columns can still take is projected out (``P_o``, one more linearised refit of the others, on the
fit's Jacobian). With ``r_p = P_o r_d``, ``e_o = P_o e`` and ``g = r_p - e_o`` (what moving to the profile point
changes), suppose the truth lay at the profile point: ``r_p`` is then the noise ``n`` and ``e_o = n - g``, so the fit's
sum of squares is lower by ``Delta = |r_p|^2 - |e_o|^2 = 2 n.g - |g|^2`` and ``Delta + |g|^2 = 2 g.r_p`` has mean 0 and
standard deviation ``2 sqrt(V)``, ``V`` the long-run variance of the products ``e_i g_i`` binned in time (Newey-West
with the fit's robust lag window, :mod:`sysid.covariance`; the residual's time correlation counts, as
:func:`sysid.gel_law.null_spread` counts it for a law). Where the truth is at the fit instead, ``g.r_p = |g|^2 + e.g``
grows with the profile's change of cost. The point is excluded
where ``z = 2 g.r_p / (2 sqrt(V)) = g.r_p / sqrt(V) > NULL_SIGMAS`` (:data:`sysid.gel_law.NULL_SIGMAS`, a one-sided
test at about 2.3 % under the null, as the gel law and the tack are decided). For a residual linear in the
parameters ``g = d J v`` and ``e`` orthogonal to ``J``, so ``z = |d| / sigma_j`` with ``sigma_j`` the HAC sandwich's
1-sigma of the parameter (:func:`sysid.covariance.hac_covariance`): the profile excludes exactly what the robust
2-sigma interval excludes. It departs from it where the cost is not quadratic in the parameter: a friction above the
stick threshold of every contact it acts on changes nothing more, a buckling card makes the cost rough. Measured on
this simulator's own lift-fold (true gel-card friction 0.8, fitted alone from 0.56; docs/benchmarks_log.md, session
59, 49ident): fitted 1.016, the HAC 1-sigma 0.096 below the Gauss-Newton 0.178 (2.2 sigma from the truth, session
58's miss); with the reported covariance floored at the white noise's (:meth:`sysid.covariance.RobustCovariance.
floored`) the profile's points at the 2-sigma ends (0.71, 1.44) lie within the null's spread (z 1.90, 1.92) and the
points further out (0.50; 1.68, the prior's bound) beyond it (3.5, 2.9): the interval [0.66, 1.46] holds the truth.

**The rule** (:func:`judge`, every fitted parameter, log or linear coordinate):

1. linearised, no replay: the robust 2-sigma interval ``value +- 2 sigma_robust`` (HAC plus the propagated nuisance
   priors, as reported); a side that reaches the prior's bound is open;
2. with profile replays (:func:`profile_side`, ``sysid.fit.fit(profile_replays=N)``), for each parameter whose fitted
   value lies in its prior range: each side's point at ``2 sigma_time`` (the HAC part; at most the prior's bound) is
   replayed; where ``z`` there is
   below :data:`NULL_SIGMAS` the cost is flatter than its tangent said and the side walks out, doubling ``d``, the
   side's last replay at the prior's bound, to the first point with ``z >= NULL_SIGMAS`` (the side's end interpolated
   in ``z``; where a point of the side costs less than the fit, which is then no minimum along it, the excluded point
   itself); a side with no point excluded before the prior's bound is open (also where a replay diverged: a side not
   shown to close is not closed). The
   side's width then adds the nuisance part in quadrature. Where the linearised rule closed both sides the interval is
   the union with the linearised one (the profile only widens it); where it left a side open, the profile decides
   (a cost that rises beyond the null's spread before the prior's bound closes the side, though its tangent at the
   fit is flat);
3. a parameter is identified where neither side is open; the reported interval is clipped to the prior range (the
   prior range itself where both sides are open).

**The prior range** is what the user's data sheet leaves open around the fit's start (``thinshell sysid``: the
calibration's search range, :data:`sysid.calibration.CALIBRATION_BOUNDS`: the gel's modulus and a friction within a
factor 3, a card's bending stiffness within a factor 4); a parameter without one is judged on its search bounds (a
log parameter's within a factor 1000: the old rule "the robust 2-sigma interval reaches zero").

Nothing here is chosen from a recording: the threshold is the null's (a 2.3 % one-sided test), the prior ranges are a
data sheet's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sim_core.errors import CalibrationError
from sim_core.parameter_coordinates import ParameterSpec
from sysid.covariance import bin_scores, hac_meat, time_bins

NULL_SIGMAS = 2.0
"""A profile point is excluded where its statistic exceeds this many standard deviations under the null (the same
one-sided 2.3 % as :data:`sysid.gel_law.NULL_SIGMAS`); linearised, the robust 2-sigma interval."""
ROUND_OFF = 1.0e-6
"""Relative round-off allowed on the threshold: the first point of a side sits where a linear residual's statistic is
the threshold exactly, and a point that reaches it to round-off closes the side."""
PROFILE_GROWTH = 2.0
"""Factor by which a side's profile step grows while the cost stays within the null's spread."""


@dataclass(frozen=True)
class ProfilePoint:
    """One replayed point of a parameter's profile.

    Attributes:
        delta_u: the parameter's shift from the fit, search-coordinate units.
        value: the parameter's value there (parameter units).
        z: :func:`profile_z` there (NaN where the replay diverged).
        delta_cost: whitened sum of squares there (the others' linear refit projected out) minus the fit's.
    """

    delta_u: float
    value: float
    z: float
    delta_cost: float


@dataclass(frozen=True)
class Interval:
    """What the data say about one fitted parameter (:func:`judge`).

    Attributes:
        name: parameter name.
        value: fitted value.
        lower, upper: the reported interval (parameter units): the robust 2-sigma interval, widened where the
            replayed profile is flatter, clipped to the prior range.
        prior: ``(lower, upper)`` the prior range (parameter units).
        identified: neither side of the interval reaches the prior's bound.
        open_below, open_above: the side reaches the prior's bound (the data do not close it).
        source: ``"linearised"`` (the robust sigma) or ``"profile"`` (replayed profile points).
        points: the replayed profile points (empty for ``linearised``).
        outside_prior: the fitted value lies outside the prior range.
        split: the split-sample test over the recording's phases (:func:`sysid.split_sample.split_test`,
            :func:`split_verdict`: ``SplitTest.summary()``; None: not tested). Where it excludes one constant the
            parameter is not identified.
        law: where the recording did not part the gel's laws (:func:`law_verdict`) and the other law's fit lies
            outside the interval: ``{"fitted_with", "other", "other_value"}``; the parameter is then not identified
            apart from the law. None otherwise.
    """

    name: str
    value: float
    lower: float
    upper: float
    prior: tuple[float, float]
    identified: bool
    open_below: bool
    open_above: bool
    source: str = "linearised"
    points: tuple[ProfilePoint, ...] = field(default_factory=tuple)
    outside_prior: bool = False
    split: dict[str, Any] | None = None
    law: dict[str, Any] | None = None

    @property
    def unstable(self) -> bool:
        """The split-sample test excluded one constant over the recording's phases."""
        return bool(self.split is not None and not self.split["stable"])

    def words(self) -> str:
        """The verdict in words (the report's and the CLI's)."""
        span = f"[{self.lower:.4g}, {self.upper:.4g}]"
        if self.identified:
            return f"identified, {span} ({self.source})"
        if self.law is not None:
            return (f"NOT IDENTIFIED apart from the gel's law: the recording does not part the laws (the delta-BIC "
                    f"within the null's spread) and {self.law['other']} puts it at {self.law['other_value']:.4g}, "
                    f"outside {self.law['fitted_with']}'s interval; the data give {span} (both laws' intervals, "
                    f"clipped to the prior range [{self.prior[0]:.4g}, {self.prior[1]:.4g}])")
        if self.unstable:
            phases = ", ".join(f"{a:.2f}-{b:.2f} s: {v:.4g} (z {z:+.2f})" for (a, b), v, z in
                               zip(self.split["phases_s"], self.split["leave_out"], self.split["z"]))
            return (f"NOT IDENTIFIED as one constant: fitted without each phase of the motion it moves by more than "
                    f"the null allows (|z| > {self.split['threshold']:.3g}; without {phases}): the model's missing "
                    f"physics enters it differently in each phase; the data give {span} (every phase's 2-sigma "
                    f"interval, clipped to the prior range [{self.prior[0]:.4g}, {self.prior[1]:.4g}])")
        sides = [s for s, o in (("below", self.open_below), ("above", self.open_above)) if o]
        text = (f"NOT IDENTIFIED: the cost does not rise beyond the null's spread {' or '.join(sides)} the fit within "
                f"the prior range [{self.prior[0]:.4g}, {self.prior[1]:.4g}]; the data give {span} ({self.source})")
        if self.outside_prior:
            text += "; the fitted value lies outside the prior range"
        return text

    def summary(self) -> dict[str, Any]:
        """fit.json's ``fit.parameters.<name>.interval``."""
        return {"lower": self.lower, "upper": self.upper, "prior": list(self.prior), "identified": self.identified,
                "open_below": self.open_below, "open_above": self.open_above, "source": self.source,
                "outside_prior": self.outside_prior, "split": self.split, "law": self.law,
                "profile": [{"delta_u": p.delta_u, "value": p.value, "z": p.z, "delta_cost": p.delta_cost}
                            for p in self.points]}


def prior_ranges(start: Mapping[str, float], table: Mapping[str, tuple[str, float, float]]) -> dict[str, tuple[float, float]]:
    """Prior range ``name -> (lower, upper)`` (parameter units) of each parameter of ``start`` listed in ``table``
    (``(kind, low, high)`` as :data:`sysid.calibration.CALIBRATION_BOUNDS`: ``factor`` times the start, ``absolute``,
    or ``offset`` plus the start).

    Raises:
        CalibrationError: an unknown kind, or a range that does not contain the start.
    """
    out: dict[str, tuple[float, float]] = {}
    for name, value in start.items():
        if name not in table:
            continue
        kind, low, high = table[name]
        value = float(value)
        if kind == "factor":
            lo, hi = sorted((value * low, value * high))
        elif kind == "offset":
            lo, hi = value + low, value + high
        elif kind == "absolute":
            lo, hi = float(low), float(high)
        else:
            raise CalibrationError(f"prior range of {name}: unknown kind {kind!r} (factor, offset, absolute)")
        if not lo <= value <= hi:
            raise CalibrationError(f"prior range of {name}: [{lo:.6g}, {hi:.6g}] does not contain its start {value:.6g}")
        out[name] = (lo, hi)
    return out


def prior_of(spec: ParameterSpec, prior: Mapping[str, tuple[float, float]] | None) -> tuple[float, float]:
    """The prior range of ``spec``: ``prior[name]`` within the search bounds, else the search bounds."""
    lo, hi = (prior or {}).get(spec.name, (spec.lower, spec.upper))
    return max(float(lo), spec.lower), min(float(hi), spec.upper)


def linearised(spec: ParameterSpec, value: float, sigma_robust: float | None,
               prior: tuple[float, float]) -> Interval:
    """Rule 1 of the module docstring: the robust 2-sigma interval ``value +- 2 sigma_robust`` against ``prior``
    (``sigma_robust`` None or not finite: both sides open)."""
    lo_p, hi_p = prior
    if sigma_robust is None or not math.isfinite(sigma_robust):
        lo_d, hi_d = -math.inf, math.inf
    else:
        lo_d, hi_d = value - 2.0 * sigma_robust, value + 2.0 * sigma_robust
    return _clipped(spec.name, value, lo_d, hi_d, prior, "linearised", ())


def _clipped(name: str, value: float, lo_d: float, hi_d: float, prior: tuple[float, float], source: str,
             points: Sequence[ProfilePoint]) -> Interval:
    lo_p, hi_p = prior
    open_below, open_above = lo_d <= lo_p, hi_d >= hi_p
    lo, hi = max(lo_d, lo_p), min(hi_d, hi_p)
    outside = not lo_p <= value <= hi_p
    if lo > hi:  # the data's interval lies beyond the prior range: the data's, flagged
        lo, hi = lo_d, hi_d
    return Interval(name, float(value), float(lo), float(hi), (float(lo_p), float(hi_p)),
                    not (open_below or open_above or outside), bool(open_below), bool(open_above), source,
                    tuple(points), bool(outside))


def profile_direction(J: np.ndarray, j: int) -> np.ndarray:
    """``v = H^-1 e_j / (H^-1)_jj`` ``(p,)``, ``H = J^T J`` of the whitened Jacobian ``J`` ``(m, p)``: the shift of every
    coordinate per unit shift of coordinate ``j`` with the others at their first-order optimum.

    Raises:
        CalibrationError: a singular ``J^T J``.
    """
    H = J.T @ J
    w, V = np.linalg.eigh(H)
    if w.size == 0 or w[-1] <= 0.0 or w[0] <= 1e-12 * w[-1]:
        raise CalibrationError(f"J^T W J is singular (eigenvalues {w.tolist()}): no profile direction")
    col = (V / w) @ V[j]
    return col / col[j]


def null_sd(e: np.ndarray, g: np.ndarray, times_s: np.ndarray, bin_s: float, lag: int) -> float:
    """``sqrt(V)``: the long-run standard deviation of ``e.g`` for noise ``e`` with its own time correlation (Newey-West,
    Bartlett weights up to ``lag`` bins, :func:`sysid.covariance.hac_meat`), at least the white unit noise's ``|g|``
    (the whitened residual holds at least the sensor's noise; :meth:`sysid.covariance.RobustCovariance.floored`);
    ``e``, ``g`` ``(m,)`` whitened, ``times_s`` ``(m,)`` s."""
    g = np.asarray(g, dtype=float)
    scores = bin_scores(g[:, None], np.asarray(e, dtype=float), time_bins(times_s, bin_s))
    return float(math.sqrt(max(float(hac_meat(scores, int(lag))[0, 0]), float(g @ g))))


def profile_z(r_point: np.ndarray, e: np.ndarray, J_others: np.ndarray, times_s: np.ndarray, bin_s: float,
              lag: int) -> tuple[float, float]:
    """The profile statistic ``z = g.r_p / sqrt(V)`` at a profile point (module docstring) and ``|r_p|^2 - |e_o|^2``.

    Args:
        r_point: whitened residual at the profile point ``(m,)``.
        e: whitened residual at the fit ``(m,)``.
        J_others: whitened Jacobian of the other coordinates at the fit ``(m, p - 1)`` (may have no column).
        times_s, bin_s, lag: residual times (s), time bin (s) and lag window (bins) of :func:`null_sd`.

    Returns:
        ``(z, delta_cost)``; z is ``inf`` where the null's spread is zero and ``g`` is not.
    """
    r_point, e = np.asarray(r_point, dtype=float), np.asarray(e, dtype=float)
    if J_others.shape[1]:
        Q = np.linalg.qr(J_others)[0]
        r_p, e_o = r_point - Q @ (Q.T @ r_point), e - Q @ (Q.T @ e)
    else:
        r_p, e_o = r_point, e
    g = r_p - e_o
    s = null_sd(e_o, g, times_s, bin_s, lag)
    num = float(g @ r_p)
    z = num / s if s > 0.0 else (math.inf if num > 0.0 else 0.0)
    return z, float(r_p @ r_p - e_o @ e_o)


def profile_side(residual: Callable[[np.ndarray], np.ndarray | None], u_hat: np.ndarray, v: np.ndarray, j: int,
                 spec: ParameterSpec, sign: float, first_u: float, bound_u: float, e: np.ndarray,
                 J_others: np.ndarray, times_s: np.ndarray, bin_s: float, lag: int, replays: int,
                 known: Mapping[float, np.ndarray | None] | None = None) -> tuple[float, bool, list[ProfilePoint]]:
    """One side of a parameter's profile (rule 2 of the module docstring).

    Args:
        residual: whitened residual at a point of the search coordinates ``(p,)`` (None where the replay diverged).
        u_hat: the fit ``(p,)``; v: :func:`profile_direction` ``(p,)``; j: the parameter's index; spec: its coordinate.
        sign: +1 (above the fit) or -1 (below).
        first_u: the first point's distance from the fit (> 0, search units): the linearised 2-sigma (HAC part).
        bound_u: the distance to the prior's bound on this side (> 0, search units).
        e, J_others, times_s, bin_s, lag: as :func:`profile_z`.
        replays: most replays on this side.
        known: residuals already replayed, by distance (the first point's, replayed beside the other parameters').

    Returns:
        ``(width_u, open, points)``: the side's end and whether it is open, and the points replayed. Where the first
        point is excluded, the end is where ``z`` reaches ``NULL_SIGMAS`` on the line through the fit (``z`` grows in
        proportion to ``d`` where the cost is quadratic); where the side walked out, interpolated linearly in ``z``
        between the last point within the null's spread and the first beyond it, except where a point of the side
        costs less than the fit (the fit is no minimum along it: a rough cost), where the end is the first excluded
        point itself. Open where that end is the prior's bound, where no point is excluded before it, or where a
        replay diverged.
    """
    points: list[ProfilePoint] = []
    last_d, last_z, cheaper = 0.0, 0.0, False
    d = min(first_u, bound_u)
    for k in range(max(int(replays), 0)):
        u = np.asarray(u_hat, dtype=float) + sign * d * v
        r = (known or {}).get(d) if k == 0 and known is not None and d in known else residual(u)
        if r is None:
            points.append(ProfilePoint(sign * d, spec.to_value(float(u[j])), math.nan, math.nan))
            return bound_u, True, points
        z, dc = profile_z(r, e, J_others, times_s, bin_s, lag)
        points.append(ProfilePoint(sign * d, spec.to_value(float(u[j])), z, dc))
        cheaper = cheaper or dc < 0.0
        if z >= NULL_SIGMAS * (1.0 - ROUND_OFF):
            if not k:  # on the line through the fit (z proportional to d where the cost is quadratic)
                return float(d * min(NULL_SIGMAS / z, 1.0)) if math.isfinite(z) else float(d), False, points
            if cheaper or not math.isfinite(z):  # the fit is no minimum along it: nothing interpolated
                return (bound_u, True, points) if d >= bound_u else (float(d), False, points)
            width = last_d + (d - last_d) * (NULL_SIGMAS - last_z) / (z - last_z)
            return float(min(max(width, last_d), d)), False, points
        if d >= bound_u:
            return bound_u, True, points
        last_d, last_z = d, z
        d = bound_u if k + 2 >= replays else min(PROFILE_GROWTH * d, bound_u)  # the last replay at the bound
    return bound_u, True, points


def judge(specs: Sequence[ParameterSpec], values: Mapping[str, float], sigma_robust: Mapping[str, float] | None,
          prior: Mapping[str, tuple[float, float]] | None = None) -> dict[str, Interval]:
    """Rule 1 (linearised) for every parameter of ``specs`` (module docstring): name -> :class:`Interval`.

    Args:
        specs: the fitted parameters' coordinates; values: fitted value per name.
        sigma_robust: robust 1-sigma per name (None: every side open).
        prior: name -> prior range (parameter units; :func:`prior_ranges`); a name without one: its search bounds.
    """
    return {s.name: linearised(s, float(values[s.name]), (sigma_robust or {}).get(s.name), prior_of(s, prior))
            for s in specs}


def profiled(spec: ParameterSpec, value: float, u_hat_j: float, linear: Interval, width_lo: float, width_hi: float,
             open_lo: bool, open_hi: bool, points: Sequence[ProfilePoint]) -> Interval:
    """The :class:`Interval` of rule 2 from the two sides' widths (search units, the nuisance part added), clipped to
    the prior range; a side :func:`profile_side` left open reaches the prior's bound. Where the linearised rule closed
    both sides the interval is the union with the linearised one (the replays widen a tangent's interval, they do not
    narrow it); where it left a side open the replayed profile decides alone (the quadratic extrapolated to the prior's
    bound is not evidence that the cost stays flat there)."""
    lo_p, hi_p = spec.to_value(u_hat_j - width_lo), spec.to_value(u_hat_j + width_hi)
    if linear.identified:
        lo_p, hi_p = min(lo_p, linear.lower), max(hi_p, linear.upper)
    lo_d = -math.inf if open_lo else lo_p
    hi_d = math.inf if open_hi else hi_p
    return _clipped(spec.name, value, lo_d, hi_d, linear.prior, "profile", points)


def profile_intervals(residual: Callable[[np.ndarray], np.ndarray | None], specs: Sequence[ParameterSpec],
                      u_hat: np.ndarray, J: np.ndarray, e: np.ndarray, robust: Any, linear: Mapping[str, Interval],
                      times_s: np.ndarray, bin_s: float, replays: int,
                      many: Callable[[list[np.ndarray]], list[np.ndarray | None]] | None = None) -> dict[str, Interval]:
    """Rule 2 of the module docstring for every parameter the linearised rule identifies (the others keep their
    :class:`Interval` of ``linear``).

    Args:
        residual: whitened residual at a point of the search coordinates ``(p,)``, None where the replay diverged.
        specs: the fitted parameters' coordinates; u_hat: the fit ``(p,)``.
        J: whitened Jacobian at the fit ``(m, p)``; e: whitened residual at the fit ``(m,)``.
        robust: the fit's :class:`sysid.covariance.RobustCovariance` (its lag window; its time-correlation part, and
            the nuisance part added to the profile's widths in quadrature).
        linear: :func:`judge`'s intervals.
        times_s, bin_s: residual times ``(m,)`` and time bin, s (:func:`sysid.covariance.model_residual_times`).
        replays: most replays on each side of each parameter.
        many: residuals of several points at once (replayed side by side where it can; None: one by one): the first
            point of every side.

    Raises:
        CalibrationError: a singular ``J^T J``.
    """
    u_hat = np.asarray(u_hat, dtype=float)
    cov = np.asarray(robust.covariance_u, dtype=float)
    time_cov = cov if robust.time_covariance_u is None else np.asarray(robust.time_covariance_u, dtype=float)
    s_time = np.sqrt(np.maximum(np.diag(time_cov), 0.0))
    s_nuis2 = np.maximum(np.diag(cov) - np.diag(time_cov), 0.0)
    out = dict(linear)
    plan = []
    for j, spec in enumerate(specs):
        iv = linear[spec.name]
        if iv.outside_prior or replays < 1 or not s_time[j] > 0.0:
            continue
        bounds = (u_hat[j] - spec.to_u(iv.prior[0]), spec.to_u(iv.prior[1]) - u_hat[j])
        plan.append((j, spec, profile_direction(J, j), bounds))
    firsts = {}
    points = [(j, sign, u_hat + sign * min(2.0 * s_time[j], b[k]) * v)
              for j, spec, v, b in plan for k, sign in enumerate((-1.0, 1.0))]
    if many is not None and points:
        for (j, sign, _), r in zip(points, many([u for _, _, u in points])):
            firsts[(j, sign)] = r
    for j, spec, v, bounds in plan:
        J_others = np.delete(J, j, axis=1)
        sides = []
        for k, sign in enumerate((-1.0, 1.0)):
            first = min(2.0 * s_time[j], bounds[k])
            known = {first: firsts[(j, sign)]} if (j, sign) in firsts else None
            width, is_open, pts = profile_side(residual, u_hat, v, j, spec, sign, first, bounds[k], e, J_others,
                                               times_s, bin_s, robust.lag_bins, replays, known)
            total = math.sqrt(width ** 2 + 4.0 * s_nuis2[j])  # a nuisance part past the prior's bound opens the side
            sides.append((min(total, bounds[k]), is_open or total >= bounds[k], pts))
        (w_lo, open_lo, p_lo), (w_hi, open_hi, p_hi) = sides
        out[spec.name] = profiled(spec, linear[spec.name].value, float(u_hat[j]), linear[spec.name], w_lo, w_hi,
                                  open_lo, open_hi, [*reversed(p_lo), *p_hi])
    return out


def _value(spec: ParameterSpec, u: float) -> float:
    """``spec``'s value at ``u`` held within its search bounds (a nearly flat direction's shift would overflow)."""
    lo, hi = spec.u_bounds
    return spec.to_value(min(max(float(u), lo), hi))


def split_verdict(specs: Sequence[ParameterSpec], u_hat: np.ndarray, intervals: Mapping[str, Interval],
                  tests: Mapping[str, Any]) -> dict[str, Interval]:
    """The intervals with the split-sample test's verdict (:mod:`sysid.split_sample`): a parameter whose value moves
    between the recording's phases by more than the null allows is not identified, its interval widened to hold
    every phase-left-out estimate's 2-sigma interval (search coordinate), clipped to the prior range; the others keep
    their interval, the test recorded.

    Args:
        specs: the fitted parameters' coordinates; u_hat: the fit ``(p,)``, search coordinates.
        intervals: name -> :class:`Interval` (:func:`judge` or :func:`profile_intervals`).
        tests: name -> :class:`sysid.split_sample.SplitTest`.
    """
    out = dict(intervals)
    for j, spec in enumerate(specs):
        test, iv = tests.get(spec.name), intervals[spec.name]
        if test is None:
            continue
        summary = test.summary(float(u_hat[j]), lambda u, spec=spec: _value(spec, u))
        if test.stable:
            out[spec.name] = replace(iv, split=summary)
            continue
        lows = [float(u_hat[j]) + du - 2.0 * sd for du, sd in zip(test.leave_out_du, test.leave_out_sd)]
        highs = [float(u_hat[j]) + du + 2.0 * sd for du, sd in zip(test.leave_out_du, test.leave_out_sd)]
        lo = min([_value(spec, min(lows))] + ([iv.lower] if math.isfinite(iv.lower) else []))
        hi = max([_value(spec, max(highs))] + ([iv.upper] if math.isfinite(iv.upper) else []))
        widened = _clipped(spec.name, iv.value, lo, hi, iv.prior, iv.source, iv.points)
        out[spec.name] = replace(widened, identified=False, split=summary)
    return out


def law_verdict(intervals: Mapping[str, Interval], chosen: str, other: str, decided: bool,
                fitted: Mapping[str, Mapping[str, float]]) -> dict[str, Interval]:
    """The intervals with the gel law's structural uncertainty (model uncertainty: Draper 1995, JRSS B 57(1)):
    where the recording did not part the laws (``decided`` False: the other law fitted better, but within the
    null's spread of the delta-BIC, :class:`sysid.gel_law.GelLawChoice`), a parameter whose value under the other law
    (its step at the fit's start, ``fitted[other]``) lies outside the interval fitted with ``chosen`` is not
    identified apart from the law: its interval widened to hold the other law's value with the same relative
    2-sigma half-widths (log coordinates), clipped to the prior range. Decided choices and parameters inside their
    interval are returned as they are.

    Args:
        intervals: name -> :class:`Interval` of the fit made with ``chosen``.
        chosen, other: the law replayed and the other law compared.
        decided: :attr:`sysid.gel_law.GelLawChoice.decided`.
        fitted: law -> name -> value (parameter units) after each law's step.
    """
    out = dict(intervals)
    values = fitted.get(other) or {}
    if decided or not values:
        return out
    for name, iv in intervals.items():
        v_o = values.get(name)
        if v_o is None or not (v_o > 0.0 and iv.value > 0.0 and iv.lower > 0.0) or iv.lower <= v_o <= iv.upper:
            continue
        lo = min(iv.lower, v_o * iv.lower / iv.value)
        hi = max(iv.upper, v_o * iv.upper / iv.value)
        widened = _clipped(name, iv.value, lo, hi, iv.prior, iv.source, iv.points)
        out[name] = replace(widened, identified=False, split=iv.split,
                            law={"fitted_with": chosen, "other": other, "other_value": float(v_o)})
    return out


RECORD_TO_IDENTIFY = {
    "sheet.bending_stiffness": "a motion that bends the card beyond the pad: a lift that carries it or a fold "
                               "(under a press-slide the card lies flat between pad and table)",
    "friction.gel_sheet": "a slide of the gel over the card under a steady load, long enough to slip (a lift whose "
                          "card never slides on the gel does not load it)",
    "gel.youngs_modulus": "a press to a known depth with the force recorded",
}
"""What a user must record to identify a parameter a recording left unidentified (the report's advice)."""


def lower_cost_note(interval: Interval) -> str | None:
    """A warning where a replayed point of the parameter's profile costs less than the fit (the fit did not reach the
    cost's minimum along it: a rough cost, or a stop before the minimum), else None."""
    better = [p for p in interval.points if math.isfinite(p.delta_cost) and p.delta_cost < 0.0]
    if not better:
        return None
    best = min(better, key=lambda p: p.delta_cost)
    return (f"{interval.name}: a point of its profile at {best.value:.4g} costs less than the fit at {interval.value:.4g} "
            f"(whitened sum of squares {best.delta_cost:.4g}, the others re-fitted to first order): the fit did not "
            "reach the cost's minimum along it, so its value is where the fit stopped, not the best the data allow")


def not_identified_note(interval: Interval) -> str:
    """The warning for a parameter the recording does not identify: its interval, the prior range and what to
    record."""
    what = RECORD_TO_IDENTIFY.get(interval.name, "a motion that loads it")
    return (f"{interval.name} is not identified by this recording: {interval.words()}; the fitted value "
            f"{interval.value:.4g} is where the fit stopped along a direction the data barely see, not a measurement. "
            f"Keep the data-sheet value (leave it out of --params) or record {what}")
