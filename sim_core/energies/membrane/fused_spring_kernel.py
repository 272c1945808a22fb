"""ThinShellLab's spring membrane in Taichi: energy, gradient and exact (or PSD-projected) Hessian into CSR slots.

The fused counterpart of :class:`sim_core.energies.membrane.reference.SpringMembrane` (the reference and
test oracle; Wang et al., ICLR 2024, public code) for the Newton loop::

    E = sum_edges K_l (1 - l / l0)^2 l0 + sum_triangles K_a (1 - A / A0)^2 A0.

Edge ``(a, b)``, ``u = (x_b - x_a) / l``: ``f' = 2 K_l (l - l0) / l0``, ``f'' = 2 K_l / l0``, block
``h3 = f'' u u^T + f' / l (I - u u^T)`` on ``[[+, -], [-, +]]``. Triangle, ``n = (x1 - x0) x (x2 - x0)``,
``A = |n| / 2``, ``w_a = x_{a+2} - x_{a+1}`` (``dn/dx_a = [w_a]_x``): ``dA/dx_a = n_hat x w_a / 2``,
``g' = 2 K_a (A - A0) / A0``, ``g'' = 2 K_a / A0``, and the 3x3 block ``(a, b)`` of the Hessian

    g'' dA_a dA_b^T + g' / 2 ([w_a]_x^T (I - n_hat n_hat^T) [w_b]_x / |n| + Q_ab),
    Q_{a, a+1} = -[n_hat]_x,  Q_{a+1, a} = [n_hat]_x,  0 otherwise,

evaluated with ``[w_a]_x^T (I - n_hat n_hat^T) [w_b]_x = (w_a . w_b) I - w_b w_a^T - 4 dA_a dA_b^T``
(``[a]_x^T [b]_x = (a . b) I - b a^T`` and ``[w]_x^T n_hat = n_hat x w = 2 dA``), which spares the
two 3x3 products per block (less compile and run time).

The projected fallback (:meth:`FusedSpringMembrane.add_projected`) projects the edge blocks in closed
form (``f' / l`` clamped at 0, or its absolute value: the other eigenvalue, ``f''``, is >= 0) and
the triangle blocks by the reduced eigen-decomposition of
:class:`~sim_core.ti_kernels.block_projection.TranslationFreeProjector`: the reference's projection
to round-off, without its NumPy evaluation (about 1.2 ms in place of 3.6-4.8 ms per call on the
Forming benchmark, 210 triangles and 337 edges).

Entries go straight into the solver's static pattern values through
:meth:`sim_core.assembly.StaticPattern.slot_map` of the potential's block vertices (triangles, then
edges padded to ``[a, b, b]``), packed by :func:`sim_core.ti_kernels.block_projection.upper_slot_table`.
Serial loops on the CPU, parallel on CUDA, as in :mod:`sim_core.energies.neohookean.fused_kernel`
(reproducible sums).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.membrane.reference import SpringMembrane
from sim_core.ti_backend import current_arch, require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import on_device, rows_on_device
from sim_core.ti_kernels.copy_vectors import copy_energies, element_copies
from sim_core.ti_kernels.launch import fast_kernel, summing_kernel
from sim_core.ti_kernels.linalg import projection_code
from sim_core.worker_recipe import part_recipe
from sim_core.ti_kernels.block_projection import (
    TranslationFreeProjector, add_projected_where_run, add_upper_entry, BoundSlotTables, marked_rows, projected_rows,
    stage_projected_rows, upper_index,
)

_F64_1, _F64_2, _F64_3, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_2
_I32_1 = linalg.I32_1


@ti.func
def _cross_matrix(v):
    """``[v]_x`` with ``[v]_x w = v x w``."""
    return ti.Matrix([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], ti.f64)


@summing_kernel
def spring_membrane_energy(
    x: _F64_2, triangles: _I32_2, edges: _I32_2, area0: _F64_1, length0: _F64_1, k_length: ti.f64, k_area: ti.f64,
    energy: _F64_1,
):
    """Energy in J (module docstring)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for e in range(edges.shape[0]):
        l = (linalg.row3(x, edges[e, 1]) - linalg.row3(x, edges[e, 0])).norm()
        energy[e % energy.shape[0]] += k_length * (1.0 - l / length0[e]) ** 2 * length0[e]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(triangles.shape[0]):  # the triangles numbered after the edges (element_terms' cells)
        x0 = linalg.row3(x, triangles[t, 0])
        A = 0.5 * (linalg.row3(x, triangles[t, 1]) - x0).cross(linalg.row3(x, triangles[t, 2]) - x0).norm()
        energy[(edges.shape[0] + t) % energy.shape[0]] += k_area * (1.0 - A / area0[t]) ** 2 * area0[t]


