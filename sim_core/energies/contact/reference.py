"""Penalty contact with side memory: vertex-triangle, edge-edge and vertex-plane pairs.

Energy per pair (DESIGN.md "Contact", ThinShellLab): ``E = k_c / 2 (d - eps)^2`` for ``d < eps``,
0 otherwise (C1 at ``d = eps``), with ``k_c`` the penalty stiffness (N/m) and ``eps`` the contact
offset (m). The distance ``d`` and its region-wise definition (signed along the remembered side
in the face / interior region, unsigned elsewhere) are documented in
:mod:`sim_core.collision.distances`. Derivatives: ``grad E = k_c (d - eps) grad d`` and
``hess E = k_c (grad d grad d^T + (d - eps) hess d)``, the latter PSD-projected per pair.

The potentials take *candidate* pairs (from :mod:`sim_core.collision.candidates`); pairs with
``d >= eps`` contribute nothing, so the candidate set may be larger than the active set.
:meth:`contact_frames` gives the normal force magnitude ``lam = k_c (eps - d)``, the unit normal (the
direction of the force on the first side: the vertex, or edge a) and the barycentric weights of
the closest points, which friction (:mod:`sim_core.energies.friction.reference`) and the wrench need.

Side 0 means *unsigned*: the pair has no remembered side (it was not above the face / interior
when its step began, so the side of the plane through the triangle or of the line-line normal says
nothing about which way it came from) and ``d`` is the Euclidean distance in every region, i.e. the
side is that of the evaluated configuration itself. A side fixed per step for every pair makes the
energy one function of ``x`` within a step; a side chosen from each Newton iterate did not, and
Newton cycled (:mod:`sim_core.contact_set`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim_core.collision.distance_bounds import edge_edge_may_touch, point_triangle_may_touch
from sim_core.collision.distances import (
    DistanceDerivatives,
    EdgeEdgeRegion,
    PointTriangleRegion,
    edge_edge_closest_points,
    edge_edge_contact_distance,
    edge_edge_side,
    point_triangle_closest_point,
    point_triangle_contact_distance,
    point_triangle_side,
)
from sim_core.energies.base import (HessianBlocks, Projection, positions_key, project_psd, scatter_gradient,
                                   sum_by_copy)
from sim_core.errors import ConfigError
from sim_core.unique import spread_rows
from sim_core.workspace import workspace_of


class ContactFrames(NamedTuple):
    """Active contact pairs at one configuration, as friction and the wrench consume them.

    Attributes:
        vertices: global vertex indices per pair, shape ``(p, m)`` int64.
        weights: closest-point weights, shape ``(p, m)``: the relative position of the first side
            w.r.t. the second is ``sum_j weights[:, j] x[vertices[:, j]]`` (first side positive).
        normal: unit contact normal, direction of the force on the first side, shape ``(p, 3)``.
        lam: normal force magnitude ``k_c (eps - d)`` in N, shape ``(p,)``.
        pair_index: row of each pair in the potential's pair list, shape ``(p,)``.
    """

    vertices: np.ndarray
    weights: np.ndarray
    normal: np.ndarray
    lam: np.ndarray
    pair_index: np.ndarray


def _check_penalty(stiffness: float, eps: float, where: str) -> None:
    if not (np.isfinite(stiffness) and stiffness > 0):
        raise ConfigError(f"{where}: contact stiffness must be finite and > 0 (N/m), got {stiffness}")
    if not (np.isfinite(eps) and eps > 0):
        raise ConfigError(f"{where}: contact eps must be finite and > 0 (m), got {eps}")


def _check_sides(sides: np.ndarray, count: int, where: str, values: bool = True) -> np.ndarray:
    """``sides`` as float64 ``(count,)``; with ``values`` each checked to be +1, -1 or 0 (a pass over every pair)."""
    sides = np.asarray(sides, dtype=float).reshape(-1)
    if sides.shape[0] != count:
        raise ConfigError(f"{where}: {count} pairs but {sides.shape[0]} sides")
    # (|s| == 1 or s == 0 by comparisons only: boolean temporaries, no float64 copy of a million sides)
    if values and not np.all((sides == 1.0) | (sides == -1.0) | (sides == 0.0)):
        raise ConfigError(f"{where}: sides must be +1 or -1 (0: unsigned)")
    return sides


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def vertex_triangle_vertices(pairs: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Global vertices ``[p, a, b, c]`` ``(k, 4)`` of vertex-triangle pairs ``(vertex, triangle)`` ``(k, 2)``
    over ``triangles`` ``(t, 3)`` (``np.take`` of rows: several times faster than fancy indexing by a
    strided index column)."""
    out = np.empty((len(pairs), 4), dtype=np.result_type(pairs, triangles))  # (one array: no (k, 3) copy after)
    out[:, 0] = pairs[:, 0]
    out[:, 1:] = np.take(triangles, pairs[:, 1], axis=0)
    return out


