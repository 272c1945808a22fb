"""The envelope Cholesky by panels of columns (sim_core.ti_kernels.envelope_blocks, ``BatchedEnvelope(schedule=
"blocks")``): each panel's rows listed as the elimination needs them; each copy's factor equal to a dense Cholesky of
its matrix in the envelope's order to 1e-10 relative and its solve to SciPy's, with panels that do and do not divide
the order and a CUDA block's lanes run one after another on the CPU. The schedules' shared cases (widening,
indefinite and diverged copies, copies left out, float32 factors): ``test_envelope_cholesky.py``; lockstep batches
through it (the CPU arch's default schedule): ``tests/sim_core/batch/test_lockstep.py``'s envelope cases and
``test_friction_device_rows.py``."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from tests.sim_core.ti_kernels.test_envelope_cholesky import _grid_block, _upper


def test_each_panels_rows_are_its_own_then_those_of_later_panels_reaching_it():
    from sim_core.ti_kernels.envelope_blocks import panel_rows

    rng = np.random.default_rng(3)
    m = 61
    first = np.array([rng.integers(max(0, i - 9), i + 1) for i in range(m)])
    first[[30, 47, 60]] = [2, 0, 41]  # a few long rows (contact couplings)
    for panel in (1, 3, 7, 12, 61, 64):
        pptr, prows = panel_rows(first, panel)
        assert pptr.size - 1 == -(-m // panel)
        for p in range(pptr.size - 1):
            j0, j1 = p * panel, min((p + 1) * panel, m)
            want = list(range(j0, j1)) + [i for i in range(j1, m) if first[i] < j1]
            assert prows[pptr[p]:pptr[p + 1]].tolist() == want


def _dense_factor(solver, copy: int) -> np.ndarray:
    """Copy ``copy``'s Cholesky factor ``L = W D^-1/2`` from the solver's envelope (positions in its order)."""
    from sim_core.ti_kernels.envelope_cholesky import envelope_rows

    first = solver._first
    off = envelope_rows(first)[0]
    env = solver._arrays["env"].to_numpy()[copy * solver.entries:(copy + 1) * solver.entries]
    W = np.zeros((first.size, first.size))
    for i in range(first.size):
        W[i, first[i]:i + 1] = env[off[i]:off[i + 1]]
    return W / np.sqrt(np.diag(W))[None, :]


@pytest.mark.parametrize("lanes, panel", [(1, 5), (3, 4), (2, 1)])
def test_factors_equal_a_dense_cholesky_and_solves_scipys(ti_cpu, lanes, panel):
    """Panels of 5 and 4 columns (the order, 3 x 28 = 84, not a multiple) and of 1; one, three and two lanes a copy
    (CUDA's sharing of a panel's rows, block and front; run in turn here)."""
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

    blocks = [_grid_block(7, 4, seed, shift) for seed, shift in ((41, 1e-3), (42, 1.0), (43, 10.0))]
    A = sp.block_diag(blocks, format="csr")
    m = blocks[0].shape[0]
    solver = BatchedEnvelope(np.repeat(np.arange(3), m), schedule="blocks", lanes=lanes, panel=panel)
    assert solver.factorize(_upper(A))
    b = np.random.default_rng(6).normal(size=3 * m)
    x = solver.solve(b)
    assert not solver.indefinite.any()
    for c, block in enumerate(blocks):
        order = solver._order[c] - c * m
        L = np.linalg.cholesky(block.toarray()[np.ix_(order, order)])
        assert np.abs(_dense_factor(solver, c) - L).max() <= 1e-10 * np.abs(L).max()
    want = spla.spsolve(A.tocsc(), b)
    assert np.abs(x - want).max() <= 1e-10 * np.abs(want).max()


def test_a_cuda_blocks_lanes_run_in_turn_on_the_cpu_solve_exactly_and_blocks_is_the_cpus_default(ti_cpu):
    """:data:`CUDA_LANES` lanes a copy (CUDA's sharing of each panel's rows, block and front, and the substitutions'
    rows and columns; one after another in a copy's thread here) give each copy's exact solution; with no schedule given
    the CPU arch takes the panels (one thread a copy)."""
    from sim_core.ti_kernels import envelope_cholesky

    blocks = [_grid_block(5, 4, seed, 1.0) for seed in (51, 52)]
    A = sp.block_diag(blocks, format="csr")
    m = blocks[0].shape[0]
    segments = np.repeat(np.arange(2), m)
    assert envelope_cholesky.BatchedEnvelope(segments).schedule == "blocks" == envelope_cholesky.SCHEDULE
    with pytest.raises(ValueError, match="panel must be at least 1 column, got 0"):
        envelope_cholesky.BatchedEnvelope(segments, schedule="blocks", panel=0)
    solver = envelope_cholesky.BatchedEnvelope(segments, schedule="blocks", lanes=envelope_cholesky.CUDA_LANES,
                                               panel=5)
    solver.factorize(_upper(A))
    b = np.random.default_rng(7).normal(size=2 * m)
    want = spla.spsolve(A.tocsc(), b)
    assert np.abs(solver.solve(b) - want).max() <= 1e-10 * np.abs(want).max()