@ti.func
def _edge_terms(x: ti.template(), edges: ti.template(), length0: ti.template(), k_length, e):
    """Edge ``e``: unit direction ``u``, length ``l`` (m), ``f' = 2 K_l (l - l0) / l0`` (N) and
    ``f'' = 2 K_l / l0`` (N/m)."""
    dx = linalg.row3(x, edges[e, 1]) - linalg.row3(x, edges[e, 0])
    l = dx.norm()
    l0 = length0[e]
    return dx / l, l, 2.0 * k_length * (l - l0) / l0, 2.0 * k_length / l0


@ti.func
def _add_edge_block(values: ti.template(), upper: ti.template(), row, u, f2, across):
    """Add the 6x6 edge block ``[[h3, -h3], [-h3, h3]]``, ``h3 = f'' u u^T + across (I - u u^T)``
    (N/m; ``across = f' / l`` for the exact block), through row ``row`` of the packed upper slot table."""
    uu = u.outer_product(u)
    h3 = f2 * uu + across * (ti.Matrix.identity(ti.f64, 3) - uu)
    for c, d in ti.static(ti.ndrange(3, 3)):
        if ti.static(c <= d):
            add_upper_entry(values, upper[row, upper_index(9, c, d)], h3[c, d])
            add_upper_entry(values, upper[row, upper_index(9, 3 + c, 3 + d)], h3[c, d])
        add_upper_entry(values, upper[row, upper_index(9, c, 3 + d)], -h3[c, d])


@ti.func
def _triangle_terms(x: ti.template(), triangles: ti.template(), area0: ti.template(), k_area, t):
    """Triangle ``t``: area ``A`` (m^2), ``g' = 2 K_a (A - A0) / A0`` (N/m), ``g'' = 2 K_a / A0``
    (N/m^3), ``|n|``, ``[n_hat]_x`` and the lists ``w_a``, ``dA/dx_a`` (module docstring)."""
    X0 = linalg.row3(x, triangles[t, 0])
    X1 = linalg.row3(x, triangles[t, 1])
    X2 = linalg.row3(x, triangles[t, 2])
    n = (X1 - X0).cross(X2 - X0)
    n_norm = n.norm()
    n_hat = n / n_norm
    A = 0.5 * n_norm
    A0 = area0[t]
    w0 = X2 - X1
    w1 = X0 - X2
    w2 = X1 - X0
    dA = [0.5 * n_hat.cross(w0), 0.5 * n_hat.cross(w1), 0.5 * n_hat.cross(w2)]
    return A, 2.0 * k_area * (A - A0) / A0, 2.0 * k_area / A0, n_norm, _cross_matrix(n_hat), [w0, w1, w2], dA


@ti.func
def _area_block(a: ti.template(), b: ti.template(), g1, g2, n_norm, K, W, dA):
    """The 3x3 block ``(a, b)`` (N/m) of a triangle's area Hessian (module docstring), from
    :func:`_triangle_terms`."""
    # [w_a]_x^T (I - n_hat n_hat^T) [w_b]_x = (w_a . w_b) I - w_b w_a^T - 4 dA_a dA_b^T
    ab = dA[a].outer_product(dA[b])
    B = g2 * ab + (0.5 * g1 / n_norm) * (W[a].dot(W[b]) * ti.Matrix.identity(ti.f64, 3)
                                         - W[b].outer_product(W[a]) - 4.0 * ab)
    if ti.static(b == (a + 1) % 3):
        B -= 0.5 * g1 * K
    elif ti.static(a == (b + 1) % 3):
        B += 0.5 * g1 * K
    return B


