"""Per-copy operations on the stacked DoF vectors of a lockstep batch held in Taichi ndarrays.

A lockstep batch (:mod:`sim_core.batch.stacked`) stacks ``B`` copies of a scene into ``N`` vertices; its Newton
iterate, update and gradient are ``(N, 3)`` float64 arrays, and its Newton iteration asks per copy for dot products,
largest entries, finiteness, trial points ``x + a_c d`` with a step ``a_c`` per copy, and updates of whole copies
(:class:`~sim_core.batch.copy_runs.CopyRuns` does the same on NumPy arrays). :class:`CopyVectors` does them on
ndarrays (device memory on CUDA), so that the host reads back ``(B,)`` arrays of per-copy scalars only.

Per-copy reductions run :data:`REDUCTION_LANES` threads a copy: lane ``k`` of copy ``c`` visits the copy's ``k``-th
vertex, then every ``REDUCTION_LANES``-th (the vertices listed copy by copy, ``order[start[c]:start[c + 1]]``), and
adds its partial result once (:func:`copy_sums`, shared with the batched CG of :mod:`sim_core.ti_kernels.pcg`). Sums
are thus taken in another order than NumPy's: equal to :class:`CopyRuns`'s to round-off (and, on CUDA, with the lanes'
atomic adds in an order that varies from launch to launch); maxima and the other operations are exact.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import threading

import numpy as np

from sim_core.ti_backend import current_arch, serial_loops, ti
from sim_core.ti_kernels import device_copy, transfer
from sim_core.ti_kernels.buffers import unheld_rows
from sim_core.ti_kernels.launch import element_cells, fast_kernel

_F64 = ti.types.ndarray(dtype=ti.f64, ndim=1)
_I32 = ti.types.ndarray(dtype=ti.i32, ndim=1)
_I64 = ti.types.ndarray(dtype=ti.i64, ndim=1)
_VEC = ti.types.ndarray(dtype=ti.f64, ndim=2)  # stacked (N, 3) positions, updates, gradients

REDUCTION_LANES = 64
"""Threads per copy of a per-copy sum or maximum: each visits every ``REDUCTION_LANES``-th vertex of its copy and adds
its partial result once (``B * REDUCTION_LANES`` atomic adds a reduction, spread over the copies, in place of one per
DoF into the same ``B`` addresses)."""

_KEEP, TAKE, _ZERO = 0, 1, 2
"""Per-copy actions of ``_blend``: ``TAKE`` sets a copy from the source (:meth:`CopyVectors.blend_actions`)."""
ACTION_BUFFERS = 2
"""Device buffers of per-copy blend actions that remember what they hold (:meth:`CopyVectors._copy_values`)."""

ENERGY_CHUNK = 64
"""Vertices a thread of :func:`add_diagonal_quadratic` sums the energy of (one partial sum each, added on the host in
a fixed order: the same energy at every launch)."""


@ti.func
def lane_count(start: ti.template(), c: ti.i32, k: ti.i32) -> ti.i32:
    """How many of copy ``c``'s vertices lane ``k`` visits (its ``k``-th, then every ``REDUCTION_LANES``-th)."""
    return (start[c + 1] - start[c] - k + REDUCTION_LANES - 1) // REDUCTION_LANES


@ti.func
def lane_vertex(order: ti.template(), start: ti.template(), c: ti.i32, k: ti.i32, q: ti.i32) -> ti.i32:
    """The ``q``-th vertex lane ``k`` of copy ``c`` visits."""
    return order[start[c] + k + q * REDUCTION_LANES]


@ti.func
def copy_sums(u: ti.template(), v: ti.template(), out: ti.template(), active: ti.template(), order: ti.template(),
              start: ti.template(), copies: ti.i32):
    """``out[c] += u_c . v_c`` for every active copy ``c`` of flat ``(3 N,)`` vectors (:data:`REDUCTION_LANES` threads
    a copy); one device pass at a kernel's top level."""
    for c, k in ti.ndrange(copies, REDUCTION_LANES):
        if active[c] != 0:
            acc = 0.0
            for q in range(lane_count(start, c, k)):
                t = lane_vertex(order, start, c, k, q)
                acc += u[3 * t] * v[3 * t] + u[3 * t + 1] * v[3 * t + 1] + u[3 * t + 2] * v[3 * t + 2]
            ti.atomic_add(out[c], acc)


@ti.func
def _not_finite(x: ti.f64) -> ti.i32:
    """1 where the float64 ``x`` is a NaN or an infinity (all exponent bits set), else 0: a test of the bits, which no
    simplification of ``x != x`` can remove."""
    return ti.i32(((ti.bit_cast(x, ti.u64) >> ti.u64(52)) & ti.u64(0x7FF)) == ti.u64(0x7FF))


@ti.func
def _is_nan(x: ti.f64) -> ti.i32:
    """1 where the float64 ``x`` is a NaN (all exponent bits set, a mantissa bit set), else 0."""
    return _not_finite(x) & ti.i32((ti.bit_cast(x, ti.u64) & ti.u64(0xFFFFFFFFFFFFF)) != ti.u64(0))


@fast_kernel
def _dots(u: _VEC, v: _VEC, out: _F64, order: _I32, start: _I32, copies: ti.i32):
    """``out[c] = sum_k u_k v_k`` over copy ``c``'s DoFs."""
    for c in range(copies):
        out[c] = 0.0
    for c, k in ti.ndrange(copies, REDUCTION_LANES):
        acc = 0.0
        for q in range(lane_count(start, c, k)):
            t = lane_vertex(order, start, c, k, q)
            acc += u[t, 0] * v[t, 0] + u[t, 1] * v[t, 1] + u[t, 2] * v[t, 2]
        ti.atomic_add(out[c], acc)


