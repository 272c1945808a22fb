"""The lockstep step's state kept on the device between steps (``DeviceIterates.keep_resident``): the kernels that make
the velocities, the inertia's centre, the first iterate and the contact force's sign there equal NumPy's operations,
and a Forming batch stepped on CUDA's paths (emulated on the CPU arch) takes its first iterates, inertia centres and
velocities from the last step's device arrays from its second step on, and the copies' states are gathered there, each
copy at its separate run's states."""

from __future__ import annotations

import numpy as np
import pytest

from tests.sim_core.ti_kernels.conftest import TEST_ARCH, assert_same_sums
from tests.support.emulated_cuda import emulate_cuda


def test_state_kernels_equal_numpy(ti_cpu):
    """``(x - x0) / dt``, ``x + dt v``, ``0 - a`` (a signed zero included) and ``a`` with some DoFs replaced, each as
    NumPy computes it (bit for bit on the CPU); the kept pairs are found by array object only, frozen arrays only."""
    from sim_core.batch.device_iterates import DeviceIterates
    from sim_core.batch.iterates import frozen

    rng = np.random.default_rng(0)
    copies, n = 3, 40
    vectors = DeviceIterates(np.arange(copies * n).reshape(copies, n))
    x, x0, v = (rng.normal(size=(copies * n, 3)) for _ in range(3))
    x[5, 1] = -0.0
    dt = 0.005
    xd, x0d, vd = vectors.upload(x), vectors.upload(x0), vectors.upload(v)
    assert_same_sums(vectors.download(vectors.difference_quotient(xd, x0d, dt)), (x - x0) / dt)
    assert_same_sums(vectors.download(vectors.advanced(x0d, vd, dt)), x0 + dt * v)
    negated = vectors.download(vectors.negated(xd))
    np.testing.assert_array_equal(negated, np.subtract(0.0, x))
    assert not np.signbit(negated[5, 1])
    dofs = np.flatnonzero(rng.random(3 * copies * n) < 0.3)
    want = x0.copy()
    want.reshape(-1)[dofs] = x.reshape(-1)[dofs]
    np.testing.assert_array_equal(vectors.download(vectors.copied_with_dofs(x0d, dofs, x.reshape(-1)[dofs])), want)
    # the start from a kept x^n: the same values as the upload of the caller's x
    kept_x = frozen(x0.copy())
    vectors.keep_resident((kept_x, x0d), (x.copy(), xd))  # (a writeable array is not kept)
    assert vectors.resident(kept_x) is x0d and vectors.resident(x0.copy()) is None and len(vectors._resident) == 1
    start = vectors.start(want.copy(), kept_x, dofs)
    np.testing.assert_array_equal(vectors.download(start.device), want)
    made = vectors.velocities(start, kept_x, dt)
    assert made is not None and not made[0].flags.writeable
    assert_same_sums(made[0], (want - x0) / dt)
    vectors.forget_resident()
    assert vectors.resident(kept_x) is None and vectors.velocities(start, kept_x, dt) is None
    # the copies' rows gathered on the device: the host gather's values (translated back where asked)
    index = rng.permutation(copies * n).reshape(copies, n)
    shuffled = DeviceIterates(index)
    offsets = rng.normal(size=(copies, 3))
    chosen = np.array([2, 0])
    moved, plain = shuffled.copy_rows([(xd, True), (xd, False)], chosen, offsets)
    np.testing.assert_array_equal(moved, x[index[chosen]] - offsets[chosen][:, None, :])
    np.testing.assert_array_equal(plain, x[index[chosen]])


@pytest.mark.skipif(TEST_ARCH != "cpu", reason="runs CUDA's lockstep paths emulated on the CPU arch beside the host "
                                               "path, which only the CPU arch runs (the default, and CI)")
