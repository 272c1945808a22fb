"""The step sides of a contact set's candidate lists decided in one launch where the lists' indices are.

:meth:`sim_core.contact_set.ContactSet._pair_sides` gives every candidate pair its step side
(:func:`sim_core.collision.step_sides.step_sides`: the remembered side of a pair above its face / with interior closest
points at ``x^n``, else its geometric side there; 0 for any other pair) and the edge-edge pairs their ``keep`` (not
near-parallel). On the host path a launch copies back one int32 geometry code a pair
(:func:`~sim_core.energies.contact.setup_kernel.pair_codes`), the host decodes it into five arrays and places the
sides, and the pair batch then sends the float64 sides to the device again (1.9 million pairs at 1024 stacked Forming
copies: 7.6 MB back, 15 MB up, and the host's passes). :func:`step_sides_on_device` makes the same sides in one launch of
:func:`_sides_kernel`: each pair's region and geometric side measured by the set-up kernel's functions (the same
expressions: the same codes), its step side written into a float64 array that stays where the launch wrote it (on CUDA
a device array the pair batch reads as it is, :class:`~sim_core.energies.contact.batch_kernel.PairBatch`'s
``device_sides``), then the remembered sides placed at the rows the host found for the memory's pairs among the lists'
sorted keys (:meth:`~sim_core.collision.memory.ContactMemory.found_in`: one search a remembered pair, no pass over the
lists); what comes back is one int8 a pair (the side and the two flags), from which the host's sides are one table
lookup. The values equal the host path's bit for bit (sides are exactly -1, 0, +1; tests).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

from typing import NamedTuple

import numpy as np

from sim_core.energies.contact.pair_lists import DEVICE_INDEX_NAMES
from sim_core.energies.contact.setup_kernel import (_device_launch, _edge_edge_measures, _kept_indices,
                                                    _positions_or_held, _vertex_triangle_code)
from sim_core.ti_backend import current_arch, require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import LaunchArrays, unheld_rows
from sim_core.ti_kernels.launch import fast_kernel

_F64_1, _F64_2, _I32_1, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.I32_1, linalg.I32_2
_I8_1 = ti.types.ndarray(dtype=ti.i8, ndim=1)

_KEEP, _ABOVE = 3, 6
"""A pair's int8 code is ``side + 1 + 3 keep + 6 above`` (``side`` -1, 0, +1; ``keep``: an edge-edge pair not
near-parallel, 1 for every vertex-triangle pair; ``above``: the pair's side is the remembered / geometric one, above
its face or with interior closest points, and kept)."""

_SIDE_OF_CODE = np.array([(c % 3) - 1.0 for c in range(12)])
"""The step side of each int8 code, float64 ``(12,)``."""


@ti.func
def _coded(side: ti.i32, keep: ti.i32, above: ti.i32) -> ti.i8:
    """The int8 code of a pair (:data:`_KEEP`)."""
    return ti.cast(side + 1 + _KEEP * keep + _ABOVE * above, ti.i8)


@fast_kernel
def _sides_kernel(x: _F64_2, vt: _I32_2, vt_count: ti.i32, ee: _I32_2, ee_count: ti.i32, min_sine: ti.f64,
                  found: _I32_1, found_count: ti.i32, sides: _F64_1, codes: _I8_1):
    """Rows ``k < vt_count`` of ``vt`` and ``k < ee_count`` of ``ee`` (int32 ``[p, a, b, c]`` / ``[a0, a1, b0, b1]``):
    their step sides into ``sides[:vt_count + ee_count]`` (the vertex-triangle pairs, then the edge-edge ones) and
    their codes (:data:`_KEEP`) into ``codes``; then the remembered sides of the memory's rows ``found[:found_count]``
    (``2 row + 1`` for a side +1, ``2 row`` for -1; rows of the same ``vt_count + ee_count``) placed where the row is
    above (the geometric side stays elsewhere). The regions and sides are :func:`~sim_core.energies.contact.setup_kernel._codes_kernel`'s."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(vt_count):
        code = ti.cast(_vertex_triangle_code(x, vt, k), ti.i32)
        above = ti.select(ti.abs(code) > 1, 1, 0)
        side = ti.select(code > 0, 1, ti.select(code < 0, -1, 0)) * above
        sides[k] = ti.cast(side, ti.f64)
        codes[k] = _coded(side, 1, above)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(ee_count):
        m = _edge_edge_measures(x, ee, k)
        code = (1 + ti.cast(m[1], ti.i32) + ti.select(m[0] > min_sine, 2, 0)) * ti.cast(m[2], ti.i32)
        size = ti.abs(code)
        keep = ti.select(size > 2, 1, 0)
        above = keep * ti.select(size % 2 == 0, 1, 0)  # kept and interior
        side = ti.select(code > 0, 1, ti.select(code < 0, -1, 0)) * above
        sides[vt_count + k] = ti.cast(side, ti.f64)
        codes[vt_count + k] = _coded(side, keep, above)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for f in range(found_count):
        row = found[f] // 2
        code = ti.cast(codes[row], ti.i32)
        if code >= _ABOVE:  # above: the remembered side (+1 / -1)
            side = 2 * (found[f] % 2) - 1
            sides[row] = ti.cast(side, ti.f64)
            codes[row] = ti.cast(code - (code % 3) + side + 1, ti.i8)


