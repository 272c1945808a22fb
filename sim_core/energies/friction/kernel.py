"""Lagged IPC friction in Taichi kernels: energy, gradient and Hessian blocks of the frozen pairs.

The Taichi twin of :class:`sim_core.energies.friction.reference.LaggedFriction` (the reference and test
oracle; Li et al., "Incremental Potential Contact", SIGGRAPH 2020, eq. 14-15). Per pair ``k`` with
block vertices ``j`` (weights ``w_kj``), tangent basis ``T_k`` (3 x 2) and ``c_k = mu_k lam_k`` (N):

    u_k = T_k^T sum_j w_kj (x_j - x^n_j),   y_k = |u_k|,   E = sum_k c_k f0(y_k),
    dE/dx_j = c_k (f1(y)/y) w_kj T_k u_k,
    d2E/dx_a dx_b = c_k w_ka w_kb T_k [(f1/y) I + ((f1' y - f1) / y^3) u u^T] T_k^T,

with the mollifier ``f0`` of :func:`sim_core.energies.friction.reference.smooth_friction_f0` and the same
piecewise forms of ``f1/y`` and ``(f1' y - f1)/y^3`` (``eps_u = eps_v dt``). A Forming step has
about a hundred pairs: the NumPy reference spends its time in a dozen small array operations per
call, here each request is one launch of one kernel (:func:`_friction_kernel`, the parts a request
wants as a runtime argument; the gradient's launch computes the Hessian blocks too). A friction
keeps the kernel's input arrays (positions and coefficients copied in), so its launches re-bind
only the output array (:mod:`sim_core.ti_kernels.launch`); on CUDA it keeps them in device memory
instead, the constant ones sent once, and copies back the outputs a request wants in one copy (energy, gradient rows
and blocks packed into one array: one synchronous copy a launch instead of three). The kernel sees the
pairs' own vertices only (positions and gradient rows of the vertices its pairs name, ``v = unique(vertices)``):
a Forming step's pairs name 10-17 % of the scene's vertices. Loops are serial on the CPU (the
energy and the gradient sum in pair order), parallel on CUDA. Results equal the reference to
round-off (tests: 1e-12 relative).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection, positions_key
from sim_core.energies.contact.reference import ContactFrames
from sim_core.energies.contact.setup_kernel import tangent_basis
from sim_core.energies.friction.reference import LaggedFriction
from sim_core.ti_backend import current_arch, require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import (DeviceHessianBlocks, DeviceRows, LaunchArrays, copy_back, on_device,
                                        rows_on_device)
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.device_copy import new_ndarray
from sim_core.ti_kernels.transfer import positions_on_device, same_shapes, upload
from sim_core.unique import compact_indices, spread_rows
from sim_core.workspace import workspace_of

_F64_1, _F64_2, _F64_3, _I32_1, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_1, linalg.I32_2


@ti.func
def _tangential_displacement(x: ti.template(), x_prev: ti.template(), vertices: ti.template(),
                             weights: ti.template(), tangent: ti.template(), k: ti.i32):
    """``u = T^T sum_j w_j (x_j - x^n_j)`` (2-vector, m) of pair ``k``."""
    rel = ti.Vector.zero(ti.f64, 3)
    for j in range(vertices.shape[1]):
        v = vertices[k, j]
        for d in ti.static(range(3)):
            rel[d] += weights[k, j] * (x[v, d] - x_prev[v, d])
    u = ti.Vector.zero(ti.f64, 2)
    for i in ti.static(range(2)):
        for d in ti.static(range(3)):
            u[i] += tangent[k, d, i] * rel[d]
    return u


@ti.func
def _f0(y, eps_u):
    r = y
    if y < eps_u:
        r = -(y ** 3) / (3.0 * eps_u ** 2) + y * y / eps_u + eps_u / 3.0
    return r


@ti.func
def _f1_over_x(y, eps_u):
    r = 0.0
    if y < eps_u:
        r = 2.0 / eps_u - y / eps_u ** 2
    else:
        r = 1.0 / ti.max(y, eps_u)
    return r


@ti.func
def _f2_x_minus_f1_over_x3(y, eps_u):
    r = 0.0
    if y > 0.0:
        if y < eps_u:
            r = -1.0 / (eps_u ** 2 * y)
        else:
            r = -1.0 / y ** 3
    return r


@ti.func
def _pair_force(x: ti.template(), x_prev: ti.template(), vertices: ti.template(), weights: ti.template(),
                tangent: ti.template(), coefficient: ti.template(), eps_u: ti.f64, k: ti.i32):
    """``c_k (f1(y)/y) T_k u_k`` (3-vector, N) of pair ``k``: its block vertex ``j``'s gradient is ``w_kj`` times it."""
    u = _tangential_displacement(x, x_prev, vertices, weights, tangent, k)
    scale = coefficient[k] * _f1_over_x(ti.sqrt(u[0] * u[0] + u[1] * u[1]), eps_u)
    tu = ti.Vector.zero(ti.f64, 3)
    for d in ti.static(range(3)):
        tu[d] = (tangent[k, d, 0] * u[0] + tangent[k, d, 1] * u[1]) * scale
    return tu


