"""Contact side memory: lookups, updates, independent copies."""

import numpy as np
import pytest

from sim_core.collision.memory import CollisionMemory, ContactMemory
from sim_core.errors import ConfigError


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


def _brute_lookup(memory: ContactMemory, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    stored = {tuple(p): s for p, s in zip(memory.pairs.tolist(), memory.sides)}
    found = np.array([tuple(p) in stored for p in pairs.tolist()], dtype=bool)
    return np.array([stored.get(tuple(p), 0.0) for p in pairs.tolist()]), found


def test_lookup_of_sorted_and_unsorted_pair_lists_matches_a_dictionary():
    rng = np.random.default_rng(3)
    memory = ContactMemory("edge_edge")
    remembered = np.unique(rng.integers(0, 40, (25, 2)), axis=0)
    memory.update(remembered, np.where(rng.random(len(remembered)) < 0.5, -1.0, 1.0))
    candidates = np.unique(np.concatenate([rng.integers(0, 40, (300, 2)), remembered[::3]]), axis=0)  # sorted
    for pairs in (candidates, candidates[rng.permutation(len(candidates))], candidates[:1], candidates[:0],
                  np.concatenate([candidates[:5], candidates[:5]]), remembered):
        sides, found = memory.lookup(pairs)
        expected_sides, expected_found = _brute_lookup(memory, pairs)
        np.testing.assert_array_equal(found, expected_found)
        np.testing.assert_array_equal(sides, expected_sides)
        current = np.where(rng.random(len(pairs)) < 0.5, -1.0, 1.0)
        np.testing.assert_array_equal(memory.resolve(pairs, current), np.where(expected_found, expected_sides, current))
    assert ContactMemory().lookup(candidates)[1].sum() == 0


def test_update_keeps_remembered_sides_sorts_and_rejects_duplicates():
    memory = ContactMemory("vertex_triangle")
    memory.update(np.array([[4, 1], [2, 7]]), np.array([1.0, -1.0]))
    memory.update(np.array([[9, 0], [4, 1], [0, 3]]), np.array([-1.0, -1.0, 1.0]))  # (4, 1) keeps +1
    np.testing.assert_array_equal(memory.pairs, [[0, 3], [4, 1], [9, 0]])
    np.testing.assert_array_equal(memory.sides, [1.0, 1.0, -1.0])
    with pytest.raises(ConfigError, match="duplicate pairs"):
        memory.update(np.array([[1, 1], [0, 0], [1, 1]]), np.ones(3))
    with pytest.raises(ConfigError, match="duplicate pairs"):
        memory.update(np.array([[1, 1], [1, 1]]), np.ones(2))
    with pytest.raises(ConfigError, match="signs must be"):
        memory.update(np.array([[1, 1]]), np.array([0.5]))


def test_found_in_sorted_keys_gives_the_lookups_of_the_keys():
    """``found_in`` of sorted unique keys (a candidate list's) names the remembered keys' rows and sides, as looking
    every key up does; empty memories and lists give nothing."""
    rng = np.random.default_rng(3)
    pairs = np.unique(rng.integers(0, 40, size=(300, 2)), axis=0)
    keys = (pairs[:, 0] << 32) | pairs[:, 1]
    m = ContactMemory()
    assert [len(a) for a in m.found_in(keys)] == [0, 0]
    remembered = np.concatenate([pairs[rng.choice(len(pairs), 25, replace=False)], [[50, 1], [41, 0], [0, 45]]])
    m.update(remembered, rng.choice([-1.0, 1.0], size=len(remembered)))
    rows, sides = m.found_in(keys)
    want, found = m.lookup(pairs)
    np.testing.assert_array_equal(rows, np.flatnonzero(found))
    np.testing.assert_array_equal(sides, want[found])
    assert len(rows) == 25 and [len(a) for a in m.found_in(keys[:0])] == [0, 0]
