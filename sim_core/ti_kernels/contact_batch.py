"""One kernel launch evaluates a vertex-triangle and an edge-edge contact potential together.

The Newton solver asks the step's two pair potentials for their energy (line search), then for the
gradient and Hessian (iterate) at the same positions, one potential after the other. Evaluated
separately, each potential launches the distance kernels of :mod:`sim_core.ti_kernels.contact_distance`
once or twice per request (values of every pair, then derivatives of the active ones) after a NumPy
gather of the pair positions. A :class:`PairBatch` links the two potentials: the first request at
new positions ``x`` evaluates both in one launch of :func:`_batch_kernel` (the pair positions
gathered in the kernel; the distance of every pair; with derivatives, the gradient and Hessian of
the active pairs ``d < eps``), and each potential keeps its part as its evaluation of ``x`` (the
``_last`` of :meth:`sim_core.potentials.contact._PairPenalty._evaluate`), so the second request
finds it there.

When both potentials already keep the distances of ``x`` (the energy of the accepted line-search
point, the next Newton iterate), the derivatives are computed for their active pairs only. The
kernel calls the same Taichi functions as the separate kernels, so every distance, gradient and
Hessian equals theirs bit for bit (tests).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.collision.distances import DistanceDerivatives
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels import contact_distance as cd
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.launch import fast_kernel

_F64_1, _F64_2, _F64_3, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_2
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@ti.func
def _pair(z: ti.template(), i: ti.i32, side: ti.f64, eps: ti.f64, point_first: ti.i32,
          derivatives: ti.i32, d: ti.template(), region: ti.template(), grad: ti.template(),
          hess: ti.template()):
    region[i], d[i] = cd._distance_value(z, i, side, point_first)
    if derivatives:
        if d[i] < eps:
            cd._pair_derivatives(z, i, side, point_first, d, region, grad, hess)


@fast_kernel
def _batch_kernel(x: _F64_2, vertices: _I32_2, side: _F64_1, rows: _I32_1, split: ti.i32, eps_vt: ti.f64,
                  eps_ee: ti.f64, derivatives: ti.i32, z: _F64_3, d: _F64_1, region: _I32_1, grad: _F64_2,
                  hess: _F64_3):
    """Pairs ``k = rows[i]`` (``k < split`` vertex-triangle, else edge-edge): positions gathered into
    ``z[i]``, distance ``d[i]`` and region; with ``derivatives`` the gradient and Hessian rows ``i``
    of the pairs with ``d < eps`` of their kind (the other rows are left as they are). ``derivatives``
    (0 or 1) and the pair kind are runtime values: one compiled kernel for every request."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(rows.shape[0]):
        k = rows[i]
        for a in ti.static(range(4)):
            v = vertices[k, a]
            for c in ti.static(range(3)):
                z[i, a, c] = x[v, c]
        point_first = 0
        eps = eps_ee
        if k < split:
            point_first = 1
            eps = eps_vt
        _pair(z, i, side[k], eps, point_first, derivatives, d, region, grad, hess)  # inlined once, both kinds


class PairBatch:
    """Evaluates a vertex-triangle and an edge-edge pair potential in one launch (module docstring).

    Args:
        vt: a :class:`~sim_core.potentials.contact.VertexTriangleContact` (its ``vertices`` ``(p, 4)``
            and ``sides`` ``(p,)``).
        ee: an :class:`~sim_core.potentials.contact.EdgeEdgeContact` (``(q, 4)``, ``(q,)``).

    Pairs and sides are fixed at construction (as the potentials' are); each potential's own ``eps``
    is read at every evaluation.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """

    def __init__(self, vt, ee) -> None:
        require_backend("PairBatch")
        self.vt, self.ee = vt, ee
        self.split = int(vt.vertices.shape[0])
        self.vertices = np.ascontiguousarray(np.concatenate([vt.vertices, ee.vertices]), dtype=np.int32)
        self.sides = np.ascontiguousarray(np.concatenate([vt.sides, ee.sides]), dtype=np.float64)
        self._all = np.arange(self.vertices.shape[0], dtype=np.int32)
        vt._batch = ee._batch = self

    def evaluate(self, x: np.ndarray, derivatives: bool) -> None:
        """Evaluate both potentials at positions ``x`` ``(n, 3)`` (m) and keep each one's part as its
        evaluation of ``x``: active pairs and distances, with ``derivatives`` also their gradients
        ``(a, 12)`` and Hessians ``(a, 12, 12)``. Derivatives after both kept the distances of ``x``
        are computed for their active pairs only; a potential that already keeps an evaluation of
        ``x`` at least as complete keeps it."""
        pots = (self.vt, self.ee)
        kept = [pot.kept_evaluation(x, 0) for pot in pots]
        if derivatives and kept[0] is not None and kept[1] is not None:
            rows = np.concatenate([kept[0][0], kept[1][0] + self.split]).astype(np.int32)
            parts = (slice(0, len(kept[0][0])), slice(len(kept[0][0]), len(rows)))
        else:
            rows, kept = self._all, [None, None]
            parts = (slice(0, self.split), slice(self.split, len(rows)))
        # work arrays of this evaluation only (potentials kept for the adjoint must not hold them)
        m = len(rows)
        d, region = np.empty(m), np.empty(m, dtype=np.int32)
        rows_d = m if derivatives else 0
        grad, hess = np.empty((rows_d, 12)), np.empty((rows_d, 12, 12))
        if m:
            _batch_kernel(np.ascontiguousarray(x, dtype=np.float64), self.vertices, self.sides, rows, self.split,
                          float(self.vt.eps), float(self.ee.eps), int(bool(derivatives)), np.empty((m, 4, 3)), d,
                          region, grad, hess)
        order = 2 if derivatives else 0
        x_kept = np.array(x, dtype=float, copy=True)
        for pot, part, known in zip(pots, parts, kept):
            if pot.kept_evaluation(x, order) is not None:
                continue
            dk = d[part]
            if known is None:
                active = np.flatnonzero(dk < pot.eps)
                select = active
            else:  # the rows are the known active pairs, in order
                active, select = known[0], slice(None)
            if derivatives:
                dd = DistanceDerivatives(dk[select].copy(), grad[part][select].copy(), hess[part][select].copy(),
                                         region[part][select].astype(np.int64))
            else:
                dd = DistanceDerivatives(dk[select].copy(), None, None, np.zeros(active.shape, np.int64))
            pot._last = (order, x_kept, active, dd, pot.eps)


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the kernel; runs it without and with derivatives.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    from sim_core.ti_kernels.contact import TiEdgeEdgeContact, TiVertexTriangleContact

    x = np.array([[0.0, 0.0, 1.0e-3], [0.0, 0.0, 0.0], [1.0e-2, 0.0, 0.0], [0.0, 1.0e-2, 0.0]])
    vt = TiVertexTriangleContact(np.array([[0, 0]]), np.array([[1, 2, 3]]), np.ones(1), 1.0, 2.0e-3)
    ee = TiEdgeEdgeContact(np.array([[0, 1]]), np.array([[0, 1], [2, 3]]), np.ones(1), 1.0, 2.0e-3)
    batch = PairBatch(vt, ee)
    for derivatives in (False, True):
        batch.evaluate(x, derivatives)