@fast_kernel
def _extremes(a: _VEC, out: _I64, order: _I32, start: _I32, copies: ti.i32, vertex_norm: ti.template()):
    """Per copy ``c``: ``out[c]`` the bits of the largest finite ``|a_k|`` (``vertex_norm``: of the largest finite
    squared vertex norm ``|a_v|^2``), ``out[copies + c]`` 1 where an entry is NaN (``vertex_norm``: a squared norm not
    finite), else 0. The maxima are taken on the bits as int64 (the order of non-negative float64 values), with the
    integer atomics every device has."""
    for c in range(2 * copies):
        out[c] = 0
    for c, k in ti.ndrange(copies, REDUCTION_LANES):
        big = 0.0
        bad = 0
        for q in range(lane_count(start, c, k)):
            t = lane_vertex(order, start, c, k, q)
            if ti.static(vertex_norm):
                s = a[t, 0] * a[t, 0] + a[t, 1] * a[t, 1] + a[t, 2] * a[t, 2]
                if _not_finite(s):
                    bad = 1
                else:
                    big = ti.max(big, s)
            else:
                for j in ti.static(range(3)):
                    e = ti.abs(a[t, j])
                    if _is_nan(e):
                        bad = 1
                    else:
                        big = ti.max(big, e)
        ti.atomic_max(out[c], ti.bit_cast(big, ti.i64))
        ti.atomic_max(out[copies + c], ti.i64(bad))


_SCALARS = 7  # rows of _scalars' output: dot, |a| max, a NaN, |b| max, b NaN, |b_v|^2 max, b_v not finite
SCALARS = _SCALARS
"""Rows of :meth:`CopyVectors.launch_scalars`' output before its extra row (the per-copy sums read with them)."""


@fast_kernel
def _scalars(a: _VEC, b: _VEC, partial: _F64, out: _I64, order: _I32, start: _I32, copies: ti.i32, extra: _F64,
             with_extra: ti.i32):
    """Per copy ``c``, into ``out`` (int64, row ``r`` at ``out[r copies + c]``): row 0 the bits of the float64
    ``sum_k a_k b_k`` over the copy's DoFs (its lanes' partial sums, kept in ``partial``, added in lane order),
    rows 1 / 2 the bits of the largest non-NaN ``|a_k|`` and 1 where an entry of ``a`` is NaN, rows 3 / 4 the same
    of ``b``, rows 5 / 6 the bits of the largest finite squared vertex norm ``|b_v|^2`` and 1 where one is not
    finite (the maxima of :func:`_extremes`); with ``with_extra``, row 7 the bits of ``extra[c]`` (per-copy values
    read back in the same copy)."""
    for i in range(_SCALARS * copies):
        out[i] = 0
    for c, k in ti.ndrange(copies, REDUCTION_LANES):
        acc = 0.0
        big_a = 0.0
        big_b = 0.0
        big_n = 0.0
        nan_a = 0
        nan_b = 0
        bad_n = 0
        for q in range(lane_count(start, c, k)):
            t = lane_vertex(order, start, c, k, q)
            acc += a[t, 0] * b[t, 0] + a[t, 1] * b[t, 1] + a[t, 2] * b[t, 2]
            s = b[t, 0] * b[t, 0] + b[t, 1] * b[t, 1] + b[t, 2] * b[t, 2]
            if _not_finite(s):
                bad_n = 1
            else:
                big_n = ti.max(big_n, s)
            for j in ti.static(range(3)):
                ea = ti.abs(a[t, j])
                eb = ti.abs(b[t, j])
                if _is_nan(ea):
                    nan_a = 1
                else:
                    big_a = ti.max(big_a, ea)
                if _is_nan(eb):
                    nan_b = 1
                else:
                    big_b = ti.max(big_b, eb)
        partial[c * REDUCTION_LANES + k] = acc
        ti.atomic_max(out[copies + c], ti.bit_cast(big_a, ti.i64))
        ti.atomic_max(out[2 * copies + c], ti.i64(nan_a))
        ti.atomic_max(out[3 * copies + c], ti.bit_cast(big_b, ti.i64))
        ti.atomic_max(out[4 * copies + c], ti.i64(nan_b))
        ti.atomic_max(out[5 * copies + c], ti.bit_cast(big_n, ti.i64))
        ti.atomic_max(out[6 * copies + c], ti.i64(bad_n))
    for c in range(copies):
        total = 0.0
        for k in range(REDUCTION_LANES):
            total += partial[c * REDUCTION_LANES + k]
        out[c] = ti.bit_cast(total, ti.i64)
        if with_extra:
            out[_SCALARS * copies + c] = ti.bit_cast(extra[c], ti.i64)


@fast_kernel
def _moved(x: _VEC, d: _VEC, alpha: _F64, vertex_copy: _I32, out: _VEC, n: ti.i32):
    """``out_v = x_v + alpha_c d_v``, ``c`` vertex ``v``'s copy."""
    for v in range(n):
        a = alpha[vertex_copy[v]]
        for j in ti.static(range(3)):
            out[v, j] = x[v, j] + a * d[v, j]


@fast_kernel
def _difference_quotient(x: _VEC, x0: _VEC, dt: ti.f64, out: _VEC, n: ti.i32):
    """``out_v = (x_v - x0_v) / dt`` (one subtraction and one division an entry: NumPy's ``(x - x0) / dt``)."""
    for v in range(n):
        for j in ti.static(range(3)):
            out[v, j] = (x[v, j] - x0[v, j]) / dt


@fast_kernel
def _advanced(x: _VEC, v: _VEC, dt: ti.f64, out: _VEC, n: ti.i32):
    """``out_v = x_v + dt v_v`` (NumPy's ``x + dt * v``; a fused multiply-add where the device contracts one)."""
    for k in range(n):
        for j in ti.static(range(3)):
            out[k, j] = x[k, j] + dt * v[k, j]


