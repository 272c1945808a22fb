"""Statistics of the missing-physics diagnosis: score (Lagrange-multiplier) tests and model selection.

Set-up (SYSID.md "Diagnosis"). The nominal fit leaves a whitened residual ``r = (y - y_sim) / sigma``
(so ``W = I``). A candidate effect k with parameter ``beta`` (off at 0) has the signature
``J_k = d y_sim / d beta / sigma`` at ``beta = 0``; the fitted parameters have ``J_theta``. With the
projection ``P = I - J_theta (J_theta^T J_theta)^-1 J_theta^T`` (what the fitted parameters can
absorb removed) the score statistic of Rao (1948) is

    S_k = r^T P J_k (J_k^T P J_k)^-1 J_k^T P r          (= (r^T P J_k)^2 / (J_k^T P J_k) for one column),

chi-square with ``q = columns of J_k`` degrees of freedom when the effect is absent and the residual
is white with unit variance.

Trajectory residuals are neither: they are serially correlated (model error is smooth in time) and
correlated across the points of one sample (neighbouring markers share it). Two corrections:

1. Prewhitening (Cochrane & Orcutt 1949; Hamilton 1994, ch. 8): a pooled AR(p) model of the residual
   along time, order by BIC, coefficients by Levinson-Durbin on the autocovariance averaged over
   series (``statsmodels.tsa.stattools.levinson_durbin``); the same filter ``A(L)`` is applied to
   ``r``, ``J_theta`` and ``J_k``.
2. A robust (sandwich) score test (White 1982; Wooldridge 1990): the score contributions are summed
   over the series of each time sample, ``g_t = sum_s e_ts (P J_k)_ts`` (q,), and the score
   ``U = sum_t g_t`` is normalised by the Newey-West (1987) long-run variance of ``g_t`` instead of
   the white-noise variance (``g_t`` formed with the residual left after the candidate's own
   least-squares step, ``e - P J_k beta``: equal to the restricted one under the null, but it does
   not count the effect itself as noise under the alternative -- a robust Wald form): ``S = U^T V^-1 U``, asymptotically chi2(q) whatever the cross-sectional
   correlation and the variance of the residual.

Family-wise error over candidates x channels: Holm (1979). Model selection after the refit: Gaussian
log-likelihood ratio ``LR = n log(SSE_0 / SSE_1)`` and ``delta_BIC = LR - q log n`` (Schwarz 1978),
``n`` counted in time samples (conservative under cross-sectional correlation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats as _st


# ====================================================================================== AR prewhitening
@dataclass(frozen=True)
class ARFilter:
    """Prewhitening filter ``e_t = x_t - sum_{i=1..p} a_i x_{t-i}`` along axis 0.

    Attributes:
        coefs: ``a``, shape ``(p,)`` (empty for p = 0).
        innovation_variance: variance of e under the fitted model (units of x^2).
        variance: variance of x (lag-0 autocovariance).
    """

    coefs: np.ndarray
    innovation_variance: float
    variance: float

    @property
    def order(self) -> int:
        """p."""
        return int(self.coefs.shape[0])

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Filter ``x`` of shape ``(T, ...)`` along time; the first p samples are dropped.

        Returns:
            shape ``(T - p, ...)``.
        """
        x = np.asarray(x, dtype=float)
        p = self.order
        out = x[p:].copy()
        for i, a in enumerate(self.coefs, start=1):
            out -= a * x[p - i: x.shape[0] - i]
        return out