class DeviceSides(NamedTuple):
    """The step sides of two candidate lists (``p`` vertex-triangle pairs, then ``q`` edge-edge ones).

    Attributes:
        sides: float64 ``(p + q,)``, the step sides (-1, 0, +1), on the host.
        ee_keep: bool ``(q,)``, the edge-edge pairs not near-parallel.
        device: the same sides where the launch wrote them: on CUDA a float64 Taichi ndarray of at least ``p + q``
            rows (its first rows), never written while this tuple or anything else holds it
            (:func:`~sim_core.ti_kernels.buffers.unheld_rows`); None elsewhere (the host's ``sides`` is the launch's).
    """

    sides: np.ndarray
    ee_keep: np.ndarray
    device: object


_ARRAYS = LaunchArrays()
"""The launch's host arrays (the found rows with their sides copied in, the codes copied out) and its device sides."""


def step_sides_on_device(x: np.ndarray, vt_vertices: np.ndarray, ee_vertices: np.ndarray, min_sine: float,
                         device: dict, found: tuple[np.ndarray, np.ndarray], out: np.ndarray | None = None,
                         x_device=None) -> DeviceSides:
    """The step sides and edge-edge ``keep`` of candidate lists at ``x^n`` (module docstring), in one launch.

    Args:
        x: the step's start positions ``x^n`` ``(n, 3)`` (m).
        vt_vertices, ee_vertices: the lists' int32 vertices ``(p, 4)`` and ``(q, 4)``, C-contiguous
            (:meth:`~sim_core.energies.contact.pair_lists.CandidateVertices.int32_vertices`).
        min_sine: the edge-edge pairs' least sine (kept above it).
        device: the lists' device cache (:attr:`~sim_core.energies.contact.pair_lists.CandidateVertices.device`),
            where the int32 vertices are kept under :data:`~sim_core.energies.contact.pair_lists.DEVICE_INDEX_NAMES`.
        found: ``(rows, sides)``: the rows of the ``p + q`` pairs that the side memory holds (int ``(f,)``, distinct;
            the edge-edge rows offset by ``p``) and their remembered sides float64 ``(f,)`` (+1 / -1).
        out: a float64 array ``(p + q,)`` for the host's sides, or None: a new one.
        x_device: ``x`` where the solver's terms hold it on the device (read there on CUDA), or None.

    Returns:
        :class:`DeviceSides`.

    Raises:
        ConfigError: the Taichi backend is not initialised.
        ValueError: indices that are not C-contiguous int32 ``(k, 4)``, or a found row outside ``[0, p + q)``.
    """
    require_backend("step sides kernel")
    p, q = len(vt_vertices), len(ee_vertices)
    rows, remembered = np.asarray(found[0]), np.asarray(found[1], dtype=np.float64)
    if len(rows) and (rows.min() < 0 or rows.max() >= p + q):
        raise ValueError(f"step_sides_on_device: a remembered row outside [0, {p + q})")
    if p + q >= 1 << 30:
        raise ValueError(f"step_sides_on_device: {p + q} pairs, at most 2^30 - 1 (a row and its side in an int32)")
    sides = np.empty(p + q) if out is None else out
    codes_host = _ARRAYS.rows("codes", p + q, (), np.int8)
    if not p + q:
        return DeviceSides(sides, np.zeros(0, dtype=bool), None)
    indices, constant = [], {}
    for position, name, given in ((1, DEVICE_INDEX_NAMES[0], vt_vertices), (3, DEVICE_INDEX_NAMES[1], ee_vertices)):
        if len(given):
            if given.dtype != np.int32 or given.ndim != 2 or given.shape[1] != 4 or not given.flags.c_contiguous:
                raise ValueError(f"step_sides_on_device: indices must be C-contiguous int32 (k, 4), got "
                                 f"{given.dtype} {given.shape}")
            indices.append(given)
            constant[position] = (device, name)
        else:
            indices.append(_kept_indices(f"sides_{name}", given))
    f = len(rows)
    found_rows = _ARRAYS.rows("found", f, (), np.int32)  # 2 row + (side > 0): one array sent
    np.multiply(rows, 2, out=found_rows[:f], casting="unsafe")
    found_rows[:f] += remembered > 0.0
    on_gpu = current_arch() == "cuda"
    target = unheld_rows(_ARRAYS.spares(), "sides", p + q) if on_gpu else sides
    _device_launch(_sides_kernel, (_positions_or_held(x, x_device), indices[0], p, indices[1], q, float(min_sine),
                                   found_rows, f, target, codes_host), outputs={9: p + q},
                   constant=constant)
    codes = codes_host[:p + q]
    if on_gpu:
        np.take(_SIDE_OF_CODE, codes, out=sides)
    return DeviceSides(sides, codes[p:] >= _KEEP, target if on_gpu else None)