def edge_edge_vertices(pairs: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Global vertices ``[a0, a1, b0, b1]`` ``(k, 4)`` of edge-edge pairs ``(edge, edge)`` ``(k, 2)`` over
    ``edges`` ``(e, 2)`` (one ``np.take`` of rows; fancy indexing by index columns costs ~15x more)."""
    return np.take(edges, pairs, axis=0).reshape(-1, 4)


class PairVertices:
    """The global vertices ``(p, 4)`` int64 of pairs ``(p, 2)`` over their elements, gathered from the pairs by rows
    when rows are asked for, not kept whole: a pair potential's ``vertices`` where the caller keeps the lists'
    vertices elsewhere (a contact set's candidate lists on CUDA, their int32 vertices in device memory,
    :class:`~sim_core.energies.contact.pair_lists.CandidateVertices`), so that a new list costs no host gather of
    every candidate (60 MB of int64 at 1024 Forming copies) while the potentials read the rows they use (the active
    pairs', a few per cent).

    Rows (:meth:`take`, ``np.take(v, rows, axis=0)``, ``v[rows]`` with an int or bool index array) are gathered
    from ``pairs[rows]`` by ``gather`` (:func:`vertex_triangle_vertices` or :func:`edge_edge_vertices`): the values of
    the whole gather's rows, bit for bit. Anything else (``np.asarray(v)``, ``x[v]``, slices) reads the whole array,
    gathered once and kept read-only (:attr:`whole_gathers` counts those).

    Args:
        pairs: the pairs, int ``(p, 2)`` (kept, not copied).
        elements: the triangles ``(t, 3)`` or edges ``(e, 2)`` the pairs' rows index (kept).
        gather: :func:`vertex_triangle_vertices` or :func:`edge_edge_vertices`.

    Attributes:
        pairs, elements: as given.
        shape: ``(p, 4)``; dtype: int64; ndim: 2.
        whole_gathers: how many times the whole array was gathered (0 or 1).
    """

    ndim = 2

    def __init__(self, pairs: np.ndarray, elements: np.ndarray, gather) -> None:
        self.pairs, self.elements, self._gather = pairs, elements, gather
        self.shape = (len(pairs), 4)
        self.dtype = np.result_type(pairs, elements)
        self._whole: np.ndarray | None = None
        self.whole_gathers = 0

    def __len__(self) -> int:
        return self.shape[0]

    def take(self, indices, axis=None, out=None, mode="raise") -> np.ndarray:
        """Rows ``indices`` (int ``(a,)``) along axis 0: ``gather(pairs[indices])``, a new ``(a, 4)`` array (the kept
        whole array's rows where it was made); any other axis, or ``out``, takes from the whole array."""
        if axis != 0 or out is not None:
            return np.take(np.asarray(self), indices, axis=axis, out=out, mode=mode)
        if self._whole is not None:
            return np.take(self._whole, indices, axis=0, mode=mode)
        return self._gather(np.take(self.pairs, indices, axis=0, mode=mode).reshape(-1, 2), self.elements)

    def __getitem__(self, index) -> np.ndarray:
        if isinstance(index, np.ndarray) and index.ndim == 1 and (index.dtype == bool or index.dtype.kind in "iu"):
            rows = np.flatnonzero(index) if index.dtype == bool else index
            if index.dtype == bool and len(index) != self.shape[0]:
                raise IndexError(f"PairVertices: a boolean index of {len(index)} for {self.shape[0]} rows")
            return self.take(rows, axis=0)
        return np.asarray(self)[index]

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        """The whole array (gathered once, kept read-only; a new array where ``copy`` or another ``dtype`` asks)."""
        if self._whole is None:
            self._whole = self._gather(self.pairs, self.elements)
            self._whole.flags.writeable = False
            self.whole_gathers += 1
        if copy:
            return np.array(self._whole, dtype=dtype, copy=True)
        return self._whole if dtype is None else self._whole.astype(dtype, copy=False)

    def same_as(self, other: object) -> bool:
        """Whether ``other`` is a :class:`PairVertices` of equal pairs over the same elements (the same array object)
        by the same gather: the same vertices, known without gathering them."""
        return (isinstance(other, PairVertices) and other.elements is self.elements and other._gather is self._gather
                and same_rows(other.pairs, self.pairs))


class ListRows(np.lib.mixins.NDArrayOperatorsMixin):
    """The rows ``rows`` of an array ``base`` (``base[rows]``, shape ``(len(rows),) + base.shape[1:]``), gathered by
    rows when rows are asked for, not kept whole: a contact set's edge-edge potential's pairs and step sides, which
    are the kept rows (not near-parallel) of the edge-edge candidate list and of its sides
    (:meth:`sim_core.contact_set.ContactSet._search`), where the pair batch reads the sides on the device and the
    host reads only the rows it uses (the active pairs', a few per cent): no host gather of every kept candidate (23
    MB of pairs and 11 MB of sides at 1024 Forming copies) at a step's set-up.

    Rows (:meth:`take` along axis 0, ``v[rows]`` with an int or bool index array) are ``base[rows[indices]]``: the
    values of the whole gather's rows, bit for bit. Anything else (``np.asarray(v)``, arithmetic and comparisons,
    slices, other array methods) reads the whole array, gathered once and kept read-only (:attr:`whole_gathers` counts
    those).

    Args:
        base: the array whose rows these are, ``(m, ...)`` (kept, not copied; never changed while this exists).
        rows: the rows, int ``(r,)`` in ``[0, m)`` (kept).

    Attributes:
        base_rows: ``(base, rows)`` as given.
        shape, dtype, ndim: those of ``base[rows]``.
        whole_gathers: how many times the whole array was gathered (0 or 1).
    """

    def __init__(self, base: np.ndarray, rows: np.ndarray) -> None:
        self.base_rows = (base, rows)
        self.shape = (len(rows),) + tuple(base.shape[1:])
        self.dtype = base.dtype
        self.ndim = base.ndim
        self._whole: np.ndarray | None = None
        self.whole_gathers = 0

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def size(self) -> int:
        """The number of entries (``prod(shape)``)."""
        return int(np.prod(self.shape))

    def take(self, indices, axis=None, out=None, mode="raise") -> np.ndarray:
        """Rows ``indices`` (int ``(a,)``) along axis 0 (or along the only axis): ``base[rows[indices]]``, a new
        array (the kept whole array's rows where it was made); any other axis, or ``out``, takes from the whole
        array."""
        if out is not None or not (axis == 0 or (axis is None and self.ndim == 1)):
            return np.take(np.asarray(self), indices, axis=axis, out=out, mode=mode)
        if self._whole is not None:
            return np.take(self._whole, indices, axis=0, mode=mode)
        base, rows = self.base_rows
        return np.take(base, np.take(rows, indices, mode=mode), axis=0)

    def __getitem__(self, index) -> np.ndarray:
        if isinstance(index, np.ndarray) and index.ndim == 1 and (index.dtype == bool or index.dtype.kind in "iu"):
            if index.dtype == bool and len(index) != self.shape[0]:
                raise IndexError(f"ListRows: a boolean index of {len(index)} for {self.shape[0]} rows")
            return self.take(np.flatnonzero(index) if index.dtype == bool else index, axis=0)
        return np.asarray(self)[index]

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        """The whole array (gathered once, kept read-only; a new array where ``copy`` or another ``dtype`` asks)."""
        if self._whole is None:
            base, rows = self.base_rows
            self._whole = np.take(base, rows, axis=0)
            self._whole.flags.writeable = False
            self.whole_gathers += 1
        if copy:
            return np.array(self._whole, dtype=dtype, copy=True)
        return self._whole if dtype is None else self._whole.astype(dtype, copy=False)

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        """Arithmetic and comparisons on the whole array (:meth:`__array__`)."""
        inputs = tuple(np.asarray(a) if isinstance(a, ListRows) else a for a in inputs)
        if "out" in kwargs:
            kwargs["out"] = tuple(np.asarray(a) if isinstance(a, ListRows) else a for a in kwargs["out"])
        return getattr(ufunc, method)(*inputs, **kwargs)

    def __getattr__(self, name: str):
        """Any other array attribute or method (``tolist``, ``copy``, ``min`` ...) of the whole array."""
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(np.asarray(self), name)


def same_rows(a, b) -> bool:
    """Whether two arrays (or :class:`ListRows`) are known to hold the same values: the same object; for two
    :class:`ListRows`, equal rows of equal bases (rows and bases compared, each the same object or equal arrays:
    nothing gathered; a sufficient test, False where the bases differ outside the rows); False for a :class:`ListRows`
    beside an array; else equal arrays. (False only costs a caller an evaluation made again, as
    :func:`same_vertices`.)"""

    def equal(u, v) -> bool:
        return u is v or (u.shape == v.shape and np.array_equal(u, v))

    if a is b:
        return True
    if isinstance(a, ListRows) or isinstance(b, ListRows):
        return (isinstance(a, ListRows) and isinstance(b, ListRows) and equal(a.base_rows[1], b.base_rows[1])
                and equal(a.base_rows[0], b.base_rows[0]))
    return np.shape(a) == np.shape(b) and np.array_equal(a, b)


def same_vertices(a, b) -> bool:
    """Whether two pair potentials' ``vertices`` (arrays ``(p, 4)`` or :class:`PairVertices`) are known to hold the
    same values: the same object, :meth:`PairVertices.same_as` where either is a :class:`PairVertices` (nothing
    gathered; False beside an array), else equal arrays. (False only costs a caller an evaluation made again.)"""
    if a is b:
        return True
    if isinstance(a, PairVertices):
        return a.same_as(b)
    if isinstance(b, PairVertices):
        return False
    return a.shape == b.shape and np.array_equal(a, b)


class PairEvaluation:
    """An evaluation of a pair potential kept for the positions it was made at (:meth:`_PairPenalty._evaluate`).

    Distances depend on the pairs, sides, ``eps`` and positions only, so an evaluation is shared by
    the potentials of the same function (:meth:`_PairPenalty.inherit_evaluation`); what depends on
    the stiffness (energy, gradient, penalty Hessian) is kept with the stiffness it was computed for.

    Args:
        order: 0 (distances only) or 2 (with distance gradients, and distance Hessians or penalty
            Hessian blocks).
        key: :func:`positions_key` of the positions.
        active: rows of the active pairs (``d < eps``), int64 ``(a,)``.
        dd: their distances (m) and derivatives; ``dd.hess`` None when ``hessian_blocks`` are given.
        eps: the contact offset of the evaluation (m).
        hessian_blocks: None, or ``(k_c, blocks)``: the penalty Hessians
            ``k_c (grad d grad d^T + (d - eps) hess d)`` of the active pairs for stiffness ``k_c``
            (N/m), ``(a, 12, 12)``, made with the distances (the batch kernel of
            :mod:`sim_core.energies.contact.batch_kernel`): a NumPy array, or
            :class:`~sim_core.ti_kernels.buffers.DeviceRows` kept where the kernel wrote them.
        gradient: None, or ``(k_c, g)``: the penalty gradient ``dE/dx`` for stiffness ``k_c``, summed as
            :meth:`gradient` sums it (the batch kernel): ``g`` ``(n, 3)`` (N), or ``(vertices, rows, n)``, the
            rows ``(u, 3)`` of the distinct ``vertices`` ``(u,)`` of an ``(n, 3)`` gradient zero elsewhere.
        grad_rows: None, or the distance gradients ``(a, 12)`` (1) kept where the kernel wrote them (an object with
            ``to_numpy()``, :class:`~sim_core.ti_kernels.buffers.DeviceRows`; ``dd.grad`` None then): :attr:`dd` reads
            them on the host when first asked.
    """

    __slots__ = ("order", "key", "active", "_dd", "eps", "hessian_blocks", "_vertices", "_energy", "_gradient",
                 "_grad_rows")

    def __init__(self, order: int, key: tuple, active: np.ndarray, dd: DistanceDerivatives, eps: float,
                 hessian_blocks: tuple[float, np.ndarray] | None = None,
                 gradient: tuple[float, np.ndarray] | None = None, grad_rows: object = None) -> None:
        self.order, self.key, self.active, self._dd, self.eps = order, key, active, dd, eps
        self.hessian_blocks = hessian_blocks
        self._gradient = gradient
        self._grad_rows = grad_rows
        self._vertices = self._energy = None

    @property
    def dd(self) -> DistanceDerivatives:
        """The active pairs' distances (m) and derivatives (distance gradients kept on the device read here)."""
        if self._grad_rows is not None:
            self._dd = self._dd._replace(grad=np.array(self._grad_rows.to_numpy()))
            self._grad_rows = None
        return self._dd

    @property
    def distances(self) -> DistanceDerivatives:
        """:attr:`dd` as it is kept: the distances ``d`` ``(a,)`` (m) and regions; ``grad`` None while the distance
        gradients are on the device."""
        return self._dd

    def active_vertices(self, vertices: np.ndarray) -> np.ndarray:
        """``vertices[active]`` (``vertices`` ``(p, 4)``: the potential's, the same for every potential
        sharing this evaluation), int64 ``(a, 4)``, kept."""
        if self._vertices is None:
            self._vertices = np.take(vertices, self.active, axis=0)  # (np.take: a third of fancy indexing's time)
        return self._vertices

    def holds_hessian(self, stiffness: float) -> bool:
        """Whether :meth:`penalty_hessian` can give the Hessians for ``stiffness`` (N/m)."""
        blocks = self.hessian_blocks
        return self._dd.hess is not None or (blocks is not None and blocks[0] == stiffness)

    def energy(self, stiffness: float) -> float:
        """``k_c / 2 sum (d - eps)^2`` in J (kept per stiffness ``k_c``, N/m)."""
        kept = self._energy
        if kept is None or kept[0] != stiffness:
            kept = self._energy = (stiffness, float(0.5 * stiffness * np.sum((self._dd.d - self.eps) ** 2)))
        return kept[1]

    def summed_rows(self, stiffness: float) -> tuple | None:
        """The kept gradient for ``stiffness`` (N/m) as the batch kernel summed it, ``(vertices (u,), rows, n)``:
        ``rows`` ``(u, 3)`` (N) a NumPy array or rows kept on the device (an object with ``to_numpy()``,
        :class:`~sim_core.ti_kernels.buffers.DeviceRows`); None when there is no such gradient."""
        kept = self._gradient
        if kept is not None and kept[0] == stiffness and isinstance(kept[1], tuple):
            return kept[1]
        return None

    def _host_rows(self, stiffness: float) -> tuple | None:
        """:meth:`summed_rows` with rows kept on the device read on the host (once, then kept so)."""
        summed = self.summed_rows(stiffness)
        if summed is not None and not isinstance(summed[1], np.ndarray):
            summed = (summed[0], summed[1].to_numpy(), summed[2])
            self._gradient = (stiffness, summed)
        return summed

    def gradient(self, stiffness: float, vertices: np.ndarray) -> np.ndarray:
        """``dE/dx = k_c (d - eps) grad d`` summed into a new ``(n, 3)`` array (N), ``n`` the row count
        of the positions (kept per stiffness, returned as a copy)."""
        summed = self._host_rows(stiffness)
        if summed is not None:
            return spread_rows(*summed)
        kept = self._gradient
        if kept is None or kept[0] != stiffness:
            dd = self.dd
            g = stiffness * (dd.d - self.eps)[:, None] * dd.grad
            n = self.key[0][0] if isinstance(self.key, tuple) else len(self.key.x)  # positions_key's shape
            kept = self._gradient = (stiffness, scatter_gradient(n, self.active_vertices(vertices), g))
        return kept[1].copy()

    def gradient_rows(self, stiffness: float, vertices: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """:meth:`gradient` as :meth:`~sim_core.energies.base.SparseGradient.gradient_rows` gives it: the kept
        rows of the distinct vertices where the batch kernel summed them, else ``(None, gradient)``."""
        summed = self._host_rows(stiffness)
        if summed is not None:
            return summed[0], summed[1]
        return None, self.gradient(stiffness, vertices)

    def penalty_hessian(self, stiffness: float) -> np.ndarray:
        """Blocks ``k_c (grad d grad d^T + (d - eps) hess d)`` of the active pairs, ``(a, 12, 12)``
        (J/m^2): the kept ``hessian_blocks`` when made for ``stiffness``, as a read-only view (no copy of
        what can be tens of megabytes a Newton iteration; writing into it raises), else new blocks from ``dd``.

        Raises:
            ValueError: neither is available (see :meth:`holds_hessian`).
        """
        blocks = self.hessian_blocks
        if blocks is not None and blocks[0] == stiffness:
            if not isinstance(blocks[1], np.ndarray):  # kept on the device (DeviceRows): read here
                return blocks[1].to_numpy()
            view = blocks[1].view()
            view.flags.writeable = False
            return view
        dd = self.dd
        if dd.hess is None:
            raise ValueError(f"PairEvaluation: no distance Hessians, and no penalty Hessians for stiffness {stiffness}")
        H = np.multiply(dd.grad[:, :, None], dd.grad[:, None, :])  # in place below: the same sums, fewer temporaries
        H += (dd.d - self.eps)[:, None, None] * dd.hess
        H *= stiffness
        return H


class _PairPenalty:
    """Shared penalty algebra of the 4-vertex pair potentials."""

    parameter_names: tuple[str, ...] = ("stiffness",)
    vertices: np.ndarray
    sides: np.ndarray
    stiffness: float
    eps: float

    def _distance(self, z: np.ndarray, side: np.ndarray, order: int) -> DistanceDerivatives:
        raise NotImplementedError

    _geometric_side: staticmethod
    """Side of configurations ``z`` (k, 4, 3): ``point_triangle_side`` or ``edge_edge_side``."""

    def _resolve(self, z: np.ndarray, side: np.ndarray) -> np.ndarray:
        """``side`` with the unsigned pairs (0) given the side of configuration ``z`` (k, 4, 3)."""
        unsigned = side == 0.0
        if not np.any(unsigned):
            return side
        return np.where(unsigned, self._geometric_side(z), side)

    def resolved_sides(self, x: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Side of every pair (or of the pairs ``rows``, int ``(r,)`` or bool ``(p,)``) at positions
        ``x`` (n, 3) m: the fixed side, or for an unsigned pair the side of ``x`` itself; +1 / -1,
        shape ``(p,)`` (``(r,)``)."""
        if rows is None:
            return self._resolve(x[self.vertices], self.sides)
        return self._resolve(x[self.vertices[rows]], self.sides[rows])

    def _kept(self, key: tuple, order: int) -> "PairEvaluation | None":
        """The kept evaluation if it was made at positions ``key`` (:func:`positions_key`) with this
        ``eps`` and holds derivatives up to ``order`` (order 2: with the Hessians of this stiffness,
        :meth:`PairEvaluation.holds_hessian`), else None."""
        last = workspace_of(self).get(self, "evaluation")
        if (last is not None and last.order >= order and last.eps == self.eps and last.key == key
                and (order < 2 or last.holds_hessian(self.stiffness))):
            return last
        return None

    def _evaluation(self, x: np.ndarray, order: int) -> "PairEvaluation":
        """The evaluation of positions ``x`` with distance derivatives up to ``order`` (:meth:`_evaluate`)."""
        key = positions_key(x)
        kept = self._kept(key, order)
        if kept is not None:
            return kept
        kept = self._kept(key, 0)
        if kept is not None:
            active = kept.active  # order-0 result at this x: derivatives of its active pairs only
        else:
            active, d = self._active_distances(x[self.vertices])
        if order == 0:  # (only reached without a kept evaluation, which sets d)
            dd = DistanceDerivatives(d, None, None, np.zeros(active.shape, np.int64))
        else:
            order = 2
            dd = self._distance(x[self.vertices[active]], self.sides[active], order)
        return workspace_of(self).put(self, "evaluation", PairEvaluation(order, key, active, dd, self.eps))

    def _evaluate(self, x: np.ndarray, order: int) -> tuple[np.ndarray, DistanceDerivatives]:
        """Indices of the active pairs and their distance (with derivatives up to ``order``).

        Order >= 1 computes the Hessian too (the solver asks for the gradient and then the Hessian
        at the same iterate); the last result is kept (a :class:`PairEvaluation`) and reused while
        ``x`` is bitwise equal (energy, gradient and Hessian of one iterate share one evaluation).
        """
        evaluation = self._evaluation(x, order)
        # order 0: the distances (derivatives kept on the device stay there)
        return evaluation.active, (evaluation.dd if order > 0 else evaluation.distances)

    _may_touch: staticmethod
    """Exact prefilter ``(z, side, eps) -> (k,) bool``: ``point_triangle_may_touch`` or
    ``edge_edge_may_touch`` (:mod:`sim_core.collision.distance_bounds`)."""

    def _active_distances(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the active pairs (``d < eps``) of configurations ``z`` (p, 4, 3) and their ``d`` (m).

        Measures only the pairs the prefilter :attr:`_may_touch` keeps; the result equals filtering the
        distances of every pair. Returns int64 ``(a,)`` and float ``(a,)``.
        """
        near = np.flatnonzero(self._may_touch(z, self.sides, self.eps))
        d = self._distance(z[near], self.sides[near], 0).d
        hit = d < self.eps
        return near[hit], d[hit]

    def inherit_evaluation(self, other: "_PairPenalty | None") -> None:
        """Take over ``other``'s kept evaluation (:meth:`_evaluate`) if it is the same function.

        Same class, pairs (vertex arrays), sides and eps define the same distances, so the result
        kept for some ``x`` is valid here too (still matched against ``x`` on use). The contact set
        passes the potential of the previous Newton iterate, whose last evaluation is the energy at
        the accepted line-search point, the next iterate. (Both keep their evaluations in their
        workspaces, :mod:`sim_core.workspace`.)
        """
        last = None if other is None else workspace_of(other).get(other, "evaluation")
        if (last is not None and type(other) is type(self) and other.eps == self.eps
                and same_vertices(other.vertices, self.vertices)
                and same_rows(other.sides, self.sides)):
            workspace_of(self).put(self, "evaluation", last)

    def active_distances(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the active pairs (``d < eps``) at positions ``x`` ``(n, 3)`` and their distances (m):
        int64 ``(a,)`` and float ``(a,)`` (the kept evaluation of ``x`` when there is one)."""
        active, dd = self._evaluate(x, 0)
        return active, dd.d

    def keep_derivatives(self, x: np.ndarray) -> None:
        """Evaluate the pairs at positions ``x`` ``(n, 3)`` with distance derivatives and keep the result
        (:meth:`_evaluate`): the energy, gradient and Hessian at ``x`` then reuse it. The solver calls
        this at a line search's first trial point, which once accepted is the next Newton iterate. Distance
        gradients kept on the device stay there (:attr:`PairEvaluation.dd` reads them when asked)."""
        self._evaluation(x, 2)

    def distance(self, x: np.ndarray) -> np.ndarray:
        """Contact distance ``d`` of every pair in m, shape ``(p,)``."""
        return self._distance(x[self.vertices], self.sides, 0).d

    def active_vertices(self, x: np.ndarray) -> np.ndarray:
        """``vertices[active_mask(x)]``: the vertices of the pairs with ``d < eps`` at ``x`` ``(n, 3)``, int
        ``(a, 4)``, kept with the evaluation of ``x`` (read only)."""
        return self._evaluation(x, 0).active_vertices(self.vertices)

    def active_mask(self, x: np.ndarray) -> np.ndarray:
        """Pairs with ``d < eps``, bool shape ``(p,)``."""
        mask = np.zeros(self.vertices.shape[0], dtype=bool)
        mask[self._evaluate(x, 0)[0]] = True  # the kept evaluation of x when there is one
        return mask

    def energy(self, x: np.ndarray) -> float:
        """Penalty energy in J."""
        return self._evaluation(x, 0).energy(self.stiffness)

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each active pair's first vertex, J ``(copy_count,)`` (capability
        :class:`~sim_core.energies.base.CopyEnergies`; the kept evaluation of ``x`` when there is one). The active
        pairs' first vertices from the evaluation's kept rows of them (:meth:`PairEvaluation.active_vertices`, which
        the Hessian at ``x`` reads too), not a ``np.take`` of the strided column ``vertices[:, 0]``: that copies the
        whole column first (10 ms at 4 million candidate pairs against 0.4 ms for 20,000 active rows)."""
        evaluation = self._evaluation(x, 0)
        gap = evaluation.distances.d - evaluation.eps
        first = evaluation.active_vertices(self.vertices)[:, 0]
        return 0.5 * self.stiffness * sum_by_copy(copy_of_vertex, first, gap * gap, copy_count)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``."""
        return self._evaluation(x, 1).gradient(self.stiffness, self.vertices)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Blocks ``k_c (grad d grad d^T + (d - eps) hess d)`` of the active pairs, ``(a, 12, 12)``,
        projected by ``projection``."""
        return self._pair_hessian(x, projection, None)

    def hessian_of_vertices(self, x: np.ndarray, projection: Projection, vertices: np.ndarray) -> HessianBlocks:
        """:meth:`hessian`'s blocks of the active pairs whose first vertex is marked in ``vertices`` (bool
        ``(n,)``; for a mask closed under the pairs, as a stacked scene's copies: the pairs of the marked
        vertices), so that only those are projected (capability :class:`~sim_core.energies.base.SubsetHessian`)."""
        return self._pair_hessian(x, projection, vertices)

    def _pair_hessian(self, x: np.ndarray, projection: Projection, vertices: np.ndarray | None) -> HessianBlocks:
        evaluation = self._evaluation(x, 2)
        if evaluation.active.size == 0:
            return HessianBlocks.empty(4)
        H = evaluation.penalty_hessian(self.stiffness)
        pair_vertices = evaluation.active_vertices(self.vertices)
        if vertices is not None:
            rows = np.flatnonzero(np.asarray(vertices)[pair_vertices[:, 0]])
            pair_vertices, H = np.take(pair_vertices, rows, axis=0), np.take(H, rows, axis=0)
        return HessianBlocks(pair_vertices, project_psd(H, projection))

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d(stiffness) = ``(d - eps) grad d`` in m, shape ``(n, 3)``."""
        if name != "stiffness":
            raise KeyError(name)
        active, dd = self._evaluate(x, 1)
        return scatter_gradient(x.shape[0], self.vertices[active], (dd.d - self.eps)[:, None] * dd.grad)


class VertexTriangleContact(_PairPenalty):
    """Penalty between vertices and triangles, normal oriented by the remembered side.

    Args:
        pairs: ``[global vertex, row of triangles]``, shape ``(p, 2)``.
        triangles: global vertex indices, shape ``(t, 3)``.
        sides: side of each vertex w.r.t. its triangle's normal ``(b - a) x (c - a)`` remembered
            when the pair became active (+1 / -1; 0: unsigned, module docstring), shape ``(p,)``.
        stiffness: k_c in N/m (> 0).
        eps: contact offset in m (> 0).
        vertices: the pairs' global vertices ``(p, 4)`` as :func:`vertex_triangle_vertices` gives them, when the
            caller has them (a contact set's candidate lists: once per search), else computed here.
        checked: the pairs' triangle rows and the sides' values are known good (a contact set's candidate lists and
            its step sides, made from the side codes: valid by construction): the passes over every pair that check
            them are not made (the shapes still are).

    Raises:
        ConfigError: bad stiffness, eps, sides or shapes.
    """

    def __init__(self, pairs: np.ndarray, triangles: np.ndarray, sides: np.ndarray, stiffness: float, eps: float,
                 vertices: np.ndarray | None = None, checked: bool = False):
        where = "VertexTriangleContact"
        _check_penalty(stiffness, eps, where)
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        if not checked and pairs.size and (pairs[:, 1].min() < 0 or pairs[:, 1].max() >= triangles.shape[0]):
            raise ConfigError(f"{where}: triangle index out of range [0, {triangles.shape[0]})")
        self.pairs = pairs
        self.sides = _check_sides(sides, pairs.shape[0], where, values=not checked)
        if vertices is None:
            vertices = vertex_triangle_vertices(pairs, triangles)
        elif np.shape(vertices) != (pairs.shape[0], 4):
            raise ConfigError(f"{where}: {pairs.shape[0]} pairs but vertices of shape {np.shape(vertices)}")
        self.vertices = vertices
        self.stiffness = float(stiffness)
        self.eps = float(eps)

    def _distance(self, z: np.ndarray, side: np.ndarray, order: int) -> DistanceDerivatives:
        return point_triangle_contact_distance(z, self._resolve(z, side), order)

    _geometric_side = staticmethod(point_triangle_side)
    _may_touch = staticmethod(point_triangle_may_touch)

    def contact_frames(self, x: np.ndarray) -> ContactFrames:
        """Normal force, normal and closest-point weights of the active pairs (module docstring)."""
        act, dd = self._evaluate(x, 0)  # the kept evaluation of x when there is one
        d = dd.d
        z = x[self.vertices[act]]
        bary, region = point_triangle_closest_point(z[:, 0], z[:, 1], z[:, 2], z[:, 3])
        q = np.einsum("kj,kjd->kd", bary, z[:, 1:])
        face = region == PointTriangleRegion.FACE
        normal = np.zeros((act.size, 3))
        if np.any(~face):
            normal[~face] = _unit(z[~face, 0] - q[~face])
        if np.any(face):
            n = np.cross(z[face, 2] - z[face, 1], z[face, 3] - z[face, 1])
            normal[face] = self._resolve(z[face], self.sides[act][face])[:, None] * _unit(n)
        weights = np.concatenate([np.ones((act.size, 1)), -bary], axis=1)
        lam = self.stiffness * (self.eps - d)
        return ContactFrames(self.vertices[act], weights, normal, lam, act)


class EdgeEdgeContact(_PairPenalty):
    """Penalty between edges, normal oriented by the remembered side where it is defined.

    Args:
        pairs: ``[row i of edges, row j of edges]``, shape ``(p, 2)``.
        edges: global vertex indices, shape ``(e, 2)``.
        sides: remembered sign of ``((a1 - a0) x (b1 - b0)).(a0 - b0)`` (+1 / -1; 0: unsigned,
            module docstring), shape ``(p,)``.
        stiffness: k_c in N/m (> 0).
        eps: contact offset in m (> 0).
        vertices: the pairs' global vertices ``(p, 4)`` as :func:`edge_edge_vertices` gives them, when the
            caller has them (a contact set's candidate lists: once per search), else computed here.
        checked: the pairs' edge rows and the sides' values are known good (as for
            :class:`VertexTriangleContact`): not checked again; with ``checked``, ``pairs`` (int64) and ``sides``
            (float64) may be :class:`ListRows` (rows of a candidate list and of its sides), kept as they are and
            gathered by rows where read.

    Raises:
        ConfigError: bad stiffness, eps, sides or shapes.
    """

    def __init__(self, pairs: np.ndarray, edges: np.ndarray, sides: np.ndarray, stiffness: float, eps: float,
                 vertices: np.ndarray | None = None, checked: bool = False):
        where = "EdgeEdgeContact"
        _check_penalty(stiffness, eps, where)
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        if checked and isinstance(pairs, ListRows):  # rows of a checked list: gathered where read
            if pairs.dtype != np.int64 or pairs.ndim != 2 or pairs.shape[1:] != (2,):
                raise ConfigError(f"{where}: pairs of shape {pairs.shape} ({pairs.dtype}), want int64 (p, 2)")
        else:
            pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if not checked and pairs.size and (pairs.min() < 0 or pairs.max() >= edges.shape[0]):
            raise ConfigError(f"{where}: edge index out of range [0, {edges.shape[0]})")
        self.pairs = pairs
        if checked and isinstance(sides, ListRows):
            if sides.dtype != np.float64 or sides.shape != (pairs.shape[0],):
                raise ConfigError(f"{where}: {pairs.shape[0]} pairs but sides of shape {sides.shape} ({sides.dtype})")
            self.sides = sides
        else:
            self.sides = _check_sides(sides, pairs.shape[0], where, values=not checked)
        if vertices is None:
            vertices = edge_edge_vertices(pairs, edges)
        elif np.shape(vertices) != (pairs.shape[0], 4):
            raise ConfigError(f"{where}: {pairs.shape[0]} pairs but vertices of shape {np.shape(vertices)}")
        self.vertices = vertices
        self.stiffness = float(stiffness)
        self.eps = float(eps)

    def _distance(self, z: np.ndarray, side: np.ndarray, order: int) -> DistanceDerivatives:
        return edge_edge_contact_distance(z, self._resolve(z, side), order)

    _geometric_side = staticmethod(edge_edge_side)
    _may_touch = staticmethod(edge_edge_may_touch)

    def contact_frames(self, x: np.ndarray) -> ContactFrames:
        """Normal force, normal and closest-point weights of the active pairs (module docstring)."""
        act, dd = self._evaluate(x, 0)  # the kept evaluation of x when there is one
        d = dd.d
        z = x[self.vertices[act]]
        s, t, region = edge_edge_closest_points(z[:, 0], z[:, 1], z[:, 2], z[:, 3])
        weights = np.stack([1 - s, s, -(1 - t), -t], axis=1)
        rel = np.einsum("kj,kjd->kd", weights, z)
        interior = region == EdgeEdgeRegion.INTERIOR
        normal = np.zeros((act.size, 3))
        if np.any(~interior):
            normal[~interior] = _unit(rel[~interior])
        if np.any(interior):
            n = np.cross(z[interior, 1] - z[interior, 0], z[interior, 3] - z[interior, 2])
            normal[interior] = self._resolve(z[interior], self.sides[act][interior])[:, None] * _unit(n)
        lam = self.stiffness * (self.eps - d)
        return ContactFrames(self.vertices[act], weights, normal, lam, act)


class PlaneContact:
    """Penalty between vertices and a fixed plane ``normal . x = offset`` (e.g. a table z = h).

    ``d = normal . x_i - offset`` (signed; the plane's free side is along ``normal``),
    ``E = k_c / 2 (d - eps)^2`` for ``d < eps``; the force on a vertex is ``k_c (eps - d) normal``.

    Args:
        vertices: global vertex indices, shape ``(v,)``.
        normal: plane normal, shape ``(3,)`` (normalised here; must be non-zero).
        offset: plane offset in m.
        stiffness: k_c in N/m (> 0).
        eps: contact offset in m (> 0).

    Raises:
        ConfigError: zero/non-finite normal, bad stiffness or eps.
    """

    parameter_names: tuple[str, ...] = ("stiffness",)

    def __init__(self, vertices: np.ndarray, normal: np.ndarray, offset: float, stiffness: float, eps: float):
        _check_penalty(stiffness, eps, "PlaneContact")
        normal = np.asarray(normal, dtype=float).reshape(3)
        length = float(np.linalg.norm(normal))
        if not (np.isfinite(length) and length > 0):
            raise ConfigError(f"PlaneContact: normal must be finite and non-zero, got {normal.tolist()}")
        if not np.isfinite(offset):
            raise ConfigError(f"PlaneContact: offset must be finite, got {offset}")
        self.vertices = np.asarray(vertices, dtype=np.int64).reshape(-1)
        self.normal = normal / length
        self.offset = float(offset)
        self.stiffness = float(stiffness)
        self.eps = float(eps)

    def distance(self, x: np.ndarray) -> np.ndarray:
        """Signed distance ``n . x - offset`` of every vertex in m, shape ``(v,)``."""
        return x[self.vertices] @ self.normal - self.offset

    def active_mask(self, x: np.ndarray) -> np.ndarray:
        """Vertices with ``d < eps``, bool shape ``(v,)``."""
        return self.distance(x) < self.eps

    def energy(self, x: np.ndarray) -> float:
        """Penalty energy in J."""
        gap = np.minimum(self.distance(x) - self.eps, 0.0)
        return float(0.5 * self.stiffness * np.sum(gap * gap))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each vertex, J ``(copy_count,)`` (capability
        :class:`~sim_core.energies.base.CopyEnergies`)."""
        gap = np.minimum(self.distance(x) - self.eps, 0.0)
        return 0.5 * self.stiffness * sum_by_copy(copy_of_vertex, self.vertices, gap * gap, copy_count)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """``k_c (d - eps) n`` on active vertices, N, shape ``(n, 3)``."""
        gap = np.minimum(self.distance(x) - self.eps, 0.0)
        g = np.zeros_like(x, dtype=float)
        np.add.at(g, self.vertices, self.stiffness * gap[:, None] * self.normal[None, :])
        return g

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Blocks ``k_c n n^T`` (PSD) of the active vertices, shape ``(a, 3, 3)``."""
        act = np.flatnonzero(self.active_mask(x))
        blocks = np.broadcast_to(self.stiffness * np.outer(self.normal, self.normal), (act.size, 3, 3)).copy()
        return HessianBlocks(self.vertices[act][:, None], blocks)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d(stiffness) = ``(d - eps) n`` on active vertices, m, shape ``(n, 3)``."""
        if name != "stiffness":
            raise KeyError(name)
        return self.gradient(x) / self.stiffness

    def contact_frames(self, x: np.ndarray) -> ContactFrames:
        """Normal force ``k_c (eps - d)``, the plane normal and unit weights of the active vertices."""
        d = self.distance(x)
        act = np.flatnonzero(d < self.eps)
        normal = np.broadcast_to(self.normal, (act.size, 3)).copy()
        lam = self.stiffness * (self.eps - d[act])
        return ContactFrames(self.vertices[act][:, None], np.ones((act.size, 1)), normal, lam, act)


def concatenate_frames(frames: list[ContactFrames], width: int = 4) -> ContactFrames:
    """Stack frames of several pair kinds, padding to ``width`` vertices with zero weights.

    Padding repeats the pair's first vertex with weight 0, which adds nothing to any sum.
    ``pair_index`` is kept per kind (not unique across kinds).
    """
    vs, ws = [], []
    for f in frames:
        pad = width - f.vertices.shape[1]
        vs.append(np.concatenate([f.vertices, np.repeat(f.vertices[:, :1], pad, axis=1)], axis=1))
        ws.append(np.concatenate([f.weights, np.zeros((f.weights.shape[0], pad))], axis=1))
    if not frames:
        return ContactFrames(
            np.zeros((0, width), np.int64), np.zeros((0, width)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
        )
    return ContactFrames(
        np.concatenate(vs).astype(np.int64),
        np.concatenate(ws),
        np.concatenate([f.normal for f in frames]),
        np.concatenate([f.lam for f in frames]),
        np.concatenate([f.pair_index for f in frames]).astype(np.int64),
    )
