"""The step sides of a contact set's candidate lists decided where the lists' indices are.

:meth:`sim_core.contact_set.ContactSet._pair_sides` gives every candidate pair its step side
(:func:`sim_core.collision.step_sides.step_sides`: the remembered side of a pair above its face / with interior closest
points at ``x^n``, else its geometric side there; 0 for any other pair) and the edge-edge pairs their ``keep`` (not
near-parallel). On the host path a launch copies back one int32 geometry code a pair
(:func:`~sim_core.energies.contact.setup_kernel.pair_codes`), the host decodes it into five arrays and places the
sides, and the pair batch then sends the float64 sides to the device again (1.9 million pairs at 1024 stacked Forming
copies: 7.6 MB back, 15 MB up, and the host's passes over every pair). Here:

* :func:`side_codes`: one launch of :func:`_side_codes_kernel` measures each pair's region and geometric side (the
  set-up kernel's functions, the same expressions) into one int8 code a pair (:data:`_KEEP`) and its step side before the
  memory (-1, 0, +1, one int8: the host's sides are then one cast, not a decoding), kept on the device and copied back
  in one piece (3.8 MB); a :class:`SideCodes` gives the :class:`~sim_core.collision.pair_geometry.ListGeometry` of any
  rows (the end of a step's memory update reads its active pairs' only);
* :func:`step_sides_of`: the step sides from the codes and the rows the host found for the side memory's pairs among
  the lists' sorted keys (:meth:`~sim_core.collision.memory.ContactMemory.found_in`: one search a remembered pair, no
  pass over the lists): on the host one table lookup and the remembered rows placed; on CUDA also one launch of
  :func:`_place_kernel` into a float64 array that stays on the device, which the pair batch reads as it is
  (:class:`~sim_core.energies.contact.batch_kernel.PairBatch`'s ``device_sides``): no positions and no sides cross;
  and on CUDA the edge-edge pairs kept (not near-parallel) and the pair batch's layout rows made by one launch of
  :func:`_kept_rows_kernel` from the codes where they are (a mark, the marks' running sums, a scatter:
  :class:`KeptRows`), copied back in one piece, instead of the host's ``keep`` over every edge-edge candidate, its
  ``flatnonzero`` and the layout rows built and sent with every new batch (:meth:`~sim_core.energies.contact.pair_lists.
  CandidateVertices.batch_layout`).

The codes measured at a step's converged positions serve the next step's sides at its ``x^n`` (the same positions and
lists), as the host path's kept geometry does. The values equal the host path's bit for bit (tests).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

from typing import NamedTuple

import numpy as np

from sim_core.collision.pair_geometry import ListGeometry
from sim_core.energies.contact.pair_lists import DEVICE_INDEX_NAMES
from sim_core.energies.contact.setup_kernel import (_device_launch, _edge_edge_measures, _int32_rows, _kept_indices,
                                                    _positions_or_held, _vertex_triangle_code)
from sim_core.ti_backend import current_arch, require_backend, serial_loops, ti
from sim_core.ti_kernels import device_copy, linalg
from sim_core.ti_kernels.buffers import LaunchArrays, copy_back, on_device, unheld_rows
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.scan import SCAN_CHUNK, running_sums

_F64_1, _F64_2, _I32_1, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.I32_1, linalg.I32_2
_I8_1 = ti.types.ndarray(dtype=ti.i8, ndim=1)

_KEEP, _ABOVE = 3, 6
"""A pair's int8 code is ``side + 1 + 3 keep + 6 above``: ``side`` its geometric side (+1 / -1); ``keep`` 1 for a
vertex-triangle pair and for an edge-edge pair not near-parallel (sine above the least), else 0; ``above`` 1 for a
vertex above its face's interior / edges whose closest points are interior to both, else 0. A pair's step side is its
side (or the remembered one) where ``keep`` and ``above``, else 0."""

_GEOMETRIC = np.array([(c % 3) - 1.0 for c in range(12)])
"""The geometric side of each code, float64 ``(12,)``."""

_SIGNED = np.array([c >= _ABOVE and c % _ABOVE >= _KEEP for c in range(12)])
"""Whether a code's pair takes a side in the step (kept and above), bool ``(12,)``."""

_KEPT = np.zeros(256, dtype=bool)
_KEPT[:12] = [c % _ABOVE >= _KEEP for c in range(12)]
"""Whether a code's pair is kept, by the code's byte (``uint8``), bool ``(256,)`` (a lookup by bytes: no index
conversion)."""


@ti.func
def _signed(code: ti.i32) -> ti.i32:
    """1 where a code's pair takes a side in the step (:data:`_SIGNED`), else 0."""
    return ti.select(code >= _ABOVE and code % _ABOVE >= _KEEP, 1, 0)


