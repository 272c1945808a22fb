"""The gel tack's compliant shear layer fitted from a carried card: ``k_t`` searched on the sheet points up to the peel.

Shared by the lift's nominal model (:mod:`sysid.diagnose.tack`, ``thinshell sysid --tack``) and the diagnosis' plasticity refit
(:func:`sysid.diagnose.plasticity_refit.tack_base`), which both need a card held by the gel in shear, as a real gel's
adhesive layer holds it: normal-only bonds let the card slide along the gel face, so a lift-and-fold replay stays a
straight ramp where the recorded card arches and folds. The layer's physics is
:mod:`sim_core.candidates.adhesion` (shear compliance); the search is :func:`fit_shear_layer`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_core.errors import SimulationDivergedError
from sysid.diagnose.candidates import ADHESION_PROBE_WEIGHTS
from sysid.diagnose.peel import ADHESION_PARAMETER

SHEAR_STIFFNESS_SETTING = "candidate.adhesion.shear_stiffness"
"""The tack's compliant layer: tangential stiffness ``k_t``, N/m per bonded pair
(:mod:`sim_core.candidates.adhesion`)."""

NORMAL_RATIO_SETTING = "candidate.adhesion.normal_ratio"
"""The layer's normal over its shear stiffness (:mod:`sim_core.candidates.adhesion`, normal compliance)."""

LAYER_NORMAL_RATIO = 1.0
"""The normal ratio of the layer :mod:`sysid.diagnose.tack` fits (``thinshell sysid --tack``): isotropic springs, ``k_n = k_t`` a
pair, so ``k_t`` (the fitted parameter) sets both. With
the cohesive normal law (~1,100 N/m a pair at the layer's strength) the bonded patch stays flat on the gel face and the
card leaves the pad at the gel's slope; nominal_s109 shows a card that pivots about its clamp as a straight ramp while
the gel lifts it (2.1-2.3 s: z 0.1 -> 5.3 mm linearly over x 0 -> 100 mm, the patch tilted 0.24-0.99 mm under the
face), which a patch free to tilt on springs gives (mean sheet-point error 0.74 -> 0.24 mm at the engine's values,
k_t 3 N/m; docs/benchmarks_log.md, session 56)."""

LAYER_BOND_WEIGHTS = 400.0
"""Bond strength of the compliant layer's bonds, in card weights a pair: strong enough never to break before the
recorded peel (the recording says when the card leaves the gel; with the diagnosis' 4 card weights the layer's shear
pull opens the bonds as the card pivots and drops it: nominal_s109, docs/benchmarks_log.md, session 53)."""

SHEAR_STIFFNESS_BOUNDS = (0.03, 30.0)
"""Search range of ``k_t``, N/m per pair (the layer's shear stiffness at the default gel mesh)."""

SHEAR_GRID = 4
"""Log-spaced grid points of the ``k_t`` search (a factor 10 apart over the bounds)."""

SHEAR_LOG_TOL = 0.1
"""Brent's tolerance on ``ln k_t`` (10 %)."""

SHEAR_MAX_REPLAYS = 10
"""Most replays of the ``k_t`` search."""


def layer_settings(beta: float, stiffness: float, normal_ratio: float | None = None) -> dict[str, float]:
    """The simulator parameters of the tack's compliant layer: bonds of ``beta`` N a pair held in shear by
    ``stiffness`` (``k_t``, N/m a pair) and along the normal by the cohesive law (``normal_ratio`` None) or by springs of
    ``normal_ratio k_t`` (:data:`LAYER_NORMAL_RATIO`: isotropic); every replay with the layer takes them from here."""
    out = {ADHESION_PARAMETER: float(beta), SHEAR_STIFFNESS_SETTING: float(stiffness)}
    return out if normal_ratio is None else {**out, NORMAL_RATIO_SETTING: float(normal_ratio)}


