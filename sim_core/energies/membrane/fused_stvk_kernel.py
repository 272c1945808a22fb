"""StVK membrane in one Taichi kernel: energy, gradient and exact Hessian into CSR slots.

The fused counterpart of :class:`sim_core.energies.membrane.reference.StVKMembrane` (the reference and test
oracle; plane-stress Saint Venant-Kirchhoff, Bonet & Wood ch. 6) for the Newton loop. Per triangle,
with the shape-function gradients ``D_a`` (rows of ``triangle_shape_gradient``, 2-vectors in the
rest frame), ``F = sum_a x_a D_a^T`` (3x2), ``G = (F^T F - I) / 2``, ``S = 2 mu G + lam tr(G) I``
and the weight ``w = thickness * rest area``::

    E_T  = w (mu tr(G^2) + lam / 2 tr(G)^2),       dE_T/dx_a = w F S D_a,
    H[(a, d), (b, e)] = w (D_a.S D_b delta_de + mu Q_db Q_ea + mu (D_a.D_b) (F F^T)_de + lam Q_da Q_eb),

``Q = F D^T`` (``Q_db = F_d . D_b``). Entries go straight into the solver's static pattern values
through :meth:`sim_core.assembly.StaticPattern.slot_map` of the triangles. Serial loops on the CPU
(reproducible sums), parallel on CUDA, as in :mod:`sim_core.energies.neohookean.fused_kernel`.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.membrane.kernel import evaluate_stvk_hessian
from sim_core.energies.membrane.reference import StVKMembrane
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.block_projection import add_blocks
from sim_core.ti_kernels.copy_vectors import copy_energies, element_copies
from sim_core.ti_kernels.launch import summing_kernel
from sim_core.ti_kernels.linalg import projection_code

_F64_1, _F64_2, _F64_3, _I32_2, _I32_3 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_2, linalg.I32_3


@ti.func
def _triangle_state(x: ti.template(), triangles: ti.template(), shape_gradient: ti.template(), t: ti.i32):
    """``(F (3x2), D (3x2): rows D_a)`` of triangle ``t``."""
    D = ti.Matrix.zero(ti.f64, 3, 2)
    F = ti.Matrix.zero(ti.f64, 3, 2)
    for a in ti.static(range(3)):
        v = triangles[t, a]
        for j in ti.static(range(2)):
            D[a, j] = shape_gradient[t, a, j]
        for d, j in ti.static(ti.ndrange(3, 2)):
            F[d, j] += x[v, d] * D[a, j]
    return F, D


@ti.func
def _stress(F, mu, lam):
    """``(G, tr G, S)`` of ``F``."""
    G = 0.5 * (F.transpose() @ F - ti.Matrix.identity(ti.f64, 2))
    tr = G[0, 0] + G[1, 1]
    S = 2.0 * mu * G + lam * tr * ti.Matrix.identity(ti.f64, 2)
    return G, tr, S


@summing_kernel
def stvk_energy(x: _F64_2, triangles: _I32_2, shape_gradient: _F64_3, weight: _F64_1, mu: ti.f64,
                lam: ti.f64, energy: _F64_1):
    """Membrane energy in J."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(triangles.shape[0]):
        F, _ = _triangle_state(x, triangles, shape_gradient, t)
        G, tr, _S = _stress(F, mu, lam)
        energy[t % energy.shape[0]] += weight[t] * (mu * (G * G).sum() + 0.5 * lam * tr * tr)


