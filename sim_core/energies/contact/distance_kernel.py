"""Contact distances of vertex-triangle and edge-edge pairs, with derivatives, in Taichi kernels.

The Taichi twins of :func:`sim_core.collision.distances.point_triangle_contact_distance` and
:func:`~sim_core.collision.distances.edge_edge_contact_distance` (the reference and test oracle):
the same Voronoi-region tests (Ericson, *Real-Time Collision Detection*, 2005, sec. 5.1.5 and 5.1.9,
with the parallel-edge rule of ``PARALLEL_TOLERANCE``), the same distance per region, and the
closed-form first and second derivatives of :mod:`sim_core.collision.distance_derivatives`:

* point-point ``d = |u|``, ``u = z_i - z_j``: ``grad = (n, -n)``, ``hess = [[P, -P], [-P, P]]``,
  ``n = u / d``, ``P = (I - n n^T) / d``;
* point-line ``d = sqrt(|r x e|^2 / |e|^2)``, ``r = z_i - z_j``, ``e = z_l - z_j``: with ``s = r.e``,
  ``E = e.e``, ``t = s / E``, ``w = r - t e``, ``grad f = (2 w, -2 t w)`` over ``(r, e)`` and
  ``f_rr = 2 (I - e e^T / E)``, ``f_re = -2 (e r^T + s I) / E + 4 s e e^T / E^2``,
  ``f_ee = -2 r r^T / E + 4 s (r e^T + e r^T) / E^2 + 2 s^2 I / E^2 - 8 s^2 e e^T / E^3``; then
  ``grad d = grad f / (2 d)``, ``hess d = (hess f - 2 grad d grad d^T) / (2 d)``;
* signed plane / line-line distance ``d = side (n.r) / |n|``, ``n = u x v``, ``m = n / |n|``:
  ``grad = side (v x h_n, -(u x h_n), m)`` over ``(u, v, r)`` with ``h_n = (r - (m.r) m) / |n|``,
  ``h_rn = (I - m m^T) / |n|``, ``h_nn = (3 (m.r) m m^T - (m.r) I - r m^T - m r^T) / |n|^2``,
  ``H_uu = J_u^T h_nn J_u``, ``H_vv = J_v^T h_nn J_v``, ``H_uv = J_u^T h_nn J_v - [h_n]x``,
  ``H_ru = h_rn J_u``, ``H_rv = h_rn J_v`` (``J_u = -[v]x``, ``J_v = [u]x``).

A side of 0 (unsigned pair) takes the side of the configuration itself (sign of ``n.r``, as
``point_triangle_side`` / ``edge_edge_side``), so the caller passes the potential's step sides as
they are. Pairs are independent (no shared sums); the loops run serially on the CPU, where a few
hundred pairs take microseconds and a parallel launch costs more than it saves (and waits for a
second core), in parallel on CUDA. Results equal the NumPy reference to round-off (tests: 1e-12
relative).

Compile time: the pair kind (``point_first``: vertex-triangle 1, edge-edge 0) is a runtime
argument, so one compiled kernel serves both kinds, and the 3x3 products and the map of the
``(u, v, r)`` derivatives to the vertices are runtime loops (:func:`sim_core.ti_kernels.linalg.matmul`)
rather than unrolled expressions: Taichi's Python frontend builds every kernel in every process
(the offline cache skips only LLVM), and its time grows with the number of unrolled expressions.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.collision.distances import PARALLEL_TOLERANCE, DistanceDerivatives
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.linalg import matmul

_F64_1, _F64_2, _F64_3 = linalg.F64_1, linalg.F64_2, linalg.F64_3
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)

# Region codes, as sim_core.collision.distances.PointTriangleRegion / EdgeEdgeRegion.
_PT_FACE, _PT_EDGE_AB, _PT_EDGE_BC, _PT_EDGE_CA, _PT_VERTEX_A, _PT_VERTEX_B, _PT_VERTEX_C = range(7)
_EE_INTERIOR, _EE_A0_EDGE_B = 0, 1
_EE_B0_EDGE_A, _EE_A0_B0 = 3, 5

# (u, v, r) as combinations of the 4 local vertices (rows u, v, r; columns vertices 0..3).
_PLANE_MAP = ((0.0, -1.0, 1.0, 0.0), (0.0, -1.0, 0.0, 1.0), (1.0, -1.0, 0.0, 0.0))
"""Point-plane, z = [p, a, b, c]: u = b - a, v = c - a, r = p - a."""
_LINES_MAP = ((-1.0, 1.0, 0.0, 0.0), (0.0, 0.0, -1.0, 1.0), (1.0, 0.0, -1.0, 0.0))
"""Line-line, z = [a0, a1, b0, b1]: u = a1 - a0, v = b1 - b0, r = a0 - b0."""


@ti.func
def _z(z: ti.template(), k: ti.i32, a: ti.i32):
    return ti.Vector([z[k, a, 0], z[k, a, 1], z[k, a, 2]], ti.f64)


@ti.func
def _dot(u, v):
    """``u . v`` summed left to right, as the reference's ``(u * v).sum(axis=1)``."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


