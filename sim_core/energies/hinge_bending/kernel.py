"""Discrete-shell hinge bending in Taichi: energy, gradient and projected 12x12 Hessian blocks.

The same quantities as :class:`sim_core.energies.hinge_bending.reference.DiscreteShellBending` (the reference and
test oracle), one hinge per thread. Hinge ``[x0, x1, x2, x3]``, ``e = x1 - x0``,
``n0 = e x (x2 - x0)``, ``n1 = (x3 - x0) x e``, ``theta = atan2(e_hat . (n1 x n0), n0 . n1)``
(Grinspun et al. 2003; Tamstorf & Grinspun 2013 for the sign)::

    E = sum_h k_h (theta - theta_bar)^2,           k_h = (D / 2) c |e|^2 / (A0 + A1),
    dtheta/dx_v = C0_v m0 + C1_v m1,  m_i = n_i / |n_i|^2                 (Bridson et al. 2003),
    H_h = 2 k_h (dtheta dtheta^T + (theta - theta_bar) d2theta),

with the closed-form ``d2theta`` of :func:`sim_core.energies.hinge_bending.reference.dihedral_angle_hessian`
(product rule on ``C`` and ``m``; ``dm = (I - 2 n_hat n_hat^T) dn / |n|^2``). Blocks are projected
in the 9-D complement of the rigid translations (Jacobi).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection
from sim_core.energies.hinge_bending.reference import DiscreteShellBending
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels.buffers import DeviceArray, upload_constant
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.linalg import matmul, project_psd_translation_free, projection_code


@ti.func
def _hinge_positions(x: ti.types.ndarray(), hinges: ti.types.ndarray(), h: ti.i32):
    """The hinge's four vertex positions as vectors ``x0, x1, x2, x3``."""
    v0, v1, v2, v3 = hinges[h, 0], hinges[h, 1], hinges[h, 2], hinges[h, 3]
    x0 = ti.Vector([x[v0, 0], x[v0, 1], x[v0, 2]])
    x1 = ti.Vector([x[v1, 0], x[v1, 1], x[v1, 2]])
    x2 = ti.Vector([x[v2, 0], x[v2, 1], x[v2, 2]])
    x3 = ti.Vector([x[v3, 0], x[v3, 1], x[v3, 2]])
    return x0, x1, x2, x3


@ti.func
def _dihedral_angle(x0, x1, x2, x3):
    """Signed dihedral angle ``theta`` in rad (module docstring)."""
    e = x1 - x0
    n0 = e.cross(x2 - x0)
    n1 = (x3 - x0).cross(e)
    return ti.atan2(n1.cross(n0).dot(e) / e.norm(), n0.dot(n1))


@ti.func
def _theta_gradient(x0, x1, x2, x3):
    """``dtheta/dx`` as a 12-vector (vertex-major) of hinge ``[x0, x1, x2, x3]``."""
    e = x1 - x0
    le = e.norm()
    n0 = e.cross(x2 - x0)
    n1 = (x3 - x0).cross(e)
    m0 = n0 / n0.dot(n0)
    m1 = n1 / n1.dot(n1)
    c00 = (x2 - x1).dot(e) / le
    c01 = -(x2 - x0).dot(e) / le
    c10 = (x3 - x1).dot(e) / le
    c11 = -(x3 - x0).dot(e) / le
    g = ti.Vector.zero(ti.f64, 12)
    for i in ti.static(range(3)):
        g[i] = c00 * m0[i] + c10 * m1[i]
        g[3 + i] = c01 * m0[i] + c11 * m1[i]
        g[6 + i] = le * m0[i]
        g[9 + i] = le * m1[i]
    return g


@ti.func
def _cross_matrix(v):
    """``[v]_x`` with ``[v]_x w = v x w``."""
    return ti.Matrix([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], ti.f64)


@ti.func
def _d_projection_coefficient(xp, xq, p: ti.template(), q: ti.template(), e, le):
    """d/dx of ``(x_p - x_q) . e / |e|`` as a 12-vector (``e = x1 - x0``)."""
    d = xp - xq
    c = d.dot(e) / le
    e_hat = e / le
    base = d / le - (c / le) * e_hat  # times de/dx_w = sign_e[w] I, sign_e = (-1, 1, 0, 0)
    out = ti.Vector.zero(ti.f64, 12)
    for i in range(3):
        out[i] = -base[i]
        out[3 + i] = base[i]
        out[3 * p + i] += e[i] / le
        out[3 * q + i] -= e[i] / le
    return out