@ti.func
def _pair_tangent_hessian(x: ti.template(), x_prev: ti.template(), vertices: ti.template(), weights: ti.template(),
                          tangent: ti.template(), coefficient: ti.template(), eps_u: ti.f64, k: ti.i32):
    """``c_k T_k [(f1/y) I + ((f1' y - f1) / y^3) u u^T] T_k^T`` (3x3, N/m) of pair ``k``: its block ``(a, b)`` is
    ``w_ka w_kb`` times it."""
    u = _tangential_displacement(x, x_prev, vertices, weights, tangent, k)
    basis = ti.Matrix.zero(ti.f64, 3, 2)
    for d, i in ti.static(ti.ndrange(3, 2)):
        basis[d, i] = tangent[k, d, i]
    return tangent_hessian(u, basis, coefficient[k], eps_u)


@ti.func
def tangent_hessian(u, basis, c, eps_u):
    """``c T [(f1/y) I + ((f1' y - f1) / y^3) u u^T] T^T`` (3x3, N/m) of a pair's tangential displacement ``u``
    (2-vector, m, ``y = |u|``), tangent basis ``basis`` (3x2 matrix) and coefficient ``c = mu lam`` (N)."""
    y = ti.sqrt(u[0] * u[0] + u[1] * u[1])
    f1x = _f1_over_x(y, eps_u)
    f2 = _f2_x_minus_f1_over_x3(y, eps_u)
    Hu = ti.Matrix.zero(ti.f64, 2, 2)
    for i, j in ti.static(ti.ndrange(2, 2)):
        Hu[i, j] = f2 * u[i] * u[j]
        if ti.static(i == j):
            Hu[i, j] += f1x
    H3 = ti.Matrix.zero(ti.f64, 3, 3)
    for d, e in ti.static(ti.ndrange(3, 3)):
        acc = 0.0
        for i, j in ti.static(ti.ndrange(2, 2)):
            acc += basis[d, i] * Hu[i, j] * basis[e, j]
        H3[d, e] = acc * c
    return H3


@ti.func
def _pair_gradient(x: ti.template(), x_prev: ti.template(), vertices: ti.template(), weights: ti.template(),
                   tangent: ti.template(), coefficient: ti.template(), eps_u: ti.f64, k: ti.i32, grad: ti.template()):
    """Adds pair ``k``'s part of ``dE/dx`` (N) to ``grad`` (n, 3)."""
    tu = _pair_force(x, x_prev, vertices, weights, tangent, coefficient, eps_u, k)
    for j in range(vertices.shape[1]):
        v = vertices[k, j]
        for d in ti.static(range(3)):
            grad[v, d] += weights[k, j] * tu[d]


@ti.func
def _pair_hessian(x: ti.template(), x_prev: ti.template(), vertices: ti.template(), weights: ti.template(),
                  tangent: ti.template(), coefficient: ti.template(), eps_u: ti.f64, k: ti.i32, blocks: ti.template()):
    """Writes the block ``(3m, 3m)`` of pair ``k`` (N/m) into ``blocks`` ``(p, 3m, 3m)``."""
    H3 = _pair_tangent_hessian(x, x_prev, vertices, weights, tangent, coefficient, eps_u, k)
    for a in range(vertices.shape[1]):
        for b in range(vertices.shape[1]):
            wab = weights[k, a] * weights[k, b]
            for d, e in ti.static(ti.ndrange(3, 3)):
                blocks[k, 3 * a + d, 3 * b + e] = wab * H3[d, e]


