"""CSR slots of the dynamic (contact, friction) Hessian blocks in a sticky union pattern.

:class:`DynamicMerge` adds the blocks of the dynamic potentials to the static values of the
constrained upper triangle (:mod:`sim_core.assembly`). Its result is defined by this rule (the
"union pattern"), independent of the caches below:

* the CSR pattern is the static pattern plus a sorted set of dynamic keys ``row * n + col``;
* an assembly whose kept dynamic entries (``row <= col``, both DoFs free) are all in the set keeps
  the pattern; otherwise the set is rebuilt as the entries of this assembly plus the dynamic keys
  used within the last :data:`STICKY_ASSEMBLIES` assemblies (all of them before that many
  assemblies have been done) since the set was built; a new static pattern starts an empty set;
* values: the static values in their slots, plus (when there are dynamic blocks) one
  ``np.bincount`` of the kept dynamic entries in block-set, element, entry order.

So the pattern, and with it the linear solver's symbolic analysis, changes far less often than the
active contact set. The work per assembly is kept small by caching, per dynamic block set (by its
position in the list), a table of the elements (vertex tuples) seen so far with the CSR slot of each
of their entries: a repeated element costs a table look-up and a gather, only new elements are
mapped key by key, and a rebuild of the set translates the tables and the CSR arrays of the old
pattern into the new one with prefix sums instead of sorting and searching all keys again.
"""

from __future__ import annotations

import copy
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from sim_core.energies.base import HessianBlocks
from sim_core.static_pattern import StaticPattern, block_keys  # noqa: F401 (block_keys: this module's too)
from sim_core.unique import sorted_unique

STICKY_ASSEMBLIES = 50
"""A dynamic entry leaves the union pattern after this many assemblies without it (about ten
Forming steps): bounds the fill-in that contacts which moved on leave behind."""

TABLE_ELEMENTS = 8192
"""An element table holding more elements than this drops those unused since the last rebuild of
the union pattern (a cache bound only: it does not change any result)."""


