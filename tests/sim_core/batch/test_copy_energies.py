"""The lockstep line search on per-copy energies (CopyEnergies, sim_core.batch.line_search): every term of a lockstep
step splits its energy by copy (the shares add up to the stacked energy, and a move of one copy changes its share
alone, by the stacked change); each copy's accepted step meets its own Armijo condition, measured on the stacked energy
with that copy alone moved; no Armijo group energies; copies that agree take the steps of the group test."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.batch import BatchedSimulation
from sim_core.batch import lockstep as lockstep_module
from sim_core.scenes.task_scene import task_initial_state
from sim_core.solver_config import SolverConfig
from tests.support.batch_copies import MOTIONS, PARAMS, control, pad_model

DIRECT = SolverConfig(lockstep=True, backend="taichi-cpu")
DEVICE_CG = SolverConfig(lockstep=True, backend="taichi-cpu", linear_solver="pcg")  # the GPU's: device vectors


@pytest.fixture(scope="module")
def model():
    return pad_model()


def _run(model, config, params=PARAMS, motions=MOTIONS, steps=2):
    batch = BatchedSimulation.from_model(model, len(params), params=params, state=task_initial_state(model),
                                         solver_config=config)
    pose0 = batch.states[0].effector_pose["pad"].copy()
    infos = []
    for k in range(steps):
        res = batch.step([control(pose0, motions[i], k) for i in range(len(params))])
        infos.append([(info.iterations, info.backtracks) for info in res.infos])
    return batch, infos


def _stacked_energy(solver, step, x: np.ndarray) -> float:
    """The stacked incremental potential at ``x`` with the contact terms of a search there (J)."""
    terms = solver.contact.potentials(x, step.x_n, step.memory)
    return sum(p.energy(x) for p in step.loop_terms) + sum(p.energy(x) for p in terms)


def test_each_term_of_a_lockstep_step_splits_its_energy_by_copy(model, monkeypatch):
    seen = {}
    line_search = lockstep_module.LockstepSolver._line_search_copies

    def spy(self, step, x, d, alpha, slope, open_, terms, x_search, info):
        B, index = self.scene.copies, self.scene.index
        rng = np.random.default_rng(len(seen))
        moved = x.host.copy()
        moved[index[1]] += 1e-5 * rng.standard_normal((index.shape[1], 3))  # copy 1 alone
        for p in step.loop_terms + terms:
            split, split_moved = (p.copy_energies(y, self._copy_of_vertex, B) for y in (x.host, moved))
            e, e_moved = p.energy(x.host), p.energy(moved)
            scale = max(abs(e), abs(e_moved), 1e-30)
            assert np.sum(split) == pytest.approx(e, rel=1e-12, abs=1e-15 * scale), type(p).__name__
            np.testing.assert_array_equal(split_moved[[0, 2]], split[[0, 2]])
            assert split_moved[1] - split[1] == pytest.approx(e_moved - e, rel=1e-9, abs=1e-13 * scale)
            seen[type(p).__name__] = seen.get(type(p).__name__, 0) + 1
        return line_search(self, step, x, d, alpha, slope, open_, terms, x_search, info)

    monkeypatch.setattr(lockstep_module.LockstepSolver, "_line_search_copies", spy)
    _run(model, DEVICE_CG, steps=1)
    assert set(seen) == {"LumpedQuadratic", "TiLaggedFriction", "FusedElastic", "TiVertexTriangleContact",
                         "TiEdgeEdgeContact", "PlaneContact"}


@pytest.mark.parametrize("config", [DIRECT, DEVICE_CG], ids=["direct", "device-cg"])
def test_each_copy_takes_a_step_that_meets_its_own_armijo_condition(model, config, monkeypatch):
    """Copies of their own parameters and motions (they disagree): for every accepted step of every copy,
    ``E(x with copy i moved) - E(x) <= c a_i g_i.d_i`` on the stacked energy of one evaluation (no split); the
    per-copy energies kept for the next search are those of the new iterate; no Armijo group energy is evaluated."""
    checked = []
    line_search = lockstep_module.LockstepSolver._line_search_copies

    def spy(self, step, x, d, alpha, slope, open_, terms, x_search, info):
        out = line_search(self, step, x, d, alpha, slope, open_, terms, x_search, info)
        x_new, accepted, backtracks = out[0], out[4], out[5]
        kept = self._trial_energy  # the next search's e0: each copy's energy where it stands, measured afresh equal
        assert kept[0] is x_new.host and kept[1] is out[2]
        np.testing.assert_allclose(kept[2], self._copy_energies(step, x_new.host, out[2], out[3]), rtol=1e-12)
        e0 = _stacked_energy(self, step, x.host)
        for i in np.flatnonzero(accepted & open_ & (alpha > 0)):
            a = alpha[i] * 0.5 ** backtracks[i]
            y = x.host.copy()
            y[self.scene.index[i]] = x_new.host[self.scene.index[i]]
            change = _stacked_energy(self, step, y) - e0
            assert change <= self.config.armijo_c * a * slope[i] + 1e-13 * abs(e0), (i, change, a * slope[i])
            checked.append(i)
        return out

    def no_groups(*args):
        raise AssertionError("an Armijo group energy was evaluated")

    monkeypatch.setattr(lockstep_module.LockstepSolver, "_line_search_copies", spy)
    monkeypatch.setattr(lockstep_module.LockstepSolver, "_energy_with", no_groups)
    _, infos = _run(model, config)
    assert set(checked) == {0, 1, 2} and len(checked) >= sum(it for row in infos for it, _ in row) - 3 * len(infos)
    assert sum(bt for row in infos for _, bt in row) > 0  # some trial steps were halved


@pytest.mark.parametrize("config", [DIRECT, DEVICE_CG], ids=["direct", "device-cg"])
def test_copies_that_agree_take_the_steps_of_the_group_test(model, config, monkeypatch):
    """Three copies of one parameter set and motion: the per-copy test accepts the steps of the stacked energy's
    group test (the copies' path when a term does not split its energy): the same iterations and backtracks, the
    states bit for bit with the direct solver, to round-off with the device CG (two equal batches of it in one
    process already differ by up to 1e-16 m)."""
    params, motions = [PARAMS[2]] * 3, [MOTIONS[2]] * 3
    batch, infos = _run(model, config, params, motions)
    monkeypatch.setattr(lockstep_module.LockstepSolver, "_copy_energies", lambda *args: None)
    grouped, infos_grouped = _run(model, config, params, motions)
    assert infos == infos_grouped and sum(bt for row in infos for _, bt in row) > 0
    for i in range(3):
        np.testing.assert_allclose(batch.states[i].x, grouped.states[i].x, rtol=0,
                                   atol=0.0 if config is DIRECT else 1e-14)


def test_the_device_terms_add_their_copy_energies_into_one_sum_read_once(model, monkeypatch):
    """With the device CG's iterates, the lumped, friction and fused elastic terms add their per-copy energies into
    one :class:`CopySums` where their kernels run (at the iterate of their last gradient): each term's share equals its
    host split, and the line search's per-copy energies those of the host path, to round-off."""
    from sim_core.energies.base import DeviceCopyEnergies, declares
    from sim_core.ti_kernels.copy_vectors import CopySums

    seen, touching = {}, {}  # calls a term, and copies with energy
    line_search = lockstep_module.LockstepSolver._line_search_copies

    def spy(self, step, x, d, alpha, slope, open_, terms, x_search, info):
        B = self.scene.copies
        assert x.device is not None
        sums = CopySums(self._copy_of_vertex, B)
        for p in step.loop_terms + terms:
            if not declares(p, DeviceCopyEnergies):
                continue
            sums.zero()
            assert p.add_copy_energies_on_device(x.host, x.device, self._copy_of_vertex, sums), type(p).__name__
            host = p.copy_energies(x.host, self._copy_of_vertex, B)
            np.testing.assert_allclose(sums.read(), host, rtol=1e-12, atol=1e-15 * np.max(np.abs(host)))
            seen[type(p).__name__] = seen.get(type(p).__name__, 0) + 1
            touching[type(p).__name__] = touching.get(type(p).__name__, 0) + int(np.count_nonzero(host))
        np.testing.assert_allclose(self._copy_energies(step, x.host, terms, x_search, x.device),
                                   self._copy_energies(step, x.host, terms, x_search), rtol=1e-12)
        return line_search(self, step, x, d, alpha, slope, open_, terms, x_search, info)

    monkeypatch.setattr(lockstep_module.LockstepSolver, "_line_search_copies", spy)
    _run(model, DEVICE_CG, steps=1)
    assert set(seen) == {"LumpedQuadratic", "TiLaggedFriction", "FusedElastic", "TiVertexTriangleContact",
                         "TiEdgeEdgeContact"}
    assert touching["TiVertexTriangleContact"] > 0 and touching["TiEdgeEdgeContact"] > 0  # the kernels summed energies


def test_the_listed_pair_launch_gives_a_lockstep_step_the_default_states(model, monkeypatch):
    """With the device CG's iterates, the pair batch's derivatives at each new trial point in one launch whose active
    list stays on the device (``PairBatch.listed``, CUDA's default, with its two passes) give the Newton iterations and
    backtracks of the default launches and their states to round-off (two equal batches of the device CG in one
    process already differ by up to 1e-16 m), every trial point through that launch, and the pair penalties' per-copy
    energies summed from it."""
    from sim_core.energies.contact import batch_kernel, listed_kernel
    from sim_core.energies.contact.kernel import _Batched

    default, infos = _run(model, DEVICE_CG)
    launches, added = [], []
    kernel = listed_kernel._listed_kernel
    monkeypatch.setattr(listed_kernel, "_listed_kernel", lambda *a: (launches.append(a[4]), kernel(*a)))
    add = _Batched.add_copy_energies_on_device
    monkeypatch.setattr(_Batched, "add_copy_energies_on_device",
                        lambda self, *a: added.append(add(self, *a)) or added[-1])
    monkeypatch.setattr(batch_kernel.PairBatch, "two_pass", True)
    monkeypatch.setattr(batch_kernel.PairBatch, "listed", True)
    listed, infos_listed = _run(model, DEVICE_CG)
    assert infos_listed == infos and sum(bt for row in infos for _, bt in row) > 0
    assert len(launches) >= sum(max(it for it, _ in row) for row in infos)  # a launch a trial point at least
    assert added and all(added)
    for a, b in zip(default.states, listed.states):
        np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-14)