def test_lockstep_forming_steps_from_its_device_state(ti_cpu, monkeypatch):
    """Two Forming copies stepped in lockstep on CUDA's paths (emulated; the envelope solver): from the second step on
    the first iterate is made from the last result's device array (only the fixed DoFs' targets sent), the inertia's
    centre from the kept positions and velocities (no upload), and the velocities on the device, equal to
    ``(x - x^n) / dt`` of the stacked states bit for bit; each copy ends every step where its separate run (CPU arch,
    host paths) ends, to the solver's tolerance. A state replaced from outside is not taken for the kept one."""
    import copy

    from sim_core.batch.device_iterates import DeviceIterates
    from sim_core.batch.lumped import LumpedQuadratic
    from sim_core.bench.batch import _FormingRun
    from sim_core.control import Control
    from sim_core.simulation import Simulation
    from sim_core.solver_config import SolverConfig

    steps = 3
    run = _FormingRun(2, steps, "taichi-cpu", lockstep=True, linear_solver="envelope")
    model, effector = run.batch.sims[0].model, run.effector
    separate = []
    for i in range(2):
        alone = Simulation(copy.deepcopy(model), solver_config=SolverConfig(backend="taichi-cpu"))
        alone.state = run.batch.states[i].copy()
        separate.append([alone.step(Control(effector_pose_target={effector: run.targets[i][k]})) and alone.state.copy()
                         for k in range(steps)])
    from sim_core.batch.lockstep import LockstepSolver

    starts, centres, velocities, rows = [], [], [], []
    gathered = LockstepSolver.resident_rows
    monkeypatch.setattr(LockstepSolver, "resident_rows", lambda *a: (rows.append(gathered(*a)), rows[-1])[1])
    start, centre, made = DeviceIterates.start, LumpedQuadratic.use_device_center, DeviceIterates.velocities
    monkeypatch.setattr(DeviceIterates, "start", lambda self, x, x_n=None, dofs=None: (
        starts.append(self.resident(x_n) is not None and dofs is not None), start(self, x, x_n, dofs))[1])
    monkeypatch.setattr(LumpedQuadratic, "use_device_center", lambda self, c: (centres.append(1), centre(self, c))[1])
    monkeypatch.setattr(DeviceIterates, "velocities", lambda *a: (velocities.append(made(*a)), velocities[-1])[1])
    emulate_cuda(monkeypatch)
    tol = SolverConfig().tol_velocity * 0.005
    dt = run.batch.sims[0].dt
    for k in range(steps):
        before = run.batch.lockstep.state
        res = run.batch.step([Control(effector_pose_target={effector: t[k]}) for t in run.targets])
        assert res.failed_now == []
        after = run.batch.lockstep.state
        if k:
            np.testing.assert_array_equal(after.v, (after.x - before.x) / dt)
        scene = run.batch.lockstep.scene
        on_host = scene.copy_states(after, np.arange(2), np.zeros(2), np.zeros(2, dtype=np.int64))
        for i in range(2):  # the copies' states as the host's gathers make them, bit for bit
            for name in ("x", "v", "contact_force"):
                np.testing.assert_array_equal(getattr(run.batch.states[i], name), getattr(on_host[i], name))
        for i in range(2):
            assert np.max(np.abs(run.batch.states[i].x - separate[i][k].x)) <= tol, (i, k)
            assert np.max(np.abs(run.batch.states[i].v - separate[i][k].v)) <= tol / dt, (i, k)
    assert starts == [False] + [True] * (steps - 1)  # (the first step's x^n: the caller's state, uploaded)
    assert len(centres) == steps - 2  # v^n kept from the second step's velocities on (the first's: x^n not kept)
    assert velocities[0] is None and all(m is not None for m in velocities[1:])
    assert [r is not None for r in rows] == [False] + [True] * (steps - 1)  # the copies' states gathered there
    # a copy's state replaced from outside: the stacked state is made again and nothing kept is read for it
    run.batch.sims[0].state = run.batch.states[0].copy()
    run.batch.step([Control(effector_pose_target={effector: t[steps - 1]}) for t in run.targets])
    assert starts[-1] is False
