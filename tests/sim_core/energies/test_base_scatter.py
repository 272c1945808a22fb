"""scatter_gradient: per-element gradients summed into the global gradient."""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import scatter_gradient


def test_sums_equal_add_at_bit_for_bit_for_both_input_shapes():
    """Repeated vertices (within an element and across elements) are summed in the order of
    ``np.add.at``, so the result is bit-identical; ``(k, m, 3)`` and ``(k, 3 m)`` inputs agree;
    no elements give zeros."""
    rng = np.random.default_rng(5)
    n = 40
    vertices = rng.integers(0, n, size=(300, 4))
    vertices[0] = [7, 7, 3, 7]
    grad = rng.normal(size=(300, 4, 3)) * 10.0 ** rng.integers(-8, 8, size=(300, 4, 1))
    expected = np.zeros((n, 3))
    np.add.at(expected, vertices.reshape(-1), grad.reshape(-1, 3))
    for g in (grad, grad.reshape(300, 12)):
        out = scatter_gradient(n, vertices, g)
        assert out.shape == (n, 3)
        np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(scatter_gradient(n, np.zeros((0, 4), int), np.zeros((0, 12))), np.zeros((n, 3)))