def test_device_rows_from_unheld_arrays_give_a_lockstep_step_the_default_states(model, monkeypatch):
    """With the pair batch's Hessian, distance-gradient and gradient-sum rows left on the device (``device_hessian``,
    ``device_gradient``, the listed launch: CUDA's defaults) in arrays no evaluation holds (``buffers.unheld_rows``),
    a lockstep run of the device CG takes the Newton iterations and backtracks of the host rows' run and its states to
    round-off, while its launches allocate fewer arrays than they take (reused once their evaluations are gone)."""
    from sim_core.energies.contact import batch_kernel
    from sim_core.ti_kernels import buffers, device_copy

    default, infos = _run(model, DEVICE_CG)
    taken, made = [], []
    unheld = buffers.unheld_rows
    monkeypatch.setattr(batch_kernel, "unheld_rows", lambda *a, **k: taken.append(a[1]) or unheld(*a, **k))
    new = device_copy.new_ndarray
    monkeypatch.setattr(device_copy, "new_ndarray", lambda *a: (made.append(a[1]), new(*a))[1])
    for flag in ("two_pass", "listed", "device_hessian", "device_gradient"):
        monkeypatch.setattr(batch_kernel.PairBatch, flag, True)
    kept, infos_kept = _run(model, DEVICE_CG)
    assert infos_kept == infos and sum(bt for row in infos for _, bt in row) > 0
    made_rows = [shape for shape in made if len(shape) >= 2 and shape[1:] in ((12,), (12, 12))]
    assert len(taken) > 2 * len(made_rows) > 0  # (the gradient sums' (2 u, 3) arrays are counted in taken only)
    for a, b in zip(default.states, kept.states):
        np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-14)