@ti.func
def _cross(u, v):
    return ti.Vector([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]], ti.f64)


@ti.func
def _skew(w):
    """``[w]x`` with ``[w]x y = w x y``."""
    return ti.Matrix([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]], ti.f64)


@ti.func
def _clip01(a: ti.f64) -> ti.f64:
    return ti.min(ti.max(a, 0.0), 1.0)


@ti.func
def _point_triangle_tests(p, a, b, c):
    """Ericson's tests in the reference's priority order (a later test wins): the region code and
    the dot products ``(region, d1, d2, d3, d4, d5, d6, va, vb, vc)`` (reference: ``_point_triangle_tests``)."""
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    region = _PT_FACE
    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        region = _PT_EDGE_BC
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        region = _PT_EDGE_CA
    if d6 >= 0 and d5 <= d6:
        region = _PT_VERTEX_C
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        region = _PT_EDGE_AB
    if d3 >= 0 and d4 <= d3:
        region = _PT_VERTEX_B
    if d1 <= 0 and d2 <= 0:
        region = _PT_VERTEX_A
    return region, d1, d2, d3, d4, d5, d6, va, vb, vc


@ti.func
def _point_triangle_region(p, a, b, c) -> ti.i32:
    """Region code of the closest point of triangle ``a b c`` to ``p`` (:func:`_point_triangle_tests`)."""
    region, _d1, _d2, _d3, _d4, _d5, _d6, _va, _vb, _vc = _point_triangle_tests(p, a, b, c)
    return region


@ti.func
def _edge_edge_closest(a0, a1, b0, b1):
    """``(s, t, region)``: closest points ``a0 + s (a1 - a0)`` and ``b0 + t (b1 - b0)`` of two segments
    and their closest-feature code (reference: ``edge_edge_closest_points``)."""
    ea, eb, r = a1 - a0, b1 - b0, a0 - b0
    A, E = _dot(ea, ea), _dot(eb, eb)
    B, C, F = _dot(ea, eb), _dot(ea, r), _dot(eb, r)
    denom = A * E - B * B
    parallel = denom < PARALLEL_TOLERANCE * A * E
    s = 0.0
    if not parallel:
        s = _clip01((B * F - C * E) / denom)
    t = (B * s + F) / E
    if t < 0.0:
        s = _clip01(-C / A)
    elif t > 1.0:
        s = _clip01((B - C) / A)
    t = _clip01(t)
    s_end = -1
    if s <= 0.0:
        s_end = 0
    elif s >= 1.0:
        s_end = 1
    t_end = -1
    if t <= 0.0:
        t_end = 0
    elif t >= 1.0:
        t_end = 1
    region = _EE_INTERIOR
    if s_end >= 0 and t_end >= 0:
        region = _EE_A0_B0 + 2 * s_end + t_end
    elif s_end >= 0:
        region = _EE_A0_EDGE_B + s_end
    elif t_end >= 0:
        region = _EE_B0_EDGE_A + t_end
    if region == _EE_INTERIOR and parallel:
        region = _EE_A0_EDGE_B
    return s, t, region


