"""Closed-form gradients and Hessians of the contact distance primitives.

The narrow phase (:mod:`sim_core.collision.distances`) measures a pair of 4 vertices ``z`` (shape
``(k, 4, 3)``, local DoF ``3 a + d``) with one of three primitives; this module gives their values
(the same floating-point expressions as the forward-mode jets of :mod:`sim_core.collision.jets`,
which stay as the reference in the tests) and their exact first and second derivatives by the
chain rule through a few intermediate vectors, without carrying 12x12 jets through every product.

* point-point ``d = |u|``, ``u = z_i - z_j``: ``grad = (n, -n)``, ``n = u / d``;
  ``hess = [[P, -P], [-P, P]]``, ``P = (I - n n^T) / d``.
* point-line ``d = sqrt(f)``, ``f = |r x e|^2 / |e|^2 = |r|^2 - (r.e)^2 / |e|^2`` with ``r = z_i - z_j``,
  ``e = z_l - z_j``. With ``s = r.e``, ``E = e.e``, ``t = s / E`` and ``w = r - t e``:
  ``f_r = 2 w``, ``f_e = -2 t w``, ``f_rr = 2 (I - e e^T / E)``,
  ``f_re = -2 (e r^T + s I) / E + 4 s e e^T / E^2``,
  ``f_ee = -2 r r^T / E + 4 s (r e^T + e r^T) / E^2 + 2 s^2 I / E^2 - 8 s^2 e e^T / E^3``;
  then ``grad d = grad f / (2 d)``, ``hess d = (hess f - 2 grad d grad d^T) / (2 d)``.
* signed plane / line-line distance ``d = side (n.r) / |n|``, ``n = u x v``: with ``N = |n|``,
  ``m = n / N``: ``h_r = m``, ``h_n = (r - (m.r) m) / N``, ``h_rn = (I - m m^T) / N``,
  ``h_nn = (3 (m.r) m m^T - (m.r) I - r m^T - m r^T) / N^2``; ``dn/du = -[v]x``,
  ``dn/dv = [u]x`` and ``d2 n_k / du_i dv_j = eps_kij``, so ``h_uv = J_u^T h_nn J_v - [h_n]x``.

Each primitive is differentiated in its own variables (``(u, v, r)`` or ``(r, e)``), which are
fixed linear combinations of the vertices; the result is mapped back to the 12 local DoFs.
"""

from __future__ import annotations

import numpy as np

from sim_core.collision.jets import Jet

_I3 = np.eye(3)

# (u, v, r) as combinations of the 4 vertices: rows are u, v, r, columns vertices 0..3
_PLANE_MAP = np.array([[0.0, -1.0, 1.0, 0.0], [0.0, -1.0, 0.0, 1.0], [1.0, -1.0, 0.0, 0.0]])
"""Point-plane, z = [p, a, b, c]: u = b - a, v = c - a, r = p - a."""
_LINES_MAP = np.array([[-1.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 1.0], [1.0, 0.0, -1.0, 0.0]])
"""Line-line, z = [a0, a1, b0, b1]: u = a1 - a0, v = b1 - b0, r = a0 - b0."""
_POINT_LINE_MAP = np.array([[1.0, -1.0, 0.0], [0.0, -1.0, 1.0]])
"""Point-line over (p, a, b): r = p - a, e = b - a."""


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[:, :, None] * b[:, None, :]