@fast_kernel
def _negated(a: _VEC, out: _VEC, n: ti.i32):
    """``out_v = 0 - a_v`` (NumPy's ``np.subtract(0.0, a)``: ``+0`` where ``a_v`` is ``+-0``)."""
    for v in range(n):
        for j in ti.static(range(3)):
            out[v, j] = 0.0 - a[v, j]


@fast_kernel
def _copied_with_dofs(a: _VEC, dofs: _I32, values: _F64, out: _VEC, n: ti.i32, count: ti.i32):
    """``out = a``, then ``out`` at the flat DoFs ``dofs[:count]`` (``3 v + j``) set to ``values[:count]``."""
    for v in range(n):
        for j in ti.static(range(3)):
            out[v, j] = a[v, j]
    for k in range(count):
        out[dofs[k] // 3, dofs[k] % 3] = values[k]


@fast_kernel
def _copy_rows(a: _VEC, index: ti.types.ndarray(dtype=ti.i32, ndim=2), copies: _I32, minus: _VEC,
               translated: ti.i32, out: ti.types.ndarray(dtype=ti.f64, ndim=3), k: ti.i32, n: ti.i32):
    """``out[j, v] = a[index[c, v]]`` for ``c = copies[j]`` (``j < k``, ``v < n``), less ``minus[c]`` where
    ``translated`` (one subtraction an entry)."""
    for j, v in ti.ndrange(k, n):
        c = copies[j]
        r = index[c, v]
        for q in ti.static(range(3)):
            if translated:
                out[j, v, q] = a[r, q] - minus[c, q]
            else:
                out[j, v, q] = a[r, q]


@fast_kernel
def _blend(dst: _VEC, src: _VEC, scale: ti.f64, action: _I32, vertex_copy: _I32, n: ti.i32):
    """Per vertex ``v`` of copy ``c``: ``dst_v = scale src_v`` where ``action[c]`` is 1, ``dst_v = 0`` where it is 2,
    unchanged where it is 0."""
    for v in range(n):
        what = action[vertex_copy[v]]
        if what == TAKE:
            for j in ti.static(range(3)):
                dst[v, j] = scale * src[v, j]
        elif what == _ZERO:
            for j in ti.static(range(3)):
                dst[v, j] = 0.0


@fast_kernel
def _zero_dofs(a: _VEC, dofs: _I32, count: ti.i32):
    """``a`` at the flat DoFs ``dofs[:count]`` (``3 v + j``) set to 0."""
    for k in range(count):
        a[dofs[k] // 3, dofs[k] % 3] = 0.0


@fast_kernel
def _add_rows(g: _VEC, vertices: _I32, rows: _VEC, count: ti.i32):
    """``g[vertices[k]] += rows[k]`` for ``k < count`` (distinct vertices)."""
    for k in range(count):
        for j in ti.static(range(3)):
            g[vertices[k], j] += rows[k, j]


@fast_kernel
def _diagonal_quadratic(x: _VEC, center: _VEC, weight: _F64, g: _VEC, partial: _F64, n: ti.i32):
    """``g_v += w_v (x_v - y_v)``; ``partial[k]`` = the sum of ``w_v |x_v - y_v|^2 / 2`` over vertices
    ``k ENERGY_CHUNK ..`` (one thread a chunk)."""
    for k in range((n + ENERGY_CHUNK - 1) // ENERGY_CHUNK):
        acc = 0.0
        for v in range(k * ENERGY_CHUNK, ti.min(n, (k + 1) * ENERGY_CHUNK)):
            w = weight[v]
            for j in ti.static(range(3)):
                r = x[v, j] - center[v, j]
                g[v, j] += w * r
                acc += w * r * r
        partial[k] = 0.5 * acc


@fast_kernel
def _add_by_copy(values: _F64, element_copy: _I32, out: _F64, n: ti.i32):
    """``out[element_copy[k]] += values[k]`` for ``k < n``."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(n):
        out[element_copy[k]] += values[k]


@fast_kernel
def _diagonal_quadratic_by_copy(x: _VEC, center: _VEC, weight: _F64, vertex_copy: _I32, out: _F64, n: ti.i32):
    """``out[c] += w_v / 2 |x_v - y_v|^2`` for every vertex ``v < n`` of copy ``c = vertex_copy[v]``."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for v in range(n):
        w = 0.5 * weight[v]
        r0, r1, r2 = x[v, 0] - center[v, 0], x[v, 1] - center[v, 1], x[v, 2] - center[v, 2]
        out[vertex_copy[v]] += ((r0 * r0 + r1 * r1) + r2 * r2) * w


def element_copies(kept: dict, copy_of_vertex: np.ndarray, *first_vertices: np.ndarray) -> np.ndarray:
    """The copy of each element, int32 ``(k,)``: ``copy_of_vertex`` (int ``(N,)``) at the elements' first vertices
    ``first_vertices`` (one array per loop of the kernel, in loop order, concatenated), made once for each
    ``copy_of_vertex`` object and kept in ``kept``."""
    entry = kept.get("element_copies")
    if entry is None or entry[0] is not copy_of_vertex:
        first = np.concatenate(first_vertices) if len(first_vertices) > 1 else first_vertices[0]
        entry = kept["element_copies"] = (copy_of_vertex, np.ascontiguousarray(np.take(copy_of_vertex, first),
                                                                                dtype=np.int32))
    return entry[1]


def copy_energies(summed, element_copy: np.ndarray, copy_count: int, kept: dict, *args) -> np.ndarray:
    """The terms of the summing kernel ``summed`` (:func:`~sim_core.ti_kernels.launch.summing_kernel`) on ``args``,
    summed by copy: element ``k``'s term (one sum cell an element,
    :func:`~sim_core.ti_kernels.launch.element_cells`) added into copy ``element_copy[k]``. On the host arch by
    ``np.bincount`` (in element order); on a GPU where the terms are (one atomic add an element into ``copy_count``
    cells), only the sums copied back, ``element_copy`` uploaded once into ``kept``
    (:func:`~sim_core.ti_kernels.buffers.on_device`).

    Args:
        summed: a summing-kernel function whose loops number their elements ``0 .. k - 1``.
        element_copy: the copy of each element, int32 ``(k,)``, never changed in place.
        copy_count: copies ``B``.
        kept: the caller's cache of device arrays.
        args: the kernel's arguments but its sum array.

    Returns:
        the sums, float64 ``(copy_count,)`` (J for an energy kernel).
    """
    from sim_core.ti_kernels.buffers import on_device  # (buffers imports this module's siblings only)

    count = int(element_copy.shape[0])
    cells = element_cells(summed, count, *args)
    block = getattr(_COPY_SUMS, "active", None)
    if block is not None:  # added where the cells are, read with the block's other terms
        block.add_cells(cells, element_copy, kept)
        return np.zeros(copy_count)
    if isinstance(cells, np.ndarray):
        return np.bincount(element_copy, weights=cells, minlength=copy_count).astype(np.float64, copy=False)
    sums = kept.get("copy_sums")
    if sums is None or sums.shape[0] != copy_count:
        sums = kept["copy_sums"] = device_copy.new_ndarray(ti.f64, (copy_count,))
    if not device_copy.zero(sums):
        sums.fill(0.0)
    if count:
        _add_by_copy(cells, on_device(kept, "element_copy", element_copy), sums, count)
    return transfer.download(sums)


_COPY_SUMS = threading.local()
"""Per thread: ``active``, the :class:`CopySums` whose block is running, or None."""


class CopySums:
    """Per-copy sums ``(B,)`` (J) that the terms of a lockstep batch add into where their values are, read back in one
    copy for all of them: the line search's per-copy energies
    (:class:`~sim_core.energies.base.DeviceCopyEnergies`). On a GPU the sums are a Taichi ndarray in device memory
    (each term's kernels add into it, no copy back a term); on the host arch a NumPy array (the same additions, in
    the same order as :func:`copy_energies`'s ``np.bincount``). Host values (a term's constant part) are added into a
    host array beside them.

    The sums keep what was added until :meth:`zero`. Within ``with sums:`` (one block at a time on a thread),
    :func:`copy_energies` adds its element terms into these sums and returns zeros, so that a term made of several
    summing kernels (the fused elastic parts) adds them all here without a read each.

    Args:
        copy_of_vertex: the copy of each stacked vertex, int ``(N,)`` (its int32 device copy is made once:
            :attr:`vertex_copy`).
        copy_count: copies ``B``.

    Raises:
        RuntimeError: a block entered while another one is active on the same thread.
    """

    def __init__(self, copy_of_vertex: np.ndarray, copy_count: int) -> None:
        self.copy_of_vertex = copy_of_vertex
        self.copy_count = int(copy_count)
        self._host = np.zeros(self.copy_count)  # values added on the host
        self._kept: dict = {}  # device arrays: the sums, the vertices' copies, the element copies' (copy_energies)

    def __enter__(self) -> "CopySums":
        if getattr(_COPY_SUMS, "active", None) is not None:
            raise RuntimeError("CopySums: a block is already active on this thread")
        _COPY_SUMS.active = self
        return self

    def __exit__(self, *exc: object) -> None:
        _COPY_SUMS.active = None

    def _device_sums(self):
        """The sums on a GPU (a float64 ndarray ``(B,)`` kept), or None on the host arch."""
        if current_arch() != "cuda":
            return None
        sums = self._kept.get("sums")
        if sums is None:
            sums = self._kept["sums"] = device_copy.new_ndarray(ti.f64, (max(self.copy_count, 1),))
        return sums

    @property
    def values(self):
        """The array a kernel adds into: the float64 ``(B,)`` ndarray in device memory on a GPU, else the host
        array."""
        sums = self._device_sums()
        return self._host if sums is None else sums

    @property
    def vertex_copy(self):
        """The copy of each vertex, int32 ``(N,)``, where the kernels read it (device memory on a GPU: copied once)."""
        from sim_core.ti_kernels.buffers import on_device  # (buffers imports this module's siblings only)

        host = self._kept.get("vertex_copy_host")
        if host is None:
            host = self._kept["vertex_copy_host"] = np.ascontiguousarray(self.copy_of_vertex, dtype=np.int32)
        return on_device(self._kept, "vertex_copy", host)

    def zero(self) -> None:
        """Every sum set to 0."""
        self._host.fill(0.0)
        sums = self._device_sums()
        if sums is not None and not device_copy.zero(sums):
            sums.fill(0.0)

    def add(self, values: np.ndarray) -> None:
        """Add host values ``(B,)`` (J)."""
        self._host += values

    def add_cells(self, cells, element_copy: np.ndarray, kept: dict) -> None:
        """Add the cells ``(k,)`` of :func:`~sim_core.ti_kernels.launch.element_cells` (a NumPy array on the host arch,
        else a device ndarray) by the copy of each element ``element_copy`` (int32 ``(k,)``; its device copy kept in
        the caller's ``kept``)."""
        from sim_core.ti_kernels.buffers import on_device  # (buffers imports this module's siblings only)

        count = int(element_copy.shape[0])
        if isinstance(cells, np.ndarray):
            self._host += np.bincount(element_copy, weights=cells, minlength=self.copy_count)
        elif count:
            _add_by_copy(cells, on_device(kept, "element_copy", element_copy), self.values, count)

    def add_diagonal_quadratic(self, x, center, weight) -> None:
        """Add ``sum_v w_v / 2 |x_v - y_v|^2`` (J) by the copy of each vertex: ``x``, ``center`` ``(N, 3)`` (m) and
        ``weight`` ``(N,)`` (kg/s^2) where the kernels read them (Taichi ndarrays; NumPy arrays on the host arch)."""
        n = int(weight.shape[0])
        if n:
            _diagonal_quadratic_by_copy(x, center, weight, self.vertex_copy, self.values, n)

    @property
    def device_values(self):
        """The float64 ``(B,)`` ndarray in device memory the kernels add into on a GPU, or None on the host arch
        (:attr:`values` is then the host array)."""
        return self._device_sums()

    @property
    def host_values(self) -> np.ndarray:
        """The values added on the host (:meth:`add`), float64 ``(B,)`` (J; the array itself: :meth:`read` adds it to
        the device sums)."""
        return self._host

    def read(self, device_read: np.ndarray | None = None) -> np.ndarray:
        """The sums, float64 ``(B,)`` (J), a new array (on a GPU one copy back, after the kernels before it).
        ``device_read``: :attr:`device_values` already read back (float64 ``(B,)``, e.g. in one copy with other
        per-copy scalars: :meth:`CopyVectors.scalars`), then no copy here."""
        sums = self._device_sums()
        if sums is None:
            return self._host.copy()
        return (transfer.download(sums) if device_read is None else device_read) + self._host


SPARE_VECTORS = 12
"""The most ``(N, 3)`` arrays a :class:`CopyVectors` keeps to hand out again (:meth:`CopyVectors.new`): a Newton
iteration holds its iterate, gradient, direction, right-hand side and a few trial points at once."""


def new_vectors(vertex_count: int):
    """A zero-filled float64 ndarray ``(vertex_count, 3)`` (at least one row)."""
    return device_copy.new_ndarray(ti.f64, (max(int(vertex_count), 1), 3))


def add_diagonal_quadratic(x, center, weight, gradient, partial) -> None:
    """Add the gradient ``w_v (x_v - y_v)`` (J/m) of the diagonal quadratic ``E = sum_v w_v / 2 |x_v - y_v|^2`` into
    ``gradient``, and its energy by chunks of :data:`ENERGY_CHUNK` vertices into ``partial`` (J; ``E`` is
    ``partial``'s sum, in order), all Taichi ndarrays: ``x``, ``center`` (m) and ``gradient`` ``(n, 3)``, ``weight``
    ``(n,)`` (kg/s^2), ``partial`` at least ``ceil(n / ENERGY_CHUNK)`` entries. The lumped inertia / gravity / damping
    term of the lockstep loop (:class:`~sim_core.batch.lumped.LumpedQuadratic`)."""
    _diagonal_quadratic(x, center, weight, gradient, partial, int(weight.shape[0]))


def energy_chunks(vertex_count: int) -> int:
    """Entries of the partial sums of :func:`add_diagonal_quadratic` over ``vertex_count`` vertices (at least 1)."""
    return max(1, -(-int(vertex_count) // ENERGY_CHUNK))


class CopyVectors:
    """Per-copy operations on stacked ``(N, 3)`` float64 Taichi ndarrays (module docstring); Taichi must be initialised.

    Args:
        index: stacked vertex of copy ``i``'s vertex ``v``, shape ``(B, n)`` int (every stacked vertex is one copy's).

    Raises:
        ValueError: ``index`` is not a permutation of ``0 .. B n - 1``.

    Attributes:
        copies: ``B``.
        vertex_count: ``N``.
    """

    def __init__(self, index: np.ndarray) -> None:
        index = np.asarray(index)
        B, n = index.shape
        N = B * n
        vertex_copy = np.full(N, -1, dtype=np.int32)
        flat = index.reshape(-1)
        if N and (flat.min() < 0 or flat.max() >= N):
            raise ValueError(f"CopyVectors: stacked vertex indices outside 0..{N - 1}")
        vertex_copy[flat] = np.repeat(np.arange(B, dtype=np.int32), n)
        if np.any(vertex_copy < 0):
            raise ValueError("CopyVectors: the copies' vertex indices are not a permutation of the stacked vertices")
        self.copies = B
        self.vertex_count = N
        order = np.argsort(vertex_copy, kind="stable").astype(np.int32)
        start = np.zeros(B + 1, dtype=np.int32)
        np.cumsum(np.bincount(vertex_copy, minlength=B), out=start[1:])
        self._vertex_copy = self._indices(vertex_copy)
        self._order = self._indices(order)
        self._start = self._indices(start)
        self._per_copy = device_copy.new_ndarray(ti.f64, (max(B, 1),))
        self._spares: dict = {}  # (N, 3) arrays handed out by new() again once nothing else holds them
        # (device buffer, the values it holds or None), the one used latest last (_copy_values)
        self._actions = [(device_copy.new_ndarray(ti.i32, (max(B, 1),)), None) for _ in range(ACTION_BUFFERS)]
        self._out = device_copy.new_ndarray(ti.i64, (max(2 * B, 1),))
        self._out_host = np.zeros(self._out.shape, dtype=np.int64)
        self._partial = device_copy.new_ndarray(ti.f64, (max(B, 1) * REDUCTION_LANES,))
        self._scalars_out = device_copy.new_ndarray(ti.i64, (max((_SCALARS + 1) * B, 1),))  # (+ scalars' extra)
        self._scalars_host = np.zeros(self._scalars_out.shape, dtype=np.int64)
        self._dofs: tuple | None = None  # (host DoF indices, their device copy) of zero_dofs
        self._rows: tuple | None = None  # (capacity, vertices, rows) device buffers of add_rows
        self._scratch = None  # an (N, 3) buffer of add
        self._dof_values = None  # the float64 device buffer of copied_with_dofs' values
        self._index_host = index  # (B, n): copy_rows' layout
        self._rows_layout = None  # (offsets, index, offsets on the device, {k: (k, n, 3) buffer}) of copy_rows
        self._rows_copies = None  # (copies, their device copy) of copy_rows' last call

    @staticmethod
    def _indices(values: np.ndarray):
        out = device_copy.new_ndarray(ti.i32, (max(values.size, 1),))
        host = np.zeros(out.shape, dtype=np.int32)
        host[: values.size] = values
        if not device_copy.to_device(out, host):
            out.from_numpy(host)
        return out

    def new(self, zero: bool = True):
        """A ``(N, 3)`` ndarray that nothing else holds, zero-filled (one fill launch) unless ``zero`` is False (the
        caller writes every entry): one of this object's spares that no iterate, direction or caller holds any more
        (:func:`~sim_core.ti_kernels.buffers.unheld_rows`, :data:`SPARE_VECTORS` of them), else a new one; so the
        line search's trial points and the direction's vectors of a Newton iteration allocate no device memory once
        the first iterations' are dropped."""
        vectors = unheld_rows(self._spares, "vectors", max(self.vertex_count, 1), (3,), SPARE_VECTORS, exact=True)
        if zero:
            vectors.fill(0.0)
        return vectors

    def upload(self, host: np.ndarray):
        """A ``(N, 3)`` ndarray (:meth:`new`'s) holding ``host`` (``(N, 3)`` or ``3 N`` entries)."""
        return transfer.upload(self.new(zero=False), np.reshape(host, (-1, 3)))

    def download(self, a, out: np.ndarray | None = None) -> np.ndarray:
        """``a``'s values in ``out`` (C-contiguous float64 ``(N, 3)``; None: a new array that owns its memory)."""
        return transfer.download(a, out)

    def copy(self, a):
        """A new ndarray equal to ``a``."""
        out = self.new()
        transfer.add_into(out, a)
        return out

    def _copy_values(self, values: np.ndarray, dtype=np.float64):
        """The per-copy ``values`` ``(B,)`` on the device: float64 in one shared buffer (valid until the next call);
        int32 (the blends' actions) in one of :data:`ACTION_BUFFERS` buffers written by these uploads only, each
        remembering the values it holds, so values equal to a buffer's are not sent again (valid until
        :data:`ACTION_BUFFERS` other values have been sent: a Newton iteration's blends, the right-hand side's and the
        update's, repeat the last iteration's while no copy converges)."""
        host = np.ascontiguousarray(values, dtype=dtype)
        if dtype == np.float64:
            target = self._per_copy
        else:
            slots = self._actions
            hit = next((k for k, (_, sent) in enumerate(slots)
                        if sent is not None and np.array_equal(sent, host)), None)
            slots.append(slots.pop(0 if hit is None else hit))  # the one used least lately is written; latest last
            if hit is not None:
                return slots[-1][0]
            target = slots[-1][0]
            slots[-1] = (target, None)  # (until the copy below has been made)
        if not device_copy.to_device(target, host):
            target.from_numpy(host)
        if dtype != np.float64:
            self._actions[-1] = (target, host.copy())
        return target

    def moved(self, x, d, alphas: np.ndarray):
        """A new ndarray ``x + alpha_i d`` on copy ``i``'s vertices (``alphas`` ``(B,)``)."""
        return self.moved_by(x, d, self._copy_values(alphas))

    def moved_by(self, x, d, alphas):
        """:meth:`moved` with the step sizes already on the device: ``alphas`` a float64 ndarray whose first ``B``
        entries are copy ``i``'s (e.g. the row :data:`~sim_core.ti_kernels.backtrack.ALPHA` of a
        :class:`~sim_core.ti_kernels.backtrack.DeviceBacktrack`'s state): no upload."""
        out = self.new(zero=False)
        _moved(x, d, alphas, self._vertex_copy, out, self.vertex_count)
        return out

    def compile_state_kernels(self) -> None:
        """Compile (or load from the offline cache) the kernels of a step's kept state (:meth:`difference_quotient`,
        :meth:`advanced`, :meth:`negated`, :meth:`copied_with_dofs`, :meth:`copy_rows`) by launching each over no
        entries: they are first called at a batch's second and third steps, whose time would otherwise hold their
        compilation (~0.1 s each on an H200)."""
        one = new_vectors(1)
        dofs = device_copy.new_ndarray(ti.i32, (1,))
        values = device_copy.new_ndarray(ti.f64, (1,))
        _difference_quotient(one, one, 1.0, one, 0)
        _advanced(one, one, 1.0, one, 0)
        _negated(one, one, 0)
        _copied_with_dofs(one, dofs, values, one, 0, 0)
        index = device_copy.new_ndarray(ti.i32, (1, 1))
        _copy_rows(one, index, dofs, one, 0, device_copy.new_ndarray(ti.f64, (1, 1, 3)), 0, 0)

    def copy_rows(self, arrays: list, copies: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
        """Each copy's rows of stacked ``(N, 3)`` ndarrays gathered on the device and downloaded once each:
        ``arrays`` a list of ``(array, translated)``; returns, for each, a new host array ``(k, n, 3)`` whose row ``j``
        is copy ``copies[j]``'s vertices (int ``(k,)``; in the order of the ``index`` this object was made with), less
        ``offsets[copies[j]]`` (``(B, 3)``, m, sent once) where ``translated``: NumPy's ``a[index[c]] - offsets[c]``
        bit for bit."""
        copies = np.asarray(copies, dtype=np.int32)
        k, n = len(copies), self.vertex_count // max(self.copies, 1)
        if not k or not n:
            return [np.zeros((k, n, 3)) for _ in arrays]
        kept = self._rows_layout
        if kept is None or kept[0] is not offsets:
            index = device_copy.new_ndarray(ti.i32, (self.copies, n))
            index.from_numpy(np.ascontiguousarray(self._index_host, dtype=np.int32))
            minus = transfer.upload(device_copy.new_ndarray(ti.f64, (self.copies, 3)), offsets)
            kept = self._rows_layout = (offsets, index, minus, {})
        _, index, minus, buffers = kept
        out_dev = buffers.get(k)
        if out_dev is None:
            buffers.clear()
            out_dev = buffers[k] = device_copy.new_ndarray(ti.f64, (k, n, 3))
        sent = self._rows_copies
        if sent is None or not np.array_equal(sent[0], copies):  # (every copy, in order, at most steps: sent once)
            sent = self._rows_copies = (copies, self._indices(copies))
        copies_dev = sent[1]
        results = []
        for a, translated in arrays:
            _copy_rows(a, index, copies_dev, minus, int(bool(translated)), out_dev, k, n)
            results.append(transfer.download(out_dev))
        return results

    def difference_quotient(self, x, x0, dt: float):
        """A new ndarray ``(x - x0) / dt`` (e.g. the step's velocities, m/s, from its result and start, m, and ``dt``,
        s), each entry NumPy's ``(x - x0) / dt`` bit for bit."""
        out = self.new(zero=False)
        _difference_quotient(x, x0, float(dt), out, self.vertex_count)
        return out

    def advanced(self, x, v, dt: float):
        """A new ndarray ``x + dt v`` (e.g. the inertia's predicted positions ``x^n + dt v^n``, m), each entry NumPy's
        ``x + dt * v`` to one rounding (a fused multiply-add where the device contracts one)."""
        out = self.new(zero=False)
        _advanced(x, v, float(dt), out, self.vertex_count)
        return out

    def negated(self, a):
        """A new ndarray ``0 - a`` (NumPy's ``np.subtract(0.0, a)`` bit for bit)."""
        out = self.new(zero=False)
        _negated(a, out, self.vertex_count)
        return out

    def copied_with_dofs(self, a, dofs: np.ndarray, values: np.ndarray):
        """A new ndarray equal to ``a`` but at the flat DoFs ``dofs`` (int ``(f,)``, ``3 v + j``, the same object as
        :meth:`zero_dofs`' to reuse its device copy), which take ``values`` (``(f,)`` float64, sent up): the entries
        copied, not summed (``-0`` kept)."""
        kept = self._dofs
        if kept is None or kept[0] is not dofs:
            kept = self._dofs = (dofs, self._indices(np.asarray(dofs, dtype=np.int32)))
        count = int(len(dofs))
        staged = self._dof_values
        if staged is None or staged.shape[0] < max(count, 1):
            staged = self._dof_values = device_copy.new_ndarray(ti.f64, (max(count, 1),))
        if count:
            host = np.zeros(staged.shape[0])
            host[:count] = values
            transfer.upload(staged, host)
        out = self.new(zero=False)
        _copied_with_dofs(a, kept[1], staged, out, self.vertex_count, count)
        return out

    def dot(self, a, b) -> np.ndarray:
        """Per copy ``sum_k a_k b_k`` over its DoFs, shape ``(B,)``."""
        _dots(a, b, self._per_copy, self._order, self._start, self.copies)
        return transfer.download(self._per_copy)[: self.copies].copy()

    def scalars(self, a, b, sums: CopySums | None = None) -> tuple:
        """Per copy, in one launch and one read back: ``(dot, largest_abs_a, largest_abs_b, largest_norm_b)``, each
        ``(B,)``: :meth:`dot` of ``a`` and ``b`` (its lanes' partial sums added in lane order), :meth:`largest_abs` of
        ``a`` and of ``b``, and :meth:`largest_norm` of ``b`` (what a Newton iteration reads of its gradient and
        update together). With ``sums`` (a :class:`CopySums` of the ``B`` copies), a fifth entry: its
        :meth:`CopySums.read`, its device sums read back in the same copy (after the kernels launched before)."""
        B = self.copies
        device_sums = self.launch_scalars(a, b, sums)
        out = self._scalars_host
        if not device_copy.to_host(out, self._scalars_out):
            out = self._scalars_out.to_numpy()
        rows = out[: (_SCALARS + 1) * B].reshape(_SCALARS + 1, B)
        values = rows.view(np.float64)
        dot = values[0].copy()
        big_a = np.where(rows[2] > 0, np.nan, values[1])
        big_b = np.where(rows[4] > 0, np.nan, values[3])
        with np.errstate(invalid="ignore"):
            norm_b = np.sqrt(np.where(rows[6] > 0, np.nan, values[5]))
        if sums is None:
            return dot, big_a, big_b, norm_b
        return dot, big_a, big_b, norm_b, sums.read(None if device_sums is None else values[_SCALARS].copy())

    def launch_scalars(self, a, b, sums: CopySums | None = None):
        """:meth:`scalars` up to its read: the kernel launched into :attr:`scalars_out` (int64, row ``r`` of copy
        ``c`` at ``r B + c``: the bits of the dot product, the largest ``|a_k|`` and its NaN flag, ..., and with a
        device ``sums`` the bits of its device sums in row :data:`SCALARS`). Returns ``sums``' device array, or None
        (no device sums: row :data:`SCALARS` not written)."""
        device_sums = None if sums is None else sums.device_values
        extra = self._per_copy if device_sums is None else device_sums
        _scalars(a, b, self._partial, self._scalars_out, self._order, self._start, self.copies, extra,
                 int(device_sums is not None))
        return device_sums

    @property
    def scalars_out(self):
        """The device array :meth:`launch_scalars` writes (int64 ``((SCALARS + 1) B,)``)."""
        return self._scalars_out

    def _extremes(self, a, vertex_norm: bool) -> tuple[np.ndarray, np.ndarray]:
        _extremes(a, self._out, self._order, self._start, self.copies, vertex_norm)
        both = self._out_host if device_copy.to_host(self._out_host, self._out) else self._out.to_numpy()
        return both[: self.copies].view(np.float64).copy(), both[self.copies: 2 * self.copies] > 0

    def largest_abs(self, a) -> np.ndarray:
        """Per copy ``max_k |a_k|`` over its DoFs, shape ``(B,)``: NaN where the copy has a NaN, infinite where it has
        an infinity and no NaN (:meth:`CopyRuns.largest_abs <sim_core.batch.copy_runs.CopyRuns.largest_abs>`)."""
        big, nan = self._extremes(a, False)
        big[nan] = np.nan
        return big

    def largest_norm(self, a) -> np.ndarray:
        """Per copy the largest vertex norm ``max_v |a_v|``, shape ``(B,)``; NaN where a copy's entries are not finite
        (or their squares overflow)."""
        big, bad = self._extremes(a, True)
        big[bad] = np.nan
        return np.sqrt(big)

    def all_finite(self, a) -> np.ndarray:
        """Per copy whether all its DoFs are finite, shape ``(B,)`` bool."""
        return np.isfinite(self.largest_abs(a))

    def any_dof(self, a) -> np.ndarray:
        """Per copy whether any of its DoFs is non-zero (a NaN counts), shape ``(B,)`` bool."""
        return self.largest_abs(a) != 0.0

    def blend(self, dst, src, take: np.ndarray, zero: np.ndarray | None = None, scale: float = 1.0):
        """``dst`` with the copies in ``take`` (bool ``(B,)``) set to ``scale src`` and those in ``zero`` to 0, in
        place; returns ``dst``."""
        _blend(dst, src, float(scale), self.blend_actions(take, zero), self._vertex_copy, self.vertex_count)
        return dst

    def blend_actions(self, take: np.ndarray, zero: np.ndarray | None = None):
        """The per-copy actions of :meth:`blend` with ``take`` and ``zero`` on the device: an int32 ndarray whose
        first ``B`` entries are 1 (:data:`TAKE`) on the copies in ``take``, 2 on those in ``zero`` only, 0 elsewhere;
        sent only when no action buffer holds them (:meth:`_copy_values`), so right after that blend nothing travels:
        a per-copy mask that kernels of other modules read where the blend left it (e.g. the envelope's copies to
        factorise, :meth:`~sim_core.ti_kernels.envelope_cholesky.BatchedEnvelope.factorize`). Valid until
        :data:`ACTION_BUFFERS` other action arrays have been sent."""
        action = np.where(take, TAKE, _KEEP)
        if zero is not None:
            action = np.where(zero & ~take, _ZERO, action)
        return self._copy_values(action, np.int32)

    def zero_copies(self, a, mask: np.ndarray):
        """``a`` with the copies in ``mask`` (bool ``(B,)``) set to 0, in place; returns ``a``."""
        return self.blend(a, a, np.zeros(self.copies, dtype=bool), np.asarray(mask, dtype=bool))

    def copy_where(self, dst, src, mask: np.ndarray, scale: float = 1.0):
        """``dst`` with the copies in ``mask`` (bool ``(B,)``) taken from ``scale src``, in place; returns ``dst``."""
        return self.blend(dst, src, np.asarray(mask, dtype=bool), scale=scale)

    def zero_dofs(self, a, dofs: np.ndarray):
        """``a`` at the flat DoFs ``dofs`` (int ``(f,)``, ``3 v + j``) set to 0, in place; ``dofs`` travels to the
        device when it is another object than at the last call. Returns ``a``."""
        kept = self._dofs
        if kept is None or kept[0] is not dofs:
            kept = self._dofs = (dofs, self._indices(np.asarray(dofs, dtype=np.int32)))
        if len(dofs):
            _zero_dofs(a, kept[1], len(dofs))
        return a

    def add_rows(self, g, vertices: np.ndarray, rows: np.ndarray):
        """``g[vertices] += rows`` (``vertices`` distinct, int ``(k,)``; ``rows`` ``(k, 3)``), in place; returns
        ``g``."""
        k = int(np.size(vertices))
        if not k:
            return g
        kept = self._rows
        if kept is None or kept[0] < k:
            capacity = max(k, 2 * (kept[0] if kept else 0))
            kept = self._rows = (capacity, device_copy.new_ndarray(ti.i32, (capacity,)),
                                 device_copy.new_ndarray(ti.f64, (capacity, 3)), np.zeros(capacity, dtype=np.int32),
                                 np.zeros((capacity, 3)))
        capacity, v_dev, r_dev, v_host, r_host = kept
        v_host[:k] = vertices
        r_host[:k] = np.reshape(rows, (-1, 3))
        if not device_copy.to_device(v_dev, v_host):
            v_dev.from_numpy(v_host)
        transfer.upload(r_dev, r_host)
        _add_rows(g, v_dev, r_dev, k)
        return g

    def add(self, g, h: np.ndarray):
        """``g += h`` (``h`` on the host, ``(N, 3)`` or ``3 N`` entries, through one upload), in place; returns
        ``g``."""
        if self._scratch is None:
            self._scratch = self.new()
        transfer.upload(self._scratch, np.reshape(h, (-1, 3)))
        transfer.add_into(g, self._scratch)
        return g
