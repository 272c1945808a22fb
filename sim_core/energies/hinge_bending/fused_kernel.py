"""Hinge bending with per-hinge weights in one Taichi kernel: energy, gradient and exact Hessian into CSR slots.

The fused counterpart of the anisotropic bending candidate
(:class:`sim_core.candidates.anisotropic_bending.AnisotropicBendingCorrection`, the reference and
test oracle) for the Newton loop. With per-hinge weights ``s_h = beta cos(2 phi_h) k_h`` (any sign)
and ``d_h = theta_h - theta_bar_h`` (discrete shell hinges, Grinspun et al. 2003)::

    E = sum_h s_h d_h^2,
    dE/dx = sum_h 2 s_h d_h dtheta_h/dx,
    H_h = 2 s_h (dtheta_h dtheta_h^T + d_h d2theta_h/dx2),

with ``dtheta/dx`` and the closed-form ``d2theta/dx2`` of :mod:`sim_core.energies.hinge_bending.kernel`. One
launch per Newton iterate computes all three and adds the exact Hessian entries straight into the
solver's static pattern (:meth:`sim_core.assembly.StaticPattern.slot_map` of the hinges), in place of
the candidate's NumPy blocks and their dynamic merge. The projected blocks of the fallback iterations
(``max(c_h, 0) P(H_h)``, a quasi-Newton choice of the candidate) stay with the reference.

Loops are serial on the CPU (``serial_loops``): sums in hinge order, bitwise reproducible, and a
forked replay worker never enters Taichi's thread pool.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.hinge_bending.kernel import _dihedral_angle, _hinge_positions, _theta_gradient, _theta_hessian
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.block_projection import add_blocks
from sim_core.ti_kernels.copy_vectors import copy_energies, element_copies
from sim_core.ti_kernels.launch import summing_kernel

_F64_1, _F64_2, _I32_2, _I32_3 = linalg.F64_1, linalg.F64_2, linalg.I32_2, linalg.I32_3


@summing_kernel
def weighted_hinge_energy(x: _F64_2, hinges: _I32_2, theta_bar: _F64_1, weight: _F64_1, energy: _F64_1):
    """``sum_h weight_h (theta_h - theta_bar_h)^2`` in J."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for h in range(hinges.shape[0]):
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        d = _dihedral_angle(x0, x1, x2, x3) - theta_bar[h]
        energy[h % energy.shape[0]] += weight[h] * d * d