@fast_kernel
def _side_codes_kernel(x: _F64_2, vt: _I32_2, vt_count: ti.i32, ee: _I32_2, ee_count: ti.i32, min_sine: ti.f64,
                       codes: _I8_1):
    """Rows ``k < vt_count`` of ``vt`` and ``k < ee_count`` of ``ee`` (int32 ``[p, a, b, c]`` / ``[a0, a1, b0, b1]``):
    their codes (:data:`_KEEP`) into ``codes[:n]`` (``n = vt_count + ee_count``: the vertex-triangle pairs, then the
    edge-edge ones) and their step sides before the memory (the geometric side where kept and above, else 0) into
    ``codes[n:2 n]``; the regions, sides and sines are
    :func:`~sim_core.energies.contact.setup_kernel._codes_kernel`'s."""
    n = vt_count + ee_count
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(vt_count):
        code = ti.cast(_vertex_triangle_code(x, vt, k), ti.i32)  # side * (2 if above else 1)
        side = ti.select(code > 0, 1, ti.select(code < 0, -1, 0))
        coded = side + 1 + _KEEP + _ABOVE * ti.select(ti.abs(code) > 1, 1, 0)
        codes[k] = ti.cast(coded, ti.i8)
        codes[n + k] = ti.cast(_signed(coded) * side, ti.i8)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(ee_count):
        m = _edge_edge_measures(x, ee, k)
        side = ti.cast(m[2], ti.i32)
        coded = side + 1 + _KEEP * ti.select(m[0] > min_sine, 1, 0) + _ABOVE * ti.cast(m[1], ti.i32)
        codes[vt_count + k] = ti.cast(coded, ti.i8)
        codes[n + vt_count + k] = ti.cast(_signed(coded) * side, ti.i8)


@fast_kernel
def _place_kernel(codes: _I8_1, count: ti.i32, found: _I32_1, found_count: ti.i32, sides: _F64_1):
    """``sides[:count]``: the step sides before the memory ``codes[count:2 count]`` (:func:`_side_codes_kernel`), then
    the remembered sides of the memory's rows ``found[:found_count]`` (``2 row + 1`` for a side +1, ``2 row`` for -1)
    placed where the row takes a side by its code ``codes[row]`` (the geometric one stays elsewhere)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(count):
        sides[k] = ti.cast(codes[count + k], ti.f64)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for f in range(found_count):
        row = found[f] // 2
        if _signed(ti.cast(codes[row], ti.i32)):
            sides[row] = ti.cast(2 * (found[f] % 2) - 1, ti.f64)


@fast_kernel
def _kept_rows_kernel(codes: _I8_1, p: ti.i32, q: ti.i32, marks: _I32_1, chunk_total: _I32_1, rows: _I32_1):
    """The layout rows of a pair batch over every vertex-triangle pair and the kept edge-edge pairs of lists of ``p``
    and ``q`` pairs whose codes (:data:`_KEEP`) are ``codes[:p + q]``: ``rows[k] = k`` for ``k < p``, then ``p + j``
    for each kept edge-edge pair ``j`` in increasing ``j`` (``rows[p .. p + r - 1]``), the count ``r`` of those in
    ``rows[p + q]``. Scratch: ``marks`` (at least ``q + 1``: pair ``j``'s mark at ``j + 1``, then the kept pairs before
    ``j`` at ``j``), ``chunk_total`` (at least ``ceil(q / SCAN_CHUNK)``). Integer arithmetic: the same rows in any order
    of the threads."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(p):
        rows[k] = k
    ti.loop_config(serialize=True)  # one thread
    for _ in range(1):
        marks[0] = 0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for j in range(q):
        code = ti.cast(codes[p + j], ti.i32)
        marks[j + 1] = ti.select(code % _ABOVE >= _KEEP, 1, 0)
    running_sums(marks, q, chunk_total, rows, p + q)  # the ranks; the kept count into rows[p + q]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for j in range(q):
        if marks[j + 1] != marks[j]:  # kept
            rows[p + marks[j]] = p + j


