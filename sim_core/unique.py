"""Sorted unique values of a 1-D array through one sort: ``np.unique``'s results, in less time.

NumPy 2.4's ``np.unique`` goes through a hash table for integer arrays and sorts afterwards; on
the 2-core VM that costs 0.3-0.5 ms for 300 int64 keys and 3-5 ms for 20,000-30,000 (a sort of the
same arrays: 4 us and 0.1-0.2 ms). The Newton loop's assembly calls it when contacts enter the
sparsity pattern (:mod:`sim_core.dynamic_slots`) and once per static pattern
(:class:`sim_core.assembly.StaticPattern`). :func:`sorted_unique` returns what ``np.unique`` does
(first occurrences through a stable sort), from a sort and a comparison of neighbours.
:func:`compact_indices` gives ``np.unique(indices, return_inverse=True)`` of non-negative integer indices
without a sort (a presence mask): the vertices a set of contact pairs names; :func:`spread_rows` puts rows
computed on those vertices back into a full array.
"""

from __future__ import annotations

import numpy as np


def sorted_unique(values: np.ndarray, return_index: bool = False, return_inverse: bool = False):
    """The sorted distinct values of ``values``, as ``np.unique(values, return_index=..., return_inverse=...)``.

    Args:
        values: 1-D array ``(k,)`` of a sortable dtype (integers, floats without NaN, or void rows).
        return_index: also return the position of the first occurrence of each distinct value.
        return_inverse: also return the position of each value among the distinct ones.

    Returns:
        ``unique`` ``(u,)``, followed by ``index`` int64 ``(u,)`` and/or ``inverse`` int64 ``(k,)`` when
        asked for (in that order), like ``np.unique``.

    Raises:
        ValueError: ``values`` is not 1-D.
    """
    values = np.asarray(values)
    if values.ndim != 1:
        raise ValueError(f"sorted_unique: values must be 1-D, got shape {values.shape}")
    if not (return_index or return_inverse):
        ordered = np.sort(values)
        return ordered[_firsts(ordered)]
    order = np.argsort(values, kind="stable")  # equal values keep their order: the first comes first
    ordered = values[order]
    first = _firsts(ordered)
    result = [ordered[first]]
    if return_index:
        result.append(order[first])
    if return_inverse:
        inverse = np.empty(values.size, dtype=np.int64)
        inverse[order] = np.cumsum(first) - 1
        result.append(inverse)
    return tuple(result)


def _firsts(ordered: np.ndarray) -> np.ndarray:
    """Which items of the sorted ``ordered`` ``(k,)`` differ from their predecessor (the first does), bool ``(k,)``."""
    first = np.empty(ordered.size, dtype=bool)
    first[:1] = True
    first[1:] = ordered[1:] != ordered[:-1]  # the operator, not the ufunc: void rows compare too
    return first


def compact_indices(indices: np.ndarray, dtype: type = np.int64) -> tuple[np.ndarray, np.ndarray]:
    """The distinct values of non-negative integer ``indices`` and each index's position among them, as
    ``np.unique(indices, return_inverse=True)`` (the inverse in ``indices``' shape), from a presence mask
    of length ``max + 1`` instead of a sort: ``O(k + max)``; a stacked batch's contact pairs name a
    million vertex indices, which ``np.unique`` sorts in about 0.1 s. The positions are gathered with
    ``np.take`` from a table of ``dtype`` (int32 for a kernel's indices: half the bytes written, and no
    conversion pass after).

    Args:
        indices: integer array of any shape, values ``>= 0``.
        dtype: the positions' integer dtype (``np.int64`` or ``np.int32``; int32 needs fewer than 2**31 values).

    Returns:
        ``(own, local)``: ``own`` int64 ``(u,)`` sorted distinct values; ``local`` of ``dtype`` and of ``indices'``
        shape, ``own[local] == indices``.

    Raises:
        ValueError: a negative index.
    """
    indices = np.asarray(indices)
    if indices.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(indices.shape, dtype=dtype)
    if indices.min() < 0:
        raise ValueError("compact_indices: indices must be >= 0")
    named = np.zeros(int(indices.max()) + 1, dtype=bool)
    named[indices.ravel()] = True
    position = np.cumsum(named, dtype=dtype)
    position -= 1
    return np.flatnonzero(named), np.take(position, indices)


def spread_rows(own: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:
    """A new ``(n, 3)`` array: ``rows`` at the positions ``own`` (:func:`compact_indices`' distinct values),
    zero elsewhere; e.g. a gradient computed on the vertices a set of contact pairs names.

    Args:
        own: int ``(u,)`` distinct row indices in ``[0, n)``.
        rows: ``(u, 3)`` values.
        n: rows of the result.

    Returns:
        float64 ``(n, 3)``.
    """
    full = np.zeros((n, 3))
    full[own] = rows
    return full
