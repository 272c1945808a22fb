"""State.copy: an independent deep copy, field by field."""

import copy

import numpy as np

from sim_core.collision.memory import CollisionMemory
from sim_core.state import State


def _state() -> State:
    memory = CollisionMemory()
    memory.vertex_triangle.update(np.array([[0, 1], [2, 3]]), np.array([1.0, -1.0]))
    memory.edge_edge.update(np.array([[4, 5]]), np.array([-1.0]))
    return State(
        t=0.25, x=np.arange(12.0).reshape(4, 3), v=np.ones((4, 3)), hinge_theta_bar={"sheet": np.array([0.1, 0.2])},
        effector_pose={"dome": np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])}, gripper_opening={"dome": 0.01},
        contact_memory=memory, contact_force=np.full((4, 3), 2.0), step_index=7,
        candidate_state={"maxwell": {"gel": np.eye(3)[None]}, "adhesion": np.array([1, 2])},
    )


def _assert_equal(a: State, b: State) -> None:
    assert type(a) is type(b)
    assert a.t == b.t and a.step_index == b.step_index
    for name in ("x", "v", "contact_force"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in ("hinge_theta_bar", "effector_pose"):
        assert getattr(a, name).keys() == getattr(b, name).keys()
        for k in getattr(a, name):
            np.testing.assert_array_equal(getattr(a, name)[k], getattr(b, name)[k])
    assert a.gripper_opening == b.gripper_opening
    assert a.contact_memory.vertex_triangle == b.contact_memory.vertex_triangle
    assert a.contact_memory.edge_edge == b.contact_memory.edge_edge
    np.testing.assert_array_equal(a.candidate_state["maxwell"]["gel"], b.candidate_state["maxwell"]["gel"])
    np.testing.assert_array_equal(a.candidate_state["adhesion"], b.candidate_state["adhesion"])


def test_copy_equals_the_deep_copy():
    s = _state()
    _assert_equal(s.copy(), copy.deepcopy(s))


def test_copy_shares_no_mutable_part_with_the_original():
    s = _state()
    c = s.copy()
    reference = copy.deepcopy(s)
    c.x[0, 0] = -1.0
    c.v[:] = 0.0
    c.contact_force[1] = 9.0
    c.hinge_theta_bar["sheet"][0] = 3.0
    c.hinge_theta_bar["other"] = np.zeros(1)
    c.effector_pose["dome"][2] = -5.0
    c.gripper_opening["dome"] = 0.5
    c.contact_memory.vertex_triangle.update(np.array([[9, 9]]), np.array([1.0]))
    c.contact_memory.edge_edge._sides[0] = 1.0
    c.candidate_state["maxwell"]["gel"][0, 0, 0] = 4.0
    c.candidate_state["adhesion"][0] = 0
    c.candidate_state["new"] = 1
    _assert_equal(s, reference)
    assert "new" not in s.candidate_state and "other" not in s.hinge_theta_bar


def test_copy_of_a_state_without_memory_or_force():
    s = State(t=0.0, x=np.zeros((2, 3)), v=np.zeros((2, 3)))
    c = s.copy()
    assert c.contact_memory is None and c.contact_force is None and c.candidate_state == {}
    assert c.candidate_state is not s.candidate_state and c.hinge_theta_bar is not s.hinge_theta_bar
