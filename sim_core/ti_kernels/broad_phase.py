"""Broad phase in one Taichi kernel: pairs of inflated boxes that overlap, by a sweep along one axis.

The Taichi twin of :func:`sim_core.collision.candidates._grouped_box_pairs` (k-d trees per pair of
bodies, the reference and test oracle): the same pairs, found by sort and sweep (Baraff 1992;
Ericson, *Real-Time Collision Detection*, 2005, sec. 7.5.2). Boxes of set B are sorted by their
lower bound on the sweep axis (of the three, the one that leaves the fewest boxes to scan); for each box
``a`` of set A the boxes ``b`` whose lower bound lies in

    [a_lo - radius - w_max - slack,  a_hi + radius + slack]      (sweep axis; w_max = widest B box)

contain every ``b`` that can overlap ``a`` (found with ``searchsorted``; ``slack`` keeps rounding
from narrowing the range); within one set, a pair is scanned once, from the box that comes first in
the sweep order (the other lies in its range). The kernel scans these ranges and keeps the pairs of allowed bodies that
pass the reference's exact inflated-box test, evaluated with the same floating-point operations per
axis,

    a_lo - radius <= b_hi  and  b_lo <= a_hi + radius,

with ``a`` on the same side as in the reference (within one set: the box of the lower body, then
of the lower index). The kept pairs are therefore exactly the reference's, in another order; the
callers sort them (:func:`sim_core.collision.candidates.vertex_triangle_candidates`).

Loops run serially on the CPU (pairs in scan order), in parallel on CUDA (order of the atomic
counter); the output buffer grows and the kernel runs again when it was too small.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

from typing import NamedTuple

import numpy as np

from sim_core.errors import ConfigError
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.launch import fast_kernel

_F64_2, _I32_1, _I32_2 = linalg.F64_2, linalg.I32_1, linalg.I32_2


@fast_kernel
def _sweep_pairs(a_lo: _F64_2, a_hi: _F64_2, a_body: _I32_1, sorted_lo: _F64_2, sorted_hi: _F64_2,
                 sorted_body: _I32_1, b_order: _I32_1, start: _I32_1, stop: _I32_1, allowed: _I32_2, radius: ti.f64,
                 same: ti.i32, out: _I32_2, count: _I32_1):
    """``count[0]`` (set to 0 by the caller) += the number of overlapping allowed pairs; the first
    ``out.shape[0]`` of them in ``out`` as ``[index in A, index in B]``. ``sorted_*``: B's boxes in
    sweep order, ``b_order``: their indices in B."""
    capacity = out.shape[0]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(a_lo.shape[0]):
        lo_i, hi_i = linalg.row3(a_lo, i), linalg.row3(a_hi, i)
        body_i = a_body[i]
        for s in range(start[i], stop[i]):
            j = b_order[s]
            body_j = sorted_body[s]
            # within one set, the reference's side: the box of the lower body, then of the lower index
            swap = same != 0 and (body_j < body_i or (body_j == body_i and j < i))
            keep = False
            if swap:
                keep = allowed[body_j, body_i] != 0
                for d in ti.static(range(3)):
                    keep = keep and (sorted_lo[s, d] - radius <= hi_i[d]) and (lo_i[d] <= sorted_hi[s, d] + radius)
            else:
                keep = allowed[body_i, body_j] != 0
                for d in ti.static(range(3)):
                    keep = keep and (lo_i[d] - radius <= sorted_hi[s, d]) and (sorted_lo[s, d] <= hi_i[d] + radius)
            if keep:
                k = ti.atomic_add(count[0], 1)
                if k < capacity:
                    if swap:
                        out[k, 0] = j
                        out[k, 1] = i
                    else:
                        out[k, 0] = i
                        out[k, 1] = j


def grouped_box_pairs(
    a_min: np.ndarray, a_max: np.ndarray, a_body: np.ndarray,
    b_min: np.ndarray | None, b_max: np.ndarray | None, b_body: np.ndarray | None,
    radius: float, allowed: np.ndarray,
) -> np.ndarray:
    """The pairs of :func:`sim_core.collision.candidates._grouped_box_pairs`, by a sweep (module docstring).

    Args:
        a_min, a_max, a_body: boxes of set A ``(ka, 3)`` in m and the body of each ``(ka,)``.
        b_min, b_max, b_body: the same for set B, or None to pair A with itself (each unordered pair
            once, as ``[i, j]`` with ``i < j``).
        radius: inflation in m.
        allowed: ``(bodies, bodies)`` bool, symmetric.

    Returns:
        int64 ``(p, 2)`` of ``[index in A, index in B]``, rows unsorted (same set as the reference).

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    return _sweep(a_min, a_max, a_body, b_min, b_max, b_body, radius, allowed, (0, 1, 2))[0]