@ti.func
def _theta_hessian_unsymmetrized(x0, x1, x2, x3):
    """``H[3 v + i, k] = d(dtheta/dx_{v,i})/dx_k`` (12x12) in closed form (module docstring), before
    symmetrisation (``H`` and ``H^T`` differ by round-off): the product rule on
    ``dtheta/dx_v = C0_v m0 + C1_v m1`` gives ``m0_i dC0_v + C0_v dm0_i + m1_i dC1_v + C1_v dm1_i``.

    The twelve rows ``(v, i)`` are unrolled (runtime loop over the columns): ``C0_v``, ``m0_i``, ...
    are then scalars of the row, which takes a third off the run time of runtime rows; the fills
    and the ``P dn`` products stay runtime loops (compile time).
    """
    e = x1 - x0
    le = e.norm()
    e_hat = e / le
    n0 = e.cross(x2 - x0)
    n1 = (x3 - x0).cross(e)
    q0 = n0.dot(n0)
    q1 = n1.dot(n1)
    m0 = n0 / q0
    m1 = n1 / q1
    C0 = ti.Vector([(x2 - x1).dot(e) / le, -(x2 - x0).dot(e) / le, le, 0.0])
    C1 = ti.Vector([(x3 - x1).dot(e) / le, -(x3 - x0).dot(e) / le, 0.0, le])
    # dC[v] as rows of 4x12 matrices: row v = d C_v / dx
    dC0 = ti.Matrix.zero(ti.f64, 4, 12)
    dC1 = ti.Matrix.zero(ti.f64, 4, 12)
    r00 = _d_projection_coefficient(x2, x1, 2, 1, e, le)
    r01 = _d_projection_coefficient(x2, x0, 2, 0, e, le)
    r10 = _d_projection_coefficient(x3, x1, 3, 1, e, le)
    r11 = _d_projection_coefficient(x3, x0, 3, 0, e, le)
    for k in range(12):
        dC0[0, k] = r00[k]
        dC0[1, k] = -r01[k]
        dC1[0, k] = r10[k]
        dC1[1, k] = -r11[k]
    for i in range(3):
        dC0[2, i] = -e_hat[i]
        dC0[2, 3 + i] = e_hat[i]
        dC1[3, i] = -e_hat[i]
        dC1[3, 3 + i] = e_hat[i]
    # dn0/dx_w over T0 = (x0, x1, x2), dn1/dx_w over T1 = (x1, x0, x3): 3x12 each
    dn0 = ti.Matrix.zero(ti.f64, 3, 12)
    dn1 = ti.Matrix.zero(ti.f64, 3, 12)
    a0, a1, a2 = _cross_matrix(x2 - x1), _cross_matrix(x0 - x2), _cross_matrix(x1 - x0)
    b0, b1, b3 = _cross_matrix(x1 - x3), _cross_matrix(x3 - x0), _cross_matrix(x0 - x1)
    for i, j in ti.ndrange(3, 3):
        dn0[i, j] = a0[i, j]
        dn0[i, 3 + j] = a1[i, j]
        dn0[i, 6 + j] = a2[i, j]
        dn1[i, j] = b0[i, j]
        dn1[i, 3 + j] = b1[i, j]
        dn1[i, 9 + j] = b3[i, j]
    eye = ti.Matrix.identity(ti.f64, 3)
    P0 = (eye - 2.0 * n0.outer_product(n0) / q0) / q0
    P1 = (eye - 2.0 * n1.outer_product(n1) / q1) / q1
    dm0 = matmul(P0, dn0)
    dm1 = matmul(P1, dn1)
    H = ti.Matrix.zero(ti.f64, 12, 12)
    for v, i in ti.static(ti.ndrange(4, 3)):
        for k in range(12):
            H[3 * v + i, k] = (m0[i] * dC0[v, k] + C0[v] * dm0[i, k]
                               + m1[i] * dC1[v, k] + C1[v] * dm1[i, k])
    return H


@ti.func
def _theta_hessian(x0, x1, x2, x3):
    """``d2theta/dx2`` (12x12, symmetrised) in closed form: ``(H + H^T) / 2`` of
    :func:`_theta_hessian_unsymmetrized`."""
    H = _theta_hessian_unsymmetrized(x0, x1, x2, x3)
    for r in range(12):
        for s in range(r + 1, 12):
            sym = 0.5 * (H[r, s] + H[s, r])
            H[r, s] = sym
            H[s, r] = sym
    return H


