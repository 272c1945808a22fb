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


def compact_indices(indices: np.ndarray | tuple[np.ndarray, ...],
                    dtype: type = np.int64, size: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The distinct values of non-negative integer ``indices`` and each index's position among them, as
    ``np.unique(indices, return_inverse=True)`` (the inverse in ``indices``' shape), from a presence mask
    of length ``max + 1`` instead of a sort: ``O(k + max)``; a stacked batch's contact pairs name a
    million vertex indices, which ``np.unique`` sorts in about 0.1 s. The positions are gathered with
    ``np.take`` from a table of ``dtype`` (int32 for a kernel's indices: half the bytes written, and no
    conversion pass after).

    ``indices`` may also be a tuple of arrays with the same trailing shape, read as their concatenation along the
    first axis (``np.concatenate(indices)``): each part's positions are gathered by its own indices into their rows
    of one array, with no concatenated copy of the indices (a gather by int32 indices first converts them to int64:
    a temporary of their size; the contact set's int64 pair vertices are gathered as they are).

    Args:
        indices: integer array of any shape, values ``>= 0``; or a tuple of such arrays, at least 1-D, with equal
            shapes after the first axis.
        dtype: the positions' integer dtype (``np.int64`` or ``np.int32``; int32 needs fewer than 2**31 values).
        size: a bound the caller knows, every index in ``[0, size)`` (a model's vertex count), or None; with it the
            presence mask has ``size`` entries and the indices are not read for their range first (an index
            ``>= size`` raises IndexError, a negative one is not detected); the same results.

    Returns:
        ``(own, local)``: ``own`` int64 ``(u,)`` sorted distinct values; ``local`` of ``dtype`` and of ``indices'``
        shape (of the concatenation's for a tuple), ``own[local] == indices``.

    Raises:
        ValueError: a negative index (without ``size``), or parts of unequal trailing shapes.
        IndexError: an index ``>= size``.
    """
    parts = tuple(np.asarray(part) for part in indices) if isinstance(indices, tuple) else (np.asarray(indices),)
    if len(parts) > 1 and any(part.ndim < 1 or part.shape[1:] != parts[0].shape[1:] for part in parts):
        raise ValueError("compact_indices: parts must be at least 1-D with equal shapes after the first axis")
    shape = ((sum(len(part) for part in parts),) + parts[0].shape[1:]) if len(parts) > 1 else parts[0].shape
    filled = [part for part in parts if part.size]
    if not filled:
        return np.zeros(0, dtype=np.int64), np.zeros(shape, dtype=dtype)
    if size is None:
        if min(int(part.min()) for part in filled) < 0:
            raise ValueError("compact_indices: indices must be >= 0")
        size = max(int(part.max()) for part in filled) + 1
    named = np.zeros(size, dtype=bool)
    for part in filled:
        named[part.ravel()] = True
    position = np.cumsum(named, dtype=dtype)
    position -= 1
    if len(parts) == 1:
        return np.flatnonzero(named), np.take(position, parts[0])
    local = np.empty(shape, dtype=dtype)
    start = 0
    for part in parts:
        np.take(position, part, out=local[start:start + len(part)])
        start += len(part)
    return np.flatnonzero(named), local


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