@fast_kernel
def _friction_energy_by_copy(x: _F64_2, x_prev: _F64_2, vertices: _I32_2, weights: _F64_2, tangent: _F64_3,
                             coefficient: _F64_1, eps_u: ti.f64, pair_copy: _I32_1, out: _F64_1, pairs: ti.i32):
    """``out[pair_copy[k]] += c_k f0(|u_k|)`` (J) for every pair ``k < pairs`` (in pair order on the CPU)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(pairs):
        u = _tangential_displacement(x, x_prev, vertices, weights, tangent, k)
        out[pair_copy[k]] += coefficient[k] * _f0(ti.sqrt(u[0] * u[0] + u[1] * u[1]), eps_u)


_ENERGY, _GRADIENT, _HESSIAN = 1, 2, 4  # bits of _friction_kernel's ``want``
_ARRAYS = LaunchArrays()
"""Per thread, the kept arrays of the launches (:meth:`TiLaggedFriction._launch`,
:meth:`TiLaggedFriction.add_gradient_on_device`) and their device copies."""


def packed_size(rows: int, pairs: int, block_vertices: int, want: int) -> int:
    """Entries of :func:`_friction_kernel`'s ``out`` that a launch for ``want`` writes: the energy, then the gradient
    rows ``(rows, 3)`` of the pairs' vertices (with ``_GRADIENT`` or ``_HESSIAN``), then the blocks
    ``(pairs, 3m, 3m)`` (with ``_HESSIAN``; ``m = block_vertices``)."""
    if want & _HESSIAN:
        return 1 + 3 * rows + pairs * (3 * block_vertices) ** 2
    return 1 + 3 * rows if want & _GRADIENT else 1


@fast_kernel
def _friction_kernel(x: _F64_2, x_prev: _F64_2, vertices: _I32_2, weights: _F64_2, tangent: _F64_3,
                     coefficient: _F64_1, eps_u: ti.f64, want: ti.i32, out: _F64_1, pairs: ti.i32):
    """Per pair, in pair order, the parts ``want`` asks for (bits, runtime values: one compiled kernel for every
    request), packed into ``out`` (:func:`packed_size`: one array, so that a GPU launch's results come back in one
    copy): ``_ENERGY`` sets ``out[0] = sum_k c_k f0(|u_k|)`` (J), ``_GRADIENT`` sets ``out[1:1 + 3 n]`` to ``dE/dx``
    ``(n, 3)`` (N; zeroed, then the pairs' parts added), ``_HESSIAN`` writes the pair blocks ``(p, 3m, 3m)`` (N/m, PSD
    by construction) after it, ``n = x.shape[0]``, over the first ``pairs`` rows of the pair arrays (which may have
    more: device arrays kept at a capacity). The energy is written to an array rather than returned: a launch then
    needs no synchronisation for a return value."""
    rows = x.shape[0]
    m = vertices.shape[1]
    start = 1 + 3 * rows  # of the blocks
    if want & _ENERGY:
        out[0] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(3 * rows * ((want & _GRADIENT) // _GRADIENT)):
        out[1 + i] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(pairs):
        if want & _ENERGY:
            u = _tangential_displacement(x, x_prev, vertices, weights, tangent, k)
            out[0] += coefficient[k] * _f0(ti.sqrt(u[0] * u[0] + u[1] * u[1]), eps_u)
        if want & _GRADIENT:
            tu = _pair_force(x, x_prev, vertices, weights, tangent, coefficient, eps_u, k)
            for j in range(m):
                v = vertices[k, j]
                for d in ti.static(range(3)):
                    out[1 + 3 * v + d] += weights[k, j] * tu[d]
        if want & _HESSIAN:
            H3 = _pair_tangent_hessian(x, x_prev, vertices, weights, tangent, coefficient, eps_u, k)
            for a in range(m):
                for b in range(m):
                    wab = weights[k, a] * weights[k, b]
                    for d, e in ti.static(ti.ndrange(3, 3)):
                        out[start + (k * 3 * m + 3 * a + d) * 3 * m + 3 * b + e] = wab * H3[d, e]


@fast_kernel
def _friction_at_device_positions(x: _F64_2, own: _I32_1, x_own: _F64_2, x_prev: _F64_2, vertices: _I32_2,
                                  weights: _F64_2, tangent: _F64_3, coefficient: _F64_1, eps_u: ti.f64,
                                  evaluate: ti.i32, energy: _F64_1, grad_own: _F64_2, blocks: _F64_3,
                                  gradient: _F64_2):
    """Where ``evaluate`` is 1: the positions of the pairs' vertices ``own`` ``(u,)`` gathered from the whole
    positions ``x`` ``(n, 3)`` into ``x_own``, then per pair, in pair order, what :func:`_friction_kernel` computes
    with every part wanted: ``energy[0]`` (J), the gradient rows ``grad_own`` of ``own`` (N), the blocks (N/m).
    Always: ``gradient[own[i]] += grad_own[i]`` (``gradient`` ``(n, 3)``; the vertices ``own`` are distinct). The
    arrays ``x_own``, ``grad_own`` and ``blocks`` may have more rows than are used."""
    if evaluate:
        energy[0] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(own.shape[0] * evaluate):
        for d in ti.static(range(3)):
            x_own[i, d] = x[own[i], d]
            grad_own[i, d] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(vertices.shape[0] * evaluate):
        u = _tangential_displacement(x_own, x_prev, vertices, weights, tangent, k)
        energy[0] += coefficient[k] * _f0(ti.sqrt(u[0] * u[0] + u[1] * u[1]), eps_u)
        _pair_gradient(x_own, x_prev, vertices, weights, tangent, coefficient, eps_u, k, grad_own)
        _pair_hessian(x_own, x_prev, vertices, weights, tangent, coefficient, eps_u, k, blocks)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(own.shape[0]):
        for d in ti.static(range(3)):
            gradient[own[i], d] += grad_own[i, d]


class TiLaggedFriction(LaggedFriction):
    """:class:`~sim_core.energies.friction.reference.LaggedFriction` with energy, gradient and Hessian on the
    Taichi kernels of this module (same arguments, errors and parameter derivatives; needs
    :func:`sim_core.ti_backend.init_backend`)."""

    @classmethod
    def from_frames(cls, frames: ContactFrames, mu: np.ndarray | float, x_prev: np.ndarray, eps_v: float,
                    dt: float) -> "TiLaggedFriction":
        """As the reference :meth:`~sim_core.energies.friction.reference.LaggedFriction.from_frames`, the
        tangent bases from one launch of :func:`sim_core.energies.contact.setup_kernel.tangent_basis`
        (equal to the reference's bit for bit)."""
        return cls(frames.vertices, frames.weights, tangent_basis(frames.normal), frames.lam, mu, x_prev, eps_v, dt)

    def _kernel_arrays(self, x: np.ndarray) -> tuple:
        """The kernel's arrays at ``x``: kept per friction (bound to the compiled kernel once; the positions of
        the pairs' vertices and the coefficients, ``mu`` may be edited, are copied into kept arrays). The
        kernel's vertex indices are into ``self._own``, the pairs' vertices ``(u,)``."""
        arrays = self._constant_arrays(x.shape[0])
        np.take(x, self._own, axis=0, out=arrays[0])
        return arrays

    def _constant_arrays(self, n: int) -> tuple:
        """:meth:`_kernel_arrays` for ``n`` vertices with the coefficients refilled and the positions' rows not."""
        arrays = getattr(self, "_arrays", None)
        if arrays is None or self._n != n:
            require_backend("TiLaggedFriction")
            own, local = compact_indices(self.vertices, dtype=np.int32)
            self._own, self._n, self._own_index = own, n, own.astype(np.int32)
            arrays = (np.empty((len(own), 3)),
                      np.ascontiguousarray(self.x_prev[own], dtype=np.float64),
                      local,
                      np.ascontiguousarray(self.weights, dtype=np.float64),
                      np.ascontiguousarray(self.tangent, dtype=np.float64),
                      np.empty(self.vertices.shape[0]))
            self._arrays, self._energy = arrays, np.zeros(1)
        np.multiply(self.mu, self.lam, out=arrays[-1])
        return arrays

    def _launch(self, arrays: tuple, want: int, x: np.ndarray | None = None) -> tuple[float, np.ndarray, np.ndarray]:
        """One launch of :func:`_friction_kernel` on ``arrays`` (:meth:`_kernel_arrays` of the positions ``x``):
        ``(energy, rows, blocks)``, the energy (J; NaN unless ``want`` asks for it), the gradient's rows of the pairs'
        vertices ``self._own`` ``(u, 3)`` (N) and the blocks ``(p, 3m, 3m)`` (N/m), views of one new array (the parts
        ``want`` does not ask for: not set, or empty). On CUDA, where another term of the solver holds ``x`` on the
        device (:func:`~sim_core.ti_kernels.transfer.positions_on_device`), the kernel reads them there, over every
        vertex (the same sums at the pairs' vertices), instead of the pairs' vertices' positions being copied."""
        p, m = self.vertices.shape
        u = len(self._own)
        on_gpu = current_arch() == "cuda"
        x_device = positions_on_device(workspace_of(self), x) if on_gpu and x is not None else None
        rows = u if x_device is None else x.shape[0]
        size = packed_size(rows, p, m, want)
        if on_gpu:
            out = self._launch_on_device(arrays, want, size, x_device)
        else:
            out = np.empty(size)
            _friction_kernel(*arrays, self.eps_u, want, out, p)
        energy = float(out[0]) if want & _ENERGY else float("nan")
        grad = out[1:1 + 3 * rows].reshape(-1, 3) if want & (_GRADIENT | _HESSIAN) else np.zeros((0, 3))
        if x_device is not None and len(grad):
            grad = np.take(grad, self._own, axis=0)
        blocks = out[1 + 3 * rows:size].reshape(p, 3 * m, 3 * m) if want & _HESSIAN else np.zeros((0, 3 * m, 3 * m))
        return energy, grad, blocks

    def _launch_on_device(self, arrays: tuple, want: int, size: int, x_device=None) -> np.ndarray:
        """:meth:`_launch`'s kernel with every argument a Taichi ndarray in device memory (a NumPy argument of a
        CUDA launch is copied to the device and back at each launch): the pairs, weights, tangent bases and
        previous positions sent once per friction into this thread's arrays of the frictions' capacity
        (:func:`~sim_core.ti_kernels.buffers.rows_on_device`: no allocation per friction; the kernel reads ``p``
        rows), the
        positions and coefficients at each launch, and the ``size`` entries of the packed output ``want`` asks for
        copied back in one copy, into a new host array (of the device array's length; only those entries
        written) returned. ``x_device``: the positions of every vertex already on the device (read there, with
        the pairs' vertices and every previous position, each sent once per friction), or None. The device arrays
        are kept per thread (:data:`_ARRAYS`) and reused by the next friction where the shapes agree (the packed
        output grows only)."""
        device = _ARRAYS.device()
        x, x_prev, vertices, weights, tangent, coefficient = arrays
        p, m = self.vertices.shape
        rows = len(self._own) if x_device is None else max(len(self._own), x_device.shape[0])
        packed = on_device(device, "packed", _ARRAYS.rows("packed", packed_size(rows, p, m, _HESSIAN)), scratch=True)
        if x_device is None:
            x_arg = on_device(device, "x", x, refresh=True, changed=True)
            x_prev_arg = rows_on_device(device, "rows_x_prev", x_prev)
            vertices_arg = rows_on_device(device, "rows_vertices", vertices)
        else:
            every = self._every_vertex()
            x_arg, x_prev_arg, vertices_arg = (x_device, on_device(device, "x_prev_every", every[0]),
                                               rows_on_device(device, "rows_vertices_every", every[1]))
        weights_arg, tangent_arg = (rows_on_device(device, "rows_weights", weights),
                                    rows_on_device(device, "rows_tangent", tangent))
        _friction_kernel(x_arg, x_prev_arg, vertices_arg, weights_arg, tangent_arg,
                         self._device_coefficients(device, coefficient), self.eps_u, want, packed, p)
        return copy_back(np.empty(tuple(packed.shape)), packed, size)

    def _every_vertex(self) -> tuple[np.ndarray, np.ndarray]:
        """The previous positions of every vertex ``(n, 3)`` (m) and the pairs' vertices ``(p, m)`` (int32, indices of
        every vertex), made once per friction (the kernel's arrays where it reads the positions of every vertex)."""
        kept = getattr(self, "_every", None)
        if kept is None:
            kept = self._every = (np.ascontiguousarray(self.x_prev, dtype=np.float64),
                                  np.ascontiguousarray(self.vertices, dtype=np.int32))
        return kept

    def _device_coefficients(self, device: dict, coefficient: np.ndarray):
        """The device copy of the kept ``coefficient`` array ``c_k = mu_k lam_k``, sent again only when its
        values changed (``mu`` may be edited between launches; the kept array is refilled at every call)."""
        sent = device.get("coefficient_sent")
        if sent is None or sent[0] is not coefficient or not np.array_equal(sent[1], coefficient):
            device["coefficient_sent"] = (coefficient, coefficient.copy())
            return rows_on_device(device, "coefficient", coefficient, refresh=True)
        return rows_on_device(device, "coefficient", coefficient)

    def add_gradient_on_device(self, x: np.ndarray, x_device, gradient_device) -> float:
        """Add :meth:`gradient` at ``x`` (N) into the Taichi ndarray ``gradient_device``; the energy (J) returned
        where it is on the host already (the CPU arch), else None (capability
        :class:`~sim_core.energies.base.DeviceGradient`).

        One launch of :func:`_friction_at_device_positions`: the pairs' vertices' positions read from ``x_device``
        (no upload of positions), energy, gradient rows and Hessian blocks in the same sums as :meth:`gradient`'s
        launch, the rows added at their vertices into ``gradient_device``; on a GPU the energy is read back only when
        :meth:`energy` asks for it (no synchronisation here). The rows and
        blocks stay where the kernel wrote them (device memory on CUDA), kept for ``x``
        (:func:`~sim_core.energies.base.positions_key`) and the current coefficients and ``eps_u`` until this
        thread's next evaluation here: :meth:`energy`, :meth:`gradient`, :meth:`gradient_rows`, :meth:`hessian` and
        :meth:`hessian_on_device` at ``x`` read them, and a second call at ``x`` adds the kept rows again (a launch
        of the last loop only).

        Args:
            x: positions ``(n, 3)`` (m), the key of the kept evaluation.
            x_device: the same positions, a float64 Taichi ndarray ``(n, 3)``, only read.
            gradient_device: a float64 Taichi ndarray ``(n, 3)``, the gradient added into it.

        Raises:
            ValueError: ``x_device`` or ``gradient_device`` is not of ``x``'s shape.
        """
        shape = same_shapes("TiLaggedFriction.add_gradient_on_device", x, x_device, gradient_device)
        p, m = self.vertices.shape
        if not p:
            return 0.0
        arrays = self._constant_arrays(shape[0])
        device = _ARRAYS.device()
        kept = self._device_record(x, arrays[-1])
        u = len(self._own)
        x_own = on_device(device, "at_x", _ARRAYS.rows("at_x", u, (3,)), scratch=True)
        grad_own = on_device(device, "at_grad", _ARRAYS.rows("at_grad", u, (3,)), scratch=True)
        name = f"at_blocks_{m}"  # (the kept arrays grow in rows only: one per block size)
        blocks = on_device(device, name, _ARRAYS.rows(name, p, (3 * m, 3 * m)), scratch=True)
        energy = on_device(device, "at_energy", self._energy, scratch=True)
        _friction_at_device_positions(
            x_device, on_device(device, "own", self._own_index), x_own, on_device(device, "x_prev", arrays[1]),
            on_device(device, "vertices", arrays[2]), on_device(device, "weights", arrays[3]),
            on_device(device, "tangent", arrays[4]), self._device_coefficients(device, arrays[-1]), self.eps_u,
            int(kept is None), energy, grad_own, blocks, gradient_device)
        if kept is not None:
            return kept[3] if isinstance(kept[3], float) else None
        # the energy: in the host array on the CPU arch; on a GPU left where the kernel wrote it until asked for
        # (:meth:`energy`; the lockstep's line search sums the copies' energies on the device instead), so that no
        # read waits for the kernel here
        value = float(self._energy[0]) if isinstance(energy, np.ndarray) else energy
        token = device["at_owner"] = object()  # the thread's arrays now hold this evaluation
        workspace_of(self).put(self, "at_device", (positions_key(x), arrays[-1].copy(), self.eps_u, value, token,
                                                   grad_own, blocks))
        return value if isinstance(value, float) else None

    def _device_energy(self, kept: tuple) -> float:
        """The energy (J) of the kept device evaluation ``kept`` (:meth:`_device_record`): read back at the first
        call where the kernel left it on the device (:meth:`add_gradient_on_device`), and kept as a float then."""
        value = kept[3]
        if not isinstance(value, float):
            value = float(copy_back(self._energy, value)[0])
            workspace_of(self).put(self, "at_device", kept[:3] + (value,) + kept[4:])
        return value

    def add_copy_energies_on_device(self, x: np.ndarray, x_device, copy_of_vertex: np.ndarray, sums) -> bool:
        """:meth:`copy_energies` at ``x`` (J by copy) added into ``sums`` (a
        :class:`~sim_core.ti_kernels.copy_vectors.CopySums` over ``copy_of_vertex``; capability
        :class:`~sim_core.energies.base.DeviceCopyEnergies`): where :meth:`add_gradient_on_device` evaluated ``x`` (its
        gather of the pairs' vertices' positions kept), one launch adding each pair's ``c_k f0(|u_k|)`` into the copy
        of its first vertex; False (nothing added) where no such evaluation is kept."""
        p = self.vertices.shape[0]
        if not p:
            return True
        if self._device_record(x) is None:
            return False
        arrays = self._constant_arrays(x.shape[0])
        device = _ARRAYS.device()
        kept = getattr(self, "_pair_copy", None)
        if kept is None or kept[0] is not copy_of_vertex:
            kept = self._pair_copy = (copy_of_vertex, np.ascontiguousarray(np.take(copy_of_vertex, self.vertices[:, 0]),
                                                                           dtype=np.int32))
        _friction_energy_by_copy(
            on_device(device, "at_x", _ARRAYS.rows("at_x", len(self._own), (3,)), scratch=True),
            on_device(device, "x_prev", arrays[1]), on_device(device, "vertices", arrays[2]),
            on_device(device, "weights", arrays[3]), on_device(device, "tangent", arrays[4]),
            self._device_coefficients(device, arrays[-1]), self.eps_u, rows_on_device(device, "pair_copy", kept[1]),
            sums.values, p)
        return True

    def _device_record(self, x: np.ndarray, coefficient: np.ndarray | None = None) -> tuple | None:
        """The kept :meth:`add_gradient_on_device` evaluation ``(key, coefficients, eps_u, energy, token, rows,
        blocks)`` when it is of ``x``, the current coefficients ``coefficient`` (None: computed here) and ``eps_u``,
        and this thread's arrays still hold it; else None."""
        kept = workspace_of(self).get(self, "at_device")
        if kept is None or kept[4] is not _ARRAYS.device().get("at_owner") or kept[2] != self.eps_u \
                or kept[0] != positions_key(x):
            return None
        if coefficient is None:
            coefficient = np.multiply(self.mu, self.lam)
        return kept if np.array_equal(kept[1], coefficient) else None

    def _device_rows(self, kept: tuple) -> np.ndarray:
        """The gradient rows ``(u, 3)`` (N) of the kept device evaluation ``kept``, a new host array."""
        return _host_rows(kept[5], len(self._own))

    def hessian_on_device(self, x: np.ndarray) -> DeviceHessianBlocks | None:
        """The blocks of :meth:`hessian` at ``x`` left in device memory by :meth:`add_gradient_on_device` (capability
        :class:`~sim_core.energies.base.DeviceHessian`; PSD by construction, so every projection's), or None where
        they are not there (no such evaluation of ``x`` kept, or the kernels ran on host arrays)."""
        kept = self._device_record(x) if self.vertices.shape[0] else None
        if kept is None or isinstance(kept[6], np.ndarray):
            return None
        return DeviceHessianBlocks(self.vertices, DeviceRows(kept[6], 0, self.vertices.shape[0]))

    def keep_derivatives(self, x: np.ndarray) -> None:
        """Energy, gradient and Hessian blocks at ``x`` ``(n, 3)`` (m) in one launch, kept in the
        workspace (:mod:`sim_core.workspace`) for :meth:`energy` and the next :meth:`gradient` (and, through it, :meth:`hessian`) at equal
        ``x``, coefficients and ``eps_u``; the next :meth:`gradient` call drops them (the Newton
        line search evaluates a trial point this way when, once accepted, it is the next iterate)."""
        p, m = self.vertices.shape
        if not p:
            return
        arrays = self._kernel_arrays(x)
        energy, grad, blocks = self._launch(arrays, _ENERGY | _GRADIENT | _HESSIAN, x)
        workspace_of(self).put(self, "derivatives", (arrays[0].copy(), arrays[-1].copy(), self.eps_u, energy, grad, blocks))

    def _kept(self, arrays: tuple) -> tuple | None:
        """The :meth:`keep_derivatives` result for these kernel arrays (same ``x``, coefficients, ``eps_u``), or None."""
        kept = workspace_of(self).get(self, "derivatives")
        return kept if kept is not None and self._matches(kept, arrays) else None

    def energy(self, x: np.ndarray) -> float:
        """Friction dissipation potential in J."""
        if self.vertices.shape[0] == 0:
            return 0.0
        at_device = self._device_record(x)
        if at_device is not None:
            return self._device_energy(at_device)
        arrays = self._kernel_arrays(x)
        kept = self._kept(arrays)
        if kept is not None:
            return kept[3]
        return self._launch(arrays, _ENERGY, x)[0]

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N (minus the friction force), shape ``(n, 3)``.

        The same launch computes the Hessian blocks at ``x`` (the Newton solver asks for them next),
        kept in the workspace (:mod:`sim_core.workspace`) for one :meth:`hessian` call at equal ``x``,
        coefficients and ``eps_u``. The gradient is
        kept too, for one more :meth:`gradient` call at equal ``x`` (the solver's contact force at the
        converged positions, where its last iteration took the gradient): that call returns it and
        keeps nothing, so the workspace holds no arrays of a step's friction after the step.
        """
        return spread_rows(*self.gradient_rows(x), x.shape[0])

    def gradient_rows(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`gradient` as ``(vertices, rows)``: the rows ``(u, 3)`` (N) of the pairs' distinct vertices
        ``(u,)``, zero elsewhere (capability :class:`~sim_core.energies.base.SparseGradient`; what is kept is
        :meth:`gradient`'s)."""
        p, m = self.vertices.shape
        if not p:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        at_device = self._device_record(x)
        if at_device is not None:
            return self._own, self._device_rows(at_device)
        arrays = self._kernel_arrays(x)
        workspace = workspace_of(self)
        again = workspace.take(self, "gradient")
        if again is not None and self._matches(again, arrays):
            return self._own, again[3]
        kept = self._kept(arrays)
        workspace.take(self, "derivatives")  # consumed
        if kept is not None:  # evaluated at this x: the same launch's gradient and blocks
            workspace.put(self, "hessian", (kept[0], kept[1], kept[2], kept[5]))
            workspace.put(self, "gradient", (kept[0], kept[1], kept[2], kept[4]))
            return self._own, kept[4]
        _, own_grad, blocks = self._launch(arrays, _GRADIENT | _HESSIAN, x)
        kept_hessian = workspace.put(self, "hessian", (arrays[0].copy(), arrays[-1].copy(), self.eps_u, blocks))
        workspace.put(self, "gradient", kept_hessian[:3] + (own_grad,))
        return self._own, own_grad

    def _matches(self, kept: tuple, arrays: tuple) -> bool:
        """Whether ``kept`` ``(x, coefficients, eps_u, ...)`` is of the kernel ``arrays``' positions and
        coefficients and the current ``eps_u``."""
        return kept[2] == self.eps_u and np.array_equal(kept[0], arrays[0]) and np.array_equal(kept[1], arrays[-1])

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-pair blocks ``(p, 3m, 3m)``, PSD by construction (``projection`` is not needed); the
        blocks computed with the last :meth:`gradient` when that was at the same ``x`` and coefficients."""
        p, m = self.vertices.shape
        if p == 0:
            return HessianBlocks.empty(m)
        at_device = self._device_record(x)
        if at_device is not None:
            return HessianBlocks(self.vertices, _host_rows(at_device[6], p))
        arrays = self._kernel_arrays(x)
        kept = workspace_of(self).take(self, "hessian")
        if kept is not None and self._matches(kept, arrays):
            return HessianBlocks(self.vertices, kept[3])
        return HessianBlocks(self.vertices, self._launch(arrays, _HESSIAN, x)[2])


def _host_rows(array, rows: int) -> np.ndarray:
    """The first ``rows`` rows of ``array`` (a kept host array, or its device copy: a Taichi ndarray) as a new
    host array."""
    if isinstance(array, np.ndarray):
        return array[:rows].copy()
    return copy_back(np.empty(tuple(array.shape)), array, rows)[:rows]


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the kernels on one pair (every request, and the device
    positions' kernel).

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    x = np.zeros((4, 3))
    friction = TiLaggedFriction(np.arange(4)[None], np.array([[1.0, -0.5, -0.25, -0.25]]),
                                np.eye(3)[None, :, :2], np.ones(1), 0.5, x, 0.01, 0.01)
    friction.energy(x + 1e-4)
    friction.gradient(x + 1e-4)
    friction.hessian(x + 1e-4)  # the blocks kept by the gradient
    friction.hessian(x + 1e-4)  # the Hessian kernel
    friction.keep_derivatives(x + 2e-4)  # energy, gradient and Hessian in one launch
    y = x + 3e-4
    friction.add_gradient_on_device(y, upload(new_ndarray(ti.f64, y.shape), y), new_ndarray(ti.f64, y.shape))