@summing_kernel
def spring_membrane_energy_gradient_hessian(
    x: _F64_2, triangles: _I32_2, edges: _I32_2, area0: _F64_1, length0: _F64_1, upper: _I32_2,
    k_length: ti.f64, k_area: ti.f64, grad: _F64_2, values: _F64_1,
    energy: _F64_1,
):
    """Energy (J, returned); adds the gradient (N) to ``grad`` (n, 3) and the exact Hessian (N/m)
    to ``values`` through the packed upper slot table ``upper`` (rows: triangles, then edges; 45
    entries of the 9x9 blocks, :func:`~sim_core.ti_kernels.block_projection.upper_slot_table`)."""
    t_count = triangles.shape[0]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for e in range(edges.shape[0]):
        va = edges[e, 0]
        vb = edges[e, 1]
        u, l, f1, f2 = _edge_terms(x, edges, length0, k_length, e)
        l0 = length0[e]
        energy[e % energy.shape[0]] += k_length * (1.0 - l / l0) ** 2 * l0
        for i in ti.static(range(3)):
            grad[vb, i] += f1 * u[i]
            grad[va, i] -= f1 * u[i]
        _add_edge_block(values, upper, t_count + e, u, f2, f1 / l)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(t_count):
        A, g1, g2, n_norm, K, W, dA = _triangle_terms(x, triangles, area0, k_area, t)
        A0 = area0[t]
        energy[t % energy.shape[0]] += k_area * (1.0 - A / A0) ** 2 * A0
        for i in ti.static(range(3)):
            for a in ti.static(range(3)):
                grad[triangles[t, a], i] += g1 * dA[a][i]
        for a in ti.static(range(3)):
            for b in ti.static(range(a, 3)):
                B = _area_block(a, b, g1, g2, n_norm, K, W, dA)
                for c, d in ti.static(ti.ndrange(3, 3)):
                    if ti.static(a != b or c <= d):
                        add_upper_entry(values, upper[t, upper_index(9, 3 * a + c, 3 * b + d)], B[c, d])


@fast_kernel
def spring_membrane_projected_edges(
    x: _F64_2, edges: _I32_2, length0: _F64_1, upper: _I32_2, t_count: ti.i32, k_length: ti.f64,
    code: ti.i32, values: _F64_1,
):
    """Adds the projected edge blocks (N/m) into ``values`` through rows ``t_count + e`` of ``upper``.

    The reduced block of ``[[h3, -h3], [-h3, h3]]`` in the translation-free basis is ``2 h3``, with
    eigenvalues ``2 f''`` (along ``u``, >= 0) and ``2 f' / l`` (twice, across), so the projection
    (``code`` of :func:`~sim_core.ti_kernels.linalg.projection_code`: 0 none, 1 clamp, 2 abs) maps
    ``f' / l`` to ``max(f' / l, 0)`` or ``|f' / l|`` in closed form."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for e in range(edges.shape[0]):
        u, l, f1, f2 = _edge_terms(x, edges, length0, k_length, e)
        c = f1 / l
        if code == 1:
            c = ti.max(c, 0.0)
        elif code == 2:
            c = ti.abs(c)
        _add_edge_block(values, upper, t_count + e, u, f2, c)


@fast_kernel
def spring_membrane_triangle_blocks(x: _F64_2, triangles: _I32_2, area0: _F64_1, k_area: ti.f64, rows: _I32_1,
                                    count: ti.i32, blocks: _F64_3):
    """The exact 9x9 area blocks (N/m) of the triangles ``t = rows[r]``, ``r < count``, into ``blocks[t]`` (local DoF
    ``3 a + c``; the other blocks left as they are)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for r in range(count):
        t = rows[r]
        A, g1, g2, n_norm, K, W, dA = _triangle_terms(x, triangles, area0, k_area, t)
        for a in ti.static(range(3)):
            for b in ti.static(range(a, 3)):
                B = _area_block(a, b, g1, g2, n_norm, K, W, dA)
                for c, d in ti.static(ti.ndrange(3, 3)):
                    blocks[t, 3 * a + c, 3 * b + d] = B[c, d]
                    blocks[t, 3 * b + d, 3 * a + c] = B[c, d]