@ti.func
def _edge_edge_region(a0, a1, b0, b1) -> ti.i32:
    """Closest-feature code of two segments (:func:`_edge_edge_closest`)."""
    _s, _t, region = _edge_edge_closest(a0, a1, b0, b1)
    return region


@ti.func
def _plane_vectors(z: ti.template(), k: ti.i32, point_first: ti.i32):
    """``(u, v, r)`` of the plane (``point_first`` 1) or line-line distance (0) of pair ``k``."""
    u = ti.Vector([0.0, 0.0, 0.0], ti.f64)
    v = ti.Vector([0.0, 0.0, 0.0], ti.f64)
    r = ti.Vector([0.0, 0.0, 0.0], ti.f64)
    if point_first:
        z1 = _z(z, k, 1)
        u, v, r = _z(z, k, 2) - z1, _z(z, k, 3) - z1, _z(z, k, 0) - z1
    else:
        z0, z2 = _z(z, k, 0), _z(z, k, 2)
        u, v, r = _z(z, k, 1) - z0, _z(z, k, 3) - z2, z0 - z2
    return u, v, r


@ti.func
def _region_and_slots(z: ti.template(), k: ti.i32, point_first: ti.i32):
    """Region code and its local slots ``(kind, i, j, l)``: kind 0 plane / lines, 1 point-line
    (``z_i`` to the line ``z_j z_l``), 2 point-point (``z_i``, ``z_j``). ``point_first``: 1 for a
    vertex-triangle pair (``PointTriangleRegion`` codes), 0 for an edge-edge pair."""
    kind, i, j, l = 0, 0, 0, 0
    region = 0
    if point_first:
        region = _point_triangle_region(_z(z, k, 0), _z(z, k, 1), _z(z, k, 2), _z(z, k, 3))
        if region == _PT_EDGE_AB:
            kind, j, l = 1, 1, 2
        elif region == _PT_EDGE_BC:
            kind, j, l = 1, 2, 3
        elif region == _PT_EDGE_CA:
            kind, j, l = 1, 3, 1
        elif region >= _PT_VERTEX_A:
            kind, j = 2, region - _PT_VERTEX_A + 1
    else:
        region = _edge_edge_region(_z(z, k, 0), _z(z, k, 1), _z(z, k, 2), _z(z, k, 3))
        if region == 1:  # A0_EDGE_B
            kind, i, j, l = 1, 0, 2, 3
        elif region == 2:  # A1_EDGE_B
            kind, i, j, l = 1, 1, 2, 3
        elif region == 3:  # B0_EDGE_A
            kind, i, j, l = 1, 2, 0, 1
        elif region == 4:  # B1_EDGE_A
            kind, i, j, l = 1, 3, 0, 1
        elif region >= _EE_A0_B0:
            c = region - _EE_A0_B0  # A0_B0, A0_B1, A1_B0, A1_B1
            kind, i, j = 2, c // 2, 2 + c % 2
    return region, kind, i, j, l


@ti.func
def _resolved_side(side: ti.f64, n, r) -> ti.f64:
    """The step side, or for an unsigned pair (0) the side of ``n.r`` (0 maps to +1)."""
    out = side
    if side == 0.0:
        out = 1.0
        if _dot(n, r) < 0.0:
            out = -1.0
    return out


@ti.func
def _distance_value(z: ti.template(), k: ti.i32, side: ti.f64, point_first: ti.i32):
    region, kind, i, j, l = _region_and_slots(z, k, point_first)
    d = 0.0
    if kind == 0:
        u, v, r = _plane_vectors(z, k, point_first)
        n = _cross(u, v)
        d = (_dot(n, r) * (1.0 / ti.sqrt(_dot(n, n)))) * _resolved_side(side, n, r)
    elif kind == 1:
        a = _z(z, k, j)
        e = _z(z, k, l) - a
        c = _cross(_z(z, k, i) - a, e)
        d = ti.sqrt(_dot(c, c) * (1.0 / _dot(e, e)))
    else:
        w = _z(z, k, i) - _z(z, k, j)
        d = ti.sqrt(_dot(w, w))
    return region, d