@summing_kernel
def weighted_hinge_energy_gradient_hessian(
    x: _F64_2, hinges: _I32_2, theta_bar: _F64_1, weight: _F64_1, slots: _I32_3, grad: _F64_2, values: _F64_1,
    energy: _F64_1,
):
    """Energy (J, returned); adds the gradient (N) to ``grad`` ``(n, 3)`` and the exact Hessian (N/m)
    to ``values`` at ``slots[h, r, s]`` (``(h, 12, 12)``, -1 = not stored; module docstring)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for h in range(hinges.shape[0]):
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        d = _dihedral_angle(x0, x1, x2, x3) - theta_bar[h]
        w = weight[h]
        energy[h % energy.shape[0]] += w * d * d
        g = _theta_gradient(x0, x1, x2, x3)
        f = 2.0 * w * d
        for a in ti.static(range(4)):
            v = hinges[h, a]
            for c in ti.static(range(3)):
                grad[v, c] += f * g[3 * a + c]
        Hh = _theta_hessian(x0, x1, x2, x3)
        for r in range(12):
            for s in range(r, 12):
                k1 = slots[h, r, s]
                k2 = -1
                if r != s:
                    k2 = slots[h, s, r]
                if k1 >= 0 or k2 >= 0:  # entries of fixed DoFs are not computed
                    val = 2.0 * w * (g[r] * g[s] + d * Hh[r, s])
                    if k1 >= 0:
                        values[k1] += val
                    if k2 >= 0:
                        values[k2] += val


class FusedAnisotropicBending:
    """Fused Newton-loop evaluation of an :class:`AnisotropicBendingCorrection` (module docstring).

    Args:
        potential: the step's candidate term (its hinges, rest angles, weights ``beta cos 2 phi k``).

    Attributes:
        vertices: the correction's Hessian-block vertex array (its bending's ``hinges``, ``(h, 4)``),
            the same object every step (the sheet's cached bending), so the static pattern is kept.

    Raises:
        ConfigError: the Taichi backend is not initialised (:func:`sim_core.ti_backend.init_backend`).
    """

    def __init__(self, potential) -> None:
        require_backend("FusedAnisotropicBending")
        self.vertices = potential.vertices
        self._hinges = np.ascontiguousarray(potential.vertices, dtype=np.int32)
        self._copy_kept: dict = {}  # copy_energies' element copies (and their device arrays on a GPU)
        self._slots: np.ndarray | None = None
        self.potential = None
        self.update(potential)

    def accepts(self, potential) -> bool:
        """Whether ``potential`` is a correction over the same hinges (weights and rest angles may differ)."""
        return type(potential) is type(self.potential) and potential.vertices is self.vertices

    def update(self, potential) -> None:
        """Take the weights ``beta cos(2 phi_h) k_h`` (J/rad^2) and rest angles (rad) of ``potential``."""
        if potential is self.potential:
            return
        self.potential = potential
        bending = potential.bending
        self._theta_bar = np.ascontiguousarray(bending.hinge_theta_bar, dtype=np.float64)
        self._weight = np.ascontiguousarray(potential.beta * potential.hinge_cos2phi * bending.hinge_stiffness,
                                            dtype=np.float64)

    def bind(self, pattern) -> None:
        """Slot map of the hinge blocks in ``pattern`` (:class:`sim_core.assembly.StaticPattern`)."""
        self._slots = pattern.slot_map(self.vertices)

    def energy(self, x: np.ndarray) -> float:
        """Energy in J at positions ``x`` ``(n, 3)`` (may be negative)."""
        if self._hinges.shape[0] == 0:
            return 0.0
        return float(weighted_hinge_energy(x, self._hinges, self._theta_bar, self._weight))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each hinge's first vertex, J ``(copy_count,)`` (the same kernel, one
        sum cell a hinge: :func:`~sim_core.ti_kernels.copy_vectors.copy_energies`)."""
        kept = self._copy_kept
        return copy_energies(weighted_hinge_energy, element_copies(kept, copy_of_vertex, self._hinges[:, 0]),
                             copy_count, kept, x, self._hinges, self._theta_bar, self._weight)

    def evaluate(self, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
        """Energy in J (returned); adds dE/dx to ``grad`` ``(n, 3)`` and the exact Hessian to ``values``.

        ``x`` and ``grad`` must be C-contiguous float64; :meth:`bind` must have been called.
        """
        if self._hinges.shape[0] == 0:
            return 0.0
        return float(weighted_hinge_energy_gradient_hessian(x, self._hinges, self._theta_bar, self._weight,
                                                            self._slots, grad, values))

    def add_projected(self, x: np.ndarray, projection: str, values: np.ndarray) -> None:
        """Add the reference's ``projection`` blocks (``max(c_h, 0) P(H_h)`` for "clamp", see the
        candidate) into ``values``; the fallback iterations are rare, so this stays in NumPy."""
        if self._hinges.shape[0] == 0:
            return
        blocks = np.ascontiguousarray(self.potential.hessian(x, projection).blocks, dtype=np.float64)
        add_blocks(blocks, self._slots, values)


def compile_kernels() -> None:
    """Compile both kernels on one hinge (processes that fork replay workers call this first:
    :func:`sim_core.kernel_compile.compile_kernels`)."""
    require_backend("fused_hinge.compile_kernels")
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.5, -1.0, 0.1]])
    hinges = np.array([[0, 1, 2, 3]], dtype=np.int32)
    theta_bar, weight = np.zeros(1), np.ones(1)
    slots = np.arange(144, dtype=np.int32).reshape(1, 12, 12)
    weighted_hinge_energy(x, hinges, theta_bar, weight)
    weighted_hinge_energy_gradient_hessian(x, hinges, theta_bar, weight, slots, np.zeros_like(x), np.zeros(144))
