"""CopyRuns: per-copy reductions over a stacked array equal the same reductions over each copy's gathered DoFs."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.batch.copy_runs import CopyRuns
from sim_core.batch.stacked import stack_models
from tests.support.batch_copies import pad_model


@pytest.fixture(scope="module")
def stacked():
    """Four copies of the pad scene (two bodies and a table: body-major runs)."""
    return stack_models([pad_model() for _ in range(4)])


def test_runs_are_the_copies_body_runs(stacked):
    runs = CopyRuns(stacked.index)
    assert runs.copies == 4 and runs.vertex_count == stacked.model.vertex_count
    bodies = len(stacked.model.bodies)  # one material group: the scene's bodies
    assert len(runs.starts) == 4 * bodies  # one run per copy and body
    copy_of = np.repeat(runs.run_copy, runs.lengths)
    for i in range(4):
        assert np.all(copy_of[stacked.index[i]] == i)


def test_per_copy_reductions_equal_those_of_the_gathered_dofs(stacked):
    runs = CopyRuns(stacked.index)
    dofs = stacked.dof_index
    rng = np.random.default_rng(3)
    N = runs.vertex_count
    a, b = rng.normal(size=3 * N), rng.normal(size=(N, 3))
    b[stacked.index[2]] = 0.0
    np.testing.assert_allclose(runs.dot(a, b), np.einsum("ij,ij->i", a[dofs], b.reshape(-1)[dofs]), rtol=1e-12,
                               atol=1e-12)
    np.testing.assert_allclose(runs.largest_norm(b), np.linalg.norm(b[stacked.index], axis=2).max(axis=1),
                               rtol=1e-15)
    np.testing.assert_array_equal(runs.largest_abs(a), np.abs(a[dofs]).max(axis=1))
    np.testing.assert_array_equal(runs.any_dof(b.reshape(-1) != 0.0), [True, True, False, True])
    alphas = np.array([0.5, 0.0, 2.0, -1.0])
    want = a.reshape(-1, 3).copy()
    for i in range(4):
        want[stacked.index[i]] += alphas[i] * b[stacked.index[i]]
    np.testing.assert_array_equal(runs.moved(a.reshape(-1, 3), b, alphas), want)
    np.testing.assert_array_equal(runs.per_dof(alphas)[dofs], np.repeat(alphas[:, None], dofs.shape[1], axis=1))


def test_runs_of_one_length_form_blocks_that_tile_the_stacked_vertices(stacked):
    runs = CopyRuns(stacked.index)
    at = 0
    for r0, v0, m, s in runs.blocks:
        assert v0 == at and np.all(runs.lengths[r0:r0 + m] == s)
        assert np.all(runs.starts[r0:r0 + m] == v0 + s * np.arange(m))
        at += m * s
    assert at == runs.vertex_count
    assert len(runs.blocks) < len(runs.starts)  # each body's runs over the four copies are one block


def test_whole_copies_are_zeroed_and_taken_in_place(stacked):
    runs = CopyRuns(stacked.index)
    dofs = stacked.dof_index
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=3 * runs.vertex_count), rng.normal(size=3 * runs.vertex_count)
    mask = np.array([False, True, False, True])
    want = a.copy()
    want[dofs[mask]] = 0.0
    out = runs.zero_copies(a, mask)
    assert out is a
    np.testing.assert_array_equal(a, want)
    want[dofs[mask]] = b[dofs[mask]]
    assert runs.copy_where(a, b, mask) is a
    np.testing.assert_array_equal(a, want)
    # a number counts as set where it is non-zero (a NaN too): the copies with a non-zero entry
    c = np.zeros(3 * runs.vertex_count)
    c[dofs[0, 4]], c[dofs[3, -1]] = 1e-300, np.nan
    np.testing.assert_array_equal(runs.any_dof(c), [True, False, False, True])


def test_a_non_finite_entry_marks_its_copy_alone(stacked):
    runs = CopyRuns(stacked.index)
    d = np.ones((runs.vertex_count, 3))
    d[stacked.index[1, 5], 2] = np.nan
    d[stacked.index[3, 0], 0] = np.inf
    np.testing.assert_array_equal(runs.all_finite(d), [True, False, True, False])
    norms = runs.largest_norm(d)
    assert np.isnan(norms[1]) and np.isnan(norms[3])
    assert norms[0] == pytest.approx(np.sqrt(3.0)) and norms[2] == pytest.approx(np.sqrt(3.0))
    # the largest entry tells the copies apart as all_finite does (the lockstep's gradient test)
    largest = runs.largest_abs(d)
    np.testing.assert_array_equal(np.isfinite(largest), runs.all_finite(d))
    assert np.isnan(largest[1]) and largest[3] == np.inf and largest[0] == largest[2] == 1.0


def test_an_index_that_is_not_a_permutation_is_refused():
    with pytest.raises(ValueError, match="not a permutation"):
        CopyRuns(np.array([[0, 1], [1, 2]]))
    with pytest.raises(ValueError, match="outside"):
        CopyRuns(np.array([[0, 1], [2, 4]]))
