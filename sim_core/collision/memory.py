"""Contact side memory (DESIGN.md "Contact", after ThinShellLab).

When a vertex-triangle (or edge-edge) pair first becomes active, the side of the triangle (or of the
other edge) its vertex is on is stored; the contact normal stays oriented to that side until the
pair ends, so a vertex that penetrated slightly is pushed back rather than through. Pairs are keyed
by two non-negative ints packed into one int64 (``first << 32 | second``) and kept sorted, so lookups
are vectorised ``searchsorted`` calls.
"""

from __future__ import annotations

import numpy as np

from sim_core.collision.distances import edge_edge_side, point_triangle_side
from sim_core.errors import ConfigError


def _pack(pairs: np.ndarray) -> np.ndarray:
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if pairs.size and (pairs.min() < 0 or pairs.max() >= 1 << 31):
        raise ConfigError("ContactMemory: pair indices must be in [0, 2^31)")
    return (pairs[:, 0] << 32) | pairs[:, 1]


class ContactMemory:
    """Remembered side (+1 / -1) of each active pair of one kind.

    Args:
        kind: label used in error messages (e.g. ``"vertex_triangle"``, ``"edge_edge"``).
    """

    def __init__(self, kind: str = "pairs") -> None:
        self.kind = kind
        self._keys = np.zeros(0, dtype=np.int64)
        self._sides = np.zeros(0)

    def __len__(self) -> int:
        return int(self._keys.shape[0])

    @property
    def pairs(self) -> np.ndarray:
        """Remembered pairs, int64 shape ``(m, 2)``, sorted."""
        return np.stack([self._keys >> 32, self._keys & 0xFFFFFFFF], axis=1)

    @property
    def sides(self) -> np.ndarray:
        """Remembered sides of :attr:`pairs`, shape ``(m,)``."""
        return self._sides.copy()

    def lookup(self, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Remembered sides of ``pairs`` (shape ``(p, 2)``).

        Returns:
            ``(sides, found)``: shape ``(p,)`` each; ``sides`` is 0 where ``found`` is False.
        """
        return self._lookup_keys(_pack(pairs))

    def _lookup_keys(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`lookup` of packed pair keys ``(p,)``. Sorted unique keys (a candidate list: hundreds
        of pairs against a few dozen remembered ones) place the remembered keys among them, others
        are searched one by one among the remembered keys; the same result."""
        m, p = len(self), keys.shape[0]
        if not m or not p:
            return np.zeros(p), np.zeros(p, dtype=bool)
        if p > 1 and not np.all(keys[1:] > keys[:-1]):
            pos = np.minimum(np.searchsorted(self._keys, keys), m - 1)
            found = self._keys[pos] == keys
            return np.where(found, self._sides[pos], 0.0), found
        at = np.minimum(np.searchsorted(keys, self._keys), p - 1)
        hit = keys[at] == self._keys
        sides, found = np.zeros(p), np.zeros(p, dtype=bool)
        sides[at[hit]] = self._sides[hit]
        found[at[hit]] = True
        return sides, found

    def found_in(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The remembered pairs among ``keys``, packed pair keys ``(p,)`` sorted and unique (a candidate list's,
        :meth:`~sim_core.energies.contact.pair_lists.CandidateVertices.keys`): ``(rows, sides)``, the rows of
        ``keys`` that are remembered, int64 ``(f,)`` increasing, and their remembered sides ``(f,)``; the
        remembered keys are placed among ``keys`` (one search per remembered pair, no pass over ``keys``)."""
        m, p = len(self), keys.shape[0]
        if not m or not p:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        at = np.minimum(np.searchsorted(keys, self._keys), p - 1)
        hit = keys[at] == self._keys
        return at[hit], self._sides[hit]

    def resolve(self, pairs: np.ndarray, current_sides: np.ndarray) -> np.ndarray:
        """Remembered side where the pair is known, else ``current_sides``; shape ``(p,)``."""
        sides, found = self.lookup(pairs)
        return np.where(found, sides, np.asarray(current_sides, dtype=float))

    def update(self, active_pairs: np.ndarray, signs: np.ndarray) -> None:
        """Replace the memory by the currently active pairs: ended pairs are dropped.

        Args:
            active_pairs: shape ``(p, 2)``, no duplicates.
            signs: side of each pair (+1 / -1), shape ``(p,)``. Pairs that were already remembered
                keep their stored side (a pair's side never changes while it stays active).

        Raises:
            ConfigError: a sign that is not +1 / -1, mismatched lengths, duplicate pairs.
        """
        keys = _pack(active_pairs)
        signs = np.asarray(signs, dtype=float).reshape(-1)
        if signs.shape[0] != keys.shape[0]:
            raise ConfigError(
                f"ContactMemory[{self.kind}]: {keys.shape[0]} pairs but {signs.shape[0]} signs"
            )
        if not np.all(np.abs(signs) == 1.0):
            raise ConfigError(f"ContactMemory[{self.kind}]: signs must be +1 or -1")
        remembered, found = self._lookup_keys(keys)
        signs = np.where(found, remembered, signs)
        if keys.size > 1 and not np.all(keys[1:] > keys[:-1]):  # else sorted and unique already
            order = np.argsort(keys, kind="stable")
            keys, signs = keys[order], signs[order]
            if np.any(keys[1:] == keys[:-1]):
                raise ConfigError(f"ContactMemory[{self.kind}]: duplicate pairs in update")
        self._keys, self._sides = keys, signs

    def copy(self) -> "ContactMemory":
        """Independent copy (a State holds its own memory): the key and side arrays duplicated."""
        out = object.__new__(type(self))  # no __init__ (its empty arrays), no copy.copy (3 us)
        out.kind, out._keys, out._sides = self.kind, self._keys.copy(), self._sides.copy()
        return out

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, ContactMemory)
            and np.array_equal(self._keys, other._keys)
            and np.array_equal(self._sides, other._sides)
        )


class CollisionMemory:
    """Side memories of all pair kinds held by a :class:`~sim_core.state.State`.

    Attributes:
        vertex_triangle: pairs ``[global vertex, triangle row]``.
        edge_edge: pairs ``[edge row i, edge row j]``.
    """

    def __init__(self) -> None:
        self.vertex_triangle = ContactMemory("vertex_triangle")
        self.edge_edge = ContactMemory("edge_edge")

    def copy(self) -> "CollisionMemory":
        """Independent copy (each kind's memory copied)."""
        out = object.__new__(type(self))
        out.vertex_triangle, out.edge_edge = self.vertex_triangle.copy(), self.edge_edge.copy()
        return out


def vertex_triangle_pair_sides(
    x_ref: np.ndarray, pairs: np.ndarray, triangles: np.ndarray, memory: ContactMemory | None = None
) -> np.ndarray:
    """Side of each vertex-triangle pair: remembered if the pair is in ``memory``, else the current
    side at ``x_ref`` (the start-of-step positions x^n, before any penetration of the step).

    Args:
        x_ref: positions in m, shape ``(n, 3)``.
        pairs: ``[global vertex, row of triangles]``, shape ``(p, 2)``.
        triangles: global vertex indices, shape ``(t, 3)``.
        memory: side memory of vertex-triangle pairs, or None.

    Returns:
        +1 / -1 per pair w.r.t. the normal ``(b - a) x (c - a)``, shape ``(p,)``.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    z = x_ref[np.concatenate([pairs[:, :1], np.asarray(triangles)[pairs[:, 1]]], axis=1)]
    current = point_triangle_side(z)
    return current if memory is None else memory.resolve(pairs, current)


def edge_edge_pair_sides(
    x_ref: np.ndarray, pairs: np.ndarray, edges: np.ndarray, memory: ContactMemory | None = None
) -> np.ndarray:
    """Side of each edge-edge pair (sign of ``((a1 - a0) x (b1 - b0)).(a0 - b0)``): remembered if in
    ``memory``, else taken at ``x_ref``; shape ``(p,)``. Arguments as
    :func:`vertex_triangle_pair_sides` with ``pairs`` = ``[row i, row j]`` of ``edges`` ``(e, 2)``."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    edges = np.asarray(edges)
    z = x_ref[np.concatenate([edges[pairs[:, 0]], edges[pairs[:, 1]]], axis=1)]
    current = edge_edge_side(z)
    return current if memory is None else memory.resolve(pairs, current)
