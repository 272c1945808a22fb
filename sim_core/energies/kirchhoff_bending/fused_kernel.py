"""Discrete Kirchhoff plate bending in one Taichi kernel: energy, gradient and exact Hessian into CSR slots.

The fused counterpart of :class:`sim_core.energies.kirchhoff_bending.reference.KirchhoffBending` (the
reference and test oracle; shape operator of Grinspun, Gingold, Reisman, Zorin 2006) for the
Newton loop. With ``d_T = theta_T - theta_bar_T`` (the hinges of triangle T's edges, 0 on boundary
edges) and ``M_T = (D / 2) A_T W_T`` (``triangle_stiffness``)::

    E = sum_T d_T^T M_T d_T,
    dE/dtheta_h = sum_{T with h} 2 (M_T d_T)_h =: f_h,          dE/dx = sum_h f_h dtheta_h/dx,
    H = sum_T 2 G_T^T M_T G_T + sum_h f_h d2theta_h/dx2,

``G_T`` the 3 x 18 matrix of the hinge-angle gradients over the triangle's block vertices (its three
vertices and the neighbour vertex opposite each edge). One launch, three loops: hinges
(``theta``, ``dtheta/dx`` into a scratch array), triangles (energy, ``f_h``, the Gauss-Newton
term through the triangle slot table), hinges again (forces and ``f_h d2theta/dx2`` through a hinge
slot table; the closed-form ``d2theta`` of :func:`sim_core.energies.hinge_bending.kernel._theta_hessian_unsymmetrized`,
symmetrised per entry). The slot tables are the packed upper triangles of the slot maps
(:func:`sim_core.ti_kernels.block_projection.upper_slot_table`): one slot per computed entry.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.kirchhoff_bending.reference import KirchhoffBending
from sim_core.ti_backend import current_arch, require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import on_device, rows_on_device
from sim_core.ti_kernels.copy_vectors import copy_energies, element_copies
from sim_core.ti_kernels.launch import fast_kernel, summing_kernel
from sim_core.worker_recipe import part_recipe
from sim_core.ti_kernels.block_projection import (TranslationFreeProjector, add_projected_where_run, add_upper_entry,
                                                  SlotTables, marked_rows, projected_rows, stage_projected_rows,
                                                  upper_index)
from sim_core.energies.hinge_bending.kernel import (_dihedral_angle, _hinge_positions, _theta_gradient, _theta_hessian,
                                         _theta_hessian_unsymmetrized)

_F64_1, _F64_2, _F64_3, _I32_2, _I32_3 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_2, linalg.I32_3
_I32_1 = linalg.I32_1

SCRATCH_COLUMNS = 14
"""Per-hinge scratch: ``[theta, f_h, dtheta/dx (12)]``."""


@ti.func
def _triangle_deviation(scratch: ti.template(), theta_bar: ti.template(), tri_hinge: ti.template(), t: ti.i32):
    """``d_T`` (3-vector, 0 on boundary edges) from the angles in ``scratch[:, 0]``."""
    d = ti.Vector.zero(ti.f64, 3)
    for k in ti.static(range(3)):
        h = tri_hinge[t, k]
        if h >= 0:
            d[k] = scratch[h, 0] - theta_bar[h]
    return d


@ti.func
def _twice_product(M, G):
    """``2 M G`` (3 x 18) of the 3x3 ``M`` and 3 x 18 ``G``: a runtime loop over the columns, the
    three rows unrolled (the sums of Taichi's ``@``, a fraction of its compile time)."""
    MG = ti.Matrix.zero(ti.f64, 3, 18)
    for s in range(18):
        for i in ti.static(range(3)):
            MG[i, s] = 2.0 * (M[i, 0] * G[0, s] + M[i, 1] * G[1, s] + M[i, 2] * G[2, s])
    return MG


@ti.func
def _add_gauss_newton_entry(values: ti.template(), tri_upper: ti.template(), t, r, s, G: ti.template(),
                            MG: ti.template()):
    """Add ``(G^T (2 M G))[r, s]`` through the triangle's packed slot table, if it is stored (``G`` and
    ``MG`` by reference: a ``ti.func`` copies its other arguments)."""
    slot = tri_upper[t, upper_index(18, r, s)]
    if slot != -1:  # entries of fixed DoFs are not computed
        add_upper_entry(values, slot, G[0, r] * MG[0, s] + G[1, r] * MG[1, s] + G[2, r] * MG[2, s])


@summing_kernel
def kirchhoff_energy(
    x: _F64_2, hinges: _I32_2, theta_bar: _F64_1, tri_hinge: _I32_2, stiffness: _F64_3, scratch: _F64_2,
    energy: _F64_1,
):
    """Energy ``sum_T d_T^T M_T d_T`` in J (``scratch`` (h, 14) is overwritten)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for h in range(hinges.shape[0]):
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        scratch[h, 0] = _dihedral_angle(x0, x1, x2, x3)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(tri_hinge.shape[0]):
        d = _triangle_deviation(scratch, theta_bar, tri_hinge, t)
        for k, l in ti.static(ti.ndrange(3, 3)):
            energy[t % energy.shape[0]] += d[k] * stiffness[t, k, l] * d[l]


@summing_kernel
def kirchhoff_energy_gradient_hessian(
    x: _F64_2, hinges: _I32_2, theta_bar: _F64_1, tri_hinge: _I32_2, tri_local: _I32_3, stiffness: _F64_3,
    tri_upper: _I32_2, hinge_upper: _I32_2, scratch: _F64_2, grad: _F64_2, values: _F64_1,
    energy: _F64_1,
):
    """Energy (J, returned); adds the gradient (N) to ``grad`` and the exact Hessian (N/m) to ``values``.

    ``tri_local[t, k, a]``: local block vertex (0..5) of vertex ``a`` of the hinge on edge ``k``;
    ``tri_upper`` (t, 171) and ``hinge_upper`` (h, 78): the packed upper slot tables of the triangle
    and hinge blocks (:func:`~sim_core.ti_kernels.block_projection.upper_slot_table`); ``scratch`` (h, 14).
    The block vertex opposite a boundary edge (a repeat of a triangle vertex) is in no hinge and its
    columns of ``G_T`` are zero: its entries are skipped.
    """
    ti.loop_config(serialize=ti.static(serial_loops()))
    for h in range(hinges.shape[0]):
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        scratch[h, 0] = _dihedral_angle(x0, x1, x2, x3)
        scratch[h, 1] = 0.0
        g = _theta_gradient(x0, x1, x2, x3)
        for r in ti.static(range(12)):
            scratch[h, 2 + r] = g[r]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(tri_hinge.shape[0]):
        d = _triangle_deviation(scratch, theta_bar, tri_hinge, t)
        M = ti.Matrix.zero(ti.f64, 3, 3)
        for k, l in ti.static(ti.ndrange(3, 3)):
            M[k, l] = stiffness[t, k, l]
        Md = M @ d
        energy[t % energy.shape[0]] += d.dot(Md)
        G = ti.Matrix.zero(ti.f64, 3, 18)
        has_hinge = ti.Vector([1, 1, 1, 0, 0, 0])  # per block vertex: in some hinge of the triangle
        for k in ti.static(range(3)):
            h = tri_hinge[t, k]
            if h >= 0:
                has_hinge[3 + k] = 1
                scratch[h, 1] += 2.0 * Md[k]
                for a in range(4):
                    col = 3 * tri_local[t, k, a]
                    for c in ti.static(range(3)):
                        G[k, col + c] = scratch[h, 2 + 3 * a + c]
        MG = _twice_product(M, G)
        for A in range(6):
            if has_hinge[A] == 1:
                for c, dd in ti.static(ti.ndrange(3, 3)):
                    if ti.static(c <= dd):
                        _add_gauss_newton_entry(values, tri_upper, t, 3 * A + c, 3 * A + dd, G, MG)
                for B in range(A + 1, 6):
                    if has_hinge[B] == 1:
                        for c, dd in ti.static(ti.ndrange(3, 3)):
                            _add_gauss_newton_entry(values, tri_upper, t, 3 * A + c, 3 * B + dd, G, MG)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for h in range(hinges.shape[0]):
        f = scratch[h, 1]
        for a in ti.static(range(4)):
            v = hinges[h, a]
            for c in ti.static(range(3)):
                grad[v, c] += f * scratch[h, 2 + 3 * a + c]
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        H = _theta_hessian_unsymmetrized(x0, x1, x2, x3)
        u = 0
        for r in range(12):
            add_upper_entry(values, hinge_upper[h, u], f * H[r, r])
            u += 1
            for s in range(r + 1, 12):
                add_upper_entry(values, hinge_upper[h, u], f * (0.5 * (H[r, s] + H[s, r])))  # symmetrised
                u += 1


@fast_kernel
def kirchhoff_triangle_hessians(
    x: _F64_2, hinges: _I32_2, theta_bar: _F64_1, tri_hinge: _I32_2, tri_local: _I32_3, stiffness: _F64_3,
    scratch: _F64_2, rows: _I32_1, count: ti.i32, blocks: _F64_3,
):
    """The exact per-triangle Hessian blocks (N/m) of the reference, ``blocks[t]`` (18, 18) over the
    triangle's block vertices, for the triangles ``t = rows[r]``, ``r < count`` (the other blocks left as they are)::

        H_T = 2 G_T^T M_T G_T + sum_{k: edge k has hinge h} 2 (M_T d_T)_k d2theta_h/dx2

    (the reference's split of the Hessian between triangles; the fused kernel above sums the same
    terms per hinge). ``scratch`` (h, 14) is overwritten (every hinge's angle and gradient).
    """
    ti.loop_config(serialize=ti.static(serial_loops()))
    for h in range(hinges.shape[0]):
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        scratch[h, 0] = _dihedral_angle(x0, x1, x2, x3)
        g = _theta_gradient(x0, x1, x2, x3)
        for r in ti.static(range(12)):
            scratch[h, 2 + r] = g[r]
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for r_t in range(count):
        t = rows[r_t]
        d = _triangle_deviation(scratch, theta_bar, tri_hinge, t)
        M = ti.Matrix.zero(ti.f64, 3, 3)
        for k, l in ti.static(ti.ndrange(3, 3)):
            M[k, l] = stiffness[t, k, l]
        Md = M @ d
        G = ti.Matrix.zero(ti.f64, 3, 18)
        for k in ti.static(range(3)):
            h = tri_hinge[t, k]
            if h >= 0:
                for a in range(4):
                    col = 3 * tri_local[t, k, a]
                    for c in ti.static(range(3)):
                        G[k, col + c] = scratch[h, 2 + 3 * a + c]
        MG = _twice_product(M, G)
        for r in range(18):
            for s in range(r, 18):
                val = G[0, r] * MG[0, s] + G[1, r] * MG[1, s] + G[2, r] * MG[2, s]
                blocks[t, r, s] = val
                blocks[t, s, r] = val
        for k in range(3):  # a runtime loop: _theta_hessian inlined once, not three times
            h = tri_hinge[t, k]
            if h >= 0:
                f = 2.0 * Md[k]
                x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
                Hh = _theta_hessian(x0, x1, x2, x3)
                for a in range(4):
                    ra = 3 * tri_local[t, k, a]
                    for b in range(4):
                        sb = 3 * tri_local[t, k, b]
                        for c, e in ti.static(ti.ndrange(3, 3)):
                            blocks[t, ra + c, sb + e] += f * Hh[3 * a + c, 3 * b + e]


def remote_evaluate(args: tuple, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
    """:meth:`FusedKirchhoffBending.evaluate` from its :meth:`~FusedKirchhoffBending.offload_recipe`
    arguments ``(hinges, theta_bar, tri_hinge, tri_local, stiffness, tri_upper, hinge_upper, scratch)``
    (the function an :class:`~sim_core.elastic_worker.ElasticWorker` runs; the same kernel on the same
    arrays, ``scratch`` the worker's own copy)."""
    hinges = args[0]
    if hinges.shape[0] == 0:
        return 0.0
    return float(kirchhoff_energy_gradient_hessian(x, *args, grad, values))


class FusedKirchhoffBending:
    """Fused Newton-loop evaluation of a :class:`KirchhoffBending` (module docstring).

    The rest angles are read from the potential given to :meth:`update` (the solver's per-step
    copy, :meth:`sim_core.elastic.ElasticTerms.bending`); everything else is fixed at construction.

    Args:
        potential: the reference potential.

    Attributes:
        vertices: the potential's Hessian-block vertex array ``block_vertices`` (t, 6).

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """

    def __init__(self, potential: KirchhoffBending) -> None:
        require_backend("FusedKirchhoffBending")
        self.potential = potential
        self.vertices = potential.block_vertices
        self._hinges = np.ascontiguousarray(potential.hinges, dtype=np.int32)
        self._tri_hinge = np.ascontiguousarray(potential.triangle_hinge, dtype=np.int32)
        # local block vertex of each hinge vertex; boundary edges (no hinge) are never read
        self._tri_local = np.ascontiguousarray(np.maximum(potential._slots, 0), dtype=np.int32)
        self._stiffness = np.ascontiguousarray(potential.triangle_stiffness, dtype=np.float64)
        self._scratch = np.zeros((self._hinges.shape[0], SCRATCH_COLUMNS))
        self._theta_bar = np.array(potential.hinge_theta_bar, dtype=np.float64, order="C")  # own copy
        self._tri_tables: SlotTables | None = None  # the triangle blocks' slot tables of the bound pattern (bind)
        self._tri_upper: np.ndarray | None = None
        self._hinge_upper: np.ndarray | None = None
        self._blocks = np.zeros((self._tri_hinge.shape[0], 18, 18))
        self._projector = TranslationFreeProjector(6)
        self._device: dict = {}  # on CUDA: device copies of the constant arrays (buffers.on_device)
        self._recipe: tuple | None = None  # the last offload_recipe()

    def accepts(self, potential) -> bool:
        """Whether ``potential`` shares this kernel's elements and stiffness (rest angles may differ)."""
        p = self.potential
        return type(potential) is type(p) and potential.hinges is p.hinges and (
            potential.triangle_stiffness is p.triangle_stiffness)

    def update(self, potential: KirchhoffBending) -> None:
        """Take the rest angles of ``potential`` (rad, ``(h,)``); the kept array when they are equal (a
        step's new copy of unchanged angles), so that an :meth:`offload_recipe` stays the same."""
        theta_bar = np.asarray(potential.hinge_theta_bar, dtype=np.float64)
        if not (theta_bar.shape == self._theta_bar.shape and np.array_equal(theta_bar, self._theta_bar)):
            self._theta_bar = np.array(theta_bar, dtype=np.float64, order="C")  # own copy: never changed in place

    @property
    def element_count(self) -> int:
        """Triangles evaluated (:meth:`sim_core.fused_elastic.FusedElastic.offloaded_part`'s cost measure)."""
        return int(self._tri_hinge.shape[0])

    def offload_recipe(self) -> tuple[str, tuple]:
        """``(target, args)`` of :meth:`evaluate` for an :class:`~sim_core.elastic_worker.ElasticWorker`
        (:func:`remote_evaluate`); the same object while nothing changed. :meth:`bind` must have been called."""
        args = (self._hinges, self._theta_bar, self._tri_hinge, self._tri_local, self._stiffness, self._tri_upper,
                self._hinge_upper, self._scratch)
        self._recipe = part_recipe(self._recipe, f"{__name__}:remote_evaluate", args)
        return self._recipe

    def bind(self, pattern) -> None:
        """The slot tables of the triangle blocks (:class:`~sim_core.ti_kernels.block_projection.SlotTables`: packed
        upper now; full, for the projected blocks, at their first use) and of the hinge blocks (packed upper) in
        ``pattern``."""
        self._tri_tables = SlotTables(pattern, self.vertices)
        self._tri_upper = self._tri_tables.upper
        self._hinge_upper = SlotTables(pattern, self.potential.hinges).upper

    @property
    def _tri_slots(self) -> np.ndarray | None:
        """The full slot map of the triangle blocks (:attr:`SlotTables.full`, for the projected blocks): made at
        its first read; None before :meth:`bind`."""
        return None if self._tri_tables is None else self._tri_tables.full

    def energy(self, x: np.ndarray) -> float:
        """Energy in J at positions ``x`` ``(n, 3)``."""
        if self._hinges.shape[0] == 0:
            return 0.0
        d = self._device
        return float(kirchhoff_energy(x, on_device(d, "hinges", self._hinges), on_device(d, "theta_bar", self._theta_bar),
                                      on_device(d, "tri_hinge", self._tri_hinge), on_device(d, "stiffness", self._stiffness),
                                      on_device(d, "scratch", self._scratch, scratch=True)))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each triangle's first vertex, J ``(copy_count,)`` (the same kernel, one
        sum cell a triangle: :func:`~sim_core.ti_kernels.copy_vectors.copy_energies`)."""
        if self._hinges.shape[0] == 0:
            return np.zeros(copy_count)
        d = self._device
        return copy_energies(kirchhoff_energy, element_copies(d, copy_of_vertex, self.vertices[:, 0]), copy_count, d,
                             x, on_device(d, "hinges", self._hinges), on_device(d, "theta_bar", self._theta_bar),
                             on_device(d, "tri_hinge", self._tri_hinge), on_device(d, "stiffness", self._stiffness),
                             on_device(d, "scratch", self._scratch, scratch=True))

    def evaluate(self, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
        """Energy in J (returned); adds dE/dx to ``grad`` ``(n, 3)`` and the exact Hessian to ``values``."""
        if self._hinges.shape[0] == 0:
            return 0.0
        d = self._device
        return float(kirchhoff_energy_gradient_hessian(
            x, on_device(d, "hinges", self._hinges), on_device(d, "theta_bar", self._theta_bar),
            on_device(d, "tri_hinge", self._tri_hinge), on_device(d, "tri_local", self._tri_local),
            on_device(d, "stiffness", self._stiffness), on_device(d, "tri_upper", self._tri_upper),
            on_device(d, "hinge_upper", self._hinge_upper), on_device(d, "scratch", self._scratch, scratch=True),
            grad, values))

    def triangle_hessians(self, x: np.ndarray) -> np.ndarray:
        """The exact per-triangle blocks ``(t, 18, 18)`` in N/m over ``vertices`` (the reference's
        ``hessian(x, "none")`` blocks); a view of a buffer that the next call overwrites."""
        if self._hinges.shape[0] == 0:
            self._blocks[:] = 0.0
            return self._blocks
        blocks = self._triangle_hessians_where_run(x, marked_rows(self.vertices, None))
        if blocks is not self._blocks:
            self._blocks[...] = blocks.to_numpy()
        return self._blocks

    def _triangle_hessians_where_run(self, x: np.ndarray, rows: np.ndarray):
        """The blocks of :meth:`triangle_hessians` of the triangles ``rows`` (int32 ``(c,)``; the other blocks left
        as they are) in the array the kernel wrote: on CUDA a device array (the constant arrays kept there,
        :func:`~sim_core.ti_kernels.buffers.on_device`), else the kept buffer."""
        d = self._device
        blocks = on_device(d, "blocks", self._blocks, scratch=True)
        kirchhoff_triangle_hessians(x, on_device(d, "hinges", self._hinges), on_device(d, "theta_bar", self._theta_bar),
                                    on_device(d, "tri_hinge", self._tri_hinge), on_device(d, "tri_local", self._tri_local),
                                    on_device(d, "stiffness", self._stiffness),
                                    on_device(d, "scratch", self._scratch, scratch=True),
                                    rows_on_device(d, "triangle_rows", rows), rows.size, blocks)
        return blocks

    projects_subsets = True
    """:meth:`add_projected` takes a vertex mask (:meth:`sim_core.fused_elastic.FusedElastic.projected_hessian_values`)."""

    def add_projected(self, x: np.ndarray, projection: str, values: np.ndarray,
                      vertices: np.ndarray | None = None) -> None:
        """Add the ``projection`` ("none", "clamp", "abs") of the per-triangle blocks into ``values``
        (:class:`~sim_core.ti_kernels.block_projection.TranslationFreeProjector`: the eigen-decomposition
        in the translation-free 15-dimensional space); with ``vertices`` (bool ``(n,)``) only the
        triangles whose stencil touches a marked vertex. On CUDA by :meth:`add_projected_on_device` into sums kept
        there, downloaded once.

        Raises:
            ValueError: unknown projection.
        """
        if self._hinges.shape[0] and current_arch() == "cuda":  # every stage on the device, the sums downloaded
            add_projected_where_run(self, x, projection, values, vertices)
            return
        blocks, slots = self.triangle_hessians(x), self._tri_slots
        if vertices is not None:
            rows = marked_rows(self.vertices, vertices)
            blocks, slots = blocks[rows], slots[rows]
        self._projector.add_projected(blocks, projection, slots, values)

    def stage_projected_rows(self, vertices: np.ndarray | None = None, closed: bool = False) -> None:
        """The rows :meth:`add_projected_on_device` takes, sent before the projection's kernels are queued
        (:func:`~sim_core.ti_kernels.block_projection.stage_projected_rows`)."""
        stage_projected_rows(self._device, self.vertices, vertices, closed, "triangle_rows", self._projector)

    def add_projected_on_device(self, x, projection: str, values, vertices: np.ndarray | None = None,
                                closed: bool = False) -> None:
        """:meth:`add_projected` by kernels where they run (on CUDA the device; on the CPU arch the same kernels on
        host arrays), into ``values`` there (``(pattern.keys.size,)``, a device array on CUDA): the triangles'
        exact blocks (:func:`kirchhoff_triangle_hessians`, of the triangles added only) reduced, projected and
        scattered through the packed upper slot table of the exact Hessian
        (:meth:`~sim_core.ti_kernels.block_projection.TranslationFreeProjector.add_projected_rows`), nothing
        crossing to the host. The sums equal the host path's to round-off. ``closed``: ``vertices`` closed under the
        triangles' stencils (:func:`~sim_core.ti_kernels.block_projection.marked_rows`).

        Raises:
            ValueError: unknown projection.
        """
        linalg.projection_code(projection)
        if self._hinges.shape[0] == 0:
            return
        rows = projected_rows(self._device, self.vertices, vertices, closed)
        blocks = self._triangle_hessians_where_run(x, rows)  # the blocks of the triangles projected only
        self._projector.add_projected_rows(blocks, projection, on_device(self._device, "tri_upper", self._tri_upper),
                                           rows, values)
