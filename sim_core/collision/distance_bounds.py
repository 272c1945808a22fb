"""Cheap lower bounds of the contact distance: which pairs may be within ``eps`` (exact prefilter).

The penalty energy of a pair is zero unless its contact distance ``d`` (:mod:`sim_core.collision.distances`)
is below ``eps``; measuring ``d`` takes the Voronoi-region tests of every pair. These bounds leave
out pairs that are certainly farther, from a few element-wise products:

* box bound: an unsigned pair's ``d`` is the Euclidean distance between its two primitives, at least
  the largest per-axis gap between their axis-aligned bounding boxes;
* plane bound: with ``n = u x v`` the normal of the triangle (``u = b - a``, ``v = c - a``,
  ``r = p - a``) or of the two edge lines (``u = a1 - a0``, ``v = b1 - b0``, ``r = a0 - b0``),
  ``h = n.r / |n|`` is the distance to the triangle's plane (between the two lines), which no
  distance between points of the primitives is below: an unsigned pair is farther than ``|h|``. A
  signed pair has ``d = side h`` in the face / interior region and the Euclidean distance
  (``>= |h| >= side h``) elsewhere, so ``d >= side h`` always; the box bound does not hold for it
  (``d < 0`` for a vertex on the wrong side of its face at any gap).

The plane bound is used only where ``|n|^2 >= MIN_SINE_SQUARED |u|^2 |v|^2`` (round-off of ``h``
then below 1e-12 of the primitives' size); a pair counts as far when a bound exceeds
``eps (1 + RELATIVE_SLACK)``, far above the round-off of ``d``. The kept pairs are a superset of the
active ones, so the active pairs, their distances and their order are those of measuring every pair.
"""

from __future__ import annotations

from functools import reduce

import numpy as np

RELATIVE_SLACK = 1.0e-6
"""Relative margin on ``eps``: a pair is left out only when a bound exceeds ``eps (1 + RELATIVE_SLACK)``."""

MIN_SINE_SQUARED = 1.0e-6
"""The plane bound is used where the sine of the angle between ``u`` and ``v`` is at least 1e-3."""


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[:, 0] * v[:, 0] + u[:, 1] * v[:, 1] + u[:, 2] * v[:, 2]


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    nxt, prv = [1, 2, 0], [2, 0, 1]
    return u[:, nxt] * v[:, prv] - u[:, prv] * v[:, nxt]


def _may_touch(z: np.ndarray, side: np.ndarray, eps: float, first: tuple, second: tuple,
               u: np.ndarray, v: np.ndarray, r: np.ndarray) -> np.ndarray:
    limit = eps * (1.0 + RELATIVE_SLACK)
    # box gap per axis, with element-wise minima / maxima over the 1-3 vertices of each primitive
    # (NumPy's reductions over a short axis cost more than the distances they would save)
    a, b = [z[:, i] for i in first], [z[:, i] for i in second]
    gap = np.maximum(reduce(np.minimum, a) - reduce(np.maximum, b), reduce(np.minimum, b) - reduce(np.maximum, a))
    box_far = (gap[:, 0] > limit) | (gap[:, 1] > limit) | (gap[:, 2] > limit)
    n = _cross(u, v)
    nn = _dot(n, n)
    usable = nn >= MIN_SINE_SQUARED * _dot(u, u) * _dot(v, v)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(usable, _dot(n, r) / np.sqrt(nn), 0.0)
    signed = side != 0.0
    far = np.where(signed, usable & (side * h > limit), box_far | (usable & (np.abs(h) > limit)))
    return ~far


def point_triangle_may_touch(z: np.ndarray, side: np.ndarray, eps: float) -> np.ndarray:
    """Vertex-triangle pairs whose contact distance may be below ``eps`` (module docstring).

    Args:
        z: positions ``[p, a, b, c]`` of each pair, shape ``(k, 4, 3)`` (m).
        side: step side per pair, +1 / -1, or 0 for unsigned, shape ``(k,)``.
        eps: contact offset in m.

    Returns:
        bool ``(k,)``: False only for pairs with ``d > eps`` for certain.
    """
    return _may_touch(z, side, eps, (0,), (1, 2, 3), z[:, 2] - z[:, 1], z[:, 3] - z[:, 1], z[:, 0] - z[:, 1])


def edge_edge_may_touch(z: np.ndarray, side: np.ndarray, eps: float) -> np.ndarray:
    """Edge-edge pairs whose contact distance may be below ``eps`` (module docstring).

    Args:
        z: positions ``[a0, a1, b0, b1]`` of each pair, shape ``(k, 4, 3)`` (m).
        side: step side per pair, +1 / -1, or 0 for unsigned, shape ``(k,)``.
        eps: contact offset in m.

    Returns:
        bool ``(k,)``: False only for pairs with ``d > eps`` for certain.
    """
    return _may_touch(z, side, eps, (0, 1), (2, 3), z[:, 1] - z[:, 0], z[:, 3] - z[:, 2], z[:, 0] - z[:, 2])