@fast_kernel
def evaluate_hinge_energy(
    x: ti.types.ndarray(), hinges: ti.types.ndarray(), stiffness: ti.types.ndarray(),
    theta_bar: ti.types.ndarray(), hinge_energy: ti.types.ndarray(),
):
    """``hinge_energy[h] = k_h (theta_h - theta_bar_h)^2`` (J)."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for h in range(hinges.shape[0]):
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        d = _dihedral_angle(x0, x1, x2, x3) - theta_bar[h]
        hinge_energy[h] = stiffness[h] * d * d


@fast_kernel
def evaluate_hinge_gradient(
    x: ti.types.ndarray(), hinges: ti.types.ndarray(), stiffness: ti.types.ndarray(),
    theta_bar: ti.types.ndarray(), grad: ti.types.ndarray(),
):
    """``grad[v] += 2 k_h (theta - theta_bar) dtheta/dx_v`` (N); ``grad`` zeroed first."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for v, d in ti.ndrange(grad.shape[0], 3):
        grad[v, d] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for h in range(hinges.shape[0]):
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        d = _dihedral_angle(x0, x1, x2, x3) - theta_bar[h]
        g = _theta_gradient(x0, x1, x2, x3)
        f = 2.0 * stiffness[h] * d
        for a in ti.static(range(4)):
            for i in ti.static(range(3)):
                ti.atomic_add(grad[hinges[h, a], i], f * g[3 * a + i])


@fast_kernel
def evaluate_hinge_hessian(
    x: ti.types.ndarray(), hinges: ti.types.ndarray(), stiffness: ti.types.ndarray(),
    theta_bar: ti.types.ndarray(), code: ti.i32, blocks: ti.types.ndarray(),
):
    """``blocks[h] = 2 k_h (g g^T + (theta - theta_bar) d2theta)`` (12x12, N/m), projected."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for h in range(hinges.shape[0]):
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        d = _dihedral_angle(x0, x1, x2, x3) - theta_bar[h]
        g = _theta_gradient(x0, x1, x2, x3)
        H = _theta_hessian(x0, x1, x2, x3)
        f = 2.0 * stiffness[h]
        for r in range(12):
            for s in range(12):
                H[r, s] = f * (g[r] * g[s] + d * H[r, s])
        project_psd_translation_free(H, code)
        for r, s in ti.ndrange(12, 12):
            blocks[h, r, s] = H[r, s]


class TiDiscreteShellBending(DiscreteShellBending):
    """:class:`DiscreteShellBending` whose energy, gradient and Hessian run as Taichi kernels.

    Construction, validation, parameters, :meth:`theta` and :meth:`parameter_gradient` are the
    NumPy class's. ``hinge_theta_bar`` is read at every call (``ElasticTerms.bending`` replaces it
    on shallow copies), so it is uploaded per call; the rest weights are uploaded once.

    Args:
        hinges, x_rest, bending_stiffness, hinge_theta_bar: as :class:`DiscreteShellBending`.

    Raises:
        ConfigError: as :class:`DiscreteShellBending`, or the Taichi backend is not initialised.
        MeshError: as :class:`DiscreteShellBending`.
    """

    def __init__(self, hinges: np.ndarray, x_rest: np.ndarray, bending_stiffness: float,
                 hinge_theta_bar: np.ndarray | None = None) -> None:
        require_backend("TiDiscreteShellBending")
        super().__init__(hinges, x_rest, bending_stiffness, hinge_theta_bar)
        self._hinges_dev = upload_constant(self.hinges, ti.i32)
        self._stiffness_dev = upload_constant(self.hinge_stiffness, ti.f64)
        self._theta_bar = DeviceArray(ti.f64)
        self._x = DeviceArray(ti.f64)
        self._hinge_energy = DeviceArray(ti.f64)
        self._grad = DeviceArray(ti.f64)
        self._blocks = DeviceArray(ti.f64)

    def _args(self, x: np.ndarray) -> tuple:
        return (self._x.upload(x), self._hinges_dev, self._stiffness_dev, self._theta_bar.upload(self.hinge_theta_bar))

    def energy(self, x: np.ndarray) -> float:
        """Bending energy in J; ``x`` shape ``(n, 3)`` in m."""
        k = self.hinges.shape[0]
        if k == 0:
            return 0.0
        out = self._hinge_energy.ensure((k,))
        evaluate_hinge_energy(*self._args(x), out)
        return float(np.sum(out.to_numpy()))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx = 2 k_h (theta - theta_bar) dtheta/dx in N, shape ``(n, 3)``."""
        x = np.asarray(x, dtype=float)
        if self.hinges.shape[0] == 0:
            return np.zeros_like(x)
        g = self._grad.ensure(x.shape)
        evaluate_hinge_gradient(*self._args(x), g)
        return g.to_numpy()

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """12x12 blocks ``2 k_h (dtheta dtheta^T + (theta - theta_bar) d2theta)``, PSD-projected.

        Raises:
            ValueError: unknown projection.
        """
        code = projection_code(projection)
        k = self.hinges.shape[0]
        if k == 0:
            return HessianBlocks(self.hinges, np.zeros((0, 12, 12)))
        out = self._blocks.ensure((k, 12, 12))
        evaluate_hinge_hessian(*self._args(x), code, out)
        return HessianBlocks(self.hinges, out.to_numpy())
