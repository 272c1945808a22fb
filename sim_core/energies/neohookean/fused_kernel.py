"""Stable Neo-Hookean tets in one Taichi kernel: energy, gradient and exact Hessian into CSR slots.

The fused counterpart of :class:`sim_core.energies.neohookean.reference.StableNeoHookean` (the reference
and test oracle) for the Newton loop: one launch per iteration computes, per tet,

    psi = mu/2 (I_C - 3) + lam/2 (J - alpha)^2 - mu/2 log((I_C + 1) / 4) - 9 mu^2 / (32 lam),
    P   = mu (1 - 1/(I_C + 1)) F + lam (J - alpha) cof F          (Smith, de Goes, Kim 2018, eq. 18),

the energy ``V psi``, the vertex forces ``V P g_a`` (``g_a`` = row ``a`` of ``tet_dFdx``) and the
exact (unprojected) 12x12 Hessian ``V M^T (d2psi/dF2) M``, added straight into the values of the
solver's static sparsity pattern (:meth:`sim_core.assembly.StaticPattern.slot_map`, packed by
:func:`sim_core.ti_kernels.block_projection.upper_slot_table`). With
``d2psi/dF_ci dF_dl = mu_t delta_cd delta_jl + beta F_cj F_dl + lam cof_cj cof_dl
+ lam (J - alpha) eps_cdm eps_jln F_mn`` (eqs. 19-21; ``mu_t = mu (1 - 1/(I_C+1))``,
``beta = 2 mu / (I_C + 1)^2``) the vertex block of corners ``a, b`` and axes ``c, d`` is

    H[3a+c, 3b+d] = V (mu_t delta_cd g_a.g_b + beta (g_a.F_c)(g_b.F_d) + lam (g_a.k_c)(g_b.k_d)
                       + lam (J - alpha) eps_cdm F_m.(g_a x g_b)),

``F_c`` and ``k_c`` the rows of ``F`` and ``cof F``. The PSD-projected Hessian stays with the
reference potential (the solver projects only when PARDISO's Cholesky refuses the exact matrix).

Loops are serial on the CPU (``ti.loop_config(serialize=ti.static(serial_loops()))``): the sums into shared vertices and
slots are then in element order, so results are bitwise reproducible run to run.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.neohookean.kernel import evaluate_snh_hessian, evaluate_snh_hessian_rows
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.ti_backend import current_arch, require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.block_projection import (add_block_rows, add_blocks, add_projected_where_run,
                                                  add_upper_block_rows, add_upper_entry, BoundSlotTables,
                                                  marked_rows, projected_rows, stage_projected_rows, upper_index)
from sim_core.ti_kernels.buffers import on_device, rows_on_device
from sim_core.ti_kernels.copy_vectors import copy_energies, element_copies
from sim_core.ti_kernels.launch import summing_kernel
from sim_core.ti_kernels.linalg import projection_code
from sim_core.worker_recipe import part_recipe

_F64_1, _F64_2, _F64_3, _I32_2, _I32_3 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_2, linalg.I32_3


@ti.func
def _tet_state(x: ti.template(), tets: ti.template(), dFdx: ti.template(), t: ti.i32):
    """``(F, G)``: deformation gradient ``F_ij = sum_a x_{a,i} G_aj`` and ``G = dFdx[t]`` (4x3)."""
    G = ti.Matrix.zero(ti.f64, 4, 3)
    F = ti.Matrix.zero(ti.f64, 3, 3)
    for a in ti.static(range(4)):
        v = tets[t, a]
        for j in ti.static(range(3)):
            G[a, j] = dFdx[t, a, j]
        for i, j in ti.static(ti.ndrange(3, 3)):
            F[i, j] += x[v, i] * G[a, j]
    return F, G


@ti.func
def _psi(I_C, J, mu, lam, alpha):
    return (0.5 * mu * (I_C - 3.0) + 0.5 * lam * (J - alpha) ** 2
            - 0.5 * mu * ti.log((I_C + 1.0) / 4.0) - 9.0 * mu * mu / (32.0 * lam))


@summing_kernel
def snh_energy(x: _F64_2, tets: _I32_2, dFdx: _F64_3, vol: _F64_1, mu: ti.f64, lam: ti.f64, energy: _F64_1):
    """``sum_t V_t psi(F_t)`` in J."""
    alpha = 1.0 + 0.75 * mu / lam
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(tets.shape[0]):
        F, _ = _tet_state(x, tets, dFdx, t)
        energy[t % energy.shape[0]] += vol[t] * _psi((F * F).sum(), F.determinant(), mu, lam, alpha)


@ti.func
def _add_entry(values: ti.template(), upper: ti.template(), t, a, b, c: ti.template(), d: ti.template(),
               bGF: ti.template(), GF: ti.template(), lGK: ti.template(), GK: ti.template(), mgg,
               sFw: ti.template(), V):
    """Add ``H[3a+c, 3b+d]`` (module docstring) through the packed slot table, if it is stored:
    ``(beta (g_a.F_c)(g_b.F_d) + lam (g_a.k_c)(g_b.k_d) + [c = d] mgg + eps_cdm sFw_m) V`` with
    ``mgg = mu_t g_a.g_b``, ``sFw = lam (J - alpha) F (g_a x g_b)`` (the local matrices by reference:
    a ``ti.func`` copies its other arguments)."""
    slot = upper[t, upper_index(12, 3 * a + c, 3 * b + d)]
    if slot != -1:  # entries of fixed DoFs are not computed
        h = bGF[a, c] * GF[b, d] + lGK[a, c] * GK[b, d]
        if ti.static(c == d):
            h += mgg
        elif ti.static(d == (c + 1) % 3):  # eps_cdm = +1, m the third index
            h += sFw[ti.static(3 - c - d)]
        else:
            h -= sFw[ti.static(3 - c - d)]
        h *= V
        add_upper_entry(values, slot, h)


@ti.func
def free_corners(upper: ti.template(), t):
    """Per corner of tet ``t``: 1 where it has a free DoF (a stored diagonal entry in the packed upper slot table
    ``upper``), else 0 (a ``ti.Vector`` of 4 int32)."""
    free = ti.Vector.zero(ti.i32, 4)
    for a in ti.static(range(4)):
        for c in ti.static(range(3)):
            if upper[t, upper_index(12, 3 * a + c, 3 * a + c)] != -1:
                free[a] = 1
    return free


@summing_kernel
def snh_energy_gradient_hessian(
    x: _F64_2, tets: _I32_2, dFdx: _F64_3, vol: _F64_1, upper: _I32_2, mu: ti.f64, lam: ti.f64,
    grad: _F64_2, values: _F64_1,
    energy: _F64_1,
):
    """Energy (J, returned); adds the forces to ``grad`` (n, 3) in N and the exact Hessian entries
    (N/m) to ``values`` through the packed upper slot table ``upper`` (t, 78)
    (:func:`~sim_core.ti_kernels.block_projection.upper_slot_table`; module docstring). Corners
    without a free DoF are skipped (their entries are not stored)."""
    alpha = 1.0 + 0.75 * mu / lam
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(tets.shape[0]):
        F, G = _tet_state(x, tets, dFdx, t)
        I_C = (F * F).sum()
        J = F.determinant()
        cof = linalg.cofactor(F)
        V = vol[t]
        energy[t % energy.shape[0]] += V * _psi(I_C, J, mu, lam, alpha)
        mu_t = mu * (1.0 - 1.0 / (I_C + 1.0))
        stretch = lam * (J - alpha)
        P = mu_t * F + stretch * cof
        GP = G @ P.transpose()  # GP[a, i] = (P g_a)_i
        for a in ti.static(range(4)):
            v = tets[t, a]
            for i in ti.static(range(3)):
                grad[v, i] += V * GP[a, i]
        beta = 2.0 * mu / (I_C + 1.0) ** 2
        GF = G @ F.transpose()  # GF[a, c] = g_a . F_c
        GK = G @ cof.transpose()  # GK[a, c] = g_a . k_c
        bGF = beta * GF  # the left factors of the entries' products, formed once per tet
        lGK = lam * GK
        free = free_corners(upper, t)
        for a in range(4):
            if free[a] == 1:
                ga = ti.Vector([G[a, 0], G[a, 1], G[a, 2]])
                # the diagonal block: g_a x g_a = 0, its twist term adds zeros (no cross product)
                mgg_aa = mu_t * ga.dot(ga)
                no_twist = ti.Vector.zero(ti.f64, 3)
                for c, d in ti.static(ti.ndrange(3, 3)):
                    if ti.static(c <= d):
                        _add_entry(values, upper, t, a, a, c, d, bGF, GF, lGK, GK, mgg_aa, no_twist, V)
                for b in range(a + 1, 4):
                    if free[b] == 1:
                        gb = ti.Vector([G[b, 0], G[b, 1], G[b, 2]])
                        sFw = stretch * (F @ ga.cross(gb))  # lam (J - alpha) F_m . (g_a x g_b)
                        mgg = mu_t * ga.dot(gb)
                        for c, d in ti.static(ti.ndrange(3, 3)):
                            _add_entry(values, upper, t, a, b, c, d, bGF, GF, lGK, GK, mgg, sFw, V)


def remote_evaluate(args: tuple, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
    """:meth:`FusedStableNeoHookean.evaluate` from its :meth:`~FusedStableNeoHookean.offload_recipe`
    arguments ``(tets, dFdx, vol, upper, mu, lam)``: energy in J (returned), the gradient (N) added
    to ``grad`` ``(n, 3)`` and the exact Hessian (N/m) to ``values`` (the function an
    :class:`~sim_core.elastic_worker.ElasticWorker` runs; the same kernel on the same arrays, so the
    same values bit for bit)."""
    return evaluate_with(snh_energy_gradient_hessian, args, x, grad, values)


def remote_add_projected(args: tuple, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
    """:meth:`FusedStableNeoHookean.add_projected` from its
    :meth:`~FusedStableNeoHookean.offload_projected_recipe` arguments ``(tets, dFdx, vol, slots, mu,
    lam, projection code)``: the projected Hessian blocks (N/m) added into ``values`` (``grad``
    untouched); returns 0.0."""
    return add_projected_with(evaluate_snh_hessian, args, x, values)


def evaluate_with(kernel, args: tuple, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
    """A fused tet solid's ``remote_evaluate`` through its fused ``kernel`` (:func:`snh_energy_gradient_hessian` or
    another law's of the same arguments) on ``args = (tets, dFdx, vol, upper, mu, lam)``: energy in J."""
    tets, dFdx, vol, upper, mu, lam = args
    if tets.shape[0] == 0:
        return 0.0
    return float(kernel(x, tets, dFdx, vol, upper, mu, lam, grad, values))


