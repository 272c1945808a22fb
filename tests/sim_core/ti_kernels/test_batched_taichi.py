"""A batch on the Taichi backend: copies interleaved step by step share the process's kernels, launch
arrays and work buffers, and each copy still gets the states of its separate run."""

from __future__ import annotations

import numpy as np

from sim_core.batch import BatchedSimulation
from sim_core.scenes.task_scene import task_initial_state
from sim_core.solver_config import SolverConfig
from tests.support.batch_copies import MOTIONS, PARAMS, STEPS, control, pad_model, separate_run


def test_taichi_batch_gives_each_copy_its_separate_run(ti_cpu):
    model = pad_model()
    config = SolverConfig(backend=f"taichi-{ti_cpu}")
    batch = BatchedSimulation.from_model(model, 3, params=PARAMS, state=task_initial_state(model), solver_config=config)
    assert batch.backend == f"taichi-{ti_cpu}" and all(s.solver._fused_path() for s in batch.sims)
    pose0 = batch.states[0].effector_pose["pad"].copy()
    per_step = []
    for k in range(STEPS):
        res = batch.step([control(pose0, MOTIONS[i], k) for i in range(3)])
        assert res.failed_now == []
        per_step.append([s.copy() for s in batch.states])
    for i in range(3):
        alone = separate_run(model, PARAMS[i], MOTIONS[i], config)
        for k in range(STEPS):
            if ti_cpu == "cpu":  # serial kernel loops: the same sums in the same order, bit for bit
                np.testing.assert_array_equal(per_step[k][i].x, alone[k].x)
                np.testing.assert_array_equal(per_step[k][i].contact_force, alone[k].contact_force)
            else:  # parallel sums on CUDA round differently run to run: the Newton tolerance
                assert np.max(np.abs(per_step[k][i].x - alone[k].x)) <= config.tol_velocity * 0.005
