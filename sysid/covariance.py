"""Parameter covariance that holds under model error: HAC sandwich and block bootstrap over time.

The Gauss-Newton covariance ``(J^T W J)^-1`` of :func:`sysid.fit.gauss_newton_covariance` assumes
that the whitened residual ``r`` is white noise of unit variance. On a recording the model does not
follow exactly (another engine, another mesh, a compliant drive) ``r`` is dominated by a smooth,
structured misfit: neighbouring samples are strongly correlated and there are far fewer independent
pieces of evidence than residuals, so that sigma is too small by a large factor.

Two estimates replace the white-noise assumption by the residual's own correlation in time. Both
work on the per-time-bin *scores* ``g_t = sum_{i in bin t} J_i r_i`` ``(T, p)`` (every residual of
every channel recorded in bin ``t``; bins of :func:`time_bins`), so that channels sampled at
different rates are combined sample by sample:

- ``hac`` (sandwich, Newey & West 1987; White 1980):
  ``Cov = H^-1 S H^-1`` with ``H = J^T J`` and
  ``S = Gamma_0 + sum_{l=1}^{L} w_l (Gamma_l + Gamma_l^T)``, ``Gamma_l = sum_t g_t g_{t-l}^T``,
  Bartlett weights ``w_l = 1 - l / (L + 1)``. The lag window ``L`` (bins) is chosen from the data
  by Andrews (1991, "Heteroskedasticity and autocorrelation consistent covariance matrix
  estimation", Econometrica 59(3), eq. 6.4) with an AR(1) plug-in per score column:
  ``L + 1 = 1.1447 (alpha T)^(1/3)``, ``alpha = sum_a 4 rho_a^2 s_a^4 / ((1 - rho_a)^6 (1 + rho_a)^2)
  / sum_a s_a^4 / (1 - rho_a)^4``, capped at ``T / 2`` (:func:`andrews_bandwidth`).
- ``block_bootstrap`` (moving-block bootstrap, Kuensch 1989, of the linearised estimator): resample
  ``T / b`` blocks of ``b`` consecutive bins (``b = L + 1``) with replacement and take the spread of
  the Gauss-Newton estimates ``H^-1 sum_{t in sample} g_t`` (the one-step refit of the resampled
  data at the optimum). It needs no replay: at the optimum the linearisation is exact to first
  order, as for the sandwich.

Both are reported beside the formal sigma, with the method named; neither can see a misfit that is
the same in every resample (a pure bias), which is why the coverage of their intervals is measured
(docs/benchmarks_log.md, tests/sysid/test_covariance_coverage.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from sim_core.errors import CalibrationError, ConfigError

if TYPE_CHECKING:
    from sysid.observation import ObservationModel

ROBUST_METHODS = ("hac", "block_bootstrap")
DEFAULT_ROBUST_METHOD = "hac"
BOOTSTRAP_RESAMPLES = 400
"""Resamples of :func:`block_bootstrap_covariance` (its sigma is then known to about 1/sqrt(800) = 3.5 %)."""


@dataclass(frozen=True)
class RobustCovariance:
    """A covariance of the search coordinates that accounts for time-correlated residuals.

    Attributes:
        method: ``hac`` or ``block_bootstrap``.
        covariance_u: ``(p, p)`` covariance of the coordinates u.
        lag_bins: lag window L (HAC) or block length - 1 (bootstrap), in time bins.
        bin_s: width of a time bin, s.
        bins: number of time bins T holding residuals.
        inflation: ``sqrt(diag(Cov) / diag((J^T J)^-1))`` per coordinate, ``(p,)``: how many formal
            sigmas one robust sigma is.
        resamples: bootstrap resamples (0 for HAC).
        time_covariance_u: with a nuisance part (:meth:`with_nuisance`), the time-correlation part alone.
        nuisance_prior: nuisance name -> prior 1-sigma (relative / parameter units), or None.
        nuisance_shift_u: nuisance name -> ``d u / d phi`` column of ``A`` ``(p,)`` (search coordinates).
    """

    method: str
    covariance_u: np.ndarray
    lag_bins: int
    bin_s: float
    bins: int
    inflation: np.ndarray
    resamples: int = 0

    time_covariance_u: np.ndarray | None = None
    nuisance_prior: dict[str, float] | None = None
    nuisance_shift_u: dict[str, np.ndarray] | None = None

    def with_nuisance(self, cov_u: np.ndarray, prior: Mapping[str, float],
                      shift_u: Mapping[str, np.ndarray]) -> "RobustCovariance":
        """This covariance plus the propagated nuisance covariance ``cov_u`` (:func:`nuisance_covariance`);
        method ``<method>+nuisance``, the time-correlation part kept in :attr:`time_covariance_u`."""
        total = self.covariance_u + cov_u
        base = self.covariance_u if self.time_covariance_u is None else self.time_covariance_u
        formal_var = np.diag(self.covariance_u) / self.inflation ** 2
        return RobustCovariance(f"{self.method}+nuisance", total, self.lag_bins, self.bin_s, self.bins,
                                np.sqrt(np.diag(total) / formal_var), self.resamples, base, dict(prior),
                                {k: np.asarray(v, dtype=float) for k, v in shift_u.items()})

    def floored(self, J: np.ndarray) -> "RobustCovariance":
        """This covariance with its meat at least the white noise's of unit variance: ``H^-1/2 max(I, H^1/2 C H^1/2)
        H^-1/2`` (``H = J^T J`` of the whitened Jacobian ``J`` ``(m, p)``, ``C`` :attr:`covariance_u`, the maximum taken
        on the eigenvalues), so that no combination of the coordinates is known better than the sensor's own noise
        allows ((J^T J)^-1, the Gauss-Newton covariance). The whitened residual is at least that noise (its level
        estimated from the recording); a sandwich below it is the small-sample bias of a residual-based long-run
        variance, whose lag window may reach half the bins (Andrews' cap) and whose scores sum to zero at the
        optimum: this simulator's press of four steps (five bins, lag 2) gave the gel-card friction a HAC 1-sigma
        0.0014 against the Gauss-Newton 0.198, and its own lift-fold 0.096 against 0.178, 2.2 sigma from the truth
        (tests/sysid/test_identifiability.py, docs/benchmarks_log.md session 59, 49ident). ``inflation`` is
        recomputed; a nuisance part (:meth:`with_nuisance`) is to be added after the floor."""
        H = np.asarray(J, dtype=float).T @ np.asarray(J, dtype=float)
        w, V = np.linalg.eigh(H)
        if w.size == 0 or w[0] <= 1e-12 * w[-1]:
            return self
        half, inv_half = (V * np.sqrt(w)) @ V.T, (V / np.sqrt(w)) @ V.T
        m, U = np.linalg.eigh(half @ self.covariance_u @ half)
        cov = inv_half @ ((U * np.maximum(m, 1.0)) @ U.T) @ inv_half
        cov = 0.5 * (cov + cov.T)
        formal = np.diag((V / w) @ V.T)
        return RobustCovariance(self.method, cov, self.lag_bins, self.bin_s, self.bins,
                                np.sqrt(np.diag(cov) / formal), self.resamples)

    def summary(self) -> dict[str, Any]:
        """JSON-ready description (without the matrix)."""
        out = {"method": self.method, "lag_bins": int(self.lag_bins), "lag_s": float(self.lag_bins * self.bin_s),
               "bin_s": float(self.bin_s), "bins": int(self.bins), "resamples": int(self.resamples),
               "inflation": [float(v) for v in self.inflation]}
        if self.nuisance_prior is not None:
            out["nuisance_prior"] = dict(self.nuisance_prior)
            out["nuisance_shift_u"] = {k: [float(x) for x in v] for k, v in (self.nuisance_shift_u or {}).items()}
            out["time_inflation"] = [float(v) for v in np.sqrt(np.diag(self.time_covariance_u)
                                                               / (np.diag(self.covariance_u) / self.inflation ** 2))]
        return out


def time_bins(times_s: np.ndarray, bin_s: float) -> np.ndarray:
    """Index of the time bin of each residual: ``floor((t - t_min) / bin_s)``, ``(m,)`` int.

    Args:
        times_s: time of each residual ``(m,)`` in s.
        bin_s: bin width in s (> 0).
    """
    t = np.asarray(times_s, dtype=float)
    if not (math.isfinite(bin_s) and bin_s > 0.0):
        raise CalibrationError(f"time bin width must be > 0 s, got {bin_s!r}")
    return np.floor((t - t.min()) / bin_s + 1e-9).astype(np.int64)


def bin_scores(J: np.ndarray, r: np.ndarray, bins: np.ndarray) -> np.ndarray:
    """Per-bin scores ``g_t = sum_{i in bin t} J_i r_i``, ``(T, p)``, T = number of bins (empty bins kept
    as zero rows so that a lag is a fixed time).

    Args:
        J: whitened Jacobian ``(m, p)``.
        r: whitened residual ``(m,)``.
        bins: bin index per residual ``(m,)`` (:func:`time_bins`).
    """
    J, r, bins = np.asarray(J, dtype=float), np.asarray(r, dtype=float), np.asarray(bins)
    if J.ndim != 2 or J.shape[0] != r.shape[0] or bins.shape != r.shape:
        raise CalibrationError(f"scores need J (m, p), r (m,) and bins (m,); got {J.shape}, {r.shape}, {bins.shape}")
    g = np.zeros((int(bins.max()) + 1 if bins.size else 0, J.shape[1]))
    np.add.at(g, bins, J * r[:, None])
    return g


def andrews_bandwidth(g: np.ndarray) -> int:
    """Bartlett lag window L (bins) of Andrews (1991) eq. 6.4 with AR(1) plug-ins, from the scores ``(T, p)``.

    ``L + 1 = 1.1447 (alpha T)^(1/3)`` (module docstring), each column's AR(1) coefficient ``rho_a``
    clipped to [-0.97, 0.97] (a unit root would give an infinite window); capped at ``T // 2``, at
    least 0.
    """
    T = g.shape[0]
    if T < 3:
        return 0
    num = den = 0.0
    for a in range(g.shape[1]):
        x = g[:, a] - g[:, a].mean()
        x0, x1 = x[:-1], x[1:]
        d = float(x0 @ x0)
        if d <= 0.0:
            continue
        rho = float(np.clip((x0 @ x1) / d, -0.97, 0.97))
        s2 = float(np.mean((x1 - rho * x0) ** 2))
        num += 4.0 * rho ** 2 * s2 ** 2 / ((1.0 - rho) ** 6 * (1.0 + rho) ** 2)
        den += s2 ** 2 / (1.0 - rho) ** 4
    if den <= 0.0:
        return 0
    L = int(math.ceil(1.1447 * (num / den * T) ** (1.0 / 3.0))) - 1
    return int(min(max(L, 0), T // 2))


def hac_meat(g: np.ndarray, lag: int) -> np.ndarray:
    """Newey-West long-run covariance of the scores ``(T, p)`` with Bartlett weights up to ``lag`` bins, ``(p, p)``."""
    S = g.T @ g
    for l in range(1, int(lag) + 1):
        G = g[l:].T @ g[:-l]
        S += (1.0 - l / (lag + 1.0)) * (G + G.T)
    return S


def _bread(J: np.ndarray) -> np.ndarray:
    H = J.T @ J
    w, V = np.linalg.eigh(H)
    if w.size == 0 or w[-1] <= 0.0 or w[0] <= 1e-12 * w[-1]:
        raise CalibrationError(f"J^T W J is singular (eigenvalues {w.tolist()}): no robust covariance")
    return (V / w) @ V.T


def hac_covariance(J: np.ndarray, r: np.ndarray, times_s: np.ndarray, bin_s: float,
                   lag: int | None = None) -> RobustCovariance:
    """Newey-West sandwich covariance ``H^-1 S H^-1`` of the least-squares estimate (module docstring).

    Args:
        J: whitened Jacobian ``(m, p)`` at the optimum.
        r: whitened residual ``(m,)`` at the optimum.
        times_s: time of each residual ``(m,)``, s.
        bin_s: time bin width, s (the slowest channel's sample period is the natural choice).
        lag: lag window in bins (None: :func:`andrews_bandwidth`).

    Raises:
        CalibrationError: shapes that do not match, or a singular ``J^T J``.
    """
    bins = time_bins(times_s, bin_s)
    g = bin_scores(J, r, bins)
    L = andrews_bandwidth(g) if lag is None else int(lag)
    Hinv = _bread(J)
    cov = Hinv @ hac_meat(g, L) @ Hinv
    cov = 0.5 * (cov + cov.T)
    return RobustCovariance("hac", cov, L, float(bin_s), g.shape[0], np.sqrt(np.diag(cov) / np.diag(Hinv)))


def block_bootstrap_covariance(J: np.ndarray, r: np.ndarray, times_s: np.ndarray, bin_s: float,
                               block: int | None = None, resamples: int = BOOTSTRAP_RESAMPLES,
                               seed: int = 0) -> RobustCovariance:
    """Moving-block bootstrap covariance of the linearised estimate ``u + H^-1 J^T r`` (module docstring).

    Args:
        J, r, times_s, bin_s: as :func:`hac_covariance`.
        block: block length in bins (None: Andrews' lag + 1).
        resamples: bootstrap resamples.
        seed: seed of the resampling.
    """
    bins = time_bins(times_s, bin_s)
    g = bin_scores(J, r, bins)
    T = g.shape[0]
    b = andrews_bandwidth(g) + 1 if block is None else max(1, int(block))
    b = min(b, T)
    Hinv = _bread(J)
    starts = T - b + 1
    n_blocks = int(math.ceil(T / b))
    csum = np.vstack([np.zeros((1, g.shape[1])), np.cumsum(g, axis=0)])
    block_sums = csum[b:] - csum[:-b]  # (starts, p)
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, starts, size=(int(resamples), n_blocks))
    totals = block_sums[picks].sum(axis=1) * (T / (n_blocks * b))  # (R, p), scaled to T bins
    deltas = totals @ Hinv.T
    cov = np.cov(deltas, rowvar=False).reshape(g.shape[1], g.shape[1])
    return RobustCovariance("block_bootstrap", cov, b - 1, float(bin_s), T,
                            np.sqrt(np.diag(cov) / np.diag(Hinv)), int(resamples))


def robust_covariance(method: str, J: np.ndarray, r: np.ndarray, times_s: np.ndarray, bin_s: float,
                      seed: int = 0) -> RobustCovariance:
    """The robust covariance of ``method`` (:data:`ROBUST_METHODS`).

    Raises:
        ConfigError: unknown method.
    """
    if method == "hac":
        return hac_covariance(J, r, times_s, bin_s)
    if method == "block_bootstrap":
        return block_bootstrap_covariance(J, r, times_s, bin_s, seed=seed)
    raise ConfigError(f"unknown robust covariance method {method!r} (choose from {', '.join(ROBUST_METHODS)})")


def nuisance_covariance(J: np.ndarray, J_nuisance: np.ndarray, prior_sigma_u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Covariance of the fitted coordinates from the prior uncertainty of parameters the fit holds fixed.

    A fixed (nuisance) parameter ``phi`` off its true value by ``d phi`` moves the least-squares optimum
    by ``d u = A d phi`` to first order, ``A = -(J^T J)^-1 J^T J_phi`` (the Gauss-Newton step of the
    residual change ``J_phi d phi``). With independent priors of 1-sigma ``s_phi`` the fitted
    coordinates get ``Cov = A diag(s_phi^2) A^T`` (propagation of the nuisance uncertainty, e.g.
    Seber & Wild 2003, "Nonlinear Regression", ch. 5; Kennedy & O'Hagan 2001 for its role as a
    model-form term). It is the part of a model error that the fitted parameters absorb and the
    residual therefore cannot show: no sandwich sees it.

    Args:
        J: whitened Jacobian of the fitted coordinates ``(m, p)``.
        J_nuisance: whitened Jacobian of the nuisance coordinates ``(m, q)`` at the same point.
        prior_sigma_u: prior 1-sigma of each nuisance coordinate ``(q,)``.

    Returns:
        ``(Cov (p, p), A (p, q))``.

    Raises:
        CalibrationError: mismatched shapes or a singular ``J^T J``.
    """
    J, Jn = np.asarray(J, dtype=float), np.asarray(J_nuisance, dtype=float)
    s = np.asarray(prior_sigma_u, dtype=float).reshape(-1)
    if Jn.ndim != 2 or Jn.shape[0] != J.shape[0] or Jn.shape[1] != s.size:
        raise CalibrationError(f"nuisance Jacobian {Jn.shape} does not match J {J.shape} and {s.size} prior sigmas")
    A = -_bread(J) @ (J.T @ Jn)
    cov = (A * s ** 2) @ A.T
    return 0.5 * (cov + cov.T), A


def residual_times_s(stamps_ns: Mapping[str, np.ndarray], sizes: Mapping[str, int],
                     channels: Sequence[str]) -> np.ndarray:
    """Time of each element of a residual vector that concatenates ``channels`` (each ``(n, ...)``
    flattened row-major, time first), s relative to the earliest stamp, ``(m,)``.

    Args:
        stamps_ns: channel -> stamps ``(n,)`` int ns.
        sizes: channel -> number of residuals of the channel (a multiple of its stamp count).

    Raises:
        CalibrationError: a channel whose residual count is not a multiple of its stamp count.
    """
    t0 = min(int(np.asarray(stamps_ns[ch])[0]) for ch in channels)
    out = []
    for ch in channels:
        t = (np.asarray(stamps_ns[ch], dtype=np.int64) - t0) * 1e-9
        n = int(sizes[ch])
        if t.size == 0 or n % t.size:
            raise CalibrationError(f"channel {ch}: {n} residuals are not a whole number per stamp ({t.size} stamps)")
        out.append(np.repeat(t, n // t.size))
    return np.concatenate(out)


def residual_bin_s(model: "ObservationModel") -> float:
    """Time bin of the robust covariance: the longest median sample period of the fitted channels, s
    (every bin then holds a sample of every channel)."""
    stamps = _channel_stamps(model)
    periods = [float(np.median(np.diff(stamps[ch]))) * 1e-9 for ch in model.channels if stamps[ch].size > 1]
    return max(periods) if periods else 1.0


def _channel_stamps(model: "ObservationModel") -> dict[str, np.ndarray]:
    """Stamps (ns) of every fitted channel of ``model``.

    Raises:
        CalibrationError: a fitted channel without stamps in the evidence (named).
    """
    missing = [ch for ch in model.channels if ch not in model.evidence.t_ns]
    if missing:
        raise CalibrationError(f"no stamps for fitted channel(s) {', '.join(missing)}: no robust covariance")
    return {ch: np.asarray(model.evidence.t_ns[ch]) for ch in model.channels}


def model_residual_times(model: "ObservationModel") -> tuple[np.ndarray, float]:
    """Time (s) of each element of ``model``'s whitened residual ``(m,)`` (:meth:`sysid.observation.ObservationModel.
    residuals` order, each residual at its sample's stamp) and the time bin (s) of :func:`residual_bin_s`.

    Raises:
        CalibrationError: a fitted channel without stamps.
    """
    slices = model.channel_slices()
    times = residual_times_s(_channel_stamps(model), {ch: sl.stop - sl.start for ch, sl in slices.items()},
                             model.channels)
    return times, residual_bin_s(model)


def model_robust_covariance(model: "ObservationModel", J: np.ndarray, r: np.ndarray,
                            method: str = DEFAULT_ROBUST_METHOD, seed: int = 0) -> RobustCovariance:
    """Robust covariance (:func:`sysid.covariance.robust_covariance`) of a fit of ``model``: whitened Jacobian
    ``J (m, p)`` and residual ``r (m,)`` in :meth:`sysid.observation.ObservationModel.residuals` order, each residual
    placed at its sample's stamp, binned at :func:`residual_bin_s` (:func:`model_residual_times`)."""
    times, bin_s = model_residual_times(model)
    return robust_covariance(method, J, r, times, bin_s, seed=seed)


def not_identified(specs: Sequence[Any], values: Mapping[str, float],
                   sigma_robust: Mapping[str, float] | None) -> tuple[str, ...]:
    """The positive parameters whose robust 2-sigma interval ``value +- 2 sigma_robust`` reaches zero: the data
    leave even the size of the parameter open. The fit's search rule (:func:`sysid.fit_region.unidentified_coordinates`,
    ``sysid.fit.fit(hold_unidentified=True)``: such a coordinate takes no step); what a fit reports as identified is
    judged against the parameter's prior range and its cost's profile (:mod:`sysid.identifiability`), of which this
    is the linearised rule on a log parameter's search range.

    Args:
        specs: the fitted parameters (:class:`sim_core.parameter_coordinates.ParameterSpec`; only those searched
            in a log coordinate, positive by definition, are judged).
        values: fitted value per name.
        sigma_robust: robust 1-sigma per name (:func:`model_robust_covariance`), or None (nothing is judged).

    Returns:
        The names, in ``specs`` order.
    """
    if not sigma_robust:
        return ()
    return tuple(s.name for s in specs if s.log and s.name in sigma_robust
                 and values[s.name] - 2.0 * sigma_robust[s.name] <= 0.0)
