"""Lagged friction rows built and kept on the device: the frames, normal forces and coefficients of a step's active pairs.

On a GPU the contact set's friction set-up (:meth:`sim_core.contact_set.ContactSet.friction`, pair contacts only) made
the active pairs' frames in a kernel, read them back, and the friction sent them up again: its vertices, weights,
tangent bases, previous positions and coefficients, each a synchronous copy, with a host compaction of the pairs'
vertices between (session 54: ~20-25 ms and 9 copies a Forming step at B = 1024 on an H100). Here one launch of
:func:`_rows_kernel` builds every row where the friction's kernels read it: from the active pairs' vertices, steps
sides and distances (one upload) and ``x^n`` (read where the solver's terms hold it), each pair's closest-point
weights, unit normal and tangent basis (the functions of
:func:`~sim_core.energies.contact.setup_kernel.friction_frames`: the same values bit for bit), its vertices'
previous positions, its lagged normal force ``lam = k_c (eps - d)`` and its Coulomb coefficient ``mu`` from the
bodies' table (:class:`~sim_core.coulomb_coefficients.CoulombCoefficients`), in one row of one float64 device array
(:data:`ROW`). :class:`DeviceLaggedFriction` evaluates energy, gradient, Hessian blocks and energies by copy from
those rows on the device; its host arrays (weights, tangent bases, normal forces, coefficients: what the adjoint's
rows and the host paths read) are copied back in one copy only when one is asked for.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as objects.

import numpy as np

from sim_core.energies.base import positions_key
from sim_core.energies.contact.setup_kernel import _edge_edge_frame, _point_triangle_frame, _tangent_frame
from sim_core.energies.friction.kernel import TiLaggedFriction, _f0, _f1_over_x, tangent_hessian
from sim_core.ti_backend import serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import (DeviceHessianBlocks, DeviceRows, LaunchArrays, copy_back, on_device,
                                        rows_on_device, unheld_rows)
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.workspace import workspace_of

_F64_1, _F64_2, _F64_3, _I32_1, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_1, linalg.I32_2

_W, _N, _T, _XP, _LAM, _MU, _C = 0, 4, 7, 13, 25, 26, 27
"""Columns of a row: weights (4), unit normal (3), ``T`` row by row (6: ``T[d, i]`` at ``_T + 2 d + i``), the pair's
vertices' positions at ``x^n`` (4 x 3), ``lam`` (N), ``mu``, ``c = mu lam`` (N)."""
ROW = 28
"""Entries of a row of :func:`_rows_kernel`'s ``rows``."""
PAIR_FIELDS = 6
"""Entries of a row of :func:`_rows_kernel`'s input ``pairs``: the pair's four vertices, its side, its distance (m)."""

_ARRAYS = LaunchArrays()
"""Per thread: the rows' launch inputs (sent at each set-up) and the spare device arrays the frictions' rows, blocks
and energies are taken from (:func:`~sim_core.ti_kernels.buffers.unheld_rows`: an array a friction holds is never
written for another)."""


