"""The pair batch's per-pair Taichi functions: one candidate pair measured into a launch's work rows.

:func:`measure_pair` gathers a vertex-triangle or edge-edge pair's positions, rules it out with the exact distance
bounds of :mod:`sim_core.collision.distance_bounds` (:func:`_may_touch`), measures its distance and region and, with
derivatives and ``d < eps``, its distance gradient, penalty Hessian ``k_c (grad d grad d^T + (d - eps) hess d)`` and
penalty gradient ``k_c (d - eps) grad d`` summed per vertex: what every launch of
:mod:`sim_core.energies.contact.batch_kernel` and :mod:`sim_core.energies.contact.listed_kernel` does with a pair
(the same functions, so their values are equal bit for bit).
"""

# No ``from __future__ import annotations`` here: Taichi reads ti.func annotations as objects.

from sim_core.collision.distance_bounds import MIN_SINE_SQUARED, RELATIVE_SLACK
from sim_core.energies.contact import distance_kernel as cd
from sim_core.energies.contact.setup_kernel import _vertex
from sim_core.ti_backend import serial_loops, ti


@ti.func
def _may_touch(z0, z1, z2, z3, side: ti.f64, eps: ti.f64, point_first: ti.i32) -> ti.i32:
    """0 when pair ``[z0, z1, z2, z3]`` (``[p, a, b, c]`` with ``point_first``, else ``[a0, a1, b0, b1]``)
    is farther than ``eps`` for certain: the box and plane bounds of
    :mod:`sim_core.collision.distance_bounds` (same tests and margins, one pair)."""
    limit = eps * (1.0 + RELATIVE_SLACK)
    # the first primitive's points z0 (and z1 for an edge), the second's z2, z3 (and z1 for a triangle)
    w, y = z1, z1
    u, v, r = z2 - z1, z3 - z1, z0 - z1
    if point_first:
        w = z0
    else:
        y = z2
        u, v, r = z1 - z0, z3 - z2, z0 - z2
    a_lo, a_hi = ti.min(z0, w), ti.max(z0, w)
    b_lo, b_hi = ti.min(ti.min(z2, z3), y), ti.max(ti.max(z2, z3), y)
    gap = ti.max(a_lo - b_hi, b_lo - a_hi)
    box_far = gap[0] > limit or gap[1] > limit or gap[2] > limit
    n = cd._cross(u, v)
    nn = cd._dot(n, n)
    usable = nn >= MIN_SINE_SQUARED * cd._dot(u, u) * cd._dot(v, v)
    h = 0.0
    if usable:
        h = cd._dot(n, r) / ti.sqrt(nn)
    far = usable and side * h > limit
    if side == 0.0:
        far = box_far or (usable and ti.abs(h) > limit)
    return ti.cast(not far, ti.i32)


@ti.func
def _penalty_hessian(i: ti.i32, gap: ti.f64, stiffness: ti.f64, grad: ti.template(), hess: ti.template()):
    """Row ``i`` of ``hess``, a distance Hessian, replaced by the penalty Hessian
    ``k_c (grad d grad d^T + (d - eps) hess d)`` (``gap = d - eps``), the reference's operations in its order."""
    for a in range(12):
        for b in range(12):
            hess[i, a, b] = (grad[i, a] * grad[i, b] + gap * hess[i, a, b]) * stiffness


@ti.func
def _scatter_penalty_gradient(i: ti.i32, k: ti.i32, scale: ti.f64, first_row: ti.i32, vertices: ti.template(),
                              grad: ti.template(), gradients: ti.template()):
    """``gradients[first_row + v] += scale * grad d`` over the vertices ``v`` of pair ``k`` (its distance
    gradient in row ``i`` of ``grad``, ``scale = k_c (d - eps)``): the sums of the reference's
    ``scatter_gradient`` (one ``np.bincount`` in pair, vertex, axis order) when pairs come in order."""
    for a in range(4):
        row = first_row + vertices[k, a]
        for c in ti.static(range(3)):
            gradients[row, c] += scale * grad[i, 3 * a + c]


@ti.func
def measure_pair(x: ti.template(), vertices: ti.template(), side: ti.template(), k: ti.i32, i: ti.i32,
                  split: ti.i32, eps_vt: ti.f64, eps_ee: ti.f64, stiffness_vt: ti.f64, stiffness_ee: ti.f64,
                  rows_ee: ti.i32, derivatives: ti.i32, z: ti.template(), d: ti.template(), region: ti.template(),
                  grad: ti.template(), hess: ti.template(), gradients: ti.template()):
    """Pair ``k`` (``k < split`` vertex-triangle, else edge-edge) into row ``i`` of the work arrays: its positions
    gathered into ``z[i]``, distance ``d[i]`` and region, or ``d[i] = inf`` and region -1 where the bounds of
    :func:`_may_touch` rule it out; with ``derivatives`` and ``d < eps`` (``eps`` of its kind) the distance gradient
    ``grad[i]``, the penalty Hessian ``hess[i]`` and its penalty gradient added per vertex into ``gradients`` (rows
    ``v``, or ``rows_ee + v`` for an edge-edge pair). Returns 1 where ``d < eps``, else 0."""
    point_first = 0
    eps, stiffness, first_row = eps_ee, stiffness_ee, rows_ee
    if k < split:
        point_first = 1
        eps, stiffness, first_row = eps_vt, stiffness_vt, 0
    p0, p1, p2, p3 = (_vertex(x, vertices, k, 0), _vertex(x, vertices, k, 1), _vertex(x, vertices, k, 2),
                      _vertex(x, vertices, k, 3))
    if _may_touch(p0, p1, p2, p3, side[k], eps, point_first):
        for c in ti.static(range(3)):
            z[i, 0, c], z[i, 1, c], z[i, 2, c], z[i, 3, c] = p0[c], p1[c], p2[c], p3[c]
        region[i], d[i] = cd._distance_value(z, i, side[k], point_first)  # inlined once, both kinds
        if derivatives:
            if d[i] < eps:
                cd._pair_derivatives(z, i, side[k], point_first, d, region, grad, hess)
                _penalty_hessian(i, d[i] - eps, stiffness, grad, hess)
                _scatter_penalty_gradient(i, k, stiffness * (d[i] - eps), first_row, vertices, grad, gradients)
    else:
        region[i], d[i] = -1, ti.math.inf
    return ti.cast(d[i] < eps, ti.i32)


@ti.func
def zero_sums(gradients: ti.template(), rows: ti.i32, active_count: ti.template()):
    """The pair kernels' preamble: ``gradients[:rows] = 0`` and ``active_count[0] = 0``. Called at a kernel's top level,
    so that its two loops are top-level loops of the kernel (parallel on a GPU, serial where :func:`serial_loops`)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for j in range(rows):
        for c in ti.static(range(3)):
            gradients[j, c] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for _ in range(1):
        active_count[0] = 0