@fast_kernel
def _values_kernel(z: _F64_3, side: _F64_1, point_first: ti.i32, d: _F64_1, region: _I32_1):
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(z.shape[0]):
        region[k], d[k] = _distance_value(z, k, side[k], point_first)


@ti.func
def _add_block(hess: ti.template(), k: ti.i32, a: ti.i32, b: ti.i32, block):
    """``hess[k]`` block ``(a, b)`` (3x3) ``+= block`` (a runtime loop: inlined 13 times per kernel)."""
    for p, q in ti.ndrange(3, 3):
        hess[k, 3 * a + p, 3 * b + q] += block[p, q]


@ti.func
def _plane_derivatives(z: ti.template(), k: ti.i32, side: ti.f64, point_first: ti.i32,
                       grad: ti.template(), hess: ti.template()) -> ti.f64:
    """Signed plane / line-line distance of pair ``k`` (returned); sets ``grad[k]`` and adds the Hessian
    to ``hess[k]`` (module docstring). The derivatives over ``(u, v, r)`` map to the four vertices
    through the rows of ``_PLANE_MAP`` / ``_LINES_MAP`` (``C``, 3x4): ``block_ab = sum_pq C_pa C_qb H_pq``,
    in runtime loops over the nonzero coefficients (the gradient's sum adds the zero terms: exact zeros)."""
    u, v, r = _plane_vectors(z, k, point_first)
    n = _cross(u, v)
    s = _resolved_side(side, n, r)
    h = _dot(n, r)
    N = ti.sqrt(_dot(n, n))
    d = (h * (1.0 / N)) * s
    m = n / N
    mr = _dot(m, r)
    h_n = (r - mr * m) / N
    g = ti.Matrix.rows([_cross(v, h_n) * s, -_cross(u, h_n) * s, m * s])  # rows over (u, v, r)
    eye = ti.Matrix.identity(ti.f64, 3)
    mm = m.outer_product(m)
    h_rn = (eye - mm) / N
    h_nn = (3.0 * mr * mm - mr * eye - r.outer_product(m) - m.outer_product(r)) / (N * N)
    Ju, Jv = -_skew(v), _skew(u)
    JuT = Ju.transpose()
    H_uu = matmul(matmul(JuT, h_nn), Ju)
    H_vv = matmul(matmul(Jv.transpose(), h_nn), Jv)
    H_uv = matmul(matmul(JuT, h_nn), Jv) - _skew(h_n)
    H_ru, H_rv = matmul(h_rn, Ju), matmul(h_rn, Jv)
    H = ti.Matrix.zero(ti.f64, 9, 9)  # blocks (p, q) over (u, v, r)
    for i, j in ti.ndrange(3, 3):
        H[i, j] = H_uu[i, j]
        H[i, 3 + j] = H_uv[i, j]
        H[i, 6 + j] = H_ru[j, i]
        H[3 + i, j] = H_uv[j, i]
        H[3 + i, 3 + j] = H_vv[i, j]
        H[3 + i, 6 + j] = H_rv[j, i]
        H[6 + i, j] = H_ru[i, j]
        H[6 + i, 3 + j] = H_rv[i, j]
    C = ti.Matrix(_LINES_MAP, ti.f64)
    if point_first:
        C = ti.Matrix(_PLANE_MAP, ti.f64)
    for a in range(4):
        for c in range(3):
            ga = 0.0
            for p in range(3):
                ga += C[p, a] * g[p, c]
            grad[k, 3 * a + c] = ga
        for b in range(4):
            block = ti.Matrix.zero(ti.f64, 3, 3)
            for p in range(3):
                if C[p, a] != 0.0:
                    inner = ti.Matrix.zero(ti.f64, 3, 3)
                    for q in range(3):
                        if C[q, b] != 0.0:
                            for i, j in ti.static(ti.ndrange(3, 3)):
                                inner[i, j] += C[q, b] * H[3 * p + i, 3 * q + j]
                    for i, j in ti.static(ti.ndrange(3, 3)):
                        block[i, j] += C[p, a] * inner[i, j]
            for i, j in ti.static(ti.ndrange(3, 3)):
                hess[k, 3 * a + i, 3 * b + j] += block[i, j] * s
    return d