@summing_kernel
def stvk_energy_gradient_hessian(
    x: _F64_2, triangles: _I32_2, shape_gradient: _F64_3, weight: _F64_1, slots: _I32_3, mu: ti.f64,
    lam: ti.f64, grad: _F64_2, values: _F64_1,
    energy: _F64_1,
):
    """Energy (J, returned); adds the gradient (N) to ``grad`` and the exact Hessian (N/m) to ``values``."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(triangles.shape[0]):
        F, D = _triangle_state(x, triangles, shape_gradient, t)
        G, tr, S = _stress(F, mu, lam)
        w = weight[t]
        energy[t % energy.shape[0]] += w * (mu * (G * G).sum() + 0.5 * lam * tr * tr)
        PD = F @ S @ D.transpose()  # PD[d, a] = (F S D_a)_d
        for a in ti.static(range(3)):
            v = triangles[t, a]
            for d in ti.static(range(3)):
                grad[v, d] += w * PD[d, a]
        Q = F @ D.transpose()  # Q[d, b] = F_d . D_b
        DSD = D @ S @ D.transpose()
        DD = D @ D.transpose()
        FF = F @ F.transpose()
        for a in range(3):
            for b in range(a, 3):
                for d, e in ti.static(ti.ndrange(3, 3)):
                    if a != b or ti.static(d <= e):
                        r = 3 * a + d
                        s = 3 * b + e
                        k = slots[t, r, s]
                        k2 = -1
                        if r != s:
                            k2 = slots[t, s, r]
                        if k >= 0 or k2 >= 0:  # entries of fixed DoFs are not computed
                            h = mu * Q[d, b] * Q[e, a] + mu * DD[a, b] * FF[d, e] + lam * Q[d, a] * Q[e, b]
                            if ti.static(d == e):
                                h += DSD[a, b]
                            h *= w
                            if k >= 0:
                                values[k] += h
                            if k2 >= 0:
                                values[k2] += h


class FusedStVKMembrane:
    """Fused Newton-loop evaluation of a :class:`StVKMembrane` (module docstring).

    Args:
        potential: the reference potential (triangles, shape gradients, weights, Lamé parameters).

    Attributes:
        vertices: the potential's Hessian-block vertex array (its ``triangles``).

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """

    def __init__(self, potential: StVKMembrane) -> None:
        require_backend("FusedStVKMembrane")
        self.potential = potential
        self.vertices = potential.triangles
        self._triangles = np.ascontiguousarray(potential.triangles, dtype=np.int32)
        self._copy_kept: dict = {}  # copy_energies' element copies (and their device arrays on a GPU)
        self._shape_gradient = np.ascontiguousarray(potential.triangle_shape_gradient, dtype=np.float64)
        self._weight = np.ascontiguousarray(potential.thickness * potential.triangle_rest_area, dtype=np.float64)
        self._slots: np.ndarray | None = None
        self._blocks: np.ndarray | None = None  # projected blocks (t, 9, 9), allocated on first use

    def accepts(self, potential) -> bool:
        """Whether ``potential`` is evaluated by this kernel as it stands (same elements, parameters)."""
        p = self.potential
        return potential is p or (type(potential) is type(p) and potential.triangles is p.triangles
                                  and (potential.mu, potential.lam, potential.thickness) == (p.mu, p.lam, p.thickness))

    def update(self, potential) -> None:
        """Nothing changes between steps."""

    def bind(self, pattern) -> None:
        """Slot maps of the blocks in ``pattern`` (:class:`sim_core.assembly.StaticPattern`)."""
        self._slots = pattern.slot_map(self.vertices)

    def energy(self, x: np.ndarray) -> float:
        """Energy in J at positions ``x`` ``(n, 3)``."""
        if self._triangles.shape[0] == 0:
            return 0.0
        p = self.potential
        return float(stvk_energy(x, self._triangles, self._shape_gradient, self._weight, p.mu, p.lam))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each triangle's first vertex, J ``(copy_count,)`` (the same kernel, one
        sum cell a triangle: :func:`~sim_core.ti_kernels.copy_vectors.copy_energies`)."""
        p = self.potential
        kept = self._copy_kept
        return copy_energies(stvk_energy, element_copies(kept, copy_of_vertex, self._triangles[:, 0]), copy_count,
                             kept, x, self._triangles, self._shape_gradient, self._weight, p.mu, p.lam)

    def evaluate(self, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
        """Energy in J (returned); adds dE/dx to ``grad`` ``(n, 3)`` and the exact Hessian to ``values``."""
        if self._triangles.shape[0] == 0:
            return 0.0
        p = self.potential
        return float(stvk_energy_gradient_hessian(x, self._triangles, self._shape_gradient, self._weight,
                                                  self._slots, p.mu, p.lam, grad, values))

    def add_projected(self, x: np.ndarray, projection: str, values: np.ndarray) -> None:
        """Add the ``projection`` ("none", "clamp", "abs") Hessian blocks into ``values``: the Taichi
        twin's blocks (:func:`sim_core.energies.membrane.kernel.evaluate_stvk_hessian`, projected in the
        translation-free subspace as the reference).

        Raises:
            ValueError: unknown projection.
        """
        code = projection_code(projection)
        if self._triangles.shape[0] == 0:
            return
        if self._blocks is None:
            self._blocks = np.zeros((self._triangles.shape[0], 9, 9))
        p = self.potential
        evaluate_stvk_hessian(x, self._triangles, self._shape_gradient, self._weight, p.mu, p.lam, code,
                              self._blocks)
        add_blocks(self._blocks, self._slots, values)