def _translation(survive: np.ndarray, insert_at: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions in a sorted array after dropping and inserting items, by prefix sums (no search).

    Args:
        survive: which of the ``N`` old items stay, bool ``(N,)``.
        insert_at: ``np.searchsorted(old, new_items)`` of the sorted, distinct inserted items, ``(a,)``.

    Returns:
        ``(trans, placed, before)``: new position of each old item (-1 for dropped ones) with one
        more entry ``trans[N]`` = the new length, int64 ``(N + 1,)``; new position of each inserted
        item, ``(a,)``; number of kept old items before each old position, ``(N + 1,)``.
    """
    size = survive.size
    before = np.zeros(size + 1, dtype=np.int64)  # survivors before each old position
    np.cumsum(survive, out=before[1:])
    # inserted items at or before each old position: a step function, the prefix sums of their counts
    inserted = np.cumsum(np.bincount(insert_at, minlength=size + 1))
    trans = before + inserted
    trans[:size][~survive] = -1
    placed = before[insert_at] + np.arange(insert_at.size)
    return trans, placed, before


class UnionPattern:
    """The static pattern plus a sorted set of dynamic keys, as CSR arrays.

    Attributes:
        pattern: the :class:`sim_core.assembly.StaticPattern`.
        built_at: assembly counter of the build.
        dyn_keys: sorted unique dynamic keys ``row * n + col`` (some may also be static keys), ``(d,)``.
        last_used: assembly counter of the last use of each dynamic key recorded here, ``(d,)``
            (uses by the element tables of :class:`DynamicMerge` are recorded there until a rebuild).
        keys: the union's sorted keys, ``(nnz,)``; static_slots: slot of each static key;
            dyn_slots: slot of each dynamic key; indptr, indices: the CSR arrays (int32 when they fit).
    """

    def __init__(self, pattern: StaticPattern, keys: np.ndarray, static_slots: np.ndarray, dyn_keys: np.ndarray,
                 dyn_slots: np.ndarray, indptr: np.ndarray, indices: np.ndarray, built_at: int) -> None:
        self.pattern = pattern
        self.built_at = built_at
        self.keys = keys
        self.static_slots = static_slots
        self.dyn_keys = dyn_keys
        self.dyn_slots = dyn_slots
        self.last_used = np.zeros(dyn_keys.size, dtype=np.int64)
        self.nnz = keys.size
        # int32 like the indices (SciPy stores them so anyway when they fit): the CSR matrix of each
        # assembly is then built without converting and re-checking the index arrays
        self.indptr = indptr.astype(np.int32) if keys.size < np.iinfo(np.int32).max else indptr
        self.indices = indices
        self._template: sp.csr_matrix | None = None
        self._static_mask: np.ndarray | None = None
        self._expanded: np.ndarray | None = None  # expand()'s array
        self._diagonal: tuple[np.ndarray, np.ndarray] | None = None

    def expand(self, static_data: np.ndarray) -> np.ndarray:
        """Static values ``(pattern.keys.size,)`` in this union's layout, ``(nnz,)``, 0 in the dynamic-only
        slots (the static slots are increasing: one boolean-mask copy). The array is kept: the next call
        overwrites it (its dynamic-only slots stay 0 as long as callers write static slots only)."""
        expanded = self._expanded
        if expanded is None:
            expanded = self._expanded = np.zeros(self.nnz)
        expanded[self.static_mask()] = static_data
        return expanded

    def static_mask(self) -> np.ndarray:
        """Which slots hold a static key, bool ``(nnz,)`` (made on first use, then kept)."""
        if self._static_mask is None:
            self._static_mask = np.zeros(self.nnz, dtype=bool)
            self._static_mask[self.static_slots] = True
        return self._static_mask

    def diagonal_slots(self) -> tuple[np.ndarray, np.ndarray]:
        """Slots of every DoF's diagonal entry ``(n,)`` and of the fixed DoFs' (the static pattern's
        ``diag_slots`` and ``fixed_diag_slots`` in this union)."""
        if self._diagonal is None:
            self._diagonal = (self.static_slots[self.pattern.diag_slots], self.static_slots[self.pattern.fixed_diag_slots])
        return self._diagonal

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The CSR matrix ``(n, n)`` of values ``data`` ``(nnz,)`` in this pattern (sorted indices).

        SciPy's ``csr_matrix((data, indices, indptr))`` scans the index arrays on every call (their
        dtype and bounds); a pattern's matrices are instead shallow copies of one matrix built (and
        checked) once, with ``data`` put in. They share the index arrays, which are read-only (an
        in-place change of one matrix's pattern raises instead of changing the others'), and
        identical objects from one assembly to the next let the linear solver recognise the pattern
        without comparing it (:class:`sim_core.linsolve.IdentityRows`).
        """
        template = self._template
        if template is None:
            n = self.pattern.dof_count
            template = sp.csr_matrix((np.zeros(self.nnz), self.indices, self.indptr), shape=(n, n))
            template.has_sorted_indices = True  # keys are sorted and unique
            template.indices.flags.writeable = False
            template.indptr.flags.writeable = False
            self._template = template
        if data.shape != (self.nnz,):
            raise ValueError(f"UnionPattern.matrix: {data.shape[0]} values for {self.nnz} slots")
        matrix = copy.copy(template)
        matrix.data = data
        return matrix

    @classmethod
    def build(cls, pattern: StaticPattern, dyn_keys: np.ndarray, built_at: int) -> "UnionPattern":
        """The union of ``pattern``'s keys and the sorted unique ``dyn_keys`` (a merge, no re-sort)."""
        static = pattern.keys
        pos = np.minimum(np.searchsorted(static, dyn_keys), max(static.size - 1, 0))
        extra = dyn_keys[static[pos] != dyn_keys] if static.size else dyn_keys
        keys = np.insert(static, np.searchsorted(static, extra), extra)
        static_slots = np.arange(static.size) + np.searchsorted(extra, static)
        n = pattern.dof_count
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(keys // n, minlength=n), out=indptr[1:])
        return cls(pattern, keys, static_slots, dyn_keys, np.searchsorted(keys, dyn_keys), indptr,
                   (keys % n).astype(np.int32), built_at)

    def rebuilt(
        self, recent: np.ndarray, added: np.ndarray, built_at: int
    ) -> tuple["UnionPattern", np.ndarray, np.ndarray]:
        """The union of the static keys, the dynamic keys flagged ``recent`` and ``added``.

        Args:
            recent: which dynamic keys stay, bool ``(d,)``.
            added: sorted unique keys that are not dynamic keys of this union, ``(a,)``.
            built_at: assembly counter.

        Returns:
            ``(union, slot_trans, dyn_trans)``: the new union; the new slot of each old slot (-1 if
            dropped), ``(nnz + 1,)`` with ``slot_trans[nnz]`` = the new nnz; the new dynamic-key
            index of each old one, ``(d + 1,)`` likewise.
        """
        static = self.pattern.keys
        n = self.pattern.dof_count
        dyn_trans, dyn_placed, _ = _translation(recent, np.searchsorted(self.dyn_keys, added))
        dyn_keys = np.empty(dyn_trans[-1], dtype=np.int64)
        dyn_keys[dyn_trans[:-1][recent]] = self.dyn_keys[recent]
        dyn_keys[dyn_placed] = added
        survive = self.static_mask().copy()
        survive[self.dyn_slots[recent]] = True
        pos = np.minimum(np.searchsorted(static, added), max(static.size - 1, 0))
        is_static = static[pos] == added if static.size else np.zeros(added.size, dtype=bool)
        new = added[~is_static]
        slot_trans, placed, before = _translation(survive, np.searchsorted(self.keys, new))
        keys = np.empty(slot_trans[-1], dtype=np.int64)
        kept_at = slot_trans[:-1][survive]
        keys[kept_at] = self.keys[survive]
        keys[placed] = new
        indices = np.empty(keys.size, dtype=np.int32)  # CSR arrays translated too (no key division)
        indices[kept_at] = self.indices[survive]
        indices[placed] = new % n
        # row r starts after the kept old entries of rows < r and the new keys below r n
        indptr = before[self.indptr] + np.searchsorted(new, np.arange(n + 1) * n)
        dyn_slots = np.empty(dyn_keys.size, dtype=np.int64)
        dyn_slots[dyn_trans[:-1][recent]] = slot_trans[self.dyn_slots[recent]]
        added_slots = np.empty(added.size, dtype=np.int64)
        added_slots[is_static] = slot_trans[self.static_slots[pos[is_static]]]
        added_slots[~is_static] = placed
        dyn_slots[dyn_placed] = added_slots
        union = UnionPattern(self.pattern, keys, slot_trans[self.static_slots], dyn_keys, dyn_slots, indptr, indices,
                             built_at)
        return union, slot_trans, dyn_trans


class _ElementTable:
    """Elements of one dynamic block set seen so far, with the slots of their entries in one union.

    Rows are appended (amortised, no re-sort of the row arrays); a sorted index of the element
    identifiers finds them.

    Attributes:
        m: vertices per element (of ``vertex_count``); size: element count ``E``;
        slots: CSR slot of each entry, ``(E, (3m)^2)``, the dummy slot ``nnz`` where not kept (the key
            of every other entry is one of the union's dynamic keys);
        last: assembly counter of the last use of each element since the union was built, 0 if none,
            ``(E,)``; call: (signature, union, rows) of the last call (:meth:`DynamicMerge._place`).
    """

    def __init__(self, m: int, vertex_count: int) -> None:
        self.m = m
        self.size = 0
        self._ids = _element_ids(np.zeros((0, m), dtype=np.int64), vertex_count)  # sorted
        self._rows = np.zeros(0, dtype=np.int64)  # row of each sorted identifier
        self._slots = np.zeros((0, (3 * m) ** 2), dtype=np.int64)
        self._last = np.zeros(0, dtype=np.int64)
        self.call: tuple | None = None
        self._gathered: tuple | None = None  # (call, (kept entries, their slots)) of gathered()

    @property
    def slots(self) -> np.ndarray:
        return self._slots[: self.size]

    @property
    def last(self) -> np.ndarray:
        return self._last[: self.size]

    def gathered(self, dummy: int) -> tuple[np.ndarray, np.ndarray]:
        """The kept entries of the last call's elements (``call``'s rows), as positions in their
        flattened blocks ``(a,)``, and their slots ``(a,)`` (entries whose slot is ``dummy`` are not
        kept); one tuple per call tuple (the same object while ``call`` is)."""
        cached = self._gathered
        if cached is None or cached[0] is not self.call:
            flat = self.slots[self.call[2]].reshape(-1)
            kept = np.flatnonzero(flat != dummy)
            cached = self._gathered = (self.call, (kept, flat[kept]))
        return cached[1]

    def find(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the elements ``ids`` and whether each is there (the row is arbitrary where not)."""
        if not self.size:
            return np.zeros(ids.size, dtype=np.int64), np.zeros(ids.size, dtype=bool)
        pos = np.minimum(np.searchsorted(self._ids, ids), self.size - 1)
        return self._rows[pos], self._ids[pos] == ids

    def add(self, ids: np.ndarray, slots: np.ndarray) -> None:
        """Append new sorted unique element ``ids`` with their entry slots ``(a, q)``."""
        count = ids.size
        if self.size + count > self._last.size:
            capacity = max(2 * (self.size + count), 64)
            for name in ("_slots", "_last"):
                old = getattr(self, name)
                grown = np.zeros((capacity,) + old.shape[1:], dtype=old.dtype)
                grown[: self.size] = old[: self.size]
                setattr(self, name, grown)
        rows = np.arange(self.size, self.size + count)
        self._slots[rows], self._last[rows] = slots, 0
        at = np.searchsorted(self._ids, ids)
        self._ids = np.insert(self._ids, at, ids)
        self._rows = np.insert(self._rows, at, rows)
        self.size += count
        self.call = None

    def replace(self, keep: np.ndarray, slots: np.ndarray) -> np.ndarray:
        """Keep only the elements ``keep`` (bool ``(E,)``), with new ``slots`` ``(E, q)``; returns the new
        row of each old row (meaningless for dropped ones)."""
        new_row = np.cumsum(keep) - 1
        in_index = keep[self._rows]
        self._ids = self._ids[in_index]
        self._rows = new_row[self._rows[in_index]]
        self._slots, self._last = slots[keep], self.last[keep]
        self.size = self._last.size
        self.call = None
        return new_row


def _element_ids(vertices: np.ndarray, vertex_count: int) -> np.ndarray:
    """One comparable identifier per element of ``vertices`` ``(k, m)``: the vertex tuple as one int64
    ``((v_0 N + v_1) N + ...)`` when ``N^m`` fits (``N = vertex_count``), else the row's bytes."""
    v = np.ascontiguousarray(vertices, dtype=np.int64)
    m = v.shape[1]
    if vertex_count ** m >= 2**62:
        return v.view(np.dtype((np.void, 8 * m))).reshape(-1)
    ids = v[:, 0].copy()
    for a in range(1, m):
        ids *= vertex_count
        ids += v[:, a]
    return ids


class DynamicMerge:
    """Merge dynamic Hessian blocks into the union pattern of one assembler (see the module doc).

    Args:
        dof_count: ``3 * vertex_count``.
    """

    def __init__(self, dof_count: int) -> None:
        self.dof_count = dof_count
        self.union: UnionPattern | None = None
        self._tables: dict[int, _ElementTable] = {}
        self._free_bytes: bytes | None = None
        self._assemblies = 0
        self._slots_cache: tuple | None = None  # (gathered tuples, their slots concatenated) of _sum

    def merge(
        self, pat: StaticPattern, static_data: np.ndarray, dynamic: Sequence[HessianBlocks], free: np.ndarray
    ) -> sp.csr_matrix:
        """CSR upper triangle ``(n, n)`` of the static values (``pat``'s slots, ``(pat.keys.size,)``)
        plus the kept entries of the ``dynamic`` blocks (``free``: bool ``(n,)`` free-DoF mask)."""
        union, blocks = self._place(pat, dynamic, free)
        return union.matrix(self._sum(union, blocks, union.expand(static_data)))

    def merge_values(
        self, pat: StaticPattern, static_values: np.ndarray, diagonal: np.ndarray, dynamic: Sequence[HessianBlocks],
        free: np.ndarray,
    ) -> sp.csr_matrix:
        """:meth:`merge` of the static data ``static_values`` plus ``diagonal`` on the DoFs' diagonal
        slots, then 1 on the fixed DoFs' (:meth:`sim_core.assembly.HessianAssembler.assemble_upper_values`),
        without forming that static data in ``pat``'s slots: the same values bit for bit.

        Args:
            pat: the static pattern; static_values: its values ``(pat.keys.size,)`` (not modified);
            diagonal: extra diagonal ``(n,)``; dynamic, free: as :meth:`merge`.
        """
        union, blocks = self._place(pat, dynamic, free)
        static = union.expand(static_values)
        diagonal_slots, fixed_slots = union.diagonal_slots()
        static[diagonal_slots] += diagonal
        static[fixed_slots] = 1.0
        return union.matrix(self._sum(union, blocks, static))

    def _sum(self, union: UnionPattern, blocks: list[HessianBlocks], static: np.ndarray) -> np.ndarray:
        """The union's values, a new ``(nnz,)`` array: one ``np.bincount`` of the kept entries of ``blocks``
        (placed by :meth:`_place`) in block-set, element, entry order, plus the static values in the
        union's layout ``static`` (``(nnz,)``, 0 in the dynamic-only slots; :meth:`UnionPattern.expand`);
        a copy of ``static`` when there are no blocks."""
        if not blocks:
            return static.copy()
        gathered = [self._tables[j].gathered(union.nnz) for j in range(len(blocks))]
        cached = self._slots_cache
        if cached is None or len(cached[0]) != len(gathered) or any(a is not b for a, b in zip(cached[0], gathered)):
            cached = self._slots_cache = (gathered, np.concatenate([g[1] for g in gathered]))
        values = np.concatenate([b.blocks.reshape(-1)[g[0]] for b, g in zip(blocks, gathered)])
        # float64 also when no entry is kept (NumPy's bincount of an empty list is int64 even with weights)
        data = np.bincount(cached[1], weights=values, minlength=union.nnz).astype(np.float64, copy=False)
        # dynamic sums first, then the static value added: the same D + s per slot as adding s into the
        # slots (0 + s in the static-only slots; 0 + 0 in the dynamic-only ones)
        data += static
        return data

    def _place(
        self, pat: StaticPattern, dynamic: Sequence[HessianBlocks], free: np.ndarray
    ) -> tuple[UnionPattern, list[HessianBlocks]]:
        """This assembly's union pattern (rebuilt if needed) and its non-empty dynamic block sets; the
        ``call`` of element table ``j`` is then ``(signature, union, rows)`` of set ``j``, ``rows`` the
        row of each of its elements in the table."""
        n = self.dof_count
        self._assemblies += 1
        count = self._assemblies
        blocks = [b for b in dynamic if b.blocks.shape[0]]
        union = self.union
        free_bytes = np.packbits(free).tobytes()
        if union is None or union.pattern is not pat:
            self._start(pat, blocks, free, free_bytes, count)
            union = self.union
        elif free_bytes != self._free_bytes:
            self._flush()
            self._free_bytes = free_bytes
        signatures, rows, pending = [], [], []
        for j, b in enumerate(blocks):
            m = b.vertices.shape[1]
            table = self._tables.get(j)
            if table is None or table.m != m:
                if table is not None:
                    self._flush_table(table)
                table = self._tables[j] = _ElementTable(m, n // 3)
            signature = (b.vertices.shape, b.vertices.dtype.str, b.vertices.tobytes())
            if table.call is not None and table.call[0] == signature and table.call[1] is union:
                pos = table.call[2]  # the same elements as the last call: the same rows
            else:
                ids = _element_ids(b.vertices, n // 3)
                pos, found = table.find(ids)
                if not found.all():
                    new_ids, first = sorted_unique(ids[~found], return_index=True)
                    keys = self._kept_keys(b.vertices[~found][first], free)
                    slots, absent = self._slots(union, keys)
                    table.add(new_ids, slots)
                    if absent.any():
                        pending.append((table, new_ids, keys, absent))
                    pos, _ = table.find(ids)
            table.last[pos] = count
            signatures.append(signature)
            rows.append(pos)
        if pending:  # the tables were translated into the new union (and may have dropped elements)
            union, new_rows = self._rebuild(pending, count)
            rows = [new_rows[j][pos] for j, pos in enumerate(rows)]  # this call's elements are all kept
        for j in range(len(blocks)):
            table = self._tables[j]
            call = table.call
            if call is None or call[0] != signatures[j] or call[1] is not union:
                table.call = (signatures[j], union, rows[j])
        return union, blocks

    def _kept_keys(self, vertices: np.ndarray, free: np.ndarray) -> np.ndarray:
        """Keys ``row * n + col`` of the entries of blocks over ``vertices``, -1 where not kept, ``(k, q)``."""
        n = self.dof_count
        r, c = block_keys(vertices, n)
        keep = (r <= c) & free[r] & free[c]
        return np.where(keep, r * n + c, -1).reshape(vertices.shape[0], -1)

    @staticmethod
    def _slots(union: UnionPattern, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slots of ``keys`` ``(k, q)`` (``-1``: not kept) in ``union``, the dummy ``nnz`` where not kept or
        not a dynamic key of ``union``; and which kept keys are not (bool ``(k, q)``)."""
        d = union.dyn_keys.size
        kept = keys >= 0
        dyn = np.full(keys.shape, d, dtype=np.int64)
        absent = kept.copy()
        if d:
            pos = np.minimum(np.searchsorted(union.dyn_keys, keys[kept]), d - 1)
            there = union.dyn_keys[pos] == keys[kept]
            dyn[kept] = np.where(there, pos, d)
            absent[kept] = ~there
        return np.append(union.dyn_slots, union.nnz)[dyn], absent

    def _start(
        self, pat: StaticPattern, blocks: list[HessianBlocks], free: np.ndarray, free_bytes: bytes, count: int
    ) -> None:
        """A new union for a new static pattern: the kept dynamic keys of this assembly."""
        self._tables = {}
        self._free_bytes = free_bytes
        keys = [self._kept_keys(b.vertices, free).reshape(-1) for b in blocks]
        dyn_keys = sorted_unique(np.concatenate(keys + [np.zeros(0, np.int64)]))
        self.union = UnionPattern.build(pat, dyn_keys[dyn_keys >= 0], count)

    def _flush_table(self, table: _ElementTable) -> None:
        """Record the uses of ``table``'s elements in the union's ``last_used`` before it is dropped."""
        union = self.union
        stamp = np.zeros(union.nnz + 1, dtype=np.int64)  # last use per slot
        used = table.last > 0
        np.maximum.at(stamp, table.slots[used], table.last[used][:, None])
        np.maximum(union.last_used, stamp[union.dyn_slots], out=union.last_used)

    def _flush(self) -> None:
        """Drop all element tables (free mask changed), keeping their uses."""
        for table in self._tables.values():
            self._flush_table(table)
        self._tables = {}

    def _rebuild(self, pending: list, count: int) -> tuple[UnionPattern, dict[int, np.ndarray]]:
        """Rebuild the union with this assembly's missing keys; translate the tables into it.

        Returns:
            the new union; per table position, the new row of each old row.
        """
        old = self.union
        used_slots = np.zeros(old.nnz + 1, dtype=bool)  # slots (each one key) of recently used elements
        for table in self._tables.values():
            used_slots[table.slots[table.last > count - STICKY_ASSEMBLIES]] = True
        recent = (old.last_used > count - STICKY_ASSEMBLIES) | used_slots[old.dyn_slots]
        missing = sorted_unique(np.concatenate([keys[absent] for _, _, keys, absent in pending]))
        union, slot_trans, _ = old.rebuilt(recent, missing, count)
        is_dyn = np.zeros(union.nnz + 2, dtype=bool)  # index -1 (a dropped slot) reads the last: False
        is_dyn[union.dyn_slots] = True
        is_dyn[union.nnz] = True  # the dummy
        pend = {id(t): (ids, keys) for t, ids, keys, _ in pending}
        new_rows = {}
        for j, table in self._tables.items():
            slots = slot_trans[table.slots]
            if id(table) in pend:
                ids, keys = pend[id(table)]
                rows, _ = table.find(ids)
                slots[rows] = self._slots(union, keys)[0]
            keep = is_dyn[slots].all(axis=1)  # every key of the element still a dynamic key
            if table.size > TABLE_ELEMENTS:
                keep &= table.last > 0
            new_rows[j] = table.replace(keep, slots)
            table.last[table.last != count] = 0
        self.union = union
        return union, new_rows