@ti.func
def _point_line_derivatives(z: ti.template(), k: ti.i32, i: ti.i32, j: ti.i32, l: ti.i32,
                            grad: ti.template(), hess: ti.template()) -> ti.f64:
    a = _z(z, k, j)
    r, e = _z(z, k, i) - a, _z(z, k, l) - a
    c = _cross(r, e)
    E = _dot(e, e)
    d = ti.sqrt(_dot(c, c) * (1.0 / E))
    s = _dot(r, e)
    t = s / E
    w = r - t * e
    g_r, g_e = 2.0 * w / (2.0 * d), -2.0 * t * w / (2.0 * d)
    eye = ti.Matrix.identity(ti.f64, 3)
    ee, re = e.outer_product(e), r.outer_product(e)
    f_rr = 2.0 * (eye - ee / E)
    f_re = -2.0 * (re.transpose() + s * eye) / E + 4.0 * s * ee / E**2
    f_ee = (-2.0 * r.outer_product(r) / E + 4.0 * s * (re + re.transpose()) / E**2
            + 2.0 * s**2 * eye / E**2 - 8.0 * s**2 * ee / E**3)
    H_rr = (f_rr - 2.0 * g_r.outer_product(g_r)) / (2.0 * d)
    H_re = (f_re - 2.0 * g_r.outer_product(g_e)) / (2.0 * d)
    H_ee = (f_ee - 2.0 * g_e.outer_product(g_e)) / (2.0 * d)
    # r = z_i - z_j, e = z_l - z_j
    for c3 in ti.static(range(3)):
        grad[k, 3 * i + c3] += g_r[c3]
        grad[k, 3 * j + c3] += -g_r[c3] - g_e[c3]
        grad[k, 3 * l + c3] += g_e[c3]
    H_er = H_re.transpose()
    _add_block(hess, k, i, i, H_rr)
    _add_block(hess, k, i, l, H_re)
    _add_block(hess, k, l, i, H_er)
    _add_block(hess, k, l, l, H_ee)
    _add_block(hess, k, i, j, -(H_rr + H_re))
    _add_block(hess, k, j, i, -(H_rr + H_er))
    _add_block(hess, k, l, j, -(H_er + H_ee))
    _add_block(hess, k, j, l, -(H_re + H_ee))
    _add_block(hess, k, j, j, (H_rr + H_re) + (H_er + H_ee))
    return d


@ti.func
def _point_point_derivatives(z: ti.template(), k: ti.i32, i: ti.i32, j: ti.i32,
                             grad: ti.template(), hess: ti.template()) -> ti.f64:
    u = _z(z, k, i) - _z(z, k, j)
    d = ti.sqrt(_dot(u, u))
    n = u / d
    P = (ti.Matrix.identity(ti.f64, 3) - n.outer_product(n)) / d
    for c3 in ti.static(range(3)):
        grad[k, 3 * i + c3] += n[c3]
        grad[k, 3 * j + c3] += -n[c3]
    _add_block(hess, k, i, i, P)
    _add_block(hess, k, j, j, P)
    _add_block(hess, k, i, j, -P)
    _add_block(hess, k, j, i, -P)
    return d