def pooled_autocovariance(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Autocovariance along axis 0 averaged over every other axis (series are not demeaned: residuals).

    Args:
        x: shape ``(T, ...)``.
        max_lag: largest lag, < T.

    Returns:
        shape ``(max_lag + 1,)``, biased estimator (divides by T), positive semi-definite.
    """
    x = np.asarray(x, dtype=float).reshape(x.shape[0], -1)
    T = x.shape[0]
    return np.array([np.sum(x[k:] * x[:T - k]) / (T * x.shape[1]) for k in range(max_lag + 1)])


def fit_ar(x: np.ndarray, max_order: int = 8) -> ARFilter:
    """Pooled AR(p) model of residual series ``x (T, ...)``, p in ``0..max_order`` by BIC.

    ``BIC(p) = T log sigma_p^2 + p log T`` with the innovation variances sigma_p^2 of the
    Levinson-Durbin recursion.

    Raises:
        ValueError: fewer than ``max_order + 2`` time samples, or an all-zero residual.
    """
    from statsmodels.tsa.stattools import levinson_durbin

    x = np.asarray(x, dtype=float)
    T = x.shape[0]
    if T < max_order + 2:
        raise ValueError(f"AR prewhitening needs more than {max_order + 1} time samples, got {T}")
    acov = pooled_autocovariance(x, max_order)
    if not acov[0] > 0.0:
        raise ValueError("AR prewhitening: the residual is identically zero")
    best_p, best_bic = 0, T * math.log(acov[0])
    if max_order > 0:
        res = levinson_durbin(acov, nlags=max_order, isacov=True)
        sig = np.asarray(res.sigma, dtype=float)  # sig[p] = innovation variance of AR(p)
        for p in range(1, max_order + 1):
            if sig[p] <= 0.0:
                break
            bic = T * math.log(sig[p]) + p * math.log(T)
            if bic < best_bic:
                best_p, best_bic = p, bic
        coefs = np.asarray(res.phi, dtype=float)[1:best_p + 1, best_p] if best_p else np.zeros(0)
        innov = float(sig[best_p])
    else:
        coefs, innov = np.zeros(0), float(acov[0])
    return ARFilter(np.asarray(coefs, dtype=float), innov, float(acov[0]))


# ====================================================================================== projection
def project_out(J_theta: np.ndarray | None, X: np.ndarray, rcond: float = 1e-10) -> np.ndarray:
    """``P X`` with ``P = I - J_theta J_theta^+`` (least-squares projection, rows flattened).

    Args:
        J_theta: shape ``(m, p)`` or None / ``p = 0`` (nothing to project).
        X: shape ``(m,)`` or ``(m, q)``.

    Returns:
        same shape as X.
    """
    X = np.asarray(X, dtype=float)
    if J_theta is None or J_theta.size == 0:
        return X.copy()
    J = np.asarray(J_theta, dtype=float).reshape(X.shape[0], -1)
    coef, *_ = np.linalg.lstsq(J, X, rcond=rcond)
    return X - J @ coef


# ====================================================================================== score tests
@dataclass(frozen=True)
class ScoreResult:
    """One score test.

    Attributes:
        statistic: S (chi2(dof) under the null).
        dof: q.
        p_value: upper tail (one-sided tests: of the signed root, 1 when the estimate has the wrong sign).
        beta: one-step estimate of the candidate parameters ``(P J)^+ P r``, shape ``(q,)``.
        classical: the white-noise statistic on the same (prewhitened, projected) quantities scaled
            by the residual's innovation variance.
        contributions: per-time score contributions ``g_t . (V^-1 U)``, shape ``(T',)``; they sum to S.
        ar_order: order of the prewhitening filter (0: none).
    """

    statistic: float
    dof: int
    p_value: float
    beta: np.ndarray
    classical: float
    contributions: np.ndarray
    ar_order: int


def newey_west(g: np.ndarray, lags: int) -> np.ndarray:
    """Long-run covariance ``sum_{|l| <= L} (1 - |l|/(L+1)) Gamma_l`` of score terms ``g (T, q)`` (uncentred).

    Newey & West (1987), Bartlett weights; positive semi-definite.
    """
    g = np.asarray(g, dtype=float).reshape(g.shape[0], -1)
    V = g.T @ g
    for lag in range(1, lags + 1):
        w = 1.0 - lag / (lags + 1.0)
        G = g[lag:].T @ g[:-lag]
        V += w * (G + G.T)
    return V


def _p_value(S: float, dof: int, beta: np.ndarray, one_sided: bool) -> float:
    if one_sided and dof == 1:
        return float(_st.norm.sf(math.copysign(math.sqrt(max(S, 0.0)), beta[0]))) if beta[0] != 0 else 0.5
    return float(_st.chi2.sf(S, dof))


def score_test(r: np.ndarray, J_k: np.ndarray, J_theta: np.ndarray | None = None, *, one_sided: bool = False,
               prewhiten: bool = True, robust: bool = True, max_ar_order: int = 8,
               hac_lags: int | None = None) -> ScoreResult:
    """Score test of a candidate on one channel.

    Args:
        r: whitened residual, shape ``(T, S)`` (time, series) or ``(T,)``.
        J_k: whitened signature ``d y / d beta / sigma``, shape ``(T, S, q)`` (or ``(T, S)`` / ``(T,)``).
        J_theta: whitened Jacobian of the fitted parameters, ``(T, S, p)`` or None.
        one_sided: beta >= 0 only (q must be 1); the p-value is that of the signed root.
        prewhiten: AR prewhitening (:func:`fit_ar`) of residual and Jacobians.
        robust: sandwich (Newey-West) variance of the time-aggregated score, floored by the
            conventional one ``s_alt^2 J^T P J`` of the residual left once the candidate is fitted (the
            smaller of the two statistics; else the white-noise variance ``s^2 J^T P J`` with s^2 the
            innovation variance).
        max_ar_order: largest AR order tried.
        hac_lags: Newey-West lags (default ``floor(4 (T/100)^(2/9))``).

    Returns:
        :class:`ScoreResult`.

    Raises:
        ValueError: inconsistent shapes, one-sided with q > 1, or a signature that the fitted
            parameters absorb completely (``J_k^T P J_k = 0``).
    """
    r = np.asarray(r, dtype=float)
    T = r.shape[0]
    r = r.reshape(T, -1)
    S_ = r.shape[1]
    J = np.asarray(J_k, dtype=float).reshape(T, S_, -1)
    q = J.shape[2]
    if one_sided and q != 1:
        raise ValueError(f"a one-sided score test needs one parameter, got {q}")
    Jt = None if J_theta is None else np.asarray(J_theta, dtype=float).reshape(T, S_, -1)
    ar_order = 0
    if prewhiten:
        # AR model of the residual with the fitted AND the candidate directions removed (Cochrane-Orcutt on
        # the full regression): fitted on r alone, a smooth effect would be taken for serial correlation
        # and filtered away with it.
        X = J.reshape(T * S_, q) if Jt is None else np.concatenate([Jt.reshape(T * S_, -1), J.reshape(T * S_, q)], 1)
        base = project_out(X, r.reshape(-1)).reshape(T, S_)
        filt = fit_ar(base, max_order=min(max_ar_order, max(T // 10, 0)))
        ar_order = filt.order
        r, J = filt.apply(r), filt.apply(J)
        Jt = None if Jt is None else filt.apply(Jt)
        T = r.shape[0]
    m = T * S_
    Jt_flat = None if Jt is None else Jt.reshape(m, -1)
    e = project_out(Jt_flat, r.reshape(m))
    PJ = project_out(Jt_flat, J.reshape(m, q))
    M = PJ.T @ PJ
    scale = np.sqrt(np.diag(M))
    if not np.all(scale > 1e-12 * max(1.0, float(np.sqrt(np.sum(J ** 2))))):
        raise ValueError("the candidate's signature lies in the span of the fitted parameters' Jacobian "
                         "(J_k^T P J_k = 0): the fit absorbs it, it cannot be tested")
    U = PJ.T @ e
    beta, *_ = np.linalg.lstsq(M, U, rcond=1e-12)
    p_dof = 0 if Jt_flat is None else np.linalg.matrix_rank(Jt_flat)
    s2 = float(e @ e) / max(m - p_dof, 1)
    classical = float(U @ beta) / s2
    if robust:
        # Variance of the score from the residual left once the candidate is fitted (e - PJ beta): the
        # same as from e under the null, but e itself carries the effect under the alternative and
        # inflates V so that S could never exceed the number of time samples the effect spans.
        e_alt = e - PJ @ beta
        g = (e_alt[:, None] * PJ).reshape(T, S_, q).sum(axis=1)
        lags = hac_lags if hac_lags is not None else int(math.floor(4.0 * (T / 100.0) ** (2.0 / 9.0)))
        # small-sample (HC1-type) correction for the q + p directions fitted out of e_alt
        V = newey_west(g, lags) * (T / max(T - q - p_dof - lags, 1))
        w, *_ = np.linalg.lstsq(V, U, rcond=1e-12)
        statistic = float(U @ w)
        # floor: the conventional variance s_alt^2 J^T P J from the same residual. Where a few time
        # samples carry the signature, the Newey-West variance of the score is estimated from those
        # few terms and is too small (16.5 % rejections at nominal 1 % for a 3-sample transient on
        # white noise); the larger of the two variances (the smaller statistic) is the small-sample
        # hedge of Angrist & Pischke (2009, sec. 8.2), as in :func:`heldout_test`.
        s2_alt = float(e_alt @ e_alt) / max(m - p_dof - q, 1)
        if s2_alt > 0.0:
            w_conv, *_ = np.linalg.lstsq(s2_alt * M, U, rcond=1e-12)
            if float(U @ w_conv) < statistic:
                w, statistic = w_conv, float(U @ w_conv)
        contributions = (e[:, None] * PJ).reshape(T, S_, q).sum(axis=1) @ w
    else:
        statistic = classical
        w = beta / s2
        contributions = (e[:, None] * PJ).reshape(T, S_, q).sum(axis=1) @ w
    statistic = max(statistic, 0.0)
    return ScoreResult(statistic, q, _p_value(statistic, q, beta, one_sided), beta, classical,
                       contributions, ar_order)


# ====================================================================================== multiplicity
def holm(p_values: np.ndarray | list[float], alpha: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Holm's step-down correction of a family of p-values.

    Args:
        p_values: shape ``(n,)``.
        alpha: family-wise error rate.

    Returns:
        ``(adjusted p-values (n,), reject (n,) bool)``; ``adjusted_i = max_{j <= rank i} min(1, (n - j) p_(j))``.
    """
    p = np.asarray(p_values, dtype=float).reshape(-1)
    n = p.shape[0]
    order = np.argsort(p, kind="stable")
    adj_sorted = np.minimum(1.0, np.maximum.accumulate((n - np.arange(n)) * p[order]))
    adjusted = np.empty(n)
    adjusted[order] = adj_sorted
    return adjusted, adjusted <= alpha


# ====================================================================================== model selection
def likelihood_ratio(sse_0: float, sse_1: float, n: int) -> float:
    """Gaussian log-likelihood ratio statistic ``n log(SSE_0 / SSE_1)`` (variance profiled out)."""
    if not (sse_0 > 0.0 and sse_1 > 0.0):
        raise ValueError(f"sums of squares must be positive, got {sse_0}, {sse_1}")
    return float(n * math.log(sse_0 / sse_1))


def delta_bic(sse_0: float, sse_1: float, n: int, q: int) -> float:
    """``BIC_0 - BIC_1 = n log(SSE_0/SSE_1) - q log n`` for q added parameters (> 10: strong evidence)."""
    return likelihood_ratio(sse_0, sse_1, n) - q * math.log(n)


# ====================================================================================== held-out comparison
@dataclass(frozen=True)
class HeldoutResult:
    """Held-out test of a refit's prediction change ``delta`` against the nominal residual ``r_0``.

    Attributes:
        beta: the scale of the change the held-out rows support, ``sum r_0 . delta / sum delta . delta``
            (1: the refit's size is right; 0: the change does not help at all).
        beta0: the scale tested against.
        statistic: ``(sum r_0 . delta - beta0 sum delta . delta) / sqrt(V)`` (t-like).
        p_value: one-sided, the held-out rows support a scale above ``beta0`` (Student t, ``T - 1`` dof).
        p_below: one-sided, the scale is below ``beta0``.
        samples: number of held-out time samples T.
    """

    beta: float
    beta0: float
    statistic: float
    p_value: float
    p_below: float
    samples: int


def heldout_test(a: np.ndarray, b: np.ndarray, beta0: float = 0.0, c: np.ndarray | None = None,
                 n: np.ndarray | None = None, hac_lags: int | None = None) -> HeldoutResult:
    """Score (Lagrange-multiplier) test, on held-out rows, of the direction a refit changed the prediction.

    With the whitened nominal residual ``r_0`` and the whitened prediction change ``delta`` of a refit
    fitted on the *training* rows (so ``delta`` is fixed with respect to the held-out noise), the
    held-out score is ``U = sum_t a_t`` with ``a_t = sum_s r_0,ts delta_ts`` (summed over the series
    of time sample t) and ``b_t = sum_s delta_ts^2``. Under ``beta = beta0`` (``r_0 = beta0 delta +
    noise``), ``U - beta0 sum b_t`` has mean 0. Its variance is the larger of

    - the robust one: the Newey-West (1987) long-run variance of the per-time contributions
      ``a_t - beta_hat b_t`` (residual left by the fitted scale, White's form; Bartlett weights,
      lags ``floor(4 (T/100)^(2/9))``, small-sample factor ``T / (T - 1 - lags)``), so that
      cross-sectional and serial correlation of the residual do not count as evidence;
    - the conventional one ``s^2 sum b_t`` with ``s^2`` the per-value variance of the residual left
      by the fitted scale (given ``c_t = sum_s r_0,ts^2`` and the value counts ``n_t``), which floors
      the robust one where few samples carry the change (an effect at one motion onset: the robust
      variance of a single term is no estimate at all). Taking the larger of the two standard errors
      is the small-sample hedge of Angrist & Pischke (2009, sec. 8.2).

    Unlike the Diebold-Mariano test of the loss differential ``2 a_t - b_t``, the deterministic
    heterogeneity of ``b_t`` (an effect concentrated in a few samples) does not enter the variance,
    so an effect confined to one window keeps its power. p-values: Student t, ``T - 1`` dof.

    Args:
        a, b: ``(T,)`` per-time sums above (``b >= 0``).
        beta0: scale under the null (0: the change explains nothing; 0.5: the change leaves the
            held-out fit as it was).
        c, n: ``(T,)`` per-time residual sums of squares and value counts (both or neither).

    Raises:
        ValueError: shapes differ, fewer than 3 samples, or ``delta = 0``.
    """
    a = np.asarray(a, dtype=float).reshape(-1)
    b = np.asarray(b, dtype=float).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"heldout_test: shapes {a.shape} and {b.shape} differ")
    T = a.shape[0]
    if T < 3:
        raise ValueError(f"a held-out test needs at least 3 samples, got {T}")
    D = float(b.sum())
    if not D > 0.0:
        raise ValueError("heldout_test: the refit does not change the held-out prediction")
    U = float(a.sum())
    beta = U / D
    lags = hac_lags if hac_lags is not None else int(math.floor(4.0 * (T / 100.0) ** (2.0 / 9.0)))
    V = float(newey_west((a - beta * b)[:, None], lags)[0, 0]) * T / max(T - 1 - lags, 1)
    if c is not None and n is not None:
        values = float(np.sum(n))
        sse = float(np.sum(c)) - 2.0 * beta * U + beta * beta * D
        V = max(V, max(sse, 0.0) / max(values - 1.0, 1.0) * D)
    num = U - beta0 * D
    stat = num / math.sqrt(V) if V > 0 else math.copysign(math.inf, num) if num else 0.0
    return HeldoutResult(beta, beta0, float(stat), float(_st.t.sf(stat, T - 1)), float(_st.t.cdf(stat, T - 1)), T)


# ====================================================================================== discriminating tests
@dataclass(frozen=True)
class EqualityResult:
    """Test that several groups of values support one common scale of a prediction change.

    Attributes:
        coefficients: least-squares scale of each group, shape ``(q,)``.
        statistic: Hotelling's ``T^2`` of the contrasts ``b_j - b_1`` with the equal-weighted cosine
            variance (for ``q = 2`` the square of a Student t statistic).
        dof: ``(q - 1, B - q + 2)`` of the F reference.
        p_value: upper tail of ``F(dof)`` for ``T^2 (B - q + 2) / ((q - 1) B)``.
        samples: time samples T (after prewhitening).
        cosines: number of cosine weights B (the variance's degrees of freedom).
    """

    coefficients: np.ndarray
    statistic: float
    dof: tuple[int, int]
    p_value: float
    samples: int
    cosines: int


def scale_equality_test(r: np.ndarray, X: np.ndarray, cosines: int = 12, prewhiten: bool = True,
                        max_ar_order: int = 8) -> EqualityResult:
    """Test that the columns of ``X`` enter the residual ``r`` with one common coefficient.

    ``r = X b + e`` by least squares (``X``'s columns are typically one prediction change masked to
    disjoint groups of values, e.g. the force and the moment axes of a wrench); under the null ``b_1 =
    ... = b_q``. The contrasts ``c = C b`` (``C``: ``b_j - b_1``) are the sum over time of ``c_t = C
    (X^T X)^-1 X_t^T e0_t``, with ``e0`` the residual of the *common*-scale fit (a score form: under the
    null ``e0_t`` is the noise, and ``sum_t c_t = C b`` exactly). Trajectory residuals are serially
    correlated and the samples few (30-40 informative ones in a benchmark recording), where a Newey-West
    variance with a handful of lags is liberal (19 % rejections at 5 % for AR(1) 0.6 and 24 samples in
    simulation); instead residual and columns are first AR-prewhitened as in :func:`score_test`
    (Cochrane-Orcutt on the common-scale fit), and the long-run variance of ``c_t`` is then the
    equal-weighted cosine (EWC) estimate ``Omega = (1/B) sum_j L_j L_j^T``, ``L_j = sqrt(2/T) sum_t
    cos(pi j (t + 1/2) / T) c_t``, j = 1..B, tested with Hotelling's ``T^2`` against the fixed-b
    reference ``F(q - 1, B - q + 2)`` (Lazarus, Lewis, Stock & Watson 2018, "HAR inference:
    recommendations for practice", JBES 36(4); for ``q = 2`` a Student t with B degrees of freedom).
    Unlike batch means over B contiguous blocks, every sample enters every weight, so the p-value does
    not jump with where block boundaries fall. In simulation (28-32 samples, AR(1) 0 - 0.8 with a
    factor common to the series, 400 draws, B = 12): 4.5-9 % rejections at 5 %, 0.5-1.25 % at 1 %;
    power at 1 % against a moment at 0.45 of the force's scale 0.77-1.0, against 0.5-0.87 for eight
    batch means (docs/benchmarks_log.md, session 40, 23loa).

    Args:
        r: whitened residual, shape ``(T, S)``.
        X: whitened columns, shape ``(T, S, q)``, ``q >= 2``.
        cosines: B, cosine weights, ``q - 1 <= B < T`` (B is lowered to ``T - 1`` on shorter series).
        prewhiten: AR prewhitening (:func:`fit_ar`, order up to ``min(max_ar_order, T // 10)``).
        max_ar_order: largest AR order tried.

    Raises:
        ValueError: ``q < 2``, fewer than ``max(q + 1, 2 q)`` samples, B out of range, or a column that is zero.
    """
    r = np.asarray(r, dtype=float)
    T = r.shape[0]
    r = r.reshape(T, -1)
    X = np.asarray(X, dtype=float).reshape(T, r.shape[1], -1)
    q = X.shape[2]
    if q < 2:
        raise ValueError(f"scale_equality_test needs at least 2 columns, got {q}")
    if T < max(q + 1, 2 * q):
        raise ValueError(f"scale_equality_test needs at least {max(q + 1, 2 * q)} samples, got {T}")
    k = q - 1
    if int(cosines) < k:
        raise ValueError(f"scale_equality_test needs at least {k} cosine weights, got {cosines}")
    if not np.all(np.einsum("tsi,tsi->i", X, X) > 0.0):
        raise ValueError("scale_equality_test: a column is zero")
    if prewhiten:
        # Cochrane-Orcutt on the common-scale fit: a pooled AR model of its residual filters r and X
        x1 = X.sum(axis=2)
        e = r - float(np.sum(x1 * r) / np.sum(x1 * x1)) * x1
        filt = fit_ar(e, max_order=min(max_ar_order, max(T // 10, 0)))
        if filt.order and T - filt.order >= max(q + 1, 2 * q, k + 1):
            r, X = filt.apply(r), filt.apply(X)
            T = r.shape[0]
    B = min(int(cosines), T - 1)
    XtX = np.einsum("tsi,tsj->ij", X, X)
    Xi = np.linalg.inv(XtX)
    b = Xi @ np.einsum("tsi,ts->i", X, r)
    x1 = X.sum(axis=2)  # the common-scale column
    b0 = float(np.sum(x1 * r) / np.sum(x1 * x1))
    e0 = r - b0 * x1
    C = np.zeros((k, q))
    C[:, 0] = -1.0
    C[np.arange(k), np.arange(1, q)] = 1.0
    c_t = np.einsum("ki,ij,tsj,ts->tk", C, Xi, X, e0)  # (T, q - 1), sums to C b
    # cosine weights: orthogonal to a constant, so the estimate needs no demeaning
    W = np.sqrt(2.0 / T) * np.cos(np.pi * np.arange(1, B + 1)[:, None] * (np.arange(T)[None] + 0.5) / T)
    L = W @ c_t  # (B, q - 1)
    cov = L.T @ L / B
    m = c_t.sum(axis=0) / math.sqrt(T)
    try:
        T2 = float(m @ np.linalg.solve(cov, m))
    except np.linalg.LinAlgError:
        T2 = 0.0
    dof2 = B - k + 1
    F = T2 * dof2 / (k * B)
    p = float(_st.f.sf(F, k, dof2))
    return EqualityResult(b, T2, (k, dof2), p, T, B)
