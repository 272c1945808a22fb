"""The lockstep's simplified Newton test per copy (sim_core.batch.simplified): each copy's touching contacts compared
as sets, and a lockstep run that ends copies by the test at the iterates and iteration counts of a run without it,
with fewer factorisations."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim_core.batch import BatchedSimulation
from sim_core.batch.simplified import active_by_copy, active_sets, same_active_by_copy, same_active_sets
from sim_core.energies.contact.reference import VertexTriangleContact
from sim_core.scenes.task_scene import task_initial_state
from sim_core.solver_config import SolverConfig
from tests.support.batch_copies import MOTIONS, PARAMS, STEPS, control, pad_model


class _Penalty:
    """A penalty contact term (capability PenaltyContact): entries touch where their first vertex's z < 0."""

    def __init__(self, vertices):
        self.vertices = np.asarray(vertices)

    def active_mask(self, x):
        first = self.vertices if self.vertices.ndim == 1 else self.vertices[:, 0]
        return x[first, 2] < 0.0


def test_each_copys_touching_contacts_are_compared_as_a_set():
    copy_of = np.repeat(np.arange(4), 5)  # 4 copies of 5 vertices
    pairs = _Penalty([[0, 1, 2, 3], [5, 6, 7, 8], [10, 11, 12, 13], [11, 10, 12, 13], [1, 0, 2, 4], [7, 5, 6, 8],
                      [12, 10, 11, 13]])
    planes = _Penalty([2, 9, 14, 19])
    x = np.ones((20, 3))
    x[[0, 1, 5, 10, 11, 14, 19], 2] = -1.0
    before = active_by_copy([pairs, planes], x, copy_of)
    assert before[0][0].tolist() == [0, 0, 1, 2, 2] and before[1][0].tolist() == [2, 3]
    # the same contacts found in another order (a new candidate list): the same for every copy
    shuffled = active_by_copy([_Penalty(pairs.vertices[::-1]), planes], x, copy_of)
    np.testing.assert_array_equal(same_active_by_copy(before, shuffled, 4), [True] * 4)
    # copy 1 gains a pair, copy 2's plane contact lets go, copy 3 has none either way
    x2 = x.copy()
    x2[7, 2], x2[14, 2] = -1.0, 1.0
    after = active_by_copy([pairs, planes], x2, copy_of)
    np.testing.assert_array_equal(same_active_by_copy(before, after, 4), [True, False, False, True])
    # as many contacts, one of them another: copy 2's pair [10,11,12,13] lets go and [12,10,11,13] touches
    x3 = x.copy()
    x3[10, 2], x3[12, 2] = 1.0, -1.0
    moved = active_by_copy([pairs, planes], x3, copy_of)
    assert np.bincount(moved[0][0], minlength=4).tolist() == np.bincount(before[0][0], minlength=4).tolist()
    np.testing.assert_array_equal(same_active_by_copy(before, moved, 4), [True, True, False, True])
    assert not same_active_by_copy(before, None, 4).any() and not same_active_by_copy(before, before[:1], 4).any()
    assert active_by_copy([object()], x, copy_of) is None  # not a penalty contact: no test