@dataclass(frozen=True)
class ShearLayer:
    """The tack's compliant layer fitted from the carried card (:func:`fit_shear_layer`).

    Attributes:
        stiffness: ``k_t`` at the fit's best, N/m per bonded pair.
        beta: the layer's bond strength per pair, N (:data:`LAYER_BOND_WEIGHTS` card weights).
        rms: sheet points' whitened RMS up to the peel at ``stiffness``.
        profile: ``((k_t, rms), ...)`` every replay of the search, by ``k_t``.
        log_sigma: 1-sigma of ``ln k_t`` from the curvature of the sheet points' cost at the best (:func:`_log_sigma`;
            nan when the search ends on a bound).
        normal_ratio: the bonds' normal over shear stiffness, None for the cohesive normal law (:func:`layer_settings`).
        replay: the search's replay at ``stiffness`` (a :class:`~sysid.replay_trace.SimTrace` with its states, the
            parameters given to :func:`fit_shear_layer` with :meth:`settings`), where the search kept it
            (``keep_best``); None otherwise. Not part of the summary or of equality.
    """

    stiffness: float
    beta: float
    rms: float
    profile: tuple[tuple[float, float], ...]
    log_sigma: float
    normal_ratio: float | None = None
    replay: Any = field(default=None, compare=False, repr=False)

    def settings(self) -> dict[str, float]:
        """The simulator parameters of the layer at its best, as :func:`fit_shear_layer` replayed it (bond strength and
        ``k_t``): a replay with the layer takes these, not values rebuilt by its caller."""
        return layer_settings(self.beta, self.stiffness, self.normal_ratio)

    def summary(self) -> dict[str, Any]:
        """fit.json's ``diagnostics.tack.shear_layer``."""
        return {"shear_stiffness_N_per_m": self.stiffness, "bond_strength_N": self.beta, "sheet_rms_to_peel": self.rms,
                "log_sigma": None if math.isnan(self.log_sigma) else self.log_sigma,
                "profile": [list(p) for p in self.profile]}


def fit_shear_layer(model, params: dict[str, float], card_beta: float, data: np.ndarray, sigma: np.ndarray,
                    rows: np.ndarray, bounds: tuple[float, float] = SHEAR_STIFFNESS_BOUNDS, grid: int = SHEAR_GRID,
                    max_replays: int = SHEAR_MAX_REPLAYS, normal_ratio: float | None = None,
                    keep_best: bool = False) -> ShearLayer | None:
    """The tangential stiffness ``k_t`` of the tack's compliant layer that best follows the carried card.

    The layer (:mod:`sim_core.candidates.adhesion`, shear compliance) holds the bonded card points in shear with
    ``k_t`` per pair; its bonds are :data:`LAYER_BOND_WEIGHTS` card weights strong, so that they hold the card until
    the recorded peel as the recording shows (the peel itself comes from the recording). With the materials held
    at ``params``, ``ln k_t`` is searched over :data:`SHEAR_STIFFNESS_BOUNDS` on the sheet points' whitened RMS over
    ``rows`` (the carried phase): a grid of :data:`SHEAR_GRID` points, then Brent's bounded search between the best
    one's neighbours to :data:`SHEAR_LOG_TOL` (at most :data:`SHEAR_MAX_REPLAYS` replays in all); the sigma of
    ``ln k_t`` from the cost's curvature there (:func:`_log_sigma`).

    Args:
        model: the :class:`~sysid.observation.ObservationModel` (drive set).
        params: simulator parameters with the tack and its release time.
        card_beta: the card-weight bond strength of the tack, N per pair (> 0).
        data: recorded sheet points ``(n, p, 3)`` m; sigma: their noise, broadcastable; rows: bool ``(n,)``.
        bounds: search range of ``k_t``, N/m per pair; grid: its log-spaced grid points; max_replays: most replays
            (defaults: the search at the start's materials).
        normal_ratio: the bonds' normal law (:func:`layer_settings`: None the cohesive law, a number springs of that
            ratio to ``k_t``).
        keep_best: make every replay with its states and keep the best one (:attr:`ShearLayer.replay`), so that a
            caller who needs the layer's replay at the fitted ``k_t`` takes it instead of making it again; at most
            two replays' states are held at once (the best so far and the newest).

    Returns:
        the :class:`ShearLayer`, or None when every replay diverged.
    """
    from scipy.optimize import minimize_scalar

    beta = LAYER_BOND_WEIGHTS / ADHESION_PROBE_WEIGHTS * float(card_beta)
    seen: dict[float, float] = {}
    corr: dict[float, int] = {}  # k -> rows per independent datum of its residual (:func:`_rows_per_datum`)
    kept: dict[str, Any] = {}  # with keep_best: "key" (rms, k) and "trace" of the best replay so far

    def cost(u: float) -> float:
        k = float(math.exp(u))
        if k not in seen:
            try:
                trace = model.simulate({**params, **layer_settings(beta, k, normal_ratio)}, keep_states=keep_best)
                pred = model.predict(trace)["sheet_points"]
                seen[k] = sheet_rms(pred, data, sigma, rows)
                corr[k] = _rows_per_datum((np.asarray(pred)[rows] - data[rows]) / sigma)
                # the best is the profile's first minimum by k (min over the sorted profile, below)
                if keep_best and ("key" not in kept or (seen[k], k) < kept["key"]):
                    kept["key"], kept["trace"] = (seen[k], k), trace
            except SimulationDivergedError:
                seen[k] = math.inf
        return seen[k]

    lo, hi = (math.log(b) for b in bounds)
    points = np.linspace(lo, hi, grid)
    costs = [cost(float(u)) for u in points]
    if not np.isfinite(costs).any():
        return None
    i = int(np.argmin(costs))
    a, b = points[max(i - 1, 0)], points[min(i + 1, points.size - 1)]
    minimize_scalar(cost, bounds=(a, b), method="bounded",
                    options={"xatol": SHEAR_LOG_TOL, "maxiter": max(max_replays - grid, 1)})
    profile = tuple(sorted(seen.items()))
    k_best, rms_best = min(profile, key=lambda kv: kv[1])
    data_count = int(rows.sum()) / corr[k_best]
    replay = kept.get("trace") if kept.get("key", (None, None))[1] == k_best else None
    return ShearLayer(k_best, beta, rms_best, profile, _log_sigma(profile, k_best, data_count), normal_ratio, replay)


