"""The lockstep iterates' helpers (sim_core.batch.iterates): the stacked gradient summed in term order with sparse
terms' rows added at their vertices (the dense sum bit for bit), and frozen iterates."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.batch.iterates import frozen, summed_gradient


class _Dense:
    """A term with a dense gradient (kept: the sum must not write into it)."""

    def __init__(self, g):
        self.g = g

    def gradient(self, x):
        return self.g


class _Sparse(_Dense):
    """A term declaring SparseGradient: rows at distinct vertices (or the dense gradient when ``dense``)."""

    def __init__(self, g, vertices, dense=False):
        super().__init__(g)
        self.vertices, self.dense = vertices, dense

    def gradient_rows(self, x):
        return (None, self.g) if self.dense else (self.vertices, self.g[self.vertices])


def _terms(rng, n, kinds):
    out = []
    for kind in kinds:
        g = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-6, 3)
        if kind == "dense":
            out.append(_Dense(g))
            continue
        vertices = rng.choice(n, size=n // 5, replace=False)
        sparse = np.zeros_like(g)
        sparse[vertices] = g[vertices]
        out.append(_Sparse(sparse, vertices, dense=kind == "dense rows"))
    return out


@pytest.mark.parametrize("kinds", [("dense", "dense", "sparse", "dense", "sparse", "sparse"),
                                   ("sparse", "dense", "dense rows", "sparse"), ("sparse",), ("dense",),
                                   ("sparse", "sparse")])
def test_sparse_rows_give_the_dense_sum_in_term_order_bit_for_bit(kinds):
    rng = np.random.default_rng(len(kinds))
    n = 50
    terms = _terms(rng, n, kinds)
    kept = [t.g.copy() for t in terms]
    want = terms[0].g.reshape(-1) + (terms[1].g.reshape(-1) if len(terms) > 1 else 0.0)
    for t in terms[2:]:
        want = want + t.g.reshape(-1)
    got = summed_gradient(terms, np.zeros((n, 3)))
    assert got.shape == (3 * n,) and got.dtype == np.float64
    np.testing.assert_array_equal(got, want)
    for t, g in zip(terms, kept):  # no term's gradient written into, and the sum is an array of its own
        np.testing.assert_array_equal(t.g, g)
        assert not np.shares_memory(got, t.g)
    assert not np.any(summed_gradient([], np.zeros((n, 3))))


class _Fresh(_Dense):
    """A dense term whose gradient is a new array of each call (the lumped-mass quadratic's)."""

    def gradient(self, x):
        self.last = self.g.copy()
        return self.last


def test_a_fresh_first_gradient_is_summed_into_in_term_order_bit_for_bit():
    rng = np.random.default_rng(9)
    n = 50
    terms = [_Fresh(rng.normal(size=(n, 3)))] + _terms(rng, n, ("dense", "sparse", "dense"))
    want = summed_gradient([_Dense(terms[0].g)] + terms[1:], np.zeros((n, 3)))
    got = summed_gradient(terms, np.zeros((n, 3)), fresh_first=True)
    np.testing.assert_array_equal(got, want)
    assert np.shares_memory(got, terms[0].last)  # accumulated into the fresh array: no array of its own
    for t in terms[1:]:
        assert not np.shares_memory(got, t.g)


def test_a_frozen_iterate_is_read_only():
    x = frozen(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="read-only"):
        x[0, 0] = 1.0
