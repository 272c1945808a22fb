"""The solver owns the evaluations its potentials share (sim_core.workspace): the potentials keep
none themselves, the solver's terms keep theirs in the solver's workspace, an entry goes with its
owner, and the workspace is only a memo: a run that never reuses an entry gives the same states bit
for bit."""

from __future__ import annotations

import copy
import gc
import pickle

import numpy as np

from sim_core.control import Control
from sim_core.energies.contact.reference import VertexTriangleContact
from sim_core.energies.friction.reference import LaggedFriction
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.mesh.tet import tet_box
from sim_core.scenes.task_scene import build_task_scene, task_initial_state
from sim_core.simulation import Simulation
from sim_core.workspace import Workspace, workspace_of
from tests.support.press_scenes import EPS, pad_scene, paper_sheet

MEMO_ATTRIBUTES = ("_last", "_kept", "_kept_all", "_kept_hessian", "_kept_gradient")
"""Names under which potentials kept evaluations before the workspace held them."""


class _Forgetful(Workspace):
    """A workspace that keeps nothing: every request is computed afresh."""

    def get(self, owner, name):
        return None

    def take(self, owner, name):
        return None


def _press_sim(workspace: Workspace | None = None) -> Simulation:
    """A paper sheet pressed by the gel pad onto a table plane, with friction (gel, contact, friction)."""
    scene = pad_scene({"sheet": paper_sheet((0.03, 0.024), (6, 5), (-0.015, -0.012, 0.00035))},
                      0.00035 + 0.00015 + EPS + 0.0002,
                      [{"pair": ["pad", "sheet"], "mu": 0.8}, {"pair": ["sheet", "table"], "mu": 0.3}])
    model = build_task_scene(scene)
    sim = Simulation(model)
    if workspace is not None:
        sim.solver.workspace = workspace
        sim.solver.notify_model_changed()
    sim.state = task_initial_state(model)
    return sim


def _run(sim: Simulation, steps: int = 6) -> list[np.ndarray]:
    pose = sim.state.effector_pose["pad"].copy()
    control, states = Control(), []
    for i in range(steps):
        target = pose.copy()
        target[2] -= 1.0e-3 * min(1.0, (i + 1) / 4)
        target[0] += 2.0e-3 * max(0, i - 3)
        control.effector_pose_target["pad"] = target
        sim.step(control)
        states.append(sim.state.x.copy())
    return states


def test_the_solver_terms_keep_their_evaluations_in_the_solver_workspace():
    sim = _press_sim()
    _run(sim, 4)
    solver = sim.solver
    terms = solver.last_record.terms  # the step's potentials: inertia, gravity, elastic, contact, friction
    kinds = {type(p).__name__ for p in terms}
    assert {"StableNeoHookean", "VertexTriangleContact", "LaggedFriction"} <= kinds
    for p in terms:
        if isinstance(p, (StableNeoHookean, VertexTriangleContact, LaggedFriction)):
            assert workspace_of(p) is solver.workspace, type(p).__name__
    assert len(solver.workspace) > 0  # the gel's deformation, the contact evaluations
    for p in terms:
        assert not set(MEMO_ATTRIBUTES) & set(vars(p)), type(p).__name__
    solver.reset_caches()
    assert len(solver.workspace) == 0


def test_the_workspace_is_only_a_memo():
    """The same press, once with the solver's workspace and once with one that keeps nothing:
    the same states bit for bit."""
    kept = _run(_press_sim())
    fresh = _run(_press_sim(_Forgetful()))
    for a, b in zip(kept, fresh):
        np.testing.assert_array_equal(a, b)
    assert np.ptp(kept[-1][:, 2]) > 0.0


def test_an_entry_goes_with_its_owner_and_copies_of_a_workspace_are_empty():
    """Copies of the gel potential (same dF/dx) share its entry; the entries go when their owners
    go (the workspace extends no potential's life); a pickled workspace comes back empty."""
    mesh = tet_box((0.01, 0.01, 0.005), (2, 2, 2), (0.0, 0.0, 0.0))
    workspace = Workspace()
    gel = StableNeoHookean(mesh.tets, mesh.x, 3e5, 0.45)
    gel.workspace = workspace
    x = mesh.x * 1.01
    e = gel.energy(x)
    assert len(workspace) == 1
    twin = copy.copy(gel)
    assert twin.energy(x) == e and len(workspace) == 1
    contact = VertexTriangleContact(np.array([[0, 0]]), np.array([[1, 2, 3]]), np.ones(1), 1.0e4, 2.0e-3)
    contact.workspace = workspace
    y = np.array([[0.0, 0.0, 1.0e-3], [0.0, 0.0, 0.0], [1.0e-2, 0.0, 0.0], [0.0, 1.0e-2, 0.0]])
    assert contact.energy(y) == 0.5 * 1.0e4 * (1.0e-3 - 2.0e-3) ** 2
    assert len(workspace) == 2
    assert len(pickle.loads(pickle.dumps(workspace))) == 0 and len(copy.deepcopy(workspace)) == 0
    del gel, twin, contact
    gc.collect()
    assert len(workspace) == 0