class SideCodes(NamedTuple):
    """The codes (:data:`_KEEP`) of two candidate lists at one set of positions (``split`` vertex-triangle pairs, then
    the edge-edge ones) and their step sides before the memory.

    Attributes:
        both: int8 ``(2 (p + q),)`` on the host: the codes, then the step sides (-1, 0, +1).
        device: the same where the launch wrote them (on CUDA an int8 Taichi ndarray ``(2 (p + q),)``, its own), or
            None (the host's array is the launch's).
        split: ``p``.
    """

    both: np.ndarray
    device: object
    split: int

    @property
    def codes(self) -> np.ndarray:
        """The codes, int8 ``(p + q,)`` (a view)."""
        return self.both[:len(self.both) // 2]

    @property
    def steps(self) -> np.ndarray:
        """The step sides before the memory, int8 ``(p + q,)`` (a view)."""
        return self.both[len(self.both) // 2:]

    def rows(self, vt_rows: np.ndarray, ee_rows: np.ndarray) -> ListGeometry:
        """The :class:`~sim_core.collision.pair_geometry.ListGeometry` of the vertex-triangle rows ``vt_rows`` ``(a,)``
        and the edge-edge rows ``ee_rows`` ``(b,)`` (rows of each list)."""
        vt, ee = np.take(self.codes, vt_rows), np.take(self.codes[self.split:], ee_rows)
        return ListGeometry(vt >= _ABOVE, np.take(_GEOMETRIC, vt), ee % _ABOVE >= _KEEP, ee >= _ABOVE,
                            np.take(_GEOMETRIC, ee))

    def geometry(self) -> ListGeometry:
        """The :class:`~sim_core.collision.pair_geometry.ListGeometry` of every pair."""
        return self.rows(np.arange(self.split), np.arange(len(self.codes) - self.split))


class KeptRows(NamedTuple):
    """The edge-edge pairs kept (not near-parallel) of two candidate lists (``p`` vertex-triangle pairs, then ``q``
    edge-edge ones) as a pair batch's layout rows (:class:`~sim_core.energies.contact.pair_lists.BatchLayout`), made on
    the device (:func:`_kept_rows_kernel`).

    Attributes:
        rows: int32 ``(p + r,)`` on the host: ``0 .. p - 1``, then ``p + j`` for the ``r`` kept edge-edge pairs ``j``
            (increasing).
        ee_rows: int64 ``(r,)``, the kept edge-edge pairs' rows of the edge-edge list (``rows[p:] - p``).
        device: the same rows where a CUDA launch reads them: an int32 Taichi ndarray of at least ``p + r`` rows (its
            first rows), never written while this tuple or anything else holds it
            (:func:`~sim_core.ti_kernels.buffers.unheld_rows`).
    """

    rows: np.ndarray
    ee_rows: np.ndarray
    device: object


class DeviceSides(NamedTuple):
    """The step sides of two candidate lists (``p`` vertex-triangle pairs, then ``q`` edge-edge ones).

    Attributes:
        sides: float64 ``(p + q,)``, the step sides (-1, 0, +1), on the host.
        ee_keep: bool ``(q,)``, the edge-edge pairs not near-parallel, on the host; None on CUDA (:attr:`kept` instead).
        device: the same sides on CUDA: a float64 Taichi ndarray of at least ``p + q`` rows (its first rows), never
            written while this tuple or anything else holds it (:func:`~sim_core.ti_kernels.buffers.unheld_rows`); None
            elsewhere.
        kept: on CUDA the kept edge-edge pairs as layout rows made on the device (:class:`KeptRows`); None elsewhere.
    """

    sides: np.ndarray
    ee_keep: np.ndarray | None
    device: object
    kept: KeptRows | None = None

    def kept_edge_edge_rows(self) -> np.ndarray:
        """The kept edge-edge pairs' rows of the edge-edge list, int64 ``(r,)`` (increasing)."""
        return self.kept.ee_rows if self.kept is not None else np.flatnonzero(self.ee_keep)


_ARRAYS = LaunchArrays()
"""The launches' host arrays (the found rows with their sides copied in) and the device sides' spares."""


def side_codes(x: np.ndarray, vt_vertices: np.ndarray, ee_vertices: np.ndarray, min_sine: float, device: dict,
               x_device=None) -> SideCodes:
    """The :class:`SideCodes` of candidate lists at ``x``, in one launch of :func:`_side_codes_kernel`.

    Args:
        x: positions ``(n, 3)`` (m).
        vt_vertices, ee_vertices: the lists' int32 vertices ``(p, 4)`` and ``(q, 4)``, C-contiguous, never changed in
            place (:meth:`~sim_core.energies.contact.pair_lists.CandidateVertices.int32_vertices`), or Taichi int32
            ndarrays where the search gathered them (:meth:`~sim_core.energies.contact.pair_lists.CandidateVertices.
            index_arrays`: read there).
        min_sine: the edge-edge pairs' least sine (kept above it).
        device: the lists' device cache (:attr:`~sim_core.energies.contact.pair_lists.CandidateVertices.device`),
            where the int32 vertices are kept under :data:`~sim_core.energies.contact.pair_lists.DEVICE_INDEX_NAMES`.
        x_device: ``x`` where the solver's terms hold it on the device (read there on CUDA), or None.

    Raises:
        ConfigError: the Taichi backend is not initialised.
        ValueError: indices that are not C-contiguous int32 ``(k, 4)``.
    """
    require_backend("side_codes")
    p, q = vt_vertices.shape[0], ee_vertices.shape[0]
    codes = np.empty(2 * (p + q), dtype=np.int8)
    if not p + q:
        return SideCodes(codes, None, p)
    indices, constant = [], {}
    for position, name, given in ((1, DEVICE_INDEX_NAMES[0], vt_vertices), (3, DEVICE_INDEX_NAMES[1], ee_vertices)):
        if given.shape[0]:
            indices.append(_int32_rows(given, "side_codes"))
            constant[position] = (device, name)
        else:
            indices.append(_kept_indices(f"sides_{name}", given))
    target = device_copy.new_ndarray(ti.i8, (2 * (p + q),)) if current_arch() == "cuda" else codes
    _device_launch(_side_codes_kernel, (_positions_or_held(x, x_device), indices[0], p, indices[1], q,
                                        float(min_sine), target), outputs={}, constant=constant)
    if target is codes:
        return SideCodes(codes, None, p)
    copy_back(codes, target)
    return SideCodes(codes, target, p)


def step_sides_of(codes: SideCodes, found: tuple[np.ndarray, np.ndarray], out: np.ndarray | None = None
                  ) -> DeviceSides:
    """The step sides and edge-edge ``keep`` of the lists of ``codes`` with the side memory's pairs ``found``
    (module docstring).

    Args:
        codes: the lists' :class:`SideCodes` at the step's start positions ``x^n``.
        found: ``(rows, sides)``: the rows of the ``p + q`` pairs that the side memory holds (int ``(f,)``, distinct;
            the edge-edge rows offset by ``p``) and their remembered sides float64 ``(f,)`` (+1 / -1).
        out: a float64 array ``(p + q,)`` for the host's sides, or None: a new one.

    Raises:
        ValueError: a found row outside ``[0, p + q)``, or ``p + q >= 2**30``.
    """
    count = len(codes.codes)
    rows, remembered = np.asarray(found[0], dtype=np.int64), np.asarray(found[1], dtype=np.float64)
    if len(rows) and (rows.min() < 0 or rows.max() >= count):
        raise ValueError(f"step_sides_of: a remembered row outside [0, {count})")
    if count >= 1 << 30:
        raise ValueError(f"step_sides_of: {count} pairs, at most 2^30 - 1 (a row and its side in an int32)")
    sides = np.empty(count) if out is None else out
    sides[...] = codes.steps  # (a cast: the kernel wrote the sides before the memory)
    signed = np.take(_SIGNED, np.take(codes.codes, rows))
    sides[rows[signed]] = remembered[signed]
    if codes.device is None:
        return DeviceSides(sides, np.take(_KEPT, codes.codes[codes.split:].view(np.uint8)), None)
    f = len(rows)
    coded = _ARRAYS.rows("found", f, (), np.int32)  # 2 row + (side > 0): one array sent
    np.multiply(rows, 2, out=coded[:f], casting="unsafe")
    coded[:f] += remembered > 0.0
    target = unheld_rows(_ARRAYS.spares(), "sides", count)
    _device_launch(_place_kernel, (codes.device, count, coded, f, target), outputs={})
    return DeviceSides(sides, None, target, kept_rows(codes))


def kept_rows(codes: SideCodes) -> KeptRows:
    """The :class:`KeptRows` of the lists of ``codes`` (on the device: ``codes.device`` not None), by one launch of
    :func:`_kept_rows_kernel` and one copy back of its ``p + q + 1`` int32 rows into a new host array.

    Raises:
        ValueError: ``codes`` without a device copy (the host's ``keep`` is :meth:`SideCodes.geometry`'s).
    """
    if codes.device is None:
        raise ValueError("kept_rows: codes without a device copy (the host's keep is SideCodes.geometry's)")
    p = codes.split
    q = len(codes.codes) - p
    marks = on_device(_ARRAYS.device(), "kept_marks", _ARRAYS.rows("kept_marks", q + 1, (), np.int32), scratch=True)
    chunk_total = on_device(_ARRAYS.device(), "kept_chunks",
                            _ARRAYS.rows("kept_chunks", max(1, -(-q // SCAN_CHUNK)), (), np.int32), scratch=True)
    target = unheld_rows(_ARRAYS.spares(), "layout_rows", p + q + 1, dtype=ti.i32)
    _kept_rows_kernel(codes.device, p, q, marks, chunk_total, target)
    host = copy_back(np.empty(target.shape[0], dtype=np.int32), target, p + q + 1)
    r = int(host[p + q])
    rows = host[:p + r]
    return KeptRows(rows, np.subtract(rows[p:], p, dtype=np.int64), target)
