"""Lockstep batches (SolverConfig.lockstep, sim_core.batch.lockstep / stacked): one Newton solve of all
copies per step gives, per copy, the states of separate runs to the Newton tolerance; a copy that
diverges is reported and the others finish; the stacked model keeps the copies apart."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from sim_core.batch import BatchedSimulation
from sim_core.batch.stacked import stack_models
from sim_core.control import Control
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.scenes.task_scene import task_initial_state
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from tests.support.batch_copies import MOTIONS, PARAMS, STEPS, control, pad_model, separate_run

LOCKSTEP = SolverConfig(lockstep=True)
LOCKSTEP_CG = SolverConfig(lockstep=True, backend="taichi-cpu", linear_solver="pcg")  # the GPU's: device vectors
LOCKSTEP_ENVELOPE = SolverConfig(lockstep=True, backend="taichi-cpu", linear_solver="envelope")  # direct, on the device
TOL = SolverConfig().tol_velocity * 0.005  # the Newton tolerance as a displacement per 5 ms step, m


@pytest.fixture(scope="module")
def model():
    return pad_model()


def _lockstep_batch(model, config=LOCKSTEP, params=PARAMS):
    return BatchedSimulation.from_model(model, len(params), params=params, state=task_initial_state(model),
                                        solver_config=config)


def _run(batch, steps=STEPS):
    pose0 = batch.states[0].effector_pose["pad"].copy()
    per_step, results = [], []
    for k in range(steps):
        res = batch.step([control(pose0, MOTIONS[i], k) for i in range(batch.batch_size)])
        results.append(res)
        per_step.append([s.copy() for s in batch.states])
    return per_step, results


@pytest.mark.parametrize("config, schedule", [(LOCKSTEP, None), (LOCKSTEP_CG, None), (LOCKSTEP_ENVELOPE, None),
                                              (LOCKSTEP_ENVELOPE, "panels")],
                         ids=["direct", "device-cg", "envelope", "envelope-panels"])
def test_lockstep_batch_of_three_gives_the_states_of_three_separate_runs(model, config, schedule, monkeypatch):
    """Each copy at its separate run's states; ``envelope-panels``: the envelope factorised by vertex panels (CUDA's
    schedule, ``envelope_cholesky.CUDA_SCHEDULE``; on the CPU arch ``SCHEDULE``), every other case its default."""
    if schedule is not None:
        from sim_core.ti_kernels import envelope_cholesky

        monkeypatch.setattr(envelope_cholesky, "SCHEDULE", schedule)
    batch = _lockstep_batch(model, config)
    assert batch.lockstep is not None
    if schedule is not None:
        assert batch.lockstep.solver.pcg.schedule == schedule
    per_step, results = _run(batch)
    solver = batch.lockstep.solver
    for res in results:
        assert res.failed_now == [] and all(info is not None and info.iterations >= 1 for info in res.infos)
    # one Newton iteration of all copies together: the step's iterations are the slowest copy's, and it
    # factorised far fewer matrices than the copies' iterations add up to
    first = [info.iterations for info in results[-1].infos]
    assert solver.last_stacked_info.iterations == max(first)
    stiffness = model.contact.stiffness
    for i in range(3):
        alone = separate_run(model, PARAMS[i], MOTIONS[i])
        for k in range(STEPS):
            got, ref = per_step[k][i], alone[k]
            assert np.max(np.abs(got.x - ref.x)) <= TOL, (i, k)
            assert np.max(np.abs(got.v - ref.v)) <= TOL / 0.005 * 2, (i, k)
            # a penalty force changes by the stiffness times the position change
            assert np.max(np.abs(got.contact_force - ref.contact_force)) <= stiffness * TOL, (i, k)
            assert got.step_index == ref.step_index == k + 1 and got.t == pytest.approx(ref.t)
            np.testing.assert_allclose(got.effector_pose["pad"], ref.effector_pose["pad"], atol=1e-12)
    x = batch.positions()
    assert min(np.max(np.abs(x[0] - x[1])), np.max(np.abs(x[0] - x[2])), np.max(np.abs(x[1] - x[2]))) > 100 * TOL
    # the copies' own parameters reached the stacked model: one material group per parameter set
    assert batch.lockstep.scene.model.bodies["pad#1"].material["youngs_modulus"] == 6e5
    assert batch.lockstep.scene.model.bodies["pad#0"].material["youngs_modulus"] == 3e5


def test_the_backtrack_decided_on_the_device_takes_the_host_decisions(model, monkeypatch):
    """The device-vector lockstep's line search with its further trial points' tests and halvings decided on the
    device against the same decided on the host from one read a trial point: every copy takes the same Newton iterations and backtracks,
    and the states agree to round-off (the CPU arch's parallel reductions differ run to run by ~1e-17 m)."""
    from sim_core.batch.line_search import CopyLineSearch
    from sim_core.ti_kernels.backtrack import DeviceBacktrack

    decided = []
    decide = DeviceBacktrack.decide
    monkeypatch.setattr(DeviceBacktrack, "decide", lambda self, *a: decided.append(1) or decide(self, *a))
    runs = {}
    for on_device in (True, False):
        monkeypatch.setattr(CopyLineSearch, "device_backtrack", "always" if on_device else "never")
        before = len(decided)
        runs[on_device] = _run(_lockstep_batch(model, LOCKSTEP_CG))
        assert (len(decided) > before) == on_device  # the trial points' decisions made where asked
    (device_states, device_results), (host_states, host_results) = runs[True], runs[False]
    for k in range(STEPS):
        for i in range(3):
            assert device_results[k].infos[i].iterations == host_results[k].infos[i].iterations, (k, i)
            assert device_results[k].infos[i].backtracks == host_results[k].infos[i].backtracks, (k, i)
            np.testing.assert_allclose(device_states[k][i].x, host_states[k][i].x, rtol=0, atol=1e-15)
    assert sum(info.backtracks for res in device_results for info in res.infos) > 0  # some copies halved their step


@pytest.mark.parametrize("copies", [[2, 0], [0, 1, 2]], ids=["some", "every"])
def test_copy_states_by_blocks_equal_the_gather_of_the_index(model, copies):
    same = stack_models([copy.deepcopy(model) for _ in range(3)])
    assert len(same._blocks) == len(model.bodies)  # one material group: each body's copies one block
    rng = np.random.default_rng(3)
    stacked = same.stack_states([task_initial_state(model)] * 3)
    stacked.x = stacked.x + 1e-3 * rng.normal(size=stacked.x.shape)
    stacked.v = rng.normal(size=stacked.x.shape)
    stacked.contact_force = rng.normal(size=stacked.x.shape)
    stacked.hinge_theta_bar = {k: rng.normal(size=v.shape) for k, v in stacked.hinge_theta_bar.items()}
    args = (stacked, np.array(copies), 0.1 * np.arange(1, len(copies) + 1), np.arange(4, 4 + len(copies)))
    blocks = same.copy_states(*args)
    same._blocks = None  # the gather of any layout
    for a, b in zip(blocks, same.copy_states(*args)):
        for name in ("x", "v", "contact_force"):
            assert np.array_equal(getattr(a, name), getattr(b, name))
        assert a.hinge_theta_bar.keys() == b.hinge_theta_bar.keys() and a.effector_pose.keys() == b.effector_pose.keys()
        assert all(np.array_equal(a.hinge_theta_bar[k], b.hinge_theta_bar[k]) for k in a.hinge_theta_bar)
        assert all(np.array_equal(a.effector_pose[k], b.effector_pose[k]) for k in a.effector_pose)
        assert (a.t, a.step_index, a.gripper_opening) == (b.t, b.step_index, b.gripper_opening)
    for j, i in enumerate(copies):  # the copy's rows less its offset (positions and poses), the stacked rows else
        rows = same.index[i]
        assert np.array_equal(blocks[j].x, stacked.x[rows] - same.offset[i])
        assert np.array_equal(blocks[j].v, stacked.v[rows]) and np.array_equal(blocks[j].contact_force,
                                                                               stacked.contact_force[rows])
        pose = stacked.effector_pose[f"pad#{i}"]
        assert np.array_equal(blocks[j].effector_pose["pad"], np.concatenate([pose[:3] - same.offset[i], pose[3:]]))


def test_the_device_contact_force_of_a_lockstep_step_is_the_host_sum_bit_for_bit(model, monkeypatch):
    """With the batched CG each step's contact force is summed on the device where the pair terms' gradients are
    (DeviceIterates.contact_force; the plane's and friction's then subtracted on the host): bit for bit the host's
    sum of the same terms at the same positions (step_terms.contact_force), signed zeros included."""
    from sim_core.batch.device_iterates import DeviceIterates
    from sim_core.batch.lockstep import LockstepSolver
    from sim_core.energies.base import DeviceGradient, declares
    from sim_core.solver import NewtonSolver

    summed, checked = LockstepSolver._contact_force, []

    def both(self, x, terms):
        got = summed(self, x, terms)
        want = NewtonSolver._contact_force(self, x, terms)
        assert got.tobytes() == want.tobytes()
        on_device = [declares(p, DeviceGradient) for p in terms]
        checked.append((on_device[0], not all(on_device), bool(np.any(want != 0.0))))
        return got

    device_sums = []
    original = DeviceIterates.contact_force
    monkeypatch.setattr(DeviceIterates, "contact_force",
                        lambda self, *a: (device_sums.append(1), original(self, *a))[1])
    monkeypatch.setattr(LockstepSolver, "_contact_force", both)
    _run(_lockstep_batch(model, LOCKSTEP_CG), 3)
    assert len(checked) == len(device_sums) == 3
    assert all(first and mixed for first, mixed, _ in checked) and any(nonzero for *_, nonzero in checked)


@pytest.mark.parametrize("config", [LOCKSTEP, LOCKSTEP_CG, LOCKSTEP_ENVELOPE], ids=["direct", "device-cg", "envelope"])
def test_a_lockstep_copy_that_diverges_is_reported_and_the_others_finish(model, config):
    batch = _lockstep_batch(model, config)
    sheet = model.bodies["sheet"].vertices
    # copy 1 starts from a blown-up state (one sheet vertex with a non-finite velocity): its incremental
    # potential has a non-finite gradient, and its separate run raises
    batch.sims[1].state.v[sheet[len(sheet) // 2]] = [0.0, 0.0, np.nan]
    start = batch.states[1].copy()
    alone = Simulation(copy.deepcopy(batch.sims[1].model))
    alone.state = start.copy()
    with pytest.raises(SimulationDivergedError):
        alone.step(control(start.effector_pose["pad"], MOTIONS[1], 0))
    _, results = _run(batch)
    assert results[0].failed_now == [1] and results[0].infos[1] is None
    assert batch.failures[1].startswith("step 0 ") and "non-finite gradient" in batch.failures[1]
    assert all(not res.stepped[1] and res.infos[1] is None for res in results[1:])  # not stepped again
    assert list(batch.active) == [True, False, True]
    np.testing.assert_array_equal(batch.states[1].x, start.x)  # the last good state is kept
    assert np.all(np.isfinite(batch.positions()[[0, 2]]))  # nothing of copy 1 leaked into the others
    assert batch.states[1].step_index == 0
    for i in (0, 2):
        ref = separate_run(model, PARAMS[i], MOTIONS[i])[-1]
        assert batch.states[i].step_index == STEPS
        assert np.max(np.abs(batch.states[i].x - ref.x)) <= TOL
    batch.reset()
    assert list(batch.active) == [True, True, True] and batch.states[1].step_index == 0


@pytest.mark.parametrize("config", [LOCKSTEP, LOCKSTEP_CG, LOCKSTEP_ENVELOPE], ids=["direct", "device-cg", "envelope"])
def test_a_copy_stops_by_the_force_test_where_its_gradient_is_below_tol_force(model, config):
    """The per-copy stopping tests include the force test: with ``tol_force`` above every copy's largest gradient
    entry each copy stops at its first iteration by "force" (its residual far above ``tol_velocity``), as its separate
    run does."""
    from dataclasses import replace

    loose = replace(config, tol_force=1e12)
    _, results = _run(_lockstep_batch(model, loose), steps=2)
    for res in results:
        assert [(info.iterations, info.stop_reason) for info in res.infos] == [(1, "force")] * 3
        assert all(info.residual_velocity > loose.tol_velocity for info in res.infos)
    alone = Simulation(copy.deepcopy(model), solver_config=replace(SolverConfig(), tol_force=1e12))
    alone.state = task_initial_state(model)
    info = alone.step(control(alone.state.effector_pose["pad"], MOTIONS[0], 0))
    assert (info.iterations, info.stop_reason) == (1, "force")


def test_stacked_model_keeps_the_copies_apart_and_shares_one_term_per_energy(model):
    same = stack_models([copy.deepcopy(model) for _ in range(4)])
    n = model.vertex_count
    assert same.model.vertex_count == 4 * n and same.index.shape == (4, n)
    assert sorted(np.unique(same.index)) == list(range(4 * n))  # every stacked vertex is one copy's
    # one material group: the scene's bodies, each holding all copies (one kernel per energy term)
    assert list(same.model.bodies) == list(model.bodies)
    assert same.model.bodies["sheet"].triangles.shape[0] == 4 * model.bodies["sheet"].triangles.shape[0]
    assert list(same.model.friction) == list(model.friction)
    # copies translated along the planes (their normals see no offset), farther apart than the scene
    for p in model.planes.values():
        np.testing.assert_allclose(same.offset @ np.asarray(p.normal, float), 0.0, atol=1e-12)
    extent = np.ptp(model.x_rest, axis=0).max()
    gaps = [np.linalg.norm(same.offset[i] - same.offset[j]) for i in range(4) for j in range(i)]
    assert min(gaps) >= extent + 0.5
    # positions and poses go in and come back out unchanged
    state = task_initial_state(model)
    back = same.copy_state(same.stack_states([state] * 4), 3, state.t, 0)
    np.testing.assert_allclose(back.x, state.x, atol=1e-15)
    np.testing.assert_allclose(back.effector_pose["pad"], state.effector_pose["pad"], atol=1e-15)
    # several copies' states at once: each its own positions, velocities, forces, poses, time and step
    states = []
    for i in range(4):
        s = state.copy()
        s.x = s.x + 1e-3 * i
        s.v = np.full_like(s.x, float(i))
        s.contact_force = np.full_like(s.x, -float(i))
        s.effector_pose["pad"] = s.effector_pose["pad"] + np.r_[1e-3 * i, 0, 0, 0, 0, 0, 0]
        s.hinge_theta_bar = {k: v + 0.01 * i for k, v in s.hinge_theta_bar.items()}
        states.append(s)
    backs = same.copy_states(same.stack_states(states), np.array([3, 0, 2]), np.array([0.1, 0.2, 0.3]),
                             np.array([7, 8, 9]))
    for b, i, t, k in zip(backs, (3, 0, 2), (0.1, 0.2, 0.3), (7, 8, 9)):
        np.testing.assert_allclose(b.x, states[i].x, atol=1e-15)
        np.testing.assert_array_equal(b.v, states[i].v)
        np.testing.assert_array_equal(b.contact_force, states[i].contact_force)
        np.testing.assert_allclose(b.effector_pose["pad"], states[i].effector_pose["pad"], atol=1e-15)
        assert b.t == t and b.step_index == k
        assert set(b.hinge_theta_bar) == set(state.hinge_theta_bar) and b.hinge_theta_bar
        for sheet, theta in b.hinge_theta_bar.items():
            np.testing.assert_array_equal(theta, states[i].hinge_theta_bar[sheet])

    # after steps with contact, no contact candidate pairs two copies
    batch = _lockstep_batch(model)
    _run(batch, steps=2)
    scene, contact = batch.lockstep.scene, batch.lockstep.solver.contact
    copy_of = np.empty(scene.model.vertex_count, dtype=np.int64)
    copy_of[scene.index] = np.arange(scene.copies)[:, None]
    terms = batch.lockstep.solver.last_record.terms
    vt = next(t for t in terms if type(t).__name__.endswith("VertexTriangleContact"))
    ee = next(t for t in terms if type(t).__name__.endswith("EdgeEdgeContact"))
    assert len(vt.pairs) > 0
    vt_vertices = np.column_stack([vt.pairs[:, 0], contact.triangles[vt.pairs[:, 1]]])
    ee_vertices = np.column_stack([contact.edges[ee.pairs[:, 0]], contact.edges[ee.pairs[:, 1]]])
    for verts in (vt_vertices, ee_vertices):
        assert np.all(copy_of[verts] == copy_of[verts[:, :1]])


def test_lockstep_settings_are_checked(model):
    with pytest.raises(ConfigError, match="pcg.*Taichi backend"):
        SolverConfig(lockstep=True, linear_solver="pcg")
    sims = [Simulation(copy.deepcopy(model), solver_config=LOCKSTEP), Simulation(copy.deepcopy(model), dt=0.002,
                                                                                   solver_config=LOCKSTEP)]
    with pytest.raises(ConfigError, match="batch copy 1: dt"):
        BatchedSimulation(sims)
    other = copy.deepcopy(model)
    other.set_parameter("contact.stiffness", 1e3)
    with pytest.raises(ConfigError, match="batch copy 1: its contact settings differ"):
        stack_models([model, other])
    nodal = copy.deepcopy(model)
    nodal.meta["solid_element"] = "nodal_pressure_neohookean"
    with pytest.raises(ConfigError, match="batch copy 1: its membrane / bending model / solid element differ"):
        stack_models([model, nodal])
    assert stack_models([nodal, copy.deepcopy(nodal)]).model.meta["solid_element"] == "nodal_pressure_neohookean"
    batch = _lockstep_batch(model, params=[{}, {}])
    guess = control(batch.states[0].effector_pose["pad"], MOTIONS[0], 0)
    guess.position_guess = batch.states[0].x.copy()
    with pytest.raises(ConfigError, match="batch copy 0: a lockstep batch takes no Control.position_guess"):
        batch.step([guess, None])


def test_stacked_controls_move_each_copys_pose_targets_by_its_offset(model):
    """stack_controls: the pose targets of copies with a control, translated by their copy's offset (as one array of
    7-number poses, pose by pose otherwise), the gripper targets under the stacked names; a copy without none."""
    scene = stack_models([copy.deepcopy(model) for _ in range(3)])
    rng = np.random.default_rng(5)
    poses = [np.r_[rng.normal(size=3), 0.0, 0.0, 0.0, 1.0] for _ in range(3)]
    last = Control(effector_pose_target={"pad": list(poses[2])}, gripper_target={"pad": 0.01})
    stacked = scene.stack_controls([Control(effector_pose_target={"pad": poses[0]}), None, last])
    assert list(stacked.effector_pose_target) == ["pad#0", "pad#2"] and stacked.gripper_target == {"pad#2": 0.01}
    for i in (0, 2):
        assert np.array_equal(stacked.effector_pose_target[f"pad#{i}"],
                              np.r_[poses[i][:3] + scene.offset[i], poses[i][3:]])
    odd = scene.stack_controls([Control(effector_pose_target={"pad": poses[0][:6]}), None,
                                Control(effector_pose_target={"pad": poses[2]})])  # (a 6-number target: pose by pose)
    assert np.array_equal(odd.effector_pose_target["pad#0"], np.r_[poses[0][:3] + scene.offset[0], poses[0][3:6]])
    assert np.array_equal(odd.effector_pose_target["pad#2"], np.r_[poses[2][:3] + scene.offset[2], poses[2][3:]])


@pytest.mark.parametrize("config", [LOCKSTEP_CG, LOCKSTEP_ENVELOPE], ids=["device-cg", "envelope"])
def test_lockstep_with_the_step_sides_from_device_codes_takes_the_host_sides_steps(model, monkeypatch, config):
    """The candidate lists' step sides from their int8 codes (``ContactSet.device_sides``, the CUDA default) against
    the host's: with copy 1 blown up, it alone fails and the others take the same Newton iterations and states to
    round-off (the CPU arch's parallel reductions differ run to run by ~1e-17 m), which equal their separate runs to the
    solver tolerance."""
    from sim_core.contact_set import ContactSet
    from sim_core.energies.contact import sides_kernel

    launches = []
    kernel = sides_kernel._side_codes_kernel
    monkeypatch.setattr(sides_kernel, "_side_codes_kernel", lambda *a: (launches.append(a), kernel(*a))[1])
    runs = {}
    for on_device in (True, False):
        monkeypatch.setattr(ContactSet, "device_sides", on_device)
        batch = _lockstep_batch(model, config)
        batch.sims[1].state.v[model.bodies["sheet"].vertices[len(model.bodies["sheet"].vertices) // 2]] = \
            [0.0, 0.0, np.nan]
        before = len(launches)
        runs[on_device] = (_run(batch), batch)
        assert (len(launches) > before) == on_device
    ((device_states, device_results), device_batch), ((host_states, host_results), _) = runs[True], runs[False]
    assert device_results[0].failed_now == [1] and list(device_batch.active) == [True, False, True]
    for k in range(STEPS):
        for i in (0, 2):
            assert device_results[k].infos[i].iterations == host_results[k].infos[i].iterations, (k, i)
            np.testing.assert_allclose(device_states[k][i].x, host_states[k][i].x, rtol=0, atol=1e-15)
    for i in (0, 2):
        assert np.max(np.abs(device_states[-1][i].x - separate_run(model, PARAMS[i], MOTIONS[i])[-1].x)) <= TOL



def test_the_envelope_skips_the_copies_that_have_converged_and_every_copy_steps_as_before(model, monkeypatch):
    """A Newton iteration's envelope gathers, factorises and solves only the copies with an update to find
    (``LockstepSolver.skip_closed_copies``): with the copies converging at different iterations, fewer copies are
    factorised than the step's iterations times the copies; a converged copy stays bit for bit where it stopped
    through the iterations of the others, and every copy takes the iterations and reaches the states of the batch
    that factorises every copy (to round-off: the parallel CPU kernels' atomic sums vary from run to run)."""
    from sim_core.batch.lockstep import LockstepSolver

    search = LockstepSolver._line_search_copies
    held_still = []

    def watched(self, step, x, d, alpha, slope, open_, *args):
        start = x.host.copy()
        out = search(self, step, x, d, alpha, slope, open_, *args)
        closed = self.scene.index[~open_].ravel()
        np.testing.assert_array_equal(out[0].host[closed], start[closed])
        held_still.append(len(closed))
        return out

    runs = {}
    for skip in (False, True):
        monkeypatch.setattr(LockstepSolver, "skip_closed_copies", skip)
        monkeypatch.setattr(LockstepSolver, "_line_search_copies", watched if skip else search)
        batch = _lockstep_batch(model, LOCKSTEP_ENVELOPE)
        per_step, results = _run(batch, steps=2)
        runs[skip] = (per_step, results, batch.lockstep.solver.copies_factorized)
    (states, results, full), (skipped_states, skipped_results, skipped) = runs[False], runs[True]
    iterations = [[info.iterations for info in res.infos] for res in results]
    assert iterations == [[info.iterations for info in res.infos] for res in skipped_results]
    assert any(len(set(its)) > 1 for its in iterations)  # copies that converge before the slowest one
    assert full >= sum(3 * max(its) for its in iterations)
    assert skipped <= full - sum(max(its) - min(its) for its in iterations)
    assert sum(held_still) > 0  # line searches with converged copies in the batch
    for got_step, want_step in zip(skipped_states, states):
        for got, want in zip(got_step, want_step):
            assert np.max(np.abs(got.x - want.x)) <= 1e-15
            assert np.max(np.abs(got.v - want.v)) <= 1e-15 / 0.005