def _skew(w: np.ndarray) -> np.ndarray:
    """``[w]x`` with ``[w]x y = w x y``, shape ``(k, 3, 3)``."""
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[:, 0, 1], out[:, 0, 2] = -w[:, 2], w[:, 1]
    out[:, 1, 0], out[:, 1, 2] = w[:, 2], -w[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -w[:, 1], w[:, 0]
    return out


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    nxt, prv = [1, 2, 0], [2, 0, 1]
    return u[:, nxt] * v[:, prv] - u[:, prv] * v[:, nxt]


def _sum_dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return (u * v).sum(axis=1)


def _to_vertices(coeff: np.ndarray, g: np.ndarray, H: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """Map derivatives in variables ``y_p = sum_a coeff[p, a] x_a`` to the vertices ``x_a``.

    Args:
        coeff: ``(q, m)``; g: ``(k, 3 q)``; H: ``(k, 3 q, 3 q)`` or None.

    Returns:
        ``(k, 3 m)`` gradient and ``(k, 3 m, 3 m)`` Hessian (or None).
    """
    k, (q, m) = g.shape[0], coeff.shape
    gx = np.einsum("pa,kpi->kai", coeff, g.reshape(k, q, 3)).reshape(k, 3 * m)
    if H is None:
        return gx, None
    T = np.einsum("qb,kpiqj->kpibj", coeff, H.reshape(k, q, 3, q, 3))
    Hx = np.einsum("pa,kpibj->kaibj", coeff, T).reshape(k, 3 * m, 3 * m)
    return gx, Hx


def _scatter(slots: np.ndarray, g: np.ndarray, H: np.ndarray | None, order: int) -> tuple:
    """Place per-pair local derivatives over vertex ``slots`` ``(k, m)`` into the 12 pair DoFs."""
    k, m = slots.shape
    rows = np.arange(k)[:, None]
    dof = (3 * slots[:, :, None] + np.arange(3)).reshape(k, 3 * m)
    grad = np.zeros((k, 12))
    grad[rows, dof] = g
    hess = None
    if order >= 2:
        hess = np.zeros((k, 12, 12))
        hess[rows[:, :, None], dof[:, :, None], dof[:, None, :]] = H
    return grad, hess


def point_point(z: np.ndarray, i: np.ndarray, j: np.ndarray, order: int) -> Jet:
    """``|z_i - z_j|`` with derivatives over the 12 DoFs (module docstring); slots ``(k,)`` each."""
    rows = np.arange(z.shape[0])
    u = z[rows, i] - z[rows, j]
    d = np.sqrt(_sum_dot(u, u))
    if order == 0:
        return Jet(d, None, None, 0)
    n = u / d[:, None]
    g = np.concatenate([n, -n], axis=1)
    H = None
    if order >= 2:
        P = (_I3 - _outer(n, n)) / d[:, None, None]
        H = np.concatenate([np.concatenate([P, -P], axis=2), np.concatenate([-P, P], axis=2)], axis=1)
    grad, hess = _scatter(np.stack([i, j], axis=1), g, H, order)
    return Jet(d, grad, hess, order)


def point_line(z: np.ndarray, i: np.ndarray, j: np.ndarray, l: np.ndarray, order: int) -> Jet:
    """Distance from ``z_i`` to the line through ``z_j``, ``z_l`` with derivatives (module docstring)."""
    rows = np.arange(z.shape[0])
    a = z[rows, j]
    r, e = z[rows, i] - a, z[rows, l] - a
    c = _cross(r, e)
    E = _sum_dot(e, e)
    d = np.sqrt(_sum_dot(c, c) * (1.0 / E))
    if order == 0:
        return Jet(d, None, None, 0)
    s = _sum_dot(r, e)
    t = s / E
    w = r - t[:, None] * e
    gf = np.concatenate([2.0 * w, -2.0 * t[:, None] * w], axis=1)  # (k, 6) over (r, e)
    gd = gf / (2.0 * d)[:, None]
    Hd = None
    if order >= 2:
        Ec, sc = E[:, None, None], s[:, None, None]
        ee, re = _outer(e, e), _outer(r, e)
        f_rr = 2.0 * (_I3 - ee / Ec)
        f_re = -2.0 * (np.swapaxes(re, 1, 2) + sc * _I3) / Ec + 4.0 * sc * ee / Ec**2
        f_ee = (-2.0 * _outer(r, r) / Ec + 4.0 * sc * (re + np.swapaxes(re, 1, 2)) / Ec**2
                + 2.0 * sc**2 * _I3 / Ec**2 - 8.0 * sc**2 * ee / Ec**3)
        Hf = np.concatenate([np.concatenate([f_rr, f_re], axis=2),
                             np.concatenate([np.swapaxes(f_re, 1, 2), f_ee], axis=2)], axis=1)
        Hd = (Hf - 2.0 * _outer(gd, gd)) / (2.0 * d)[:, None, None]
    g9, H9 = _to_vertices(_POINT_LINE_MAP, gd, Hd)
    grad, hess = _scatter(np.stack([i, j, l], axis=1), g9, H9, order)
    return Jet(d, grad, hess, order)


def signed_volume(z: np.ndarray, side: np.ndarray, point_first: bool, order: int) -> Jet:
    """``side (n.r) / |n|`` of a point-plane (``point_first``) or line-line pair (module docstring)."""
    if point_first:
        u, v, r, coeff = z[:, 2] - z[:, 1], z[:, 3] - z[:, 1], z[:, 0] - z[:, 1], _PLANE_MAP
    else:
        u, v, r, coeff = z[:, 1] - z[:, 0], z[:, 3] - z[:, 2], z[:, 0] - z[:, 2], _LINES_MAP
    n = _cross(u, v)
    h = _sum_dot(n, r)
    N = np.sqrt(_sum_dot(n, n))
    d = (h * (1.0 / N)) * side
    if order == 0:
        return Jet(d, None, None, 0)
    m = n / N[:, None]
    mr = _sum_dot(m, r)
    h_n = (r - mr[:, None] * m) / N[:, None]
    Ju, Jv = -_skew(v), _skew(u)  # dn/du, dn/dv
    g = np.concatenate([_cross(v, h_n), -_cross(u, h_n), m], axis=1) * side[:, None]  # (u, v, r)
    H = None
    if order >= 2:
        Nc = N[:, None, None]
        h_rn = (_I3 - _outer(m, m)) / Nc
        h_nn = (3.0 * mr[:, None, None] * _outer(m, m) - mr[:, None, None] * _I3
                - _outer(r, m) - _outer(m, r)) / Nc**2
        JuT, JvT = np.swapaxes(Ju, 1, 2), np.swapaxes(Jv, 1, 2)
        H_uu = JuT @ h_nn @ Ju
        H_vv = JvT @ h_nn @ Jv
        H_uv = JuT @ h_nn @ Jv - _skew(h_n)
        H_ru, H_rv = h_rn @ Ju, h_rn @ Jv
        zero = np.zeros_like(H_uu)
        H = np.concatenate([
            np.concatenate([H_uu, H_uv, np.swapaxes(H_ru, 1, 2)], axis=2),
            np.concatenate([np.swapaxes(H_uv, 1, 2), H_vv, np.swapaxes(H_rv, 1, 2)], axis=2),
            np.concatenate([H_ru, H_rv, zero], axis=2),
        ], axis=1) * side[:, None, None]
    grad, hess = _to_vertices(coeff, g, H)
    return Jet(d, grad, hess, order)