@fast_kernel
def _rows_kernel(x: _F64_2, pairs: _F64_2, count: ti.i32, split: ti.i32, eps_vt: ti.f64, eps_ee: ti.f64,
                 stiffness_vt: ti.f64, stiffness_ee: ti.f64, vertex_body: _I32_1, table: _F64_2, vertices: _I32_2,
                 rows: _F64_2):
    """Pairs ``k < count`` (``k < split`` vertex-triangle ``[p, a, b, c]``, else edge-edge ``[a0, a1, b0, b1]``;
    ``pairs[k]`` their vertices, side and distance ``d``): their vertices into ``vertices[k]`` (int32), their friction
    row into ``rows[k]`` (:data:`ROW` columns): the frame and tangent basis of
    :func:`~sim_core.energies.contact.setup_kernel._friction_frames_kernel`, the vertices' positions ``x[v]``,
    ``lam = k_c (eps - d)`` and ``mu = table[body(v_0), body(v_s)]`` (``s`` the second side's column: 1, or 2 of an
    edge-edge pair) of their kind, and ``mu lam``."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(count):
        for j in ti.static(range(4)):
            vertices[k, j] = ti.cast(pairs[k, j], ti.i32)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(count):
        side, d = pairs[k, 4], pairs[k, 5]
        second = 2
        lam = 0.0
        if k < split:
            _point_triangle_frame(x, vertices, k, side, rows, rows, _W, _N)
            lam = stiffness_vt * (eps_vt - d)
            second = 1
        else:
            _edge_edge_frame(x, vertices, k, side, rows, rows, _W, _N)
            lam = stiffness_ee * (eps_ee - d)
        _tangent_frame(rows, k, _N, rows, _T)
        for j in ti.static(range(4)):
            for e in ti.static(range(3)):
                rows[k, _XP + 3 * j + e] = x[vertices[k, j], e]
        mu = table[vertex_body[vertices[k, 0]], vertex_body[vertices[k, second]]]
        rows[k, _LAM], rows[k, _MU], rows[k, _C] = lam, mu, mu * lam


@ti.func
def _displacement(x: ti.template(), vertices: ti.template(), rows: ti.template(), k: ti.i32):
    """``u = T^T sum_j w_j (x_j - x^n_j)`` (2-vector, m) of row ``k`` (the reference's order of operations)."""
    rel = ti.Vector.zero(ti.f64, 3)
    for j in range(4):
        v = vertices[k, j]
        for d in ti.static(range(3)):
            rel[d] += rows[k, _W + j] * (x[v, d] - rows[k, _XP + 3 * j + d])
    u = ti.Vector.zero(ti.f64, 2)
    for i in ti.static(range(2)):
        for d in ti.static(range(3)):
            u[i] += rows[k, _T + 2 * d + i] * rel[d]
    return u


@fast_kernel
def _evaluate_kernel(x: _F64_2, vertices: _I32_2, rows: _F64_2, count: ti.i32, eps_u: ti.f64, energy: _F64_1,
                     blocks: _F64_3, gradient: _F64_2):
    """Rows ``k < count`` at positions ``x`` ``(n, 3)``: ``energy[0] = sum_k c_k f0(|u_k|)`` (J), each pair's block
    ``c_k w_a w_b T [(f1/y) I + ((f1' y - f1) / y^3) u u^T] T^T`` into ``blocks[k]`` ``(12, 12)`` (N/m), and its
    gradient ``c_k (f1/y) w_j T u`` added at its vertices into ``gradient`` ``(n, 3)`` (N; in pair order on the CPU's
    serial loops)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for _ in range(1):
        energy[0] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(count):
        u = _displacement(x, vertices, rows, k)
        y = ti.sqrt(u[0] * u[0] + u[1] * u[1])
        c = rows[k, _C]
        energy[0] += c * _f0(y, eps_u)
        scale = c * _f1_over_x(y, eps_u)
        tu = ti.Vector.zero(ti.f64, 3)
        for d in ti.static(range(3)):
            tu[d] = (rows[k, _T + 2 * d] * u[0] + rows[k, _T + 2 * d + 1] * u[1]) * scale
        for j in range(4):
            v = vertices[k, j]
            for d in ti.static(range(3)):
                gradient[v, d] += rows[k, _W + j] * tu[d]
        basis = ti.Matrix.zero(ti.f64, 3, 2)
        for d, i in ti.static(ti.ndrange(3, 2)):
            basis[d, i] = rows[k, _T + 2 * d + i]
        H3 = tangent_hessian(u, basis, c, eps_u)
        for a in range(4):
            for b in range(4):
                wab = rows[k, _W + a] * rows[k, _W + b]
                for d, e in ti.static(ti.ndrange(3, 3)):
                    blocks[k, 3 * a + d, 3 * b + e] = wab * H3[d, e]


@fast_kernel
def _energy_by_copy_kernel(x: _F64_2, vertices: _I32_2, rows: _F64_2, count: ti.i32, eps_u: ti.f64,
                           copy_of_vertex: _I32_1, out: _F64_1):
    """``out[copy_of_vertex[v_k0]] += c_k f0(|u_k|)`` (J) for every row ``k < count`` at positions ``x``."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(count):
        u = _displacement(x, vertices, rows, k)
        out[copy_of_vertex[vertices[k, 0]]] += rows[k, _C] * _f0(ti.sqrt(u[0] * u[0] + u[1] * u[1]), eps_u)


class DeviceLaggedFriction(TiLaggedFriction):
    """A :class:`~sim_core.energies.friction.kernel.TiLaggedFriction` whose rows were built on the device
    (:func:`friction_on_device`) and stay there: :meth:`add_gradient_on_device`, :meth:`add_copy_energies_on_device`,
    :meth:`hessian_on_device` and the energy of such an evaluation read them where they are. The host arrays
    ``weights`` ``(p, 4)``, ``tangent`` ``(p, 3, 2)``, ``lam`` ``(p,)`` (N) and ``mu`` ``(p,)`` are copied back (one
    copy) at the first read of any of them; from then on (``mu`` may be edited) every evaluation is the Taichi
    friction's own, on those host arrays. ``vertices`` ``(p, 4)`` and ``x_prev`` ``(n, 3)`` are host arrays from the
    start (the Newton matrix's blocks and the set-up's ``x^n``).

    Args:
        vertices: the pairs' global vertex indices, int ``(p, 4)``, ``p > 0``.
        device: ``(vertices int32 (>= p, 4), rows float64 (>= p, ROW))``, Taichi ndarrays :func:`_rows_kernel`
            wrote, held by this friction only.
        x_prev: the positions the rows were frozen at, ``(n, 3)`` (m), never changed while it exists.
        eps_v, dt: as :class:`~sim_core.energies.friction.reference.LaggedFriction`.
    """

    def __init__(self, vertices: np.ndarray, device: tuple, x_prev: np.ndarray, eps_v: float, dt: float) -> None:
        self.vertices = np.asarray(vertices, dtype=np.int64)
        self._device_arrays = device
        self._host = None
        self.x_prev = x_prev
        self.eps_v, self.dt = float(eps_v), float(dt)
        self.eps_u = self.eps_v * self.dt

    def __getstate__(self) -> dict:
        """A pickle or copy holds the host arrays (read back here if they were not yet), not the device rows."""
        state = dict(self.__dict__)
        state["_host"], state["_device_arrays"] = self._host_values(), None
        return state

    def _host_values(self) -> dict:
        """The rows' host arrays, copied back once (the device path ends here)."""
        if self._host is None:
            p = self.vertices.shape[0]
            rows = copy_back(np.empty(tuple(self._device_arrays[1].shape)), self._device_arrays[1], p)[:p]
            self._host = {"weights": rows[:, _W:_W + 4].copy(), "tangent": rows[:, _T:_T + 6].reshape(p, 3, 2).copy(),
                          "lam": rows[:, _LAM].copy(), "mu": rows[:, _MU].copy(), "normal": rows[:, _N:_N + 3].copy()}
        return self._host

    weights = property(lambda self: self._host_values()["weights"],
                       doc="Closest-point weights ``(p, 4)`` (copied back at the first read).")
    tangent = property(lambda self: self._host_values()["tangent"],
                       doc="Tangent bases ``(p, 3, 2)`` (copied back at the first read).")
    lam = property(lambda self: self._host_values()["lam"], doc="Lagged normal forces ``(p,)`` (N).")
    normal = property(lambda self: self._host_values()["normal"], doc="Unit normals at ``x^n`` ``(p, 3)``.")

    @property
    def mu(self) -> np.ndarray:
        """Coulomb coefficients ``(p,)`` (copied back at the first read; may be edited, on the host, from then on)."""
        return self._host_values()["mu"]

    @mu.setter
    def mu(self, value) -> None:
        self._host_values()["mu"] = np.broadcast_to(np.asarray(value, dtype=float), (self.vertices.shape[0],)).copy()

    def _on_device(self) -> bool:
        """Whether the evaluations read the device rows (no host array asked for yet)."""
        return self._host is None

    def add_gradient_on_device(self, x: np.ndarray, x_device, gradient_device) -> float | None:
        """:meth:`~sim_core.energies.friction.kernel.TiLaggedFriction.add_gradient_on_device` from the device rows: one
        launch of :func:`_evaluate_kernel` at ``x_device`` (energy, blocks, the gradient added into
        ``gradient_device``), the energy and blocks kept for ``x`` where they were written (the energy read when
        :meth:`energy` asks). Returns None (the energy is not on the host)."""
        if not self._on_device():
            return super().add_gradient_on_device(x, x_device, gradient_device)
        p = self.vertices.shape[0]
        spares = _ARRAYS.spares()
        blocks, energy = unheld_rows(spares, "blocks", p, (12, 12)), unheld_rows(spares, "energy", 1)
        vertices, rows = self._device_arrays
        _evaluate_kernel(x_device, vertices, rows, p, self.eps_u, energy, blocks, gradient_device)
        workspace_of(self).put(self, "rows_at", (positions_key(x), self.eps_u, energy, blocks, None))
        return None

    def _evaluation(self, x: np.ndarray) -> tuple | None:
        """The kept :meth:`add_gradient_on_device` evaluation ``(key, eps_u, energy, blocks, energy value)`` of
        ``x`` on the device rows, or None."""
        kept = workspace_of(self).get(self, "rows_at")
        if kept is None or not self._on_device() or kept[1] != self.eps_u or kept[0] != positions_key(x):
            return None
        return kept

    def hessian_on_device(self, x: np.ndarray) -> DeviceHessianBlocks | None:
        """The blocks ``(p, 12, 12)`` of the kept evaluation of ``x`` where :func:`_evaluate_kernel` wrote them, or
        None (capability :class:`~sim_core.energies.base.DeviceHessian`)."""
        if not self._on_device():
            return super().hessian_on_device(x)
        kept = self._evaluation(x)
        return None if kept is None else DeviceHessianBlocks(self.vertices, DeviceRows(kept[3], 0, len(self.vertices)))

    def energy(self, x: np.ndarray) -> float:
        """Friction dissipation potential in J: the kept device evaluation's (read back once), else the Taichi
        friction's on the host arrays."""
        kept = self._evaluation(x)
        if kept is None:
            return super().energy(x)
        if kept[4] is None:
            kept = workspace_of(self).put(self, "rows_at", kept[:4] + (float(copy_back(np.empty(
                tuple(kept[2].shape)), kept[2], 1)[0]),))
        return kept[4]

    def add_copy_energies_on_device(self, x: np.ndarray, x_device, copy_of_vertex: np.ndarray, sums) -> bool:
        """:meth:`~sim_core.energies.friction.reference.LaggedFriction.copy_energies` at ``x_device`` added into
        ``sums`` (a :class:`~sim_core.ti_kernels.copy_vectors.CopySums` over ``copy_of_vertex``) in one launch of
        :func:`_energy_by_copy_kernel` from the device rows (the copies of the vertices sent once per
        ``copy_of_vertex`` array); False (nothing added) without ``x_device``."""
        if not self._on_device():
            return super().add_copy_energies_on_device(x, x_device, copy_of_vertex, sums)
        if x_device is None:
            return False
        kept = _ARRAYS.device().get("copy_of_vertex_sent")
        if kept is None or kept[0] is not copy_of_vertex:
            kept = _ARRAYS.device()["copy_of_vertex_sent"] = (copy_of_vertex, copy_of_vertex.astype(np.int32))
        vertices, rows = self._device_arrays
        _energy_by_copy_kernel(x_device, vertices, rows, self.vertices.shape[0], self.eps_u,
                               on_device(_ARRAYS.device(), "copy_of_vertex", kept[1]), sums.values)
        return True


def friction_on_device(x_n: np.ndarray, x_device, vertices: np.ndarray, sides: np.ndarray, distances: np.ndarray,
                       split: int, parameters: tuple, vertex_body: np.ndarray, table: np.ndarray, eps_v: float,
                       dt: float) -> DeviceLaggedFriction:
    """A step's lagged friction of active pairs, its rows built by one launch of :func:`_rows_kernel`.

    Args:
        x_n: the step's start positions ``(n, 3)`` (m), frozen (never changed while they exist).
        x_device: ``x_n`` as a float64 Taichi ndarray ``(n, 3)`` where the solver's terms hold it on the device
            (read there), or None (sent).
        vertices: the active pairs' global vertex indices ``(p, 4)``, ``p > 0``: the first ``split`` rows
            vertex-triangle ``[p, a, b, c]``, the others edge-edge ``[a0, a1, b0, b1]``.
        sides: their step sides (+1 / -1, 0 unsigned) ``(p,)``.
        distances: their distances at ``x_n`` ``(p,)`` (m), each below its kind's ``eps``.
        split: number of vertex-triangle rows.
        parameters: ``(eps_vt, eps_ee, stiffness_vt, stiffness_ee)`` (m, m, N/m, N/m) of the two pair potentials.
        vertex_body: each vertex's body, int ``(n,)``; ``table``: Coulomb coefficients between bodies ``(b, b)``.
        eps_v, dt: the friction's stick speed (m/s) and the step (s).

    Returns:
        The :class:`DeviceLaggedFriction` of the rows (in the order of ``vertices``).
    """
    p = len(vertices)
    pairs = _ARRAYS.rows("pairs", p, (PAIR_FIELDS,))
    pairs[:p, :4] = vertices
    pairs[:p, 4] = sides
    pairs[:p, 5] = distances
    device = _ARRAYS.device()
    kept = device.get("vertex_body_sent")
    if kept is None or kept[0] is not vertex_body:
        kept = device["vertex_body_sent"] = (vertex_body, np.ascontiguousarray(vertex_body, dtype=np.int32))
    spares = _ARRAYS.spares()
    rows = unheld_rows(spares, "rows", p, (ROW,))
    index = _unheld_vertices(spares, p)
    x_arg = x_device if x_device is not None else on_device(device, "x", np.ascontiguousarray(x_n, dtype=np.float64),
                                                            refresh=True, changed=True)
    _rows_kernel(x_arg, rows_on_device(device, "pairs", pairs[:p]), p, int(split), *(float(v) for v in parameters),
                 on_device(device, "vertex_body", kept[1]),
                 on_device(device, "table", np.ascontiguousarray(table, dtype=np.float64)), index, rows)
    return DeviceLaggedFriction(vertices, (index, rows), x_n, eps_v, dt)


def _unheld_vertices(spares: dict, rows: int):
    """An int32 Taichi ndarray ``(>= rows, 4)`` that no friction holds (the rule of
    :func:`~sim_core.ti_kernels.buffers.unheld_rows`, for the rows' vertex indices)."""
    return unheld_rows(spares, "vertices", rows, (4,), dtype=ti.i32)


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the kernels on one pair of each kind.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    from sim_core.ti_kernels.copy_vectors import CopySums
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.transfer import upload

    x = np.array([[0.0, 0.0, 1.0e-3], [0.0, 0.0, 0.0], [1.0e-2, 0.0, 0.0], [0.0, 1.0e-2, 0.0]])
    pair = np.arange(4)[None]
    friction = friction_on_device(x, None, np.concatenate([pair, pair]), np.ones(2), np.full(2, 1.0e-3), 1,
                                  (2.0e-3, 2.0e-3, 1.0, 1.0), np.zeros(4, np.int64), np.full((1, 1), 0.5), 0.01, 0.01)
    y = x + 1e-4
    y_device = upload(new_ndarray(ti.f64, y.shape), y)
    friction.add_gradient_on_device(y, y_device, new_ndarray(ti.f64, y.shape))
    sums = CopySums(np.zeros(len(x), dtype=np.int64), 1)
    friction.add_copy_energies_on_device(y, y_device, sums.copy_of_vertex, sums)