def add_projected_with(kernel, args: tuple, x: np.ndarray, values: np.ndarray) -> float:
    """A fused tet solid's ``remote_add_projected`` through its projected-block ``kernel``
    (:func:`~sim_core.energies.neohookean.kernel.evaluate_snh_hessian` or another law's of the same arguments) on
    ``args = (tets, dFdx, vol, slots, mu, lam, projection code)``: the blocks added into ``values``; returns 0.0."""
    tets, dFdx, vol, slots, mu, lam, code = args
    if tets.shape[0] == 0:
        return 0.0
    blocks = np.zeros((tets.shape[0], 12, 12))
    kernel(x, tets, dFdx, vol, mu, lam, code, blocks)
    add_blocks(blocks, slots, values)
    return 0.0


class FusedStableNeoHookean(BoundSlotTables):
    """Fused Newton-loop evaluation of a :class:`StableNeoHookean` (module docstring).

    Args:
        potential: the reference potential (its tets, rest data and Lamé parameters are read once).

    Attributes:
        vertices: the potential's Hessian-block vertex array (its ``tets``, ``(k, 4)``), the array
            the solver's static pattern is built from.

    Raises:
        ConfigError: the Taichi backend is not initialised (:func:`sim_core.ti_backend.init_backend`).
    """

    energy_kernel = staticmethod(snh_energy)
    """The energy kernel (a :func:`~sim_core.ti_kernels.launch.summing_kernel` of ``(x, tets, dFdx, vol, mu, lam)``);
    with the three below, what a fused tet solid of another law replaces
    (:class:`sim_core.energies.green_strain.fused_kernel.FusedGreenStrainSolid`)."""
    evaluate_kernel = staticmethod(snh_energy_gradient_hessian)
    """Energy, forces and exact Hessian into the packed upper slots (:func:`snh_energy_gradient_hessian`)."""
    projected_kernel = staticmethod(evaluate_snh_hessian)
    """The projected 12x12 blocks of every tet (:func:`~sim_core.energies.neohookean.kernel.evaluate_snh_hessian`)."""
    projected_rows_kernel = staticmethod(evaluate_snh_hessian_rows)
    """... of the listed tets (:func:`~sim_core.energies.neohookean.kernel.evaluate_snh_hessian_rows`)."""
    remote_module = __name__
    """The module whose ``remote_evaluate`` and ``remote_add_projected`` a worker runs (:meth:`offload_recipe`)."""

    def __init__(self, potential: StableNeoHookean) -> None:
        require_backend(type(self).__name__)
        self.potential = potential
        self._device: dict = {}  # on CUDA: device copies of the constant arrays (buffers.on_device)
        self.vertices = potential.tets
        self._tets = np.ascontiguousarray(potential.tets, dtype=np.int32)
        self._dFdx = np.ascontiguousarray(potential.tet_dFdx, dtype=np.float64)
        self._vol = np.ascontiguousarray(potential.tet_rest_volume, dtype=np.float64)
        self._blocks: np.ndarray | None = None  # projected blocks (k, 12, 12), allocated on first use
        self._recipe: tuple | None = None  # the last offload_recipe()
        self._projected_recipe: tuple | None = None  # the last offload_projected_recipe()

    def accepts(self, potential) -> bool:
        """Whether ``potential`` is evaluated by this kernel as it stands (same elements, parameters)."""
        return (potential is self.potential
                or (type(potential) is type(self.potential) and potential.tets is self.potential.tets
                    and potential.mu == self.potential.mu and potential.lam == self.potential.lam))

    def update(self, potential) -> None:
        """Take ``potential``'s rest data (``tet_dFdx``, ``tet_rest_volume``) when it is another object
        (an accepted one: same tets and Lame parameters). The gel's own potential is the same object
        every step (nothing to do); a Maxwell branch (:mod:`sim_core.candidates.gel_viscoelasticity`) is
        a new one per step, with its relaxed rest state."""
        if potential is self.potential:
            return
        self.potential = potential
        self._dFdx = np.ascontiguousarray(potential.tet_dFdx, dtype=np.float64)
        self._vol = np.ascontiguousarray(potential.tet_rest_volume, dtype=np.float64)

    def energy(self, x: np.ndarray) -> float:
        """Energy in J at positions ``x`` ``(n, 3)``."""
        if self._tets.shape[0] == 0:
            return 0.0
        p = self.potential
        d = self._device
        return float(self.energy_kernel(x, on_device(d, "tets", self._tets), on_device(d, "dFdx", self._dFdx),
                                        on_device(d, "vol", self._vol), p.mu, p.lam))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each tet's first vertex, J ``(copy_count,)`` (the same kernel, one
        sum cell a tet: :func:`~sim_core.ti_kernels.copy_vectors.copy_energies`)."""
        p = self.potential
        d = self._device
        return copy_energies(self.energy_kernel, element_copies(d, copy_of_vertex, self._tets[:, 0]), copy_count, d, x,
                             on_device(d, "tets", self._tets), on_device(d, "dFdx", self._dFdx),
                             on_device(d, "vol", self._vol), p.mu, p.lam)

    def evaluate(self, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
        """Energy in J (returned); adds dE/dx to ``grad`` ``(n, 3)`` and the exact Hessian to ``values``.

        ``x`` and ``grad`` must be C-contiguous float64; :meth:`bind` must have been called.
        """
        if self._tets.shape[0] == 0:
            return 0.0
        p = self.potential
        d = self._device
        return float(self.evaluate_kernel(x, on_device(d, "tets", self._tets), on_device(d, "dFdx", self._dFdx),
                                          on_device(d, "vol", self._vol), on_device(d, "upper", self._upper),
                                          p.mu, p.lam, grad, values))

    @property
    def element_count(self) -> int:
        """Tets evaluated (the cost measure :class:`~sim_core.fused_elastic.FusedElastic` uses to choose
        the term it offloads)."""
        return int(self._tets.shape[0])

    def offload_recipe(self) -> tuple[str, tuple]:
        """``(target, args)`` of :meth:`evaluate` for an :class:`~sim_core.elastic_worker.ElasticWorker`:
        :func:`remote_evaluate` and ``(tets, dFdx, vol, upper, mu, lam)`` (the kept arrays: a new
        object whenever they change, so the worker is reconfigured). :meth:`bind` must have been called."""
        p = self.potential
        args = (self._tets, self._dFdx, self._vol, self._upper, float(p.mu), float(p.lam))
        self._recipe = part_recipe(self._recipe, f"{self.remote_module}:remote_evaluate", args)
        return self._recipe

    def offload_projected_recipe(self, projection: str) -> tuple[str, tuple]:
        """``(target, args)`` of :meth:`add_projected` for an :class:`~sim_core.elastic_worker.ElasticWorker`:
        :func:`remote_add_projected` and ``(tets, dFdx, vol, slots, mu, lam, projection code)``; the
        same object while nothing changed.

        Raises:
            ValueError: unknown projection.
        """
        p = self.potential
        args = (self._tets, self._dFdx, self._vol, self._slots, float(p.mu), float(p.lam), projection_code(projection))
        self._projected_recipe = part_recipe(self._projected_recipe, f"{self.remote_module}:remote_add_projected", args)
        return self._projected_recipe

    projects_subsets = True
    """:meth:`add_projected` takes a vertex mask (:meth:`sim_core.fused_elastic.FusedElastic.projected_hessian_values`)."""

    def add_projected(self, x: np.ndarray, projection: str, values: np.ndarray,
                      vertices: np.ndarray | None = None) -> None:
        """Add the ``projection`` ("none", "clamp", "abs") Hessian blocks into ``values``: the analytic
        eigensystem of d2psi/dF2 (Smith et al. 2018, section 4.2) of the Taichi twin
        (:func:`sim_core.energies.neohookean.kernel.evaluate_snh_hessian`), the reference's projection.

        With ``vertices`` (bool ``(n,)``) only the tets touching a marked vertex are added. On CUDA by
        :meth:`add_projected_on_device` into sums kept there, downloaded once.

        Raises:
            ValueError: unknown projection.
        """
        code = projection_code(projection)
        if self._tets.shape[0] == 0:
            return
        if current_arch() == "cuda":  # the blocks made and added into sums on the device, the sums downloaded
            add_projected_where_run(self, x, projection, values, vertices)
            return
        p = self.potential
        blocks = self._block_buffer()
        self.projected_kernel(x, self._tets, self._dFdx, self._vol, p.mu, p.lam, code, blocks)
        if vertices is None:
            add_blocks(blocks, self._slots, values)
        else:  # the tets touching a marked vertex
            rows = marked_rows(self._tets, vertices)
            add_block_rows(blocks, self._slots, rows, rows.size, values)

    def stage_projected_rows(self, vertices: np.ndarray | None = None, closed: bool = False) -> None:
        """The rows :meth:`add_projected_on_device` takes, sent before the projection's kernels are queued
        (:func:`~sim_core.ti_kernels.block_projection.stage_projected_rows`)."""
        stage_projected_rows(self._device, self._tets, vertices, closed, "rows")

    def add_projected_on_device(self, x, projection: str, values, vertices: np.ndarray | None = None,
                                closed: bool = False) -> None:
        """The projected blocks of :meth:`add_projected` made and added into ``values`` ``(pattern.keys.size,)`` where
        the kernels run (on CUDA a device array; on the CPU arch the same kernels on host arrays) through the
        packed upper slot table of the exact Hessian (:func:`~sim_core.ti_kernels.block_projection.
        add_upper_block_rows`: the blocks are symmetric bit for bit, so the sums are the full slot map's); with
        ``vertices`` (bool ``(n,)``) only the tets touching a marked vertex, whose blocks alone are made
        (:func:`~sim_core.energies.neohookean.kernel.evaluate_snh_hessian_rows`; ``closed``: ``vertices`` closed under
        the tets, :func:`~sim_core.ti_kernels.block_projection.marked_rows`).

        Raises:
            ValueError: unknown projection.
        """
        code = projection_code(projection)
        if self._tets.shape[0] == 0:
            return
        rows = projected_rows(self._device, self._tets, vertices, closed)  # with vertices: the tets touching one
        if rows.size == 0:
            return
        p = self.potential
        d = self._device
        blocks = on_device(d, "blocks", self._block_buffer(), scratch=True)
        rows_dev = rows_on_device(d, "rows", rows)
        self.projected_rows_kernel(x, on_device(d, "tets", self._tets), on_device(d, "dFdx", self._dFdx),
                                   on_device(d, "vol", self._vol), p.mu, p.lam, code, rows_dev, rows.size, blocks)
        add_upper_block_rows(blocks, on_device(d, "upper", self._upper), rows_dev, rows.size, values)

    def _block_buffer(self) -> np.ndarray:
        """The kept host array of the tets' projected blocks ``(t, 12, 12)`` (allocated at its first use; on CUDA only
        its shape is read, for the device array)."""
        if self._blocks is None:
            self._blocks = np.zeros((self._tets.shape[0], 12, 12))
        return self._blocks
