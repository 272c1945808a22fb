"""Where the local phase of :func:`sysid.fit.fit` may step: the first trust region's width and the coordinates it holds.

A trust-region step along a direction the residual barely sees is set by the region's size, not by the data:
SciPy's reflective ``least_squares`` (Branch, Coleman & Li 1999) with ``x_scale = 1`` and the default +-ln(1000)
bounds of a log parameter starts with a region 2.63 log units wide, and on nominal_s101 the bending stiffness'
first step was x13.8 (session 51; docs/benchmarks_log.md, session 52, 49fit). :func:`first_region_scale` makes
the first region a chosen width; :func:`unidentified_coordinates` and :func:`unseen_columns` say which
coordinates the data do not determine at a point, which ``fit(hold_unidentified=True)`` then holds by the column
:func:`held_jacobian` gives them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

from sim_core.errors import CalibrationError
from sim_core.parameter_coordinates import ParameterSpec
from sysid.covariance import model_robust_covariance, not_identified

if TYPE_CHECKING:
    from sysid.observation import ObservationModel


def first_region_scale(u: np.ndarray, lb: np.ndarray, ub: np.ndarray, first_step: float | None) -> np.ndarray | float:
    """``x_scale`` of ``scipy.optimize.least_squares(method="trf")`` that makes its first trust region at most
    ``first_step`` wide in every search coordinate at ``u`` ``(p,)`` within bounds ``lb``, ``ub`` ``(p,)``.

    The reflective method bounds a step by ``|step_i| <= Delta sqrt(v_i x_scale_i)``, ``Delta = 1`` at a start
    ``u = 0``, ``v_i`` the Coleman-Li scaling: the distance to the bound the gradient points at (Branch,
    Coleman & Li 1999, SIAM J. Sci. Comput. 21(1), sec. 2; SciPy's ``trf_bounds``), or ``|step_i| <= Delta
    x_scale_i`` where that bound is infinite. With ``x_scale = 1`` and the default ``+-ln(1000)`` bounds of a log
    parameter the first region is ``sqrt(ln 1000) = 2.63`` wide, a factor 13.8: on nominal_s101 the bending
    stiffness' first step (session 51). Here ``x_scale_i = first_step^2 / D_i``, ``D_i`` the larger finite distance
    to a bound (at least ``first_step``), and ``first_step`` where both bounds are infinite (with one bound
    infinite the region is ``first_step^2 / D_i`` wide where the gradient points at that one). The region then
    grows or shrinks by the method's own rule (doubled after a step the linear model predicted well).
    None or 0: ``x_scale = 1``.
    """
    if not first_step:
        return 1.0
    u = np.asarray(u, dtype=float)
    dist = np.stack([u - lb, ub - u])
    finite = np.isfinite(dist)
    D = np.maximum(np.where(finite, dist, 0.0).max(axis=0), float(first_step))
    return np.where(finite.any(axis=0), float(first_step) ** 2 / D, float(first_step))


def unseen_columns(J: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """``(p,)`` bool, True where column ``j`` of ``J`` ``(m, p)`` is zero to ``rcond`` of the largest column's squared
    norm: a parameter the replay does not see at all (e.g. a friction on a recording that never slides)."""
    col = np.einsum("ij,ij->j", J, J)
    return col <= rcond * col.max() if col.size and col.max() > 0.0 else np.ones(col.size, dtype=bool)


def robust_sigma(model: "ObservationModel", J: np.ndarray, r: np.ndarray, seen: np.ndarray, method: str,
                 seed: int) -> np.ndarray | None:
    """Robust 1-sigma ``(p,)`` of the search coordinates from the Jacobian ``J`` ``(m, p)``'s ``seen`` columns and the
    residual ``r`` ``(m,)`` (:func:`sysid.covariance.model_robust_covariance`; an unseen coordinate's is infinite), or
    None where it cannot be computed."""
    try:
        rob = model_robust_covariance(model, J[:, seen], r, method, seed)
    except CalibrationError:
        return None
    sigma = np.full(J.shape[1], np.inf)
    sigma[seen] = np.sqrt(np.diag(rob.covariance_u))
    return sigma


def unidentified_coordinates(specs: Sequence[ParameterSpec], u: np.ndarray, sigma_u: np.ndarray) -> np.ndarray:
    """Which coordinates :func:`sysid.covariance.not_identified` judges not identified at ``u`` ``(p,)`` given their
    1-sigma ``sigma_u`` ``(p,)`` in the search coordinates (a log parameter: ``sigma_u >= 0.5``, first order).

    Returns:
        ``(p,)`` bool, in ``specs`` order.
    """
    values = {s.name: s.to_value(float(ui)) for s, ui in zip(specs, np.asarray(u, dtype=float))}
    out = not_identified(specs, values, sigma_of(specs, values, np.diag(np.asarray(sigma_u, dtype=float) ** 2)))
    return np.array([s.name in out for s in specs], dtype=bool)


def sigma_of(specs: Sequence[ParameterSpec], values: Mapping[str, float], cov_u: np.ndarray) -> dict[str, float]:
    """1-sigma per parameter in its units from a covariance of the coordinates (first order for log ones)."""
    su = np.sqrt(np.maximum(np.diag(cov_u), 0.0))
    return {s.name: float(abs(values[s.name]) * sd if s.log else s.scale * sd) for s, sd in zip(specs, su)}


def held_jacobian(J: np.ndarray, r: np.ndarray, held: np.ndarray) -> np.ndarray:
    """The Jacobian ``(m, p)`` that ``least_squares(method="trf")`` is handed so that it takes no step along the
    ``held`` ``(p,)`` coordinates, from the replay's Jacobian ``J`` ``(m, p)`` and residual ``r`` ``(m,)``.

    A held column is replaced by one orthogonal to ``r`` and to every other column, as long as the longest column
    (unit where every column is zero): its gradient ``J^T r`` is zero and it decouples from the others, so the
    trust-region subproblem's solution has no component along it (to round-off), while ``J`` keeps full rank.
    Zeroing the column instead makes ``J`` rank deficient, and SciPy's exact trust-region solver (``solve_lsq_
    trust_region``, More & Sorensen) then returns a step on the region's boundary rather than the Gauss-Newton
    step inside it: on nominal_s101 from the scene start the first step was 0.33 / 0.37 log units in the modulus
    and friction where Gauss-Newton asked 0.027 / 0.047, and cost x5.8 (docs/benchmarks_log.md, session 52, 49fit2).

    Raises:
        CalibrationError: ``J`` has at least as many columns as rows, so no orthogonal column exists.
    """
    J = np.array(J, dtype=float)
    held = np.asarray(held, dtype=bool)
    if not held.any():
        return J
    m = J.shape[0]
    if m <= J.shape[1]:
        raise CalibrationError(f"cannot hold a parameter with {m} residuals for {J.shape[1]} parameters")
    norms = np.sqrt(np.einsum("ij,ij->j", J, J))
    length = float(norms.max()) if norms.max() > 0.0 else 1.0
    basis = [v for v in (*J[:, ~held].T, np.asarray(r, dtype=float)) if np.any(v)]
    Q = np.linalg.qr(np.stack(basis, axis=1))[0] if basis else np.zeros((m, 0))
    rng = np.random.default_rng(0)  # a fixed direction: the same Jacobian gives the same column
    for j in np.flatnonzero(held):
        c = rng.standard_normal(m)
        for _ in range(2):  # twice: Gram-Schmidt to round-off
            c -= Q @ (Q.T @ c)
        c /= np.linalg.norm(c)
        Q = np.column_stack([Q, c])
        J[:, j] = length * c
    return J