@ti.func
def _pair_derivatives(z: ti.template(), k: ti.i32, side: ti.f64, point_first: ti.i32, d: ti.template(),
                      region: ti.template(), grad: ti.template(), hess: ti.template()):
    """Distance ``d[k]``, region ``region[k]``, gradient row ``grad[k]`` and Hessian ``hess[k]`` of pair ``k``."""
    for a in range(12):
        grad[k, a] = 0.0
        for b in range(12):
            hess[k, a, b] = 0.0
    reg, kind, i, j, l = _region_and_slots(z, k, point_first)
    region[k] = reg
    if kind == 0:
        d[k] = _plane_derivatives(z, k, side, point_first, grad, hess)
    elif kind == 1:
        d[k] = _point_line_derivatives(z, k, i, j, l, grad, hess)
    else:
        d[k] = _point_point_derivatives(z, k, i, j, grad, hess)


@fast_kernel
def _derivatives_kernel(z: _F64_3, side: _F64_1, point_first: ti.i32, d: _F64_1, region: _I32_1,
                        grad: _F64_2, hess: _F64_3):
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(z.shape[0]):
        _pair_derivatives(z, k, side[k], point_first, d, region, grad, hess)


def _contact_distance(z: np.ndarray, side: np.ndarray, order: int, point_first: bool) -> DistanceDerivatives:
    require_backend("contact distance kernels")
    z = np.ascontiguousarray(z, dtype=np.float64).reshape(-1, 4, 3)
    side = np.ascontiguousarray(side, dtype=np.float64).reshape(-1)
    k = z.shape[0]
    d = np.empty(k)
    region = np.empty(k, dtype=np.int32)
    if k == 0:
        grad = np.zeros((0, 12)) if order >= 1 else None
        hess = np.zeros((0, 12, 12)) if order >= 2 else None
        return DistanceDerivatives(d, grad, hess, region.astype(np.int64))
    if order == 0:
        _values_kernel(z, side, int(point_first), d, region)
        return DistanceDerivatives(d, None, None, region.astype(np.int64))
    grad = np.empty((k, 12))
    hess = np.empty((k, 12, 12))
    _derivatives_kernel(z, side, int(point_first), d, region, grad, hess)
    return DistanceDerivatives(d, grad, hess if order >= 2 else None, region.astype(np.int64))


def point_triangle_contact_distance(z: np.ndarray, side: np.ndarray, order: int = 0) -> DistanceDerivatives:
    """Vertex-triangle contact distance and derivatives (Taichi twin of the reference, module docstring).

    Args:
        z: positions ``[p, a, b, c]`` of each pair, shape ``(k, 4, 3)`` (m).
        side: step side (+1 / -1) of p w.r.t. ``(b - a) x (c - a)``, 0 for unsigned, shape ``(k,)``.
        order: 0 value only; 1 or 2 with gradient ``(k, 12)`` and Hessian ``(k, 12, 12)`` (order 1
            computes the Hessian too and leaves it out).

    Returns:
        :class:`~sim_core.collision.distances.DistanceDerivatives` with ``PointTriangleRegion`` codes.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    return _contact_distance(z, side, order, True)


def edge_edge_contact_distance(z: np.ndarray, side: np.ndarray, order: int = 0) -> DistanceDerivatives:
    """Edge-edge contact distance and derivatives (Taichi twin of the reference, module docstring).

    Args:
        z: positions ``[a0, a1, b0, b1]`` of each pair, shape ``(k, 4, 3)`` (m).
        side: step sign of ``((a1 - a0) x (b1 - b0)).(a0 - b0)``, 0 for unsigned, shape ``(k,)``.
        order: as :func:`point_triangle_contact_distance`.

    Returns:
        :class:`~sim_core.collision.distances.DistanceDerivatives` with ``EdgeEdgeRegion`` codes.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    return _contact_distance(z, side, order, False)


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the four kernels on one pair each, so that
    the first Newton step does not pay for it.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    z = np.array([[[0.0, 0.0, 1.0e-3], [0.0, 0.0, 0.0], [1.0e-2, 0.0, 0.0], [0.0, 1.0e-2, 0.0]]])
    for distance in (point_triangle_contact_distance, edge_edge_contact_distance):
        for order in (0, 2):
            distance(z, np.ones(1), order)