class SweepSearch:
    """:func:`grouped_box_pairs` that keeps the sweep axis of its searches (same pairs, cheaper set-up).

    Choosing the axis sorts the boxes along all three and counts the boxes each leaves to scan (3
    argsorts and 6 ``searchsorted``); between two steps' searches the boxes barely move, so the axis
    chosen by one search stays good for the next. A search of a kind (A vs B or A with itself, of
    given sizes) sweeps along the axis its last choice found, and chooses again among all three every
    ``refresh``-th search of that kind. Any axis gives the same pairs (module docstring), so the
    result is :func:`grouped_box_pairs`'s.

    Args:
        refresh: searches of one kind per choice of the axis (>= 1; 1 chooses every time).

    Raises:
        ConfigError: ``refresh`` < 1.
    """

    def __init__(self, refresh: int = 8) -> None:
        if int(refresh) < 1:
            raise ConfigError(f"SweepSearch: refresh must be >= 1, got {refresh}")
        self.refresh = int(refresh)
        self.axes: dict[tuple, tuple[int, int]] = {}  # kind -> (axis, searches since it was chosen)

    def __call__(self, a_min: np.ndarray, a_max: np.ndarray, a_body: np.ndarray, b_min: np.ndarray | None,
                 b_max: np.ndarray | None, b_body: np.ndarray | None, radius: float, allowed: np.ndarray) -> np.ndarray:
        """As :func:`grouped_box_pairs` (same arguments, result and errors)."""
        plan = self.plan(a_min, a_max, a_body, b_min, b_max, b_body, radius)
        return np.zeros((0, 2), dtype=np.int64) if plan is None else _launch(plan, allowed, radius)

    def plan(self, a_min: np.ndarray, a_max: np.ndarray, a_body: np.ndarray, b_min: np.ndarray | None,
             b_max: np.ndarray | None, b_body: np.ndarray | None, radius: float) -> "SweepPlan | None":
        """The :class:`SweepPlan` of a search (arguments as :func:`grouped_box_pairs`), along the kind's
        kept axis (chosen again every ``refresh``-th search); None when a set is empty."""
        kind = (b_min is None, len(a_min), -1 if b_min is None else len(b_min))
        axis, uses = self.axes.get(kind, (None, 0))
        candidates = (0, 1, 2) if axis is None or uses >= self.refresh else (axis,)
        plan = _plan(a_min, a_max, a_body, b_min, b_max, b_body, radius, candidates)
        if plan is not None:
            self.axes[kind] = (plan.axis, 1 if len(candidates) > 1 else uses + 1)
        return plan


class SweepPlan(NamedTuple):
    """The kernel arrays of one sweep (:func:`_plan`): A's boxes and bodies, B's boxes and bodies in
    sweep order with their indices in B (``order``), the scan range ``[start, stop)`` of each A box,
    whether A is paired with itself, and the sweep axis."""

    a_lo: np.ndarray
    a_hi: np.ndarray
    a_body: np.ndarray
    sorted_lo: np.ndarray
    sorted_hi: np.ndarray
    sorted_body: np.ndarray
    order: np.ndarray
    start: np.ndarray
    stop: np.ndarray
    same: bool
    axis: int


