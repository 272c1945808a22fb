"""The lockstep solver's iterates and their stacked gradient, kept cheap for the host: an iterate is a read-only
array of its own (the terms' caches key it by identity, :func:`~sim_core.energies.base.positions_key`, instead of
reading its bytes: 28 ms a Newton iteration at 1024 Forming copies on the H200 host, docs/benchmarks_log.md,
session 40, 28lock), and the gradient sums the sparse terms' rows where they are (:func:`summed_gradient`)."""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import SparseGradient, declares


def summed_gradient(terms: list, x: np.ndarray, fresh_first: bool = False) -> np.ndarray:
    """The sum of the ``terms``' gradients at ``x`` ``(N, 3)``, in term order, as a new ``(3 N,)`` array (J/m): the
    first two dense gradients summed into it (the terms' kept gradients are left as they are), each further term's
    added into it, the rows of a term declaring :class:`~sim_core.energies.base.SparseGradient` at its vertices only
    (no ``(N, 3)`` array a term; the same sums: the other entries would add 0). ``fresh_first``: the first term's
    gradient is a new float64 array of each call (:class:`~sim_core.batch.lumped.LumpedQuadratic`), so the sum is
    accumulated into it (one stacked array fewer; the same sums)."""
    g, owned = None, False  # the sum so far; owned: an array of this function's (else a term's, not written)
    if fresh_first and terms:
        g, owned = terms[0].gradient(x).reshape(-1), True
        terms = terms[1:]
    for p in terms:
        vertices, rows = p.gradient_rows(x) if declares(p, SparseGradient) else (None, p.gradient(x))
        if vertices is None:
            rows = rows.reshape(-1)
            if g is None:
                g = rows
            elif owned:
                g += rows
            else:
                g, owned = np.add(g, rows, dtype=np.float64), True
        else:
            if not owned:
                g, owned = (np.zeros(3 * len(x)) if g is None else np.array(g, dtype=np.float64)), True
            g.reshape(-1, 3)[vertices] += rows
    if g is None:
        return np.zeros(3 * len(x))
    return g if owned else np.array(g, dtype=np.float64)


def frozen(x: np.ndarray) -> np.ndarray:
    """``x``, a new positions array ``(N, 3)`` that owns its memory, made read-only for good: the terms' caches then
    key it by identity (:func:`~sim_core.energies.base.positions_key`) instead of reading its bytes."""
    x.flags.writeable = False
    return x
