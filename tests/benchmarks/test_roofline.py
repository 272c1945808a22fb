"""The lockstep step's roofline (benchmarks/roofline.py): the per-copy sizes read from a real lockstep on the batched
CG, the band factorisation's multiply-adds counted in closed form equal to the kernels' loops run one by one, and
the table's floors the larger of the bytes' and the flops' times."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.roofline import (DEVICES, MEASURED_COUNTS, LockstepSizes, band_factorisation, cg_iteration,
                                 coupled_dofs, envelope, envelope_table, lockstep_sizes, markdown, phase_table)
from sim_core.batch.sheet_bands import copy_band_dofs
from sim_core.batch import BatchedSimulation
from sim_core.scenes.task_scene import task_initial_state
from sim_core.solver_config import SolverConfig
from tests.support.batch_copies import MOTIONS, PARAMS, control, pad_model


def _loop_counts(m: int, w: int, t: int, nt: int) -> tuple[int, int, int]:
    """Multiply-adds of the band factorisation's kernels counted by running their loops: the elimination (``S_ij -=
    S_ik S_jk / S_kk`` for ``k < j <= i <= k + w``), the tiles' inverses (band_cholesky._tile_inverses) and the
    couplings G and H (band_cholesky._tile_couplings)."""
    elimination = sum(1 for k in range(m) for j in range(k + 1, min(k + w, m - 1) + 1)
                      for i in range(j, min(k + w, m - 1) + 1))
    inverse = nt * sum(a - max(a - w, 0) for c in range(t) for a in range(c, t))
    g = sum(max(min(a, c + w - t) + 1, 0) for c in range(t) for a in range(t))
    h = sum(sum(1 for k in range(max(t + c - w, 0), t) if k >= a) for c in range(t) for a in range(t))
    return elimination, inverse, (nt - 1) * (g + h)


def test_the_factorisations_counts_are_the_kernels_loops():
    for m, w, t, nt in ((24, 5, 6, 4), (30, 7, 8, 4), (17, 9, 9, 2)):
        s = LockstepSizes(vertices=m // 3, dofs=m, free_dofs=m, full_nnz=0, upper_nnz=0, vertex_blocks=0, band_m=m,
                          band_w=w, band_t=t, band_nt=nt, tets=0, hinges=0, triangles=0, value_bytes=8)
        elimination, inverse, couplings = _loop_counts(m, w, t, nt)
        _, flops = band_factorisation(s)
        # two flops a multiply-add, one more a division of the elimination's updates, m square roots
        assert flops == 2.0 * (elimination + inverse + couplings) + elimination + m, (m, w, t, nt)


def test_the_envelope_is_each_rows_reach_to_its_first_coupled_column_in_the_order():
    m = 6
    chain = (np.arange(m - 1), np.arange(1, m))  # a tridiagonal pattern (one triangle given)
    np.testing.assert_array_equal(envelope(np.arange(m), *chain), [1, 2, 2, 2, 2, 2])
    arrow = (np.full(m - 1, m - 1), np.arange(m - 1))  # the last DoF coupled to all: its row is full, the others 1
    np.testing.assert_array_equal(envelope(np.arange(m), *arrow), [1, 1, 1, 1, 1, m])
    np.testing.assert_array_equal(envelope(np.arange(m)[::-1], *arrow), [1, 2, 3, 4, 5, 6])  # it first: it fills
    # DoFs outside the order are left out; a Cholesky of the arrow fills nothing outside its envelope
    np.testing.assert_array_equal(envelope(np.array([0, 5]), *arrow), [1, 2])
    a = np.eye(m) * m
    a[m - 1, :] = a[:, m - 1] = 1.0
    a[m - 1, m - 1] = m
    widths = envelope(np.arange(m), *arrow)
    factor = np.linalg.cholesky(a)
    outside = np.arange(m)[None, :] < (np.arange(m) - widths + 1)[:, None]
    assert np.all(factor[outside] == 0.0)


def test_sizes_of_a_real_lockstep_and_the_tables_floors():
    model = pad_model()
    batch = BatchedSimulation.from_model(model, 2, params=PARAMS[:2], state=task_initial_state(model),
                                         solver_config=SolverConfig(backend="taichi-cpu", lockstep=True,
                                                                    linear_solver="pcg"))
    pose0 = batch.states[0].effector_pose["pad"].copy()
    batch.step([control(pose0, MOTIONS[i], 0) for i in range(2)])
    engine = batch.lockstep
    s = lockstep_sizes(engine)
    pcg = engine.solver.pcg
    indptr, indices = pcg._full[0], pcg._full[1]
    rows = np.repeat(np.arange(indptr.size - 1), np.diff(indptr))
    diagonal = int(np.count_nonzero(indices[: rows.size] == rows))
    assert s.full_nnz == (2 * int(indptr[-1]) - diagonal) // 2  # both triangles, the diagonal once; 2 copies
    assert s.vertices == model.vertex_count and s.dofs == 3 * model.vertex_count
    sheet = model.bodies["sheet"]
    assert (s.band_m, s.band_w) == (pcg.bands.size, pcg.bands.width) and s.band_m == 3 * sheet.vertices.size
    assert s.hinges == len(sheet.hinges) and s.tets == len(model.bodies["pad"].tets)
    assert s.value_bytes == 4  # the CG's default mixed precision stores float32 values
    # the band block's share of a CG iteration: its tiles read (D^-1 by halves twice, G, H) and its vectors
    without = LockstepSizes(**{**s.__dict__, "band_m": 0, "band_w": 0, "band_t": 0, "band_nt": 0})
    tile_bytes = 3 * s.band_nt * s.band_t ** 2 * 4 + 4 * s.band_nt * s.band_t * 8 + 2 * s.band_m * 12
    assert cg_iteration(s)[0] - cg_iteration(without)[0] == tile_bytes + 2 * s.dofs * 8
    device = {"name": "test", "bandwidth": 1e9, "fp64": 1e9, "fp32": 2e9}
    rows = phase_table(s, MEASURED_COUNTS, device, 10)
    assert [r["phase"] for r in rows] == ["assembly (gradient, Hessian values)", "projection (projected retries)",
                                         "band factorisation", "linear solve (CG iterations)",
                                         "line search (trial points)"]
    for r in rows:
        assert r["floor_ms"] == pytest.approx(1e3 * 10 * max(r["bytes_a_scene_step"], r["flops_a_scene_step"]) / 1e9,
                                              rel=1e-12)
        assert r["bytes_a_scene_step"] > 0 and r["flops_a_scene_step"] > 0
    cg = rows[3]
    assert cg["bytes_a_scene_step"] == MEASURED_COUNTS["cg"] * cg_iteration(s)[0]
    widths = np.full(s.free_dofs, 10)
    direct = envelope_table(s, widths, MEASURED_COUNTS, device, 10)
    assert [r["phase"] for r in direct][2:4] == ["envelope factorisation", "envelope solves"]
    assert direct[2]["flops_a_pass"] == s.free_dofs * (9 * 10 + 1)  # sum (w - 1) w flops and the square roots
    # the envelope of copy 0's real Newton matrix in the reverse Cuthill-McKee order (contact couplings inside): its
    # Cholesky factor has no entry outside it, and the factor solves the copy's system
    rows_, cols_, pairs = coupled_dofs(pcg)
    order = copy_band_dofs(engine.scene, pcg._uploaded["free"], indptr, indices, pairs)[0]
    columns = np.eye(pcg._n)[:, order]
    dense = np.stack([pcg.matvec(columns[:, k]) for k in range(order.size)], axis=1)[order]  # A[order][:, order]
    factor = np.linalg.cholesky(dense)
    widths = envelope(order, rows_, cols_)
    outside = np.arange(order.size)[None, :] < (np.arange(order.size) - widths + 1)[:, None]
    assert np.abs(factor[outside]).max(initial=0.0) <= 1e-12 * np.abs(factor).max()
    assert outside.any() and len(pairs)  # an envelope, not the dense triangle; contact blocks in the matrix
    text = markdown(phase_table(s, MEASURED_COUNTS, DEVICES["h100-sxm"], 1024), 1024, DEVICES["h100-sxm"])
    assert "3.35 TB/s" in text and "scene-steps/s at B = 1024" in text