def remote_evaluate(args: tuple, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
    """:meth:`FusedSpringMembrane.evaluate` from its :meth:`~FusedSpringMembrane.offload_recipe` arguments
    ``(triangles, edges, area0, length0, upper, k_length, k_area)`` (the function an
    :class:`~sim_core.elastic_worker.ElasticWorker` runs; the same kernel on the same arrays)."""
    triangles, edges, area0, length0, upper, k_length, k_area = args
    return float(spring_membrane_energy_gradient_hessian(x, triangles, edges, area0, length0, upper, k_length, k_area,
                                                         grad, values))


class FusedSpringMembrane(BoundSlotTables):
    """Fused Newton-loop evaluation of a :class:`SpringMembrane` (module docstring).

    Args:
        potential: the reference potential (edges, triangles, rest lengths and areas read once).

    Attributes:
        vertices: the potential's Hessian-block vertex array (triangles, then padded edges).

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """

    def __init__(self, potential: SpringMembrane) -> None:
        require_backend("FusedSpringMembrane")
        self.potential = potential
        self.vertices = potential._block_vertices
        self._triangles = np.ascontiguousarray(potential.triangles, dtype=np.int32)
        self._edges = np.ascontiguousarray(potential.edges, dtype=np.int32)
        self._area0 = np.ascontiguousarray(potential.triangle_rest_area, dtype=np.float64)
        self._length0 = np.ascontiguousarray(potential.edge_rest_length, dtype=np.float64)
        self._blocks: np.ndarray | None = None  # triangle blocks of the projected Hessian, (t, 9, 9)
        self._projector = TranslationFreeProjector(3)
        self._recipe: tuple | None = None  # the last offload_recipe()
        self._device: dict = {}  # on CUDA: device copies of the constant arrays (buffers.on_device)

    def accepts(self, potential) -> bool:
        """Whether ``potential`` is evaluated by this kernel as it stands (same elements, stiffnesses)."""
        p = self.potential
        return potential is p or (type(potential) is type(p) and potential._block_vertices is p._block_vertices
                                  and potential.k_length == p.k_length and potential.k_area == p.k_area)

    def update(self, potential) -> None:
        """Nothing changes between steps."""

    def energy(self, x: np.ndarray) -> float:
        """Energy in J at positions ``x`` ``(n, 3)``."""
        p = self.potential
        d = self._device
        return float(spring_membrane_energy(x, on_device(d, "triangles", self._triangles), on_device(d, "edges", self._edges),
                                            on_device(d, "area0", self._area0), on_device(d, "length0", self._length0),
                                            p.k_length, p.k_area))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each edge's and triangle's first vertex, J ``(copy_count,)`` (the same
        kernel, one sum cell an element, the triangles after the edges:
        :func:`~sim_core.ti_kernels.copy_vectors.copy_energies`)."""
        p = self.potential
        d = self._device
        element_copy = element_copies(d, copy_of_vertex, self._edges[:, 0], self._triangles[:, 0])
        return copy_energies(spring_membrane_energy, element_copy, copy_count, d, x,
                             on_device(d, "triangles", self._triangles), on_device(d, "edges", self._edges),
                             on_device(d, "area0", self._area0), on_device(d, "length0", self._length0), p.k_length,
                             p.k_area)

    def evaluate(self, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
        """Energy in J (returned); adds dE/dx to ``grad`` ``(n, 3)`` and the exact Hessian to ``values``."""
        p = self.potential
        d = self._device
        return float(spring_membrane_energy_gradient_hessian(
            x, on_device(d, "triangles", self._triangles), on_device(d, "edges", self._edges),
            on_device(d, "area0", self._area0), on_device(d, "length0", self._length0), on_device(d, "upper", self._upper),
            p.k_length, p.k_area, grad, values))

    @property
    def element_count(self) -> int:
        """Triangles evaluated (:meth:`sim_core.fused_elastic.FusedElastic.offloaded_part`'s cost measure)."""
        return int(self._triangles.shape[0])

    def offload_recipe(self) -> tuple[str, tuple]:
        """``(target, args)`` of :meth:`evaluate` for an :class:`~sim_core.elastic_worker.ElasticWorker`
        (:func:`remote_evaluate`); the same object while nothing changed. :meth:`bind` must have been called."""
        p = self.potential
        args = (self._triangles, self._edges, self._area0, self._length0, self._upper, float(p.k_length),
                float(p.k_area))
        self._recipe = part_recipe(self._recipe, f"{__name__}:remote_evaluate", args)
        return self._recipe

    projects_subsets = True
    """:meth:`add_projected` takes a vertex mask (:meth:`sim_core.fused_elastic.FusedElastic.projected_hessian_values`)."""

    def add_projected(self, x: np.ndarray, projection: str, values: np.ndarray,
                      vertices: np.ndarray | None = None) -> None:
        """Add the ``projection`` ("none", "clamp", "abs") Hessian blocks into ``values``: the reference's
        projection (:meth:`SpringMembrane.hessian`) to round-off, the triangles' exact 9x9 blocks
        (:func:`spring_membrane_triangle_blocks`) through
        :class:`~sim_core.ti_kernels.block_projection.TranslationFreeProjector` (6-dimensional), then
        the edges' closed form (:func:`spring_membrane_projected_edges`). With ``vertices`` (bool
        ``(n,)``) the triangles projected are those touching a marked vertex (every edge is added).

        Raises:
            ValueError: unknown projection.
        """
        code = projection_code(projection)
        p = self.potential
        t_count = self._triangles.shape[0]
        if current_arch() == "cuda":  # every stage on the device, the sums downloaded once
            self.add_projected_by_kernels(x, projection, values, vertices)
            return
        if t_count:
            if self._blocks is None:
                self._blocks = np.zeros((t_count, 9, 9))
            rows = marked_rows(self._triangles, vertices)
            spring_membrane_triangle_blocks(x, self._triangles, self._area0, p.k_area, rows, rows.size, self._blocks)
            blocks, slots = self._blocks, self._slots[:t_count]
            if vertices is not None:
                blocks, slots = blocks[rows], slots[rows]
            self._projector.add_projected(blocks, projection, slots, values)
        if self._edges.shape[0]:
            spring_membrane_projected_edges(x, self._edges, self._length0, self._upper, t_count, p.k_length, code,
                                            values)

    def add_projected_by_kernels(self, x: np.ndarray, projection: str, values: np.ndarray,
                                 vertices: np.ndarray | None = None) -> None:
        """:meth:`add_projected` by kernels alone (what it runs on CUDA; on the CPU arch the same kernels on
        host arrays): :meth:`add_projected_on_device` into one array of sums kept where the kernels run (on CUDA the
        device: the blocks never cross to the host), then added to ``values`` ``(pattern.keys.size,)`` (one
        download). The sums equal :meth:`add_projected`'s host path to round-off.

        Raises:
            ValueError: unknown projection.
        """
        add_projected_where_run(self, x, projection, values, vertices)

    def stage_projected_rows(self, vertices: np.ndarray | None = None, closed: bool = False) -> None:
        """The rows :meth:`add_projected_on_device` takes, sent before the projection's kernels are queued
        (:func:`~sim_core.ti_kernels.block_projection.stage_projected_rows`)."""
        stage_projected_rows(self._device, self._triangles, vertices, closed, "triangle_rows", self._projector)

    def add_projected_on_device(self, x, projection: str, values, vertices: np.ndarray | None = None,
                                closed: bool = False) -> None:
        """The projected blocks added into ``values`` ``(pattern.keys.size,)`` where the kernels run (on CUDA a device
        array; on the CPU arch the same kernels on host arrays): the triangles' exact blocks
        (:func:`spring_membrane_triangle_blocks`) reduced, projected by the Jacobi kernel and scattered through the
        packed upper slot table by
        :meth:`~sim_core.ti_kernels.block_projection.TranslationFreeProjector.add_projected_rows` (with ``vertices``
        the triangles touching a marked vertex, whose blocks alone are made; ``closed``: ``vertices`` closed under the
        triangles, :func:`~sim_core.ti_kernels.block_projection.marked_rows`), the edges' closed form
        (:func:`spring_membrane_projected_edges`).

        Raises:
            ValueError: unknown projection.
        """
        code = projection_code(projection)
        p = self.potential
        d = self._device
        t_count = self._triangles.shape[0]
        upper = on_device(d, "upper", self._upper)
        if t_count:
            if self._blocks is None:
                self._blocks = np.zeros((t_count, 9, 9))
            blocks = on_device(d, "blocks", self._blocks, scratch=True)
            rows = projected_rows(d, self._triangles, vertices, closed)  # the blocks of these triangles made only
            spring_membrane_triangle_blocks(x, on_device(d, "triangles", self._triangles),
                                            on_device(d, "area0", self._area0), p.k_area,
                                            rows_on_device(d, "triangle_rows", rows), rows.size, blocks)
            self._projector.add_projected_rows(blocks, projection, upper, rows, values)
        if self._edges.shape[0]:
            spring_membrane_projected_edges(x, on_device(d, "edges", self._edges), on_device(d, "length0", self._length0),
                                            upper, t_count, p.k_length, code, values)