def _rows_per_datum(r: np.ndarray) -> int:
    """Rows per independent datum of a whitened residual ``r`` ``(n, ...)`` over consecutive rows: ``1 + 2 sum rho_l``
    (the integrated autocorrelation time, Sokal's window: the sum stops at the first lag whose correlation is not
    positive), ``rho_l`` the correlation of row ``i``'s residual vector with row ``i + l``'s. A card that misses its
    shape misses it for many rows; counting every row as a datum made the sigma of ``ln k_t`` 0.013 on nominal_s109,
    where the profile moves by a factor 2.4 in RMS within 14 % of ``k_t`` (docs/benchmarks_log.md, session 53)."""
    flat = np.asarray(r, dtype=float).reshape(len(r), -1)
    norm = np.sqrt(np.sum(flat ** 2, axis=1))
    ok = norm > 0
    unit = np.where(ok[:, None], flat / np.where(ok, norm, 1.0)[:, None], 0.0)
    tau = 1.0
    for lag in range(1, len(flat) // 2):
        rho = float(np.mean(np.sum(unit[:-lag] * unit[lag:], axis=1)))
        if not rho > 0.0:
            break
        tau += 2.0 * rho
    return max(int(round(tau)), 1)


def _log_sigma(profile, k_best: float, n: float) -> float:
    """1-sigma of ``ln k_t`` that holds under model error: the cost ``n (rms / rms_best)^2`` with ``n`` the carried
    rows' independent data (:func:`_rows_per_datum`: consecutive rows of a card that misses its shape err together)
    and the residual scaled by its own size at the best (the reduced chi-square set to 1), fitted by a parabola in
    ``ln k_t`` through the best point and its two nearest neighbours; nan at a bound or a flat / concave parabola."""
    ks = np.array([k for k, _ in profile])
    rms_best = dict(profile)[k_best]
    chi = n * (np.array([r for _, r in profile]) / rms_best) ** 2
    ok = np.isfinite(chi)
    ks, chi = ks[ok], chi[ok]
    j = int(np.flatnonzero(ks == k_best)[0])
    if j == 0 or j == ks.size - 1:
        return math.nan
    near = np.argsort(np.abs(np.log(ks) - math.log(k_best)))[:3]
    curv = np.polyfit(np.log(ks[near]), chi[near], 2)[0]  # chi = c u^2 + ...: sigma^2 = 1 / c
    return float(1.0 / math.sqrt(curv)) if curv > 0 else math.nan


def sheet_rms(pred: np.ndarray, data: np.ndarray, sigma: np.ndarray, rows: np.ndarray) -> float:
    """Whitened RMS of the sheet points over ``rows``."""
    return float(np.sqrt(np.mean(((np.asarray(pred)[rows] - data[rows]) / sigma) ** 2)))
