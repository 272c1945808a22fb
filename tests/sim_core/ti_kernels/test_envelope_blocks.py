"""The envelope Cholesky by panels of columns (sim_core.ti_kernels.envelope_blocks, ``BatchedEnvelope(schedule=
"blocks")``): each panel's rows listed as the elimination needs them; each copy's factor equal to a dense Cholesky of
its matrix in the envelope's order to 1e-10 relative and its solve to SciPy's, with panels that do and do not divide
the order and a CUDA block's lanes run one after another on the CPU; a lockstep batch through it at its copies'
separate runs' states. The schedules' shared cases (widening, indefinite and diverged copies, copies left out, float32
factors): ``test_envelope_cholesky.py``."""

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


def test_a_cuda_blocks_lanes_run_in_turn_on_the_cpu_solve_exactly(ti_cpu):
    """:data:`CUDA_LANES` lanes a copy (CUDA's sharing of each panel's rows, block and front, and the substitutions'
    rows and columns; one after another in a copy's thread here) give each copy's exact solution; a panel under one
    column is refused."""
    from sim_core.ti_kernels import envelope_cholesky

    blocks = [_grid_block(5, 4, seed, 1.0) for seed in (51, 52)]
    A = sp.block_diag(blocks, format="csr")
    m = blocks[0].shape[0]
    segments = np.repeat(np.arange(2), m)
    with pytest.raises(ValueError, match="panel must be at least 1 column, got 0"):
        envelope_cholesky.BatchedEnvelope(segments, schedule="blocks", panel=0)
    solver = envelope_cholesky.BatchedEnvelope(segments, schedule="blocks", lanes=envelope_cholesky.CUDA_LANES,
                                               panel=5)
    solver.factorize(_upper(A))
    b = np.random.default_rng(7).normal(size=2 * m)
    want = spla.spsolve(A.tocsc(), b)
    assert np.abs(solver.solve(b) - want).max() <= 1e-10 * np.abs(want).max()


def test_a_lockstep_batch_solved_by_panels_gives_the_states_of_separate_runs(monkeypatch):
    """Three pad copies stepped in lockstep (``linear_solver="envelope"`` on the CPU arch) with the envelope by panels
    (of 4 columns, the solver's default schedule there for this test): each copy's states those of its separate run
    (host solver) to the Newton tolerance, as ``test_lockstep.py``'s envelope case with ``"dots"``."""
    from sim_core.batch import BatchedSimulation
    from sim_core.scenes.task_scene import task_initial_state
    from sim_core.solver_config import SolverConfig
    from sim_core.ti_kernels import envelope_cholesky
    from tests.support.batch_copies import MOTIONS, PARAMS, STEPS, control, pad_model, separate_run

    monkeypatch.setattr(envelope_cholesky, "SCHEDULE", "blocks")
    monkeypatch.setattr(envelope_cholesky, "PANEL", 4)
    model = pad_model()
    config = SolverConfig(lockstep=True, backend="taichi-cpu", linear_solver="envelope")
    batch = BatchedSimulation.from_model(model, len(PARAMS), params=PARAMS, state=task_initial_state(model),
                                         solver_config=config)
    pose0 = batch.states[0].effector_pose["pad"].copy()
    states = []
    for k in range(STEPS):
        assert batch.step([control(pose0, MOTIONS[i], k) for i in range(len(PARAMS))]).failed_now == []
        states.append([s.copy() for s in batch.states])
    solver = batch.lockstep.solver.linear_solver
    assert (solver.schedule, solver.panel, solver._npanels) == ("blocks", 4, -(-solver._m // 4))
    tol = SolverConfig().tol_velocity * 0.005  # the Newton tolerance as a displacement per 5 ms step, m
    for i in range(len(PARAMS)):
        alone = separate_run(model, PARAMS[i], MOTIONS[i])
        for k in range(STEPS):
            assert np.max(np.abs(states[k][i].x - alone[k].x)) <= tol, (i, k)
