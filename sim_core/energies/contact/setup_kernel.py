"""Start- and end-of-step contact set-up in Taichi kernels: pair geometry, contact frames, tangent bases.

The Taichi twins of the NumPy set-up the contact set and lagged friction do once per step (or per
candidate search), each one launch over its pairs instead of a few dozen small array operations:

* :func:`pair_geometry`: :func:`sim_core.collision.pair_geometry.pair_geometry` (above-face /
  interior regions, geometric sides and edge sines of vertex-triangle and edge-edge pairs, both
  kinds in one launch);
* :func:`contact_frames`: the normals and closest-point weights of
  :meth:`sim_core.energies.contact.reference.VertexTriangleContact.contact_frames` and
  :meth:`~sim_core.energies.contact.reference.EdgeEdgeContact.contact_frames` (Ericson 2005, sec. 5.1.5 and
  5.1.9: closest points; the normal is the oriented face / line-line normal in the face / interior
  region, the unit closest-point direction elsewhere);
* :func:`tangent_basis`: :func:`sim_core.energies.friction.reference.tangent_basis`;
* :func:`friction_frames`: the frames of both pair kinds and their tangent bases in one launch
  (what :meth:`sim_core.contact_set.ContactSet.friction` freezes of its pairs).

The regions reuse the Voronoi tests of :mod:`sim_core.energies.contact.distance_kernel`; every
expression is the reference's in the same order (sums left to right), so the results equal the
reference bit for bit (tests). Loops are serial on the CPU, parallel on CUDA, as there. The
callers pass new arrays at every call; the functions copy them into per-thread kept arrays
(:class:`~sim_core.ti_kernels.buffers.LaunchArrays`, row counts as scalars) and the results out of
them, so a launch re-binds no array.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.collision.pair_geometry import ListGeometry, PairGeometry
from sim_core.energies.base import FrozenPositionsKey
from sim_core.energies.contact import distance_kernel as cd
from sim_core.energies.contact.pair_lists import DEVICE_INDEX_NAMES
from sim_core.ti_backend import current_arch, require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import LaunchArrays, copy_back, on_device
from sim_core.ti_kernels.launch import fast_kernel

_F64_1, _F64_2, _I32_1, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.I32_1, linalg.I32_2


@ti.func
def _vertex(x: ti.template(), vertices: ti.template(), k: ti.i32, a: ti.i32):
    v = vertices[k, a]
    return ti.Vector([x[v, 0], x[v, 1], x[v, 2]], ti.f64)


@ti.func
def _unit(v):
    """``v / |v|`` (the reference's ``v / norm(v)``)."""
    return v / ti.sqrt(cd._dot(v, v))


@ti.func
def _vertex_triangle_code(x: ti.template(), vt: ti.template(), k: ti.i32) -> ti.f64:
    """Row ``k`` of ``vt`` (vertex, triangle): its side (+1 / -1) times 2 where the vertex lies above the face's
    interior, else times 1."""
    p, a, b, c = _vertex(x, vt, k, 0), _vertex(x, vt, k, 1), _vertex(x, vt, k, 2), _vertex(x, vt, k, 3)
    above = ti.select(cd._point_triangle_region(p, a, b, c) == cd._PT_FACE, 2.0, 1.0)
    return above * cd._resolved_side(0.0, cd._cross(b - a, c - a), p - a)


@ti.func
def _edge_edge_measures(x: ti.template(), ee: ti.template(), k: ti.i32):
    """Row ``k`` of ``ee`` (two edges): ``[sine of the edges' angle, 1 if their closest points are interior to both
    else 0, side (+1 / -1)]``, a float64 3-vector."""
    a0, a1, b0, b1 = _vertex(x, ee, k, 0), _vertex(x, ee, k, 1), _vertex(x, ee, k, 2), _vertex(x, ee, k, 3)
    ea, eb = a1 - a0, b1 - b0
    n = cd._cross(ea, eb)
    sine = ti.sqrt(cd._dot(n, n)) / (ti.sqrt(cd._dot(ea, ea)) * ti.sqrt(cd._dot(eb, eb)))
    interior = ti.select(cd._edge_edge_region(a0, a1, b0, b1) == cd._EE_INTERIOR, 1.0, 0.0)
    return ti.Vector([sine, interior, cd._resolved_side(0.0, n, a0 - b0)], ti.f64)


@fast_kernel
def _geometry_kernel(x: _F64_2, vt: _I32_2, vt_count: ti.i32, ee: _I32_2, ee_count: ti.i32, geometry: _F64_1):
    """Rows ``k < vt_count`` of ``vt`` and ``k < ee_count`` of ``ee`` (kept arrays, :data:`_ARRAYS`), into one array
    ``geometry`` (copied back in one piece): ``[0, p)`` the vertex-triangle codes ``side * (2 if above else 1)``,
    ``[p, p + q)`` the edge sines, ``[p + q, p + 2 q)`` the edge-edge codes ``side * (2 if interior else 1)``
    (``p = vt_count``, ``q = ee_count``; sides are +1 / -1)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(vt_count):
        geometry[k] = _vertex_triangle_code(x, vt, k)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(ee_count):
        m = _edge_edge_measures(x, ee, k)
        geometry[vt_count + k] = m[0]
        geometry[vt_count + ee_count + k] = (1.0 + m[1]) * m[2]


@fast_kernel
def _codes_kernel(x: _F64_2, vt: _I32_2, vt_count: ti.i32, ee: _I32_2, ee_count: ti.i32, min_sine: ti.f64,
                  codes: _I32_1):
    """:func:`_geometry_kernel`'s measurements as one int32 code a pair, into ``codes`` (copied back in one piece,
    a third of the geometry's bytes): ``[0, p)`` the vertex-triangle codes ``side * (2 if above else 1)``,
    ``[p, p + q)`` the edge-edge codes ``side * (1 + (1 if interior) + (2 if sine > min_sine))`` (sides are
    +1 / -1; the sine and the side as :func:`_geometry_kernel` computes them)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(vt_count):
        codes[k] = ti.cast(_vertex_triangle_code(x, vt, k), ti.i32)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(ee_count):
        m = _edge_edge_measures(x, ee, k)
        code = 1 + ti.cast(m[1], ti.i32) + ti.select(m[0] > min_sine, 2, 0)
        codes[vt_count + k] = code * ti.cast(m[2], ti.i32)


_ARRAYS = LaunchArrays()
"""The kernels' arrays (inputs copied in, outputs copied out): launches re-bind none."""


def _device_launch(kernel, args: tuple, outputs: dict[int, int], constant: dict[int, tuple] | None = None) -> None:
    """``kernel(*args)``; on CUDA with every array of ``args`` (kept arrays of :data:`_ARRAYS`) replaced by a
    device copy kept per thread (the inputs sent at every launch, the arrays at the positions of ``outputs``,
    position -> rows the launch writes, only allocated there and those rows copied back after the launch),
    instead of NumPy arguments that cross to the device and back at each launch. ``constant``: position ->
    ``(cache, name)`` of input arrays never changed in place, whose device copies ``cache`` keeps (sent only when
    the array is another object than at the last launch); so are frozen positions in ``args[0]``
    (:meth:`~sim_core.energies.base.FrozenPositionsKey.holds`: a lockstep batch's iterates), which
    :func:`_positions` passes as they are."""
    if current_arch() != "cuda":
        kernel(*args)
        return
    device = _ARRAYS.device()
    constant = dict(constant or {})
    if isinstance(args[0], np.ndarray) and FrozenPositionsKey.holds(args[0]):
        # frozen positions (their values cannot change while they exist): sent once per array object
        constant[0] = (device, f"frozen_x:{kernel.__name__}")
    launch = [a if not isinstance(a, np.ndarray)
              else on_device(*constant[position], a) if position in constant
              else on_device(device, f"{position}:{kernel.__name__}", a, scratch=position in outputs,
                             refresh=position not in outputs, changed=True)
              for position, a in enumerate(args)]
    kernel(*launch)
    for position, rows in outputs.items():
        copy_back(args[position], launch[position], rows)


def _positions(x: np.ndarray) -> np.ndarray:
    """The positions argument ``(n, 3)`` (m) of a launch: off CUDA ``x`` itself when it is a C-contiguous float64
    array (bound by its address: no copy of a stacked batch's positions, 14 MB at 1024 Forming copies, for a
    rebinding of a few microseconds), on CUDA too when it is also frozen (:func:`_device_launch` sends it once per
    array object), else a copy in a kept array (on CUDA its device copy is sent again only when the values
    changed, :func:`_device_launch`)."""
    if type(x) is np.ndarray and x.dtype == np.float64 and x.flags.c_contiguous and (
            current_arch() != "cuda" or FrozenPositionsKey.holds(x)):
        return x
    return _ARRAYS.copy_of("x", x)


def _positions_or_held(x: np.ndarray, x_device):
    """The positions argument of a launch: on CUDA ``x_device`` where given (``x`` where the solver's terms hold it on
    the device, :func:`~sim_core.ti_kernels.transfer.positions_on_device`: read there, not sent), else
    :func:`_positions` of ``x``."""
    return x_device if x_device is not None and current_arch() == "cuda" else _positions(x)


def _kept_indices(name: str, vertices: np.ndarray) -> np.ndarray:
    """The kept int32 array ``name`` ``(capacity, 4)`` whose first rows hold ``vertices`` ``(k, 4)``."""
    vertices = np.asarray(vertices).reshape(-1, 4)
    kept = _ARRAYS.rows(name, len(vertices), (4,), np.int32)
    kept[:len(vertices)] = vertices
    return kept


def _int32_rows(vertices, where: str = "pair_geometry"):
    """``vertices`` itself, checked to be a C-contiguous int32 array ``(k, 4)`` or a Taichi int32 ndarray ``(k, 4)``
    (a candidate list's vertices gathered on the device:
    :meth:`~sim_core.energies.contact.pair_lists.CandidateVertices.index_arrays`, read there by the launch).

    Raises:
        ValueError: another dtype, shape or layout (the message names ``where``)."""
    if isinstance(vertices, np.ndarray):
        good = vertices.dtype == np.int32 and vertices.ndim == 2 and vertices.flags.c_contiguous
    else:
        good = vertices.dtype == ti.i32 and len(vertices.shape) == 2
    if not good or vertices.shape[1] != 4:
        raise ValueError(f"{where}: indices must be C-contiguous int32 (k, 4), got {vertices.dtype} "
                         f"{tuple(vertices.shape)}")
    return vertices


def pair_geometry(x: np.ndarray, vt_vertices: np.ndarray, ee_vertices: np.ndarray,
                  device: dict | None = None) -> PairGeometry:
    """Taichi twin of :func:`sim_core.collision.pair_geometry.pair_geometry` (same arguments and result).

    Args:
        x: positions, shape ``(n, 3)`` (m).
        vt_vertices: ``[p, a, b, c]`` global vertex indices, shape ``(p, 4)``.
        ee_vertices: ``[a0, a1, b0, b1]`` global vertex indices, shape ``(q, 4)``.
        device: None, or a cache of device copies (:func:`~sim_core.ti_kernels.buffers.on_device`) for index
            arrays that are C-contiguous int32 and never changed in place (a candidate list's,
            :meth:`~sim_core.energies.contact.pair_lists.CandidateVertices.int32_vertices`): the kernel then reads
            them as they are (no copy into the kept arrays), on CUDA sent once per array object.

    Returns:
        :class:`~sim_core.collision.pair_geometry.PairGeometry`.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    require_backend("contact set-up kernels")
    p, q = vt_vertices.shape[0], ee_vertices.shape[0]
    indices, constant = [], {}
    for position, name, given in ((1, DEVICE_INDEX_NAMES[0], vt_vertices), (3, DEVICE_INDEX_NAMES[1], ee_vertices)):
        if device is not None and given.shape[0]:  # the given array itself (an empty one: a kept array)
            indices.append(_int32_rows(given))
            constant[position] = (device, name)
        else:
            indices.append(_kept_indices(name, given))
    vt, ee = indices
    geometry = _ARRAYS.rows("geometry", p + 2 * q)
    if p or q:
        _device_launch(_geometry_kernel, (_positions(x), vt, p, ee, q, geometry), outputs={5: p + 2 * q},
                       constant=constant)
    vt_code, sine, ee_code = geometry[:p], geometry[p:p + q], geometry[p + q:p + 2 * q]
    return PairGeometry(np.abs(vt_code) > 1.5, np.sign(vt_code), sine.copy(), np.abs(ee_code) > 1.5, np.sign(ee_code))


def pair_codes(x: np.ndarray, vt_vertices: np.ndarray, ee_vertices: np.ndarray, min_sine: float,
               device: dict, x_device=None) -> ListGeometry:
    """:func:`pair_geometry` of a candidate list's kept int32 indices (``device``: as there) with the edge-edge
    pairs' sines compared with ``min_sine`` on the device: a :class:`~sim_core.collision.pair_geometry.ListGeometry`,
    from one int32 code a pair (:func:`_codes_kernel`) instead of the geometry's three float64 arrays (a third of the
    bytes to copy back; on CUDA 7 MB in place of 24 at 1024 Forming copies). The same values as
    :func:`pair_geometry`'s with ``ee_keep = ee_sine > min_sine``. ``x_device``: ``x`` where the solver's terms hold
    it on the device, read there on CUDA instead of ``x`` being sent (:func:`friction_frames`'), or None.

    Raises:
        ConfigError: the Taichi backend is not initialised.
        ValueError: indices that are not C-contiguous int32 ``(k, 4)``.
    """
    require_backend("contact set-up kernels")
    p, q = vt_vertices.shape[0], ee_vertices.shape[0]
    indices, constant = [], {}
    for position, name, given in ((1, DEVICE_INDEX_NAMES[0], vt_vertices), (3, DEVICE_INDEX_NAMES[1], ee_vertices)):
        if given.shape[0]:
            indices.append(_int32_rows(given, "pair_codes"))
            constant[position] = (device, name)
        else:
            indices.append(_kept_indices(name, given))
    vt, ee = indices
    codes = _ARRAYS.rows("codes", p + q, (), np.int32)
    if p or q:
        _device_launch(_codes_kernel, (_positions_or_held(x, x_device), vt, p, ee, q, float(min_sine), codes),
                       outputs={6: p + q}, constant=constant)
    vt_code, ee_code = codes[:p], codes[p:p + q]
    ee_size = np.abs(ee_code)
    return ListGeometry(np.abs(vt_code) > 1, np.sign(vt_code, dtype=np.float64), ee_size > 2,
                        (ee_size & 1) == 0, np.sign(ee_code, dtype=np.float64))


@ti.func
def _point_triangle_frame(x: ti.template(), vertices: ti.template(), k: ti.i32, side: ti.f64,
                          weights: ti.template(), normal: ti.template(), w0: ti.template(), n0: ti.template()):
    """Row ``k``'s closest-point weights in columns ``w0 ...`` of ``weights`` and unit normal in ``n0 ...`` of
    ``normal`` (one array may hold both)."""
    p, a, b, c = (_vertex(x, vertices, k, 0), _vertex(x, vertices, k, 1), _vertex(x, vertices, k, 2),
                  _vertex(x, vertices, k, 3))
    region, d1, d2, d3, d4, d5, d6, va, vb, vc = cd._point_triangle_tests(p, a, b, c)
    bary = ti.Vector([0.0, 0.0, 0.0], ti.f64)
    if region == cd._PT_FACE:
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        bary = ti.Vector([1.0 - v - w, v, w], ti.f64)
    elif region == cd._PT_EDGE_AB:
        v = d1 / (d1 - d3)
        bary = ti.Vector([1.0 - v, v, 0.0], ti.f64)
    elif region == cd._PT_EDGE_CA:
        w = d2 / (d2 - d6)
        bary = ti.Vector([1.0 - w, 0.0, w], ti.f64)
    elif region == cd._PT_EDGE_BC:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        bary = ti.Vector([0.0, 1.0 - w, w], ti.f64)
    else:
        bary[region - cd._PT_VERTEX_A] = 1.0
    n = ti.Vector([0.0, 0.0, 0.0], ti.f64)
    if region == cd._PT_FACE:
        m = cd._cross(b - a, c - a)
        n = cd._resolved_side(side, m, p - a) * _unit(m)
    else:
        n = _unit(p - ((bary[0] * a + bary[1] * b) + bary[2] * c))
    weights[k, w0] = 1.0
    for j in ti.static(range(3)):
        weights[k, w0 + j + 1] = -bary[j]
        normal[k, n0 + j] = n[j]


@ti.func
def _edge_edge_frame(x: ti.template(), vertices: ti.template(), k: ti.i32, side: ti.f64,
                     weights: ti.template(), normal: ti.template(), w0: ti.template(), n0: ti.template()):
    """As :func:`_point_triangle_frame`, of an edge-edge pair."""
    a0, a1, b0, b1 = (_vertex(x, vertices, k, 0), _vertex(x, vertices, k, 1), _vertex(x, vertices, k, 2),
                      _vertex(x, vertices, k, 3))
    s, t, region = cd._edge_edge_closest(a0, a1, b0, b1)
    w = ti.Vector([1.0 - s, s, -(1.0 - t), -t], ti.f64)
    n = ti.Vector([0.0, 0.0, 0.0], ti.f64)
    if region == cd._EE_INTERIOR:
        m = cd._cross(a1 - a0, b1 - b0)
        n = cd._resolved_side(side, m, a0 - b0) * _unit(m)
    else:
        n = _unit(((w[0] * a0 + w[1] * a1) + w[2] * b0) + w[3] * b1)
    for j in ti.static(range(4)):
        weights[k, w0 + j] = w[j]
    for j in ti.static(range(3)):
        normal[k, n0 + j] = n[j]


@fast_kernel
def _frames_kernel(x: _F64_2, vertices: _I32_2, side: _F64_1, count: ti.i32, point_first: ti.template(),
                   weights: _F64_2, normal: _F64_2):
    """Rows ``k < count`` of the kept arrays (:data:`_ARRAYS`)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(count):
        if ti.static(point_first):
            _point_triangle_frame(x, vertices, k, side[k], weights, normal, 0, 0)
        else:
            _edge_edge_frame(x, vertices, k, side[k], weights, normal, 0, 0)


def contact_frames(x: np.ndarray, vertices: np.ndarray, sides: np.ndarray, point_first: bool
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Closest-point weights and unit normals of pairs (the geometric part of the reference
    ``contact_frames``, module docstring).

    Args:
        x: positions, shape ``(n, 3)`` (m).
        vertices: ``[p, a, b, c]`` (``point_first``, vertex-triangle) or ``[a0, a1, b0, b1]``
            (edge-edge) global vertex indices, shape ``(k, 4)``.
        sides: the pairs' step sides (+1 / -1, 0 unsigned: the side of ``x`` itself), shape ``(k,)``.
        point_first: vertex-triangle (True) or edge-edge (False) pairs.

    Returns:
        ``(weights (k, 4), normal (k, 3))``: the relative position of the first side w.r.t. the
        second is ``sum_j weights[:, j] x[vertices[:, j]]``; the normal (direction of the force on
        the first side) is unit.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    require_backend("contact set-up kernels")
    k = len(vertices)
    if not k:
        return np.empty((0, 4)), np.empty((0, 3))
    side = _ARRAYS.rows("side", k)
    side[:k] = np.reshape(sides, -1)
    weights, normal = _ARRAYS.rows("weights", k, (4,)), _ARRAYS.rows("normal", k, (3,))
    _frames_kernel(_positions(x), _kept_indices("pairs", vertices), side, k, bool(point_first), weights,
                   normal)
    return weights[:k].copy(), normal[:k].copy()


@ti.func
def _tangent_frame(normal: ti.template(), k: ti.i32, n0: ti.template(), tangent: ti.template(), t0: ti.template()):
    """Tangent basis of the unit normal in columns ``n0 ...`` of row ``k`` (:func:`tangent_basis`), written into
    columns ``t0 + 2 i + j`` of row ``k`` of ``tangent`` (``T[i, j]``)."""
    n = ti.Vector([normal[k, n0], normal[k, n0 + 1], normal[k, n0 + 2]], ti.f64)
    axis = 0  # the first coordinate axis of least |n_i| (np.argmin)
    if ti.abs(n[1]) < ti.abs(n[0]):
        axis = 1
    if ti.abs(n[2]) < ti.abs(n[axis]):
        axis = 2
    e = ti.Vector([0.0, 0.0, 0.0], ti.f64)
    e[axis] = 1.0
    t1 = _unit(cd._cross(n, e))
    t2 = cd._cross(n, t1)
    for d in ti.static(range(3)):
        tangent[k, t0 + 2 * d] = t1[d]
        tangent[k, t0 + 2 * d + 1] = t2[d]


@fast_kernel
def _tangent_kernel(normal: _F64_2, count: ti.i32, tangent: _F64_2):
    """Rows ``k < count`` of the kept arrays (:data:`_ARRAYS`; ``tangent`` ``(k, 6)``: ``T`` row by row)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(count):
        _tangent_frame(normal, k, 0, tangent, 0)


@fast_kernel
def _friction_frames_kernel(x: _F64_2, vertices: _I32_2, side: _F64_1, count: ti.i32, split: ti.i32,
                            frames: _F64_2):
    """Rows ``k < count`` of the kept arrays (:data:`_ARRAYS`): vertex-triangle pairs below ``split``,
    edge-edge pairs from there; frame, then tangent basis, in one row of ``frames`` ``(k, 13)``: weights (4),
    normal (3), ``T`` row by row (6), one array copied back."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(count):
        if k < split:
            _point_triangle_frame(x, vertices, k, side[k], frames, frames, 0, 4)
        else:
            _edge_edge_frame(x, vertices, k, side[k], frames, frames, 0, 4)
        _tangent_frame(frames, k, 4, frames, 7)


def tangent_basis(normal: np.ndarray) -> np.ndarray:
    """Taichi twin of :func:`sim_core.energies.friction.reference.tangent_basis`: orthonormal tangent bases
    ``T`` (columns ``t1 = normalise(n x a)``, ``a`` the coordinate axis least aligned with ``n``, and
    ``t2 = n x t1``) of unit normals ``(p, 3)``, shape ``(p, 3, 2)``.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    require_backend("contact set-up kernels")
    normal = np.reshape(normal, (-1, 3))
    k = len(normal)
    if not k:
        return np.empty((0, 3, 2))
    kept, tangent = _ARRAYS.rows("normal_in", k, (3,)), _ARRAYS.rows("tangent_rows", k, (6,))
    kept[:k] = normal
    _tangent_kernel(kept, k, tangent)
    return tangent[:k].reshape(k, 3, 2).copy()


def friction_frames(x: np.ndarray, vertices: np.ndarray, sides: np.ndarray, split: int, x_device=None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest-point weights, unit normals and tangent bases of vertex-triangle and edge-edge pairs in
    one launch: :func:`contact_frames` of each kind, then :func:`tangent_basis` of the normals (the same
    values bit for bit), what lagged friction freezes of its pairs.

    Args:
        x: positions, shape ``(n, 3)`` (m).
        vertices: the first ``split`` rows ``[p, a, b, c]`` (vertex-triangle), the others
            ``[a0, a1, b0, b1]`` (edge-edge), global vertex indices, shape ``(k, 4)``.
        sides: the pairs' step sides (+1 / -1, 0 unsigned), shape ``(k,)``.
        split: number of vertex-triangle rows, ``0 <= split <= k``.
        x_device: ``x`` as the float64 Taichi ndarray ``(n, 3)`` where another term of the solver holds it on the
            device (:func:`~sim_core.ti_kernels.transfer.positions_on_device`), read there on CUDA instead of ``x``
            being sent (a stacked batch's positions: 14 MB at 1024 Forming copies, a new array every step); None, or
            off CUDA: ``x`` is read.

    Returns:
        ``(weights (k, 4), normal (k, 3), tangent (k, 3, 2))``.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    require_backend("contact set-up kernels")
    k = len(vertices)
    if not k:
        return np.empty((0, 4)), np.empty((0, 3)), np.empty((0, 3, 2))
    side = _ARRAYS.rows("side", k)
    side[:k] = np.reshape(sides, -1)
    frames = _ARRAYS.rows("frames", k, (13,))
    _device_launch(_friction_frames_kernel, (_positions_or_held(x, x_device), _kept_indices("pairs", vertices), side, k,
                                             int(split), frames), outputs={5: k})
    return frames[:k, :4].copy(), frames[:k, 4:7].copy(), frames[:k, 7:].reshape(k, 3, 2).copy()


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the kernels on one pair each.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    x = np.array([[0.0, 0.0, 1.0e-3], [0.0, 0.0, 0.0], [1.0e-2, 0.0, 0.0], [0.0, 1.0e-2, 0.0]])
    pair = np.arange(4)[None]
    pair_geometry(x, pair, pair)
    for point_first in (True, False):
        contact_frames(x, pair, np.ones(1), point_first)
    tangent_basis(np.array([[0.0, 0.0, 1.0]]))
    friction_frames(x, np.concatenate([pair, pair]), np.ones(2), 1)
