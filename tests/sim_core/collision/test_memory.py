"""Contact side memory: copies are independent."""

import numpy as np

from sim_core.collision.memory import CollisionMemory, ContactMemory


def test_contact_memory_copy_is_equal_and_independent():
    m = ContactMemory("vertex_triangle")
    m.update(np.array([[3, 1], [0, 2]]), np.array([-1.0, 1.0]))
    c = m.copy()
    assert c == m and c.kind == "vertex_triangle" and type(c) is ContactMemory
    c._sides[0] = -c._sides[0]
    c._keys[1] = 99
    np.testing.assert_array_equal(m.pairs, [[0, 2], [3, 1]])
    np.testing.assert_array_equal(m.sides, [1.0, -1.0])
    c.update(np.array([[5, 5]]), np.array([1.0]))
    assert len(m) == 2


def test_collision_memory_copy_copies_each_kind():
    m = CollisionMemory()
    m.vertex_triangle.update(np.array([[0, 1]]), np.array([1.0]))
    m.edge_edge.update(np.array([[2, 3]]), np.array([-1.0]))
    c = m.copy()
    assert c.vertex_triangle == m.vertex_triangle and c.edge_edge == m.edge_edge
    assert c.vertex_triangle is not m.vertex_triangle and c.edge_edge is not m.edge_edge
    c.edge_edge.update(np.zeros((0, 2), dtype=np.int64), np.zeros(0))
    assert len(m.edge_edge) == 1