def _touching(z: list[float]) -> np.ndarray:
    """Positions of 3 copies of 5 vertices: a unit triangle at z = 0 (vertices 0-2) and two points above its inside at
    heights ``z`` (vertex 3 then 4 of copy 0, then copy 1's, ...)."""
    x = np.zeros((15, 3))
    for c in range(3):
        x[5 * c: 5 * c + 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
        x[5 * c + 3: 5 * c + 5] = [[0.2, 0.2, z[2 * c]], [0.3, 0.3, z[2 * c + 1]]]
    return x


def test_the_touching_pairs_of_one_candidate_list_are_compared_by_index_as_by_their_rows():
    """The index comparison (same potential object) and the fallback for a new candidate list give, copy by copy, the
    rows comparison's answers on a real vertex-triangle potential's evaluations."""
    copy_of = np.repeat(np.arange(3), 5)
    triangles = np.array([[5 * c, 5 * c + 1, 5 * c + 2] for c in range(3)])
    pairs = np.array([[5 * c + v, c] for c in range(3) for v in (3, 4)])
    vt = VertexTriangleContact(pairs, triangles, np.zeros(len(pairs)), 1e3, 0.01)
    vt_reversed = VertexTriangleContact(pairs[::-1].copy(), triangles, np.zeros(len(pairs)), 1e3, 0.01)
    near, far = 0.005, 0.5
    x0 = _touching([near, far, near, near, far, far])
    cases = {  # positions -> each copy's "same touching pairs as at x0"
        "equal": (_touching([near, far, near, near, far, far]), [True, True, True]),
        "copy 1 lets one go, copy 2 gains one": (_touching([near, far, near, far, near, far]), [True, False, False]),
        "copy 0 swaps its touching pair": (_touching([far, near, near, near, far, far]), [False, True, True]),
    }
    before = active_sets([vt], x0)
    assert before[0][1].tolist() == [0, 2, 3]  # ascending indices into the pairs
    for name, (x, expected) in cases.items():
        reference = same_active_by_copy(active_by_copy([vt], x0, copy_of), active_by_copy([vt], x, copy_of), 3)
        np.testing.assert_array_equal(reference, expected, err_msg=name)
        now = active_sets([vt], x)
        np.testing.assert_array_equal(same_active_sets(before, now, copy_of, 3), expected, err_msg=name)
        # another potential object (a new candidate list, its pairs in another order): the rows compared
        np.testing.assert_array_equal(same_active_sets(before, active_sets([vt_reversed], x), copy_of, 3), expected,
                                      err_msg=name)
    assert not same_active_sets(before, None, copy_of, 3).any()
    assert active_sets([object()], x0) is None  # not a penalty contact: no test


def test_the_device_solvers_question_every_open_copy_the_same_is_answered_as_the_whole_comparison_answers_it():
    """``same_active_sets(..., every=mask)``: where every copy of the mask has the same touching pairs, the whole
    comparison's answer; where one of them differs, all False (found from one entry of the two index lists' symmetric
    difference: ``_first_difference`` gives such an entry for lists differing anywhere, in length or not)."""
    from sim_core.batch.simplified import _first_difference

    rng = np.random.default_rng(7)
    copies, per_copy = 6, 40
    copy_of = np.repeat(np.arange(copies), 5)
    triangles = np.array([[5 * c, 5 * c + 1, 5 * c + 2] for c in range(copies)])
    pairs = np.array([[5 * c + 3 + k % 2, c] for c in range(copies) for k in range(per_copy)])  # copy c's rows together
    vt = VertexTriangleContact(pairs, triangles, np.zeros(len(pairs)), 1e3, 0.01)
    seen = {"some differ": 0, "every one same": 0}
    for trial in range(300):
        before = np.flatnonzero(rng.random(len(pairs)) < 0.3)
        now = before.copy()
        changed = rng.choice(copies, rng.integers(0, 3), replace=False)  # these copies' touching pairs redrawn
        for c in changed:
            rows = np.arange(c * per_copy, (c + 1) * per_copy)
            now = np.union1d(now[(now < rows[0]) | (now > rows[-1])], rows[rng.random(per_copy) < 0.3])
        if not np.array_equal(before, now):
            u, v = (before, now) if trial % 2 else (now, before)
            assert _first_difference(u, v) in np.setxor1d(u, v)
        whole = same_active_sets([(vt, before)], [(vt, now)], copy_of, copies)
        mask = rng.random(copies) < 0.5
        got = same_active_sets([(vt, before)], [(vt, now)], copy_of, copies, every=mask)
        if whole[mask].all():
            seen["every one same"] += 1
            np.testing.assert_array_equal(got, whole)
        else:
            seen["some differ"] += 1
            assert not got.any()
    assert min(seen.values()) > 50  # both answers drawn often
    # one list the other's beginning (a touching pair let go at the end, or gained)
    assert _first_difference(np.array([1, 4, 9]), np.array([1, 4])) == 9
    assert _first_difference(np.array([1, 4]), np.array([1, 4, 9, 12])) == 9


@pytest.mark.parametrize("config", [SolverConfig(lockstep=True),
                                    SolverConfig(lockstep=True, backend="taichi-cpu", linear_solver="envelope")],
                         ids=["direct", "envelope"])
def test_a_lockstep_run_stops_copies_by_the_simplified_test_at_the_same_iterates_with_fewer_factorisations(config):
    """The host's direct solver and the device's envelope Cholesky (its kept factors: one substitution)."""
    model = pad_model()
    runs = {}
    for check in (0.25, 0.0):
        batch = BatchedSimulation.from_model(model, 3, params=PARAMS, state=task_initial_state(model),
                                             solver_config=dataclasses.replace(config, simplified_newton_check=check))
        pose0 = [s.effector_pose["pad"].copy() for s in batch.states]
        iterations, reasons, factorizations, positions = [], [], 0, []
        for k in range(STEPS):
            res = batch.step([control(pose0[i], MOTIONS[i], k) for i in range(3)])
            iterations.append([info.iterations for info in res.infos])
            reasons += [info.stop_reason for info in res.infos]
            factorizations += batch.lockstep.solver.last_stacked_info.factorizations
            positions.append(batch.positions())
        runs[check] = iterations, reasons, factorizations, positions
    (it_on, why_on, f_on, x_on), (it_off, why_off, f_off, x_off) = runs[0.25], runs[0.0]
    assert it_on == it_off  # each copy stopped at the iteration (and iterate) at which the velocity test stops it
    assert "simplified" in why_on and "simplified" not in why_off
    assert f_on < f_off
    for a, b in zip(x_on, x_off):  # (the device's atomic sums vary at ~1e-18 m from run to run)
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-13)