def _plan(
    a_min: np.ndarray, a_max: np.ndarray, a_body: np.ndarray,
    b_min: np.ndarray | None, b_max: np.ndarray | None, b_body: np.ndarray | None,
    radius: float, axes: tuple[int, ...],
) -> SweepPlan | None:
    """The sweep of :func:`grouped_box_pairs` (arguments as there) along the one of ``axes`` that
    leaves the fewest boxes to scan; None when a set is empty."""
    require_backend("broad-phase sweep kernel")
    same = b_min is None
    a_lo = np.ascontiguousarray(a_min, dtype=np.float64)
    a_hi = np.ascontiguousarray(a_max, dtype=np.float64)
    a_body = np.ascontiguousarray(a_body, dtype=np.int32)
    if same:
        b_lo, b_hi, b_body = a_lo, a_hi, a_body
    else:
        b_lo = np.ascontiguousarray(b_min, dtype=np.float64)
        b_hi = np.ascontiguousarray(b_max, dtype=np.float64)
        b_body = np.ascontiguousarray(b_body, dtype=np.int32)
    if a_lo.shape[0] == 0 or b_lo.shape[0] == 0:
        return None
    scale = max(float(np.max(np.abs(a_lo))), float(np.max(np.abs(a_hi))), float(np.max(np.abs(b_lo))),
                float(np.max(np.abs(b_hi))), float(radius))
    best = None
    for axis in axes:  # sweep along the axis with the fewest boxes to scan
        key = b_lo[:, axis]
        order = np.argsort(key, kind="stable")
        key = key[order]
        width = float(np.max(b_hi[:, axis] - b_lo[:, axis]))
        slack = 1e-9 * (scale + width)
        start = np.searchsorted(key, a_lo[:, axis] - radius - width - slack, side="left")
        stop = np.searchsorted(key, a_hi[:, axis] + radius + slack, side="right")
        if same:  # each unordered pair once: from the box that comes first in the sweep order
            position = np.empty_like(order)
            position[order] = np.arange(order.size)
            start = np.maximum(start, position + 1)
        scanned = int(np.sum(np.maximum(stop - start, 0))) if len(axes) > 1 else 0
        if best is None or scanned < best[0]:
            best = (scanned, order, start, stop, axis)
    _, order, start, stop, axis = best
    return SweepPlan(a_lo, a_hi, a_body, np.ascontiguousarray(b_lo[order]), np.ascontiguousarray(b_hi[order]),
                     np.ascontiguousarray(b_body[order]), order.astype(np.int32), start.astype(np.int32),
                     stop.astype(np.int32), same, axis)


def _launch(plan: SweepPlan, allowed: np.ndarray, radius: float) -> np.ndarray:
    """The pairs of ``plan`` (:func:`_sweep_pairs`; the output buffer grows until they fit)."""
    allowed_i = np.ascontiguousarray(allowed, dtype=np.int32)
    out = np.empty((max(1024, 4 * (plan.a_lo.shape[0] + plan.order.shape[0])), 2), dtype=np.int32)
    count = np.zeros(1, dtype=np.int32)
    while True:
        _sweep_pairs(plan.a_lo, plan.a_hi, plan.a_body, plan.sorted_lo, plan.sorted_hi, plan.sorted_body,
                     plan.order, plan.start, plan.stop, allowed_i, float(radius), int(plan.same), out, count)
        found = int(count[0])
        if found <= out.shape[0]:
            pairs = out[:found].astype(np.int64)
            return np.sort(pairs, axis=1) if plan.same else pairs
        out = np.empty((found, 2), dtype=np.int32)
        count[0] = 0


def _sweep(
    a_min: np.ndarray, a_max: np.ndarray, a_body: np.ndarray,
    b_min: np.ndarray | None, b_max: np.ndarray | None, b_body: np.ndarray | None,
    radius: float, allowed: np.ndarray, axes: tuple[int, ...],
) -> tuple[np.ndarray, int | None]:
    """``(pairs, axis)``: the pairs of :func:`grouped_box_pairs`, swept along the one of ``axes``
    that leaves the fewest boxes to scan (None when a set is empty); arguments as there."""
    plan = _plan(a_min, a_max, a_body, b_min, b_max, b_body, radius, axes)
    if plan is None:
        return np.zeros((0, 2), dtype=np.int64), None
    return _launch(plan, allowed, radius), plan.axis


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the sweep kernel on two boxes.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    lo = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    grouped_box_pairs(lo, lo + 1.0, np.zeros(2, np.int32), None, None, None, 0.1, np.ones((1, 1), bool))
