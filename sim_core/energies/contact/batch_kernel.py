"""One kernel launch evaluates a vertex-triangle and an edge-edge contact potential together.

The Newton solver asks the step's two pair potentials for their energy (line search), then for the
gradient and Hessian (iterate) at the same positions, one potential after the other. Evaluated
separately, each potential launches the distance kernels of :mod:`sim_core.energies.contact.distance_kernel`
once or twice per request (values of every pair, then derivatives of the active ones) after a NumPy
gather of the pair positions. A :class:`PairBatch` links the two potentials: the first request at
new positions ``x`` evaluates both in one launch of :func:`_batch_kernel` (the pair positions
gathered in the kernel; the distance of every pair; with derivatives, the distance gradient, the
penalty Hessian ``k_c (grad d grad d^T + (d - eps) hess d)`` of the active pairs ``d < eps`` and the
penalty gradient ``k_c (d - eps) grad d`` summed per vertex), and
each potential keeps its part as its evaluation of ``x`` (a
:class:`~sim_core.energies.contact.reference.PairEvaluation` in its workspace, :mod:`sim_core.workspace`,
as :meth:`sim_core.energies.contact.reference._PairPenalty._evaluate` keeps it), so the second request finds it there.
The penalty Hessian is made in the kernel from the distance Hessian it has just computed, and the
penalty gradient summed there in pair order (the reference's operations in its order: the same
blocks and sums bit for bit), so that neither the distance Hessians are copied out nor the blocks
and the gradient built in NumPy (about 30 + 15 us of NumPy per potential and Forming iterate, for
~17 us more kernel time); both are kept with the stiffness they were made for (another stiffness
evaluates the Hessian again, and sums the gradient in NumPy from the kept distance gradients). Before measuring a pair, the kernel applies the exact prefilter of
:mod:`sim_core.collision.distance_bounds` (box gap, plane / line-line bound, same margins): about
two thirds of Forming's candidate pairs are farther than ``eps`` for certain and are left out
(they are never active, so the active pairs and their values are unchanged). The kernel's work
arrays are kept per thread and shared by all batches (:data:`_ARRAYS`; bound to the compiled kernel
once, positions copied in). The kernel sees the pairs' own vertices only (``unique`` of the pairs' vertices, the
positions gathered and the summed gradients spread back on the host): on CUDA the positions and the summed
gradients cross to the device and back at each launch, and a Forming step's pairs name a fraction of its vertices.

Where arrays cross to a GPU, derivatives at new positions take two passes (:attr:`PairBatch.two_pass`) made in one
launch whose list of active pairs stays on the device between them (:attr:`PairBatch.listed`,
:mod:`sim_core.energies.contact.listed_kernel`), and the pair penalties' energies by copy are summed where the launch
left the distances (:mod:`sim_core.energies.contact.copy_energy_kernel`). The Hessian, distance-gradient and
gradient-sum rows a launch leaves on the device go into arrays that no evaluation holds any more
(:func:`~sim_core.ti_kernels.buffers.unheld_rows`), so the launches of a Newton iteration allocate no device memory.

When both potentials already keep the distances of ``x`` (the energy of the accepted line-search
point, the next Newton iterate), the derivatives are computed for their active pairs only. The
kernel calls the same Taichi functions as the separate kernels, so every distance, gradient and
Hessian equals theirs bit for bit (tests).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import weakref

import numpy as np

from sim_core.collision.distances import DistanceDerivatives
from sim_core.energies.base import positions_key
from sim_core.energies.contact.copy_energy_kernel import penalty_energy_by_copy
from sim_core.energies.contact.gradient_kernel import add_rows, gather_rows
from sim_core.energies.contact.kernel import TiEdgeEdgeContact, TiVertexTriangleContact
from sim_core.energies.contact.listed_kernel import LISTED_FIELDS, chunk_count, listed_derivatives
from sim_core.energies.contact.pair_lists import BatchLayout
from sim_core.energies.contact.pair_measure import measure_pair, zero_sums
from sim_core.energies.contact.reference import PairEvaluation
from sim_core.ti_backend import current_arch, require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import DeviceRows, LaunchArrays, copy_back, on_device, rows_on_device, unheld_rows
from sim_core.ti_kernels.copy_vectors import CopySums
from sim_core.ti_kernels.device_copy import new_ndarray
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.transfer import positions_on_device, upload
from sim_core.unique import compact_indices
from sim_core.workspace import workspace_of

_F64_1, _F64_2, _F64_3, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_2
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@fast_kernel
def _batch_kernel(x: _F64_2, vertices: _I32_2, side: _F64_1, rows: _I32_1, count: ti.i32, split: ti.i32,
                  eps_vt: ti.f64, eps_ee: ti.f64, stiffness_vt: ti.f64, stiffness_ee: ti.f64, derivatives: ti.i32,
                  pack_region: ti.i32, z: _F64_3, d: _F64_1, region: _I32_1, grad: _F64_2, hess: _F64_3,
                  gradients: _F64_2, active: _F64_2, active_count: _I32_1):
    """Pairs ``k = rows[i]`` for ``i < count`` (``k < split`` vertex-triangle, else edge-edge): distance
    ``d[i]`` and region (positions gathered into ``z[i]``); the pairs with ``d < eps`` (``eps`` of their kind)
    listed as rows ``[i, d[i]]`` of ``active`` from row 1 on (in no fixed order on a parallel arch, in row order
    on the CPU's serial loops), their count ``a`` in ``active[0, 0]`` (counted in ``active_count[0]``, zeroed
    first): the list and its length in one array, read back in one copy; with
    ``derivatives`` the distance gradient
    row ``grad[i]`` and the penalty Hessian row ``hess[i]`` (:func:`pair_measure._penalty_hessian`, with the
    ``eps`` and ``stiffness`` of their kind) of the pairs with ``d < eps`` (the other rows are left
    as they are), and their penalty gradients ``k_c (d - eps) grad d`` summed per vertex into
    ``gradients`` (``(2 n, 3)``: rows ``v`` for the vertex-triangle pairs, ``n + v`` for the edge-edge
    pairs, ``n = x.shape[0]``; zeroed first, sums in pair order: :func:`pair_measure._scatter_penalty_gradient`).
    A pair that the bounds of :func:`pair_measure._may_touch` rule out gets ``d[i] = inf`` and region -1
    (farther than ``eps``: not active, as its distance would say). ``derivatives`` (0 or 1) and the
    pair kind are runtime values: one compiled kernel for every request. With ``pack_region`` (and ``derivatives``)
    the regions are also written, as floats, after the sums: ``gradients[2 n + i // 3, i % 3] = region[i]`` (the
    array then has those rows), so that one copy back brings both."""
    n = x.shape[0]
    zero_sums(gradients, derivatives * 2 * n, active_count)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(count):
        if measure_pair(x, vertices, side, rows[i], i, split, eps_vt, eps_ee, stiffness_vt, stiffness_ee, n,
                         derivatives, z, d, region, grad, hess, gradients):  # the distance the host keeps
            slot = ti.atomic_add(active_count[0], 1) + 1
            active[slot, 0], active[slot, 1] = ti.cast(i, ti.f64), d[i]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for _ in range(1):  # after every pair: the count in the list's first row
        active[0, 0] = ti.cast(active_count[0], ti.f64)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(pack_region * derivatives * count):
        gradients[2 * n + i // 3, i % 3] = ti.cast(region[i], ti.f64)


@fast_kernel
def _packed_kernel(x: _F64_2, vertices: _I32_2, side: _F64_1, rows: _I32_1, count: ti.i32, split: ti.i32, u: ti.i32,
                   eps_vt: ti.f64, eps_ee: ti.f64, stiffness_vt: ti.f64, stiffness_ee: ti.f64, derivatives: ti.i32,
                   z: _F64_3, d: _F64_1, region: _I32_1, grad: _F64_2, hess: _F64_3, gradients: _F64_2,
                   slots: _I32_1, active_count: _I32_1, out: _F64_1):
    """Every pair ``i < count`` (``i < split`` vertex-triangle, else edge-edge; its vertices and side at row
    ``rows[i]`` of ``vertices`` and ``side``, the batch's layout) measured as :func:`_batch_kernel`
    measures it (the same functions; its work arrays ``z``, ``d``, ``region``, ``grad``, ``hess`` of at least
    ``count`` rows, ``gradients`` of at least ``2 u`` rows: the sums of the ``u`` vertices of ``x``), then its results
    packed into ``out`` in increasing pair order, for one copy back: ``out[0]`` the count ``a`` of the pairs with
    ``d < eps``, then their ``[i, d]`` (``2 a``); with ``derivatives`` then the per-vertex penalty gradient sums
    ``(2 u, 3)`` (vertex-triangle rows, then edge-edge rows; zeroed first, sums in pair order), the regions ``(a,)``,
    the distance gradients ``(a, 12)`` and the penalty Hessians ``(a, 12, 12)`` of those pairs. A pair's place in the
    order is the number of listed pairs before it (the list is built in no fixed order on a parallel arch), so the
    layout is the same on every arch: :func:`packed_size` entries."""
    zero_sums(gradients, derivatives * 2 * u, active_count)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(count):
        if measure_pair(x, vertices, side, rows[i], i, split, eps_vt, eps_ee, stiffness_vt, stiffness_ee, u,
                         derivatives, z, d, region, grad, hess, gradients):
            slots[ti.atomic_add(active_count[0], 1)] = i
    ti.loop_config(serialize=ti.static(serial_loops()))
    for s in range(count):  # the listed pairs into their places
        a = active_count[0]
        if s < a:
            i = slots[s]
            place = 0
            for t in range(a):
                if slots[t] < i:
                    place += 1
            out[1 + 2 * place], out[2 + 2 * place] = ti.cast(i, ti.f64), d[i]
            if derivatives:
                base = 1 + 2 * a + 6 * u
                out[base + place] = ti.cast(region[i], ti.f64)
                for e in range(12):
                    out[base + a + 12 * place + e] = grad[i, e]
                for e in range(144):
                    out[base + 13 * a + 144 * place + e] = hess[i, e // 12, e % 12]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for j in range(derivatives * 6 * u):
        out[1 + 2 * active_count[0] + j] = gradients[j // 3, j % 3]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for _ in range(1):
        out[0] = ti.cast(active_count[0], ti.f64)


def packed_size(active: int, vertices: int, derivatives: bool) -> int:
    """Entries of :func:`_packed_kernel`'s ``out`` for ``active`` listed pairs over ``vertices`` vertices."""
    return 1 + 2 * active + (6 * vertices + 157 * active if derivatives else 0)


def _sorted_found(listed: np.ndarray, listed_arg, rows_read: int) -> tuple[np.ndarray, np.ndarray]:
    """The kernel's list of active pairs (``listed`` the host array ``(capacity, 2)``: the count in ``[0, 0]``, rows
    ``[launch row, distance]`` from row 1 on; ``listed_arg`` the launch's: the same, or its device copy on CUDA, of
    which the first ``rows_read`` rows are copied back, and the rest of the list after them only when it is longer)
    as ``(rows int64 (a,), distances (a,))`` in increasing row order (on a parallel arch the kernel appends in no
    fixed order)."""
    if listed_arg is not listed:
        copy_back(listed, listed_arg, min(rows_read, len(listed)))
        if int(listed[0, 0]) + 1 > rows_read:
            copy_back(listed, listed_arg, int(listed[0, 0]) + 1)
    a = int(listed[0, 0])
    rows, distances = listed[1:a + 1, 0].astype(np.int64), listed[1:a + 1, 1].copy()
    if a < 2 or not np.any(rows[1:] < rows[:-1]):  # (the CPU's serial loop lists them in order)
        return rows, distances
    order = np.argsort(rows)
    return rows[order], distances[order]


PACKED_MAX_PAIRS = 1 << 16
"""The most pairs a batch evaluates by default in :func:`_packed_kernel` (:attr:`PairBatch.packed`): a single Forming
environment has about 1,600 to 1,900 candidate pairs, a stacked batch of copies millions."""

_NONE_FOUND = (np.zeros(0, dtype=np.int64), np.zeros(0))
"""No active pair (a launch over no pairs)."""

_ARRAYS = LaunchArrays()
"""The batch kernel's work arrays, per thread (:class:`~sim_core.ti_kernels.buffers.LaunchArrays`):
shared by every :class:`PairBatch` (an evaluation copies its rows out), so a step's new batch binds
no new arrays and writes into pages already mapped (fresh ``(p, 12, 12)`` arrays per batch cost
page faults at the first launches)."""


def _unheld(rows: int, tail: tuple[int, ...]):
    """A device array ``(>= rows, *tail)`` for a launch's results that stay on the device (Hessian, distance gradient
    and gradient sum rows), one of this thread's that no evaluation holds any more where there is one
    (:func:`~sim_core.ti_kernels.buffers.unheld_rows`): the launches of a Newton iteration allocate none."""
    return unheld_rows(_ARRAYS.spares(), f"rows{tail}", rows, tail)


def work_arrays(rows: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The batch kernel's kept output arrays with at least ``rows`` rows, for the calling thread:
    distance ``(>= rows,)``, region int32 ``(>= rows,)``, gradient ``(>= rows, 12)`` and Hessian
    ``(>= rows, 12, 12)`` (rows ``i`` of a launch's pairs ``i``; overwritten by the next launch)."""
    return (_ARRAYS.rows("d", rows), _ARRAYS.rows("region", rows, (), np.int32), _ARRAYS.rows("grad", rows, (12,)),
            _ARRAYS.rows("hess", rows, (12, 12)))


class PairBatch:
    """Evaluates a vertex-triangle and an edge-edge pair potential in one launch (module docstring).

    Args:
        vt: a :class:`~sim_core.energies.contact.reference.VertexTriangleContact` (its ``vertices`` ``(p, 4)``
            and ``sides`` ``(p,)``).
        ee: an :class:`~sim_core.energies.contact.reference.EdgeEdgeContact` (``(q, 4)``, ``(q,)``).

        layout: the pairs' vertices as rows of a kept compaction of candidate lists
            (:class:`~sim_core.energies.contact.pair_lists.BatchLayout`: a contact set's, made once per list and
            shared, with its device copies, by every batch over the list; its ``rows`` ``(p + q,)``, the
            vertex-triangle pairs first as rows ``0 .. p - 1``), or None: the compaction of these pairs'
            vertices (:func:`~sim_core.unique.compact_indices`), made here.
        sides: with ``layout``, the pairs' sides by row of its ``local`` (float64 ``(len(local),)``: ``vt``'s, then
            each edge-edge candidate's, ``ee``'s at the rows ``layout.ee_rows``, any value elsewhere: never read) when
            the caller has them in one array (the contact set's step sides), taken as they are (never written); None:
            made here from the potentials' sides.
        device_sides: with ``sides``, the same values where a CUDA launch reads them (a float64 Taichi ndarray of at
            least ``len(local)`` rows, never written while the batch holds it: the contact set's step sides' launch,
            :func:`~sim_core.energies.contact.sides_kernel.step_sides_of`), taken instead of a copy of
            ``sides`` sent once; None: ``sides`` sent.
        device_rows: the layout's ``rows`` where a CUDA launch reads them (an int32 Taichi ndarray of at least
            ``len(rows)`` rows holding them, never written while the batch holds it: the contact set's kept rows'
            launch, :func:`~sim_core.energies.contact.sides_kernel.kept_rows`), taken instead of a copy of ``rows``
            sent once; None: ``rows`` sent.

    Pairs and sides are fixed at construction (as the potentials' are); each potential's own ``eps``
    is read at every evaluation. The kernel reads pair ``k``'s vertices and side at row ``layout.rows[k]``.

    Raises:
        ConfigError: the Taichi backend is not initialised.
        ValueError: a ``layout`` whose rows are not the vertex-triangle rows ``0 .. p - 1`` and then ``q`` rows, or
            ``sides`` not float64 of the layout's rows.
    """

    two_pass: bool | None = None
    """Derivatives of an unevaluated ``x`` in two launches (distances of every pair, then derivatives of the
    active ones: less data through the launch, where arrays cross to a GPU and back) or one (all pairs);
    None: two on CUDA (with :attr:`listed` both passes in one launch). The results are the same."""

    device_hessian: bool | None = None
    """Derivatives of the known active pairs (the second launch of :attr:`two_pass`) written into a new Taichi
    ndarray that stays where the kernel ran, each potential keeping its rows as
    :class:`~sim_core.ti_kernels.buffers.DeviceRows` (the batched CG expands them there; the host reads them
    only when asked), instead of host arrays that cross to the device and back at the launch; None: on CUDA.
    The values are the same."""

    device_gradient: bool | None = None
    """A derivatives launch at positions given on the device (``x_device`` of :meth:`evaluate`) leaves the per-vertex
    gradient sums in a new Taichi ndarray where the kernel ran, each potential keeping its rows as
    :class:`~sim_core.ti_kernels.buffers.DeviceRows` (added into a device gradient there, read on the host only when
    asked), instead of copying them to the host; None: on CUDA. The values are the same."""

    listed: bool | None = None
    """Derivatives at positions not yet measured (:attr:`two_pass`'s case) in one launch whose list of active pairs
    stays on the device between its two passes (:mod:`sim_core.energies.contact.listed_kernel`: one copy back after
    it, instead of the list's read between two launches, the active rows' upload and the regions' read); None: on
    CUDA. The values are the same."""

    packed: bool | None = None
    """Every pair measured (with derivatives where asked) in one launch of :func:`_packed_kernel`, whose results come
    back in one copy (two when the active list is longer than the last one by a quarter), instead of the launches of
    :attr:`two_pass` and their copies; None: on CUDA at positions given on the host (``x_device`` None) for at most
    :data:`PACKED_MAX_PAIRS` pairs (a single environment, whose Newton matrix is assembled on the host; the kernel
    orders the active pairs in ``a^2`` comparisons). The values are the same."""

    def __init__(self, vt, ee, layout: BatchLayout | None = None, sides: np.ndarray | None = None,
                 device_sides=None, device_rows=None) -> None:
        require_backend("PairBatch")
        # the potentials hold the batch (_batch) and it holds them weakly: no reference cycle, so that a step's
        # batches, their device arrays and candidate layouts go when their potentials go (not at a full collection)
        self._pots = (weakref.ref(vt), weakref.ref(ee))
        self._parameters = [(vt.eps, vt.stiffness), (ee.eps, ee.stiffness)]  # (eps, stiffness) last read of each
        self.split = p = int(vt.vertices.shape[0])
        count = p + int(ee.vertices.shape[0])
        # the kernel's vertex indices are into ``own``, the vertices the pairs name
        if layout is None:
            own, local = compact_indices(np.concatenate([vt.vertices, ee.vertices], dtype=np.int32), dtype=np.int32)
            layout = BatchLayout(own, local, np.arange(count, dtype=np.int32), np.arange(count - p), {})
        rows = layout.rows
        if (len(rows) != count or len(layout.ee_rows) != count - p or (p and rows[p - 1] != p - 1)
                or (count > p and rows[p] < p)):
            raise ValueError(f"PairBatch: a layout of {len(rows)} rows ({len(layout.ee_rows)} edge-edge) for {p} + "
                             f"{count - p} pairs, or the vertex-triangle pairs not its first rows")
        self.own, self._layout = layout.own, layout
        self._all = rows  # launch row i (every pair) -> the pair's row of the layout
        # the sides by layout row (rows of candidates outside the batch: 0, never read)
        if sides is not None:
            if sides.shape != (layout.local.shape[0],) or sides.dtype != np.float64:
                raise ValueError(f"PairBatch: sides of shape {sides.shape} ({sides.dtype}) for a layout of "
                                 f"{layout.local.shape[0]} rows")
            self.sides = sides
        else:
            self.sides = np.zeros(layout.local.shape[0])
            self.sides[:p] = vt.sides
            self.sides[p:][layout.ee_rows] = ee.sides  # (int64 rows: no index conversion)
        self._x_own: np.ndarray | None = None  # off CUDA: the kernel's positions of ``own`` (_own_positions)
        self._device: dict = {}  # on CUDA: device copies of the pairs and device work arrays (buffers.on_device)
        if device_sides is not None and sides is not None:  # the given sides' device copy, taken as it is
            self._device["sides"] = (self.sides, device_sides, None)
        if device_rows is not None:  # the layout rows' device copy, taken as it is (buffers.on_device's entry)
            self._device["all_rows"] = (self._all, device_rows, None)
        self._device_x: tuple | None = None  # on CUDA: (positions key, device positions)
        self._own_int32: np.ndarray | None = None  # ``own`` as int32 (_own32)
        self._vertices_every: np.ndarray | None = None  # the pairs' vertices, int32 (_every_vertex)
        self._found_rows = 8192  # rows of the active list read back in the first copy (_sorted_found)
        self._launched: tuple | None = None  # (key, owner, (d, rows), parts, parameters) of the last launch (evaluate)
        self._own_copy: tuple | None = None  # (copy_of_vertex, own's copies int32) (add_copy_energies)
        vt._batch = ee._batch = self

    @property
    def vt(self):
        """The vertex-triangle potential, or None once it is gone (it holds the batch; the batch holds it weakly)."""
        return self._pots[0]()

    @property
    def ee(self):
        """The edge-edge potential, or None once it is gone."""
        return self._pots[1]()

    def _kernel_parameters(self) -> tuple[float, float, float, float]:
        """``(eps_vt, eps_ee, k_vt, k_ee)`` for a launch: each potential's own ``eps`` and ``stiffness``, read now, or
        the last read of one that is gone (its pairs' results are then not kept)."""
        for kind, pot in enumerate((self.vt, self.ee)):
            if pot is not None:
                self._parameters[kind] = (pot.eps, pot.stiffness)
        (eps_vt, k_vt), (eps_ee, k_ee) = self._parameters
        return float(eps_vt), float(eps_ee), float(k_vt), float(k_ee)

    def _device_arguments(self, x: np.ndarray, key: tuple, m: int, derivatives: bool, x_device,
                          gradient_rows: int) -> tuple:
        """On CUDA, the launch's arguments that need not cross to the device and back at every launch:
        the positions of the pairs' vertices ``x_own`` ``(u, 3)`` (once per ``key``: gathered on the device from
        ``x_device`` when given, else uploaded), pairs and sides (once per batch), the gathered pair positions (device
        only) and, with ``derivatives``, the per-vertex gradient sums; returns ``(x, vertices, sides, z, gradients)``
        device arrays (``gradients`` None without derivatives)."""
        dev, shared = self._device, _ARRAYS.device()
        z = on_device(shared, "z", _ARRAYS.rows("z", m, (4, 3)), scratch=True)
        gradients = (on_device(shared, "gradients", _ARRAYS.rows("gradients", gradient_rows, (3,)), scratch=True)
                     if derivatives else None)
        return (self._device_positions(x, key, x_device),
                self._layout.local_on_device(), on_device(dev, "sides", self.sides), z,
                gradients)

    def _device_positions(self, x: np.ndarray, key: tuple, x_device):
        """On CUDA, the positions of the pairs' vertices ``(u, 3)`` (m) in device memory, once per ``key``: gathered
        on the device from ``x_device`` when given, else uploaded from ``x``."""
        kept = self._device_x
        u = len(self.own)
        if kept is None or kept[0] != key or tuple(kept[1].shape) != (u, 3):
            xd = kept[1] if kept is not None and tuple(kept[1].shape) == (u, 3) else new_ndarray(ti.f64, (u, 3))
            if x_device is not None:
                gather_rows(x_device, on_device(self._device, "own", self._own32()), xd)
            else:
                upload(xd, np.take(x, self.own, axis=0))  # (np.take: a third of fancy indexing's time)
            kept = self._device_x = (key, xd)
        return kept[1]

    def _own32(self) -> np.ndarray:
        """``own`` as int32 ``(u,)``, made once per batch (the gather and scatter kernels' index)."""
        if self._own_int32 is None:
            self._own_int32 = self.own.astype(np.int32)
        return self._own_int32

    def evaluate(self, x: np.ndarray, derivatives: bool, key: tuple | None = None, x_device=None) -> None:
        """Evaluate both potentials at positions ``x`` ``(n, 3)`` (m) and keep each one's part as its
        evaluation of ``x``: active pairs and distances, with ``derivatives`` also their gradients
        ``(a, 12)`` and Hessians ``(a, 12, 12)``. Derivatives after both kept the distances of ``x``
        are computed for their active pairs only; a potential that already keeps an evaluation of
        ``x`` at least as complete keeps it. ``key``: :func:`~sim_core.energies.base.positions_key`
        of ``x`` when the caller has it. ``x_device``: the same positions as a Taichi float64 ndarray ``(n, 3)``
        where the caller keeps them (:class:`~sim_core.energies.base.DeviceGradient`), or None: the positions of the
        pairs' vertices are then gathered from it by a kernel (no host gather, no upload), and with
        :attr:`device_gradient` the per-vertex gradient sums stay where the kernel wrote them. The active pairs come
        from the kernel's list of them (no host pass over every pair's distance)."""
        if key is None:
            key = positions_key(x)
        packed = ((current_arch() == "cuda" and x_device is None and len(self._all) <= PACKED_MAX_PAIRS)
                  if self.packed is None else self.packed)
        if packed and len(self._all):
            self._evaluate_packed(x, key, derivatives)
            return
        pots = (self.vt, self.ee)
        kept = [None if pot is None else pot._kept(key, 0) for pot in pots]
        two_pass = current_arch() == "cuda" if self.two_pass is None else self.two_pass
        if derivatives and (kept[0] is None or kept[1] is None) and two_pass:
            # on the GPU every array argument crosses to the device and back at each launch: the
            # distances of all pairs first (no derivative arrays), then derivatives of the active ones
            if (current_arch() == "cuda" if self.listed is None else self.listed) and len(self._all):
                self._evaluate_listed(x, key, x_device)  # both in one launch, the list kept on the device
                return
            self.evaluate(x, False, key, x_device)
            kept = [None if pot is None else pot._kept(key, 0) for pot in pots]
        if derivatives and kept[0] is not None and kept[1] is not None:
            rows = np.concatenate([kept[0].active, kept[1].active + self.split])
            parts = (slice(0, len(kept[0].active)), slice(len(kept[0].active), len(rows)))
        else:
            rows, kept = self._all, [None, None]
            parts = (slice(0, self.split), slice(self.split, len(rows)))
        m = len(rows)
        on_gpu = current_arch() == "cuda"
        device_hessian = ((on_gpu if self.device_hessian is None else self.device_hessian)
                          and derivatives and kept[0] is not None and m > 0)
        device_gradient = ((on_gpu if self.device_gradient is None else self.device_gradient)
                           and derivatives and x_device is not None and m > 0)
        if m:
            arrays, sums, found, launched = self._launch(x, key, x_device, rows, derivatives, device_hessian,
                                                         device_gradient)
            self._launched = (key, _ARRAYS.device().get("launch_owner"), launched, parts, self._kernel_parameters())
        else:
            arrays, sums, found = (None, None), _ARRAYS.rows("gradients", 2 * len(self.own), (3,)), _NONE_FOUND
            sums[:] = 0.0
        self._keep(x.shape[0], key, derivatives, parts, kept, found, arrays, sums, device_hessian, device_gradient)

    def _evaluate_listed(self, x: np.ndarray, key: tuple, x_device) -> None:
        """:meth:`evaluate` with derivatives at positions ``x`` not yet measured, in one launch of
        :func:`~sim_core.energies.contact.listed_kernel.listed_derivatives` (:attr:`listed`) whose active pairs, their
        distances and regions come back in one copy (a second launch where more pairs are active than the arrays
        hold: the last list's length and a quarter), kept as :meth:`_keep` keeps the derivatives of known active
        pairs (the Hessians and the gradient sums left on the device as the second of :attr:`two_pass`'s launches
        leaves them)."""
        on_gpu = current_arch() == "cuda"
        device_hessian = on_gpu if self.device_hessian is None else self.device_hessian
        device_gradient = (on_gpu if self.device_gradient is None else self.device_gradient) and x_device is not None
        capacity = self._found_rows
        while True:
            arrays, sums, out, launched = self._listed_launch(x, key, x_device, capacity, device_hessian,
                                                              device_gradient)
            a = int(out[0])
            self._found_rows = a + a // 4 + 64  # the next list's capacity
            if a <= capacity:
                break
            capacity = self._found_rows
        listed = out[1:1 + LISTED_FIELDS * a].reshape(a, LISTED_FIELDS)
        rows, distances = listed[:, 0].astype(np.int64), listed[:, 1].copy()
        work_arrays(a)[1][:a] = listed[:, 2]  # the regions where _keep reads the launch's (by place)
        cut = int(np.searchsorted(rows, self.split))
        parts = (slice(0, cut), slice(cut, a))
        known = [None if pot is None else PairEvaluation(0, key, rows[part] - start, DistanceDerivatives(
            distances[part], None, None, np.zeros(part.stop - part.start, np.int64)), pot.eps)
            for pot, part, start in zip((self.vt, self.ee), parts, (0, self.split))]
        self._launched = (key, _ARRAYS.device().get("launch_owner"), launched, parts, self._kernel_parameters())
        self._keep(x.shape[0], key, True, parts, known, None, arrays, sums, device_hessian, device_gradient)

    def _listed_launch(self, x: np.ndarray, key: tuple, x_device, capacity: int, device_hessian: bool,
                       device_gradient: bool) -> tuple:
        """One launch of :func:`~sim_core.energies.contact.listed_kernel.listed_derivatives` over every pair at ``x``
        with room for ``capacity`` active pairs; returns ``((grad, hess), sums, out, (d, layout_rows))``: the active
        pairs' distance gradient and penalty Hessian rows by place (new ndarrays with ``device_hessian``, else the
        host's :func:`work_arrays`), the per-vertex gradient sums ``(2 u, 3)`` (a new ndarray with ``device_gradient``,
        else the host's, copied back), ``out`` on the host (its first ``1 + 3 capacity`` entries copied back) and the
        places' distances and layout rows where the launch left them (:meth:`add_copy_energies`)."""
        p, u = len(self._all), len(self.own)
        on_gpu = current_arch() == "cuda"
        shared = _ARRAYS.device()
        work = (_ARRAYS.rows("z", p, (4, 3)), _ARRAYS.rows("d", p), _ARRAYS.rows("region", p, (), np.int32),
                _ARRAYS.rows("marks", p + 1, (), np.int32), _ARRAYS.rows("chunk_total", chunk_count(p), (), np.int32),
                _ARRAYS.rows("active_count", 1, (), np.int32))
        listed = (_ARRAYS.rows("order", capacity, (), np.int32), _ARRAYS.rows("z_active", capacity, (4, 3)),
                  _ARRAYS.rows("d_active", capacity), _ARRAYS.rows("region_active", capacity, (), np.int32),
                  _ARRAYS.rows("layout_rows", capacity, (), np.int32))
        grad, hess = _ARRAYS.rows("grad", capacity, (12,)), _ARRAYS.rows("hess", capacity, (12, 12))
        gradients = _ARRAYS.rows("gradients", 2 * u, (3,))
        out = _ARRAYS.rows("listed_out", 1 + LISTED_FIELDS * capacity)
        names = ("z", "d", "region", "marks", "chunk_total", "active_count")
        work = tuple(on_device(shared, name, host, scratch=True) for name, host in zip(names, work))
        names = ("order", "z_active", "d_active", "region_active", "layout_rows")
        listed = tuple(on_device(shared, name, host, scratch=True) for name, host in zip(names, listed))
        out_arg = on_device(shared, "listed_out", out, scratch=True)
        gradients_arg = on_device(shared, "gradients", gradients, scratch=True)
        if on_gpu:
            x_arg, vertices, sides, rows = (self._device_positions(x, key, x_device), self._layout.local_on_device(),
                                            on_device(self._device, "sides", self.sides),
                                            on_device(self._device, "all_rows", self._all))
        else:
            x_arg, vertices, sides, rows = self._own_positions(x, x_device), self._layout.host_local(), self.sides, \
                self._all
        grad_arg, hess_arg = grad, hess
        if device_hessian:  # arrays no evaluation holds: an earlier evaluation's rows stay valid
            grad_arg, hess_arg = _unheld(capacity, (12,)), _unheld(capacity, (12, 12))
        if device_gradient:  # likewise: the sums stay where the kernel wrote them
            gradients_arg = _unheld(2 * u, (3,))
        _ARRAYS.device()["launch_owner"] = object()  # this launch's places now hold the work arrays (copy_energies)
        listed_derivatives(x_arg, vertices, sides, rows, p, self.split, capacity, self._kernel_parameters(), work,
                           listed, grad_arg, hess_arg, gradients_arg, out_arg)
        if out_arg is not out:
            copy_back(out, out_arg, 1 + LISTED_FIELDS * capacity)
        if not device_gradient and gradients_arg is not gradients:
            copy_back(gradients, gradients_arg, 2 * u)
        return (grad_arg, hess_arg), (gradients_arg if device_gradient else gradients), out, (listed[2], listed[4])

    def _evaluate_packed(self, x: np.ndarray, key: tuple, derivatives: bool) -> None:
        """:meth:`evaluate` of every pair at ``x`` in one launch of :func:`_packed_kernel` (:attr:`packed`), its
        packed results read back in one copy (a second one when the list is longer than guessed) and kept as each
        potential's evaluation of ``key``, as :meth:`_keep` keeps a launch over every pair."""
        p, n = len(self._all), x.shape[0]
        on_gpu = current_arch() == "cuda"
        live = self.vt if self.vt is not None else self.ee
        x_device = positions_on_device(workspace_of(live), x) if on_gpu else None
        u = len(self.own) if x_device is None else n  # the vertices of the kernel's positions and sums
        d, region, grad, hess = work_arrays(p)
        z, gradients = _ARRAYS.rows("z", p, (4, 3)), _ARRAYS.rows("gradients", 2 * u, (3,))
        slots, count = _ARRAYS.rows("slots", p, (), np.int32), _ARRAYS.rows("active_count", 1, (), np.int32)
        out = _ARRAYS.rows("packed", packed_size(p, u, derivatives))
        arrays = (z, d, region, grad, hess, gradients, slots, count, out)
        if on_gpu:  # device arrays of the kept arrays' capacity; the positions where another term holds them, else
            # uploaded once a key; the pairs and sides in this thread's arrays of the batches' capacity (the kernel
            # reads p rows; a batch is rebuilt every few iterations: one copy each, no allocation)
            device = _ARRAYS.device()
            names = ("z", "d", "region", "grad", "hess", "gradients", "slots", "active_count", "packed")
            arrays = tuple(on_device(device, name, host, scratch=True) for name, host in zip(names, arrays))
            if x_device is None:  # the lists' vertices, kept with them (as the other launches read them)
                x_arg, vertices = self._device_positions(x, key, None), self._layout.local_on_device()
            else:
                x_arg, vertices = x_device, rows_on_device(device, "packed_vertices_every", self._every_vertex())
            sides, rows_arg = (rows_on_device(device, "packed_sides", self.sides),
                               rows_on_device(device, "packed_rows", self._all))
        else:
            x_arg, vertices, sides, rows_arg = (self._own_positions(x, None), self._layout.host_local(), self.sides,
                                                self._all)
        _ARRAYS.device()["launch_owner"] = object()  # the work arrays no longer hold another launch's rows
        _packed_kernel(x_arg, vertices, sides, rows_arg, p, self.split, u, *self._kernel_parameters(),
                       int(bool(derivatives)), *arrays)
        read = min(packed_size(getattr(_ARRAYS, "packed_guess", 64), u, derivatives), out.size)
        copy_back(out, arrays[-1], read)
        a = int(out[0])
        if packed_size(a, u, derivatives) > read:
            copy_back(out, arrays[-1], packed_size(a, u, derivatives))
        _ARRAYS.packed_guess = a + a // 4 + 16  # the next read's guess (this thread's next batch too): one copy
        listed = out[1:1 + 2 * a].reshape(a, 2)
        rows, distances = listed[:, 0].astype(np.int64), listed[:, 1].copy()
        if derivatives:
            base = 1 + 2 * a
            sums = out[base:base + 6 * u].reshape(2 * u, 3)
            base += 6 * u
            regions, g, h = (out[base:base + a], out[base + a:base + 13 * a].reshape(a, 12),
                             out[base + 13 * a:base + 157 * a].reshape(a, 12, 12))
        order = 2 if derivatives else 0
        for kind, (pot, start, stop) in enumerate(((self.vt, 0, self.split), (self.ee, self.split, p))):
            if pot is None or pot._kept(key, order) is not None:
                continue
            lo, hi = np.searchsorted(rows, (start, stop))
            active, dk = rows[lo:hi] - start, distances[lo:hi]
            if derivatives:
                stiffness = float(pot.stiffness)
                dd = DistanceDerivatives(dk, g[lo:hi].copy(), None, regions[lo:hi].astype(np.int64))
                workspace_of(pot).put(pot, "evaluation", PairEvaluation(
                    order, key, active, dd, pot.eps, (stiffness, h[lo:hi].copy()),
                    (stiffness, (self.own, self._own_rows(sums[kind * u:(kind + 1) * u], x_device is not None), n))))
            else:
                dd = DistanceDerivatives(dk, None, None, np.zeros(active.shape, np.int64))
                workspace_of(pot).put(pot, "evaluation", PairEvaluation(order, key, active, dd, pot.eps))

    def _own_rows(self, sums: np.ndarray, every: bool) -> np.ndarray:
        """The rows of the pairs' vertices ``own`` ``(u, 3)``, a new array: of ``sums`` over ``every`` vertex, else
        ``sums`` itself (over ``own``)."""
        return np.take(sums, self.own, axis=0) if every else sums.copy()

    def _every_vertex(self) -> np.ndarray:
        """The layout's vertices (every row of ``local``, the pairs' at their rows) as indices of every vertex, int32,
        made once per batch (the packed kernel's where it reads the positions of every vertex)."""
        if self._vertices_every is None:
            self._vertices_every = np.take(self.own, self._layout.host_local()).astype(np.int32)
        return self._vertices_every

    def _launch(self, x: np.ndarray, key: tuple, x_device, rows: np.ndarray, derivatives: bool, device_hessian: bool,
                device_gradient: bool) -> tuple:
        """One launch of :func:`_batch_kernel` over the pairs ``rows`` (int ``(m,)``, ``m > 0``, pair indices; the
        batch's own row array :attr:`_all`: every pair, as their rows of the layout) at ``x``; the distances,
        regions and distance gradients are left in :func:`work_arrays`. Returns ``((grad, hess), sums, found)``: the
        distance gradient and Hessian rows' arrays (new ndarrays with ``device_hessian``), the per-vertex gradient sums
        ``(>= 2 u, 3)`` (a new ndarray with ``device_gradient``, else the host's kept array) and, when every pair was
        measured, the active pairs' launch rows int64 ``(a,)`` in increasing order and their distances ``(a,)`` (m),
        else None."""
        m, u = len(rows), len(self.own)
        d, region, grad, hess = work_arrays(m)
        on_gpu = current_arch() == "cuda"
        # on CUDA the regions come back with the gradient sums (one copy) when those are copied back
        pack = int(on_gpu and derivatives and not device_gradient)
        gradient_rows = 2 * u + pack * -(-m // 3)
        gradients = _ARRAYS.rows("gradients", gradient_rows, (3,))  # rows of the pairs' own vertices (and regions)
        listed, count = _ARRAYS.rows("active", m + 1, (2,)), _ARRAYS.rows("active_count", 1, (), np.int32)
        every = rows is self._all  # (kept as an array of the batch's: not copied)
        kept_rows = self._all if every else _ARRAYS.rows("pair_rows", m, (), np.int32)
        if not every:  # the pairs' rows of the layout
            np.take(self._all, rows, out=kept_rows[:m])
        if not derivatives:  # the kernel writes no derivatives: one-row stand-ins for their arrays
            grad_arg, hess_arg, gradients_arg = (_ARRAYS.rows("grad_unused", 1, (12,)),
                                                 _ARRAYS.rows("hess_unused", 1, (12, 12)),
                                                 _ARRAYS.rows("gradients_unused", 1, (3,)))
        else:
            grad_arg, hess_arg, gradients_arg = grad, hess, gradients
        d_arg, region_arg, listed_arg, count_arg = d, region, listed, count
        if on_gpu:  # device arrays of the kept arrays' capacity: the rows sent, the distances copied back
            x_arg, vertices_arg, sides_arg, z, gradients_device = self._device_arguments(x, key, m, derivatives,
                                                                                         x_device, gradient_rows)
            device = _ARRAYS.device()
            rows_arg = (on_device(self._device, "all_rows", self._all) if every  # sent once a batch
                        else on_device(device, "pair_rows", kept_rows, refresh=True, changed=True))
            d_arg, region_arg = on_device(device, "d", d, scratch=True), on_device(device, "region", region,
                                                                                    scratch=True)
            listed_arg = on_device(device, "active", listed, scratch=True)
            count_arg = on_device(device, "active_count", count, scratch=True)
            if derivatives:
                grad_arg, hess_arg, gradients_arg = grad[:m], hess[:m], gradients_device
            else:
                grad_arg, hess_arg, gradients_arg = (on_device(device, name, host, scratch=True) for name, host in
                                                     (("grad_unused", grad_arg), ("hess_unused", hess_arg),
                                                      ("gradients_unused", gradients_arg)))
        else:
            x_arg, vertices_arg, sides_arg, rows_arg = (self._own_positions(x, x_device), self._layout.host_local(),
                                                        self.sides, kept_rows)
            z = _ARRAYS.rows("z", m, (4, 3))
        if device_hessian:  # arrays no evaluation holds: an earlier evaluation's rows stay valid
            grad_arg, hess_arg = _unheld(m, (12,)), _unheld(m, (12, 12))
        if device_gradient:  # likewise: the sums stay where the kernel wrote them
            gradients_arg = _unheld(2 * u, (3,))
        _ARRAYS.device()["launch_owner"] = object()  # this launch's rows now hold the work arrays (copy_energies)
        _batch_kernel(x_arg, vertices_arg, sides_arg, rows_arg, m, self.split, *self._kernel_parameters(),
                      int(bool(derivatives)), pack, z, d_arg,
                      region_arg, grad_arg, hess_arg, gradients_arg, listed_arg, count_arg)
        if pack:  # the sums and, after them, the regions (the launch's rows) in one copy
            copy_back(gradients, gradients_arg, gradient_rows)
            region[:m] = gradients[2 * u:gradient_rows].reshape(-1)[:m]
        elif on_gpu and derivatives:  # the launch's rows only (the distances of known pairs: the host keeps them)
            copy_back(region, region_arg, m)
        found = None
        if every:
            found = _sorted_found(listed, listed_arg, self._found_rows)
            self._found_rows = len(found[0]) + len(found[0]) // 4 + 64  # the next read's guess: one copy

        return (grad_arg, hess_arg), (gradients_arg if device_gradient else gradients), found, (d_arg, rows_arg)

    def _keep(self, n: int, key: tuple, derivatives: bool, parts: tuple, kept: list, found: tuple | None, arrays,
              sums, device_hessian: bool, device_gradient: bool) -> None:
        """Each potential's part of a launch kept as its evaluation of the positions ``key`` (``n`` rows): the rows
        ``parts`` (slices of the launch's rows) of its pairs, its ``kept`` evaluation's active pairs (known) or, for
        a launch over every pair, its active pairs from ``found`` (:meth:`_launch`)."""
        _, region, grad, hess = work_arrays(0)
        u = len(self.own)
        grad_arg, hess_arg = arrays
        order = 2 if derivatives else 0
        shared: dict = {}  # the device Hessian's host copy, downloaded once for both potentials if asked
        shared_sums, shared_grad = {}, {}  # the device gradient sums' and distance gradients' host copies, likewise
        for kind, (pot, part, known) in enumerate(zip((self.vt, self.ee), parts, kept)):
            if pot is None or pot._kept(key, order) is not None:
                continue
            if known is None:  # the kernel's active rows of this kind, in order
                lo, hi = np.searchsorted(found[0], (part.start, part.stop))
                rows = found[0][lo:hi]
                active, dk = rows - part.start, found[1][lo:hi]
            else:  # the rows are the known active pairs, in order; their distances those kept (the same values)
                active, rows = known.active, part
                dk = known.distances.d
            stiffness = float(pot.stiffness)
            if derivatives:
                grad_rows = None
                if device_hessian:  # the rows are the slice ``part`` of the launch's rows; the distance gradients
                    # (read by the adjoint) stay on the device with the Hessians until asked for
                    g, h = None, DeviceRows(hess_arg, rows.start, rows.stop, shared)
                    grad_rows = DeviceRows(grad_arg, rows.start, rows.stop, shared_grad)
                else:
                    g, h = ((grad[rows].copy(), hess[rows].copy()) if known is not None  # (np.take: rows of 2-D arrays)
                            else (np.take(grad, rows, axis=0), np.take(hess, rows, axis=0)))
                summed = (DeviceRows(sums, kind * u, (kind + 1) * u, shared_sums) if device_gradient
                          else sums[kind * u:(kind + 1) * u].copy())
                dd = DistanceDerivatives(dk, g, None, region[rows].astype(np.int64))
                workspace_of(pot).put(pot, "evaluation", PairEvaluation(
                    order, key, active, dd, pot.eps, (stiffness, h), (stiffness, (self.own, summed, n)), grad_rows))
            else:
                dd = DistanceDerivatives(dk, None, None, np.zeros(active.shape, np.int64))
                workspace_of(pot).put(pot, "evaluation", PairEvaluation(order, key, active, dd, pot.eps))

    def add_copy_energies(self, pot, key: tuple, copy_of_vertex: np.ndarray, sums) -> bool:
        """Add potential ``pot``'s (one of the two) penalty energies at the positions ``key`` by copy (J,
        ``0.5 k_c (d - eps)^2`` of its pairs with ``d < eps`` into the copy of their first vertex in ``copy_of_vertex``)
        into ``sums`` (a :class:`~sim_core.ti_kernels.copy_vectors.CopySums`) from the distances this batch's last
        launch left where it ran (:func:`~sim_core.energies.contact.copy_energy_kernel.penalty_energy_by_copy`: no
        copy of the pairs to the host). False (nothing added) where that launch was not at ``key`` with ``pot``'s
        ``eps`` or its work arrays have since been taken by another launch."""
        launched = self._launched
        kind = 0 if pot is self.vt else 1
        if launched is None or launched[0] != key or launched[1] is not _ARRAYS.device().get("launch_owner"):
            return False
        (d, rows), part, (eps_vt, eps_ee, _, _) = launched[2], launched[3][kind], launched[4]
        if (eps_vt, eps_ee)[kind] != pot.eps:
            return False
        kept = self._own_copy
        if kept is None or kept[0] is not copy_of_vertex:
            kept = self._own_copy = (copy_of_vertex, np.take(copy_of_vertex, self.own).astype(np.int32))
        own_copy = rows_on_device(_ARRAYS.device(), "own_copy", kept[1])
        penalty_energy_by_copy(d, rows, self._layout.local_on_device() if current_arch() == "cuda"
                               else self._layout.host_local(), own_copy, part.start, part.stop, pot.eps,
                               pot.stiffness, sums.values)
        return True

    def add_gradient(self, gradient_device, summed: tuple) -> None:
        """Add summed gradient rows ``summed`` = ``(vertices (u,), rows, n)`` (an evaluation's,
        :meth:`~sim_core.energies.contact.reference.PairEvaluation.summed_rows`: ``rows`` ``(u, 3)`` (N) on the host
        or as :class:`~sim_core.ti_kernels.buffers.DeviceRows`) into the Taichi float64 ndarray ``gradient_device``
        ``(n, 3)`` at ``vertices``, on the device (``gradient[v] += row``: the host's ``g[vertices] += rows``)."""
        vertices, rows, _ = summed
        if not len(vertices):
            return
        if vertices is self.own:
            index = on_device(self._device, "own", self._own32())
        else:  # an evaluation another batch made (inherited: the same pairs)
            index = vertices.astype(np.int32)
        if isinstance(rows, DeviceRows):
            add_rows(gradient_device, index, rows.array, rows.start)
        else:
            add_rows(gradient_device, index, np.ascontiguousarray(rows, dtype=np.float64), 0)

    def _own_positions(self, x: np.ndarray, x_device) -> np.ndarray:
        """The positions ``(u, 3)`` (m) of the pairs' vertices ``own`` taken from ``x`` ``(n, 3)`` (or gathered by a
        kernel from ``x_device``, its Taichi ndarray, when given) into an array kept per batch (bound to the kernel
        once a batch; ``np.take`` into it: one pass, a third of fancy indexing's time on a stacked batch's
        vertices)."""
        kept = self._x_own
        if kept is None:
            kept = self._x_own = np.empty((len(self.own), 3))
        if x_device is not None:
            if len(kept):
                gather_rows(x_device, self._own32(), kept)
        else:
            np.take(x, self.own, axis=0, out=kept)
        return kept


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the kernel; runs it without and with derivatives.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    x = np.array([[0.0, 0.0, 1.0e-3], [0.0, 0.0, 0.0], [1.0e-2, 0.0, 0.0], [0.0, 1.0e-2, 0.0]])
    vt = TiVertexTriangleContact(np.array([[0, 0]]), np.array([[1, 2, 3]]), np.ones(1), 1.0, 2.0e-3)
    ee = TiEdgeEdgeContact(np.array([[0, 1]]), np.array([[0, 1], [2, 3]]), np.ones(1), 1.0, 2.0e-3)
    batch = PairBatch(vt, ee)
    for derivatives in (False, True):
        batch.evaluate(x, derivatives)
    batch.packed = True  # the packed launch too
    for derivatives in (False, True):
        batch.evaluate(x + 1e-5, derivatives)
    batch.packed, batch.two_pass, batch.listed = False, True, True  # and the listed one
    batch.evaluate(x + 2e-5, True)
    sums = CopySums(np.zeros(len(x), dtype=np.int64), 1)  # the penalties by copy from its launch
    vt.add_copy_energies_on_device(x + 2e-5, None, sums.copy_of_vertex, sums)
