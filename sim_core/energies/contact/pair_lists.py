"""The vertices of a contact set's candidate pair lists, computed once per list.

A candidate search (:mod:`sim_core.contact_set`) gives a vertex-triangle list ``(p, 2)`` and an edge-edge list
``(q, 2)`` that stay in use until the next search: the step's potentials are built over them (every
vertex-triangle pair, the edge-edge pairs that are not near-parallel), their geometry is measured at the converged
positions, and the next step, whose first iterates the same search usually covers, builds its potentials over them
again with new sides. :class:`CandidateVertices` keeps, for one pair of lists, the pairs' global vertices
(``[p, a, b, c]`` and ``[a0, a1, b0, b1]``, :func:`~sim_core.energies.contact.reference.vertex_triangle_vertices` and
:func:`~sim_core.energies.contact.reference.edge_edge_vertices`) and, on the Taichi backend, their positions among
the distinct vertices they name (:func:`~sim_core.unique.compact_indices`: the pair batch's kernel indices,
:class:`~sim_core.energies.contact.batch_kernel.PairBatch`), so that a stacked batch of 1024 Forming copies (1.75
million candidate pairs) gathers and compacts them once per search instead of at every potential, batch and
geometry measurement. A step's pair batch indexes the kept compaction of every candidate through its own rows
(:class:`BatchLayout`: the near-parallel edge-edge pairs a step leaves out are skipped, not cut out), so that the
vertex indices, and on CUDA their device copies (:attr:`CandidateVertices.device`), serve every step's batch over
the same lists.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim_core.array_pool import ArrayPool
from sim_core.energies.contact.reference import PairVertices, edge_edge_vertices, vertex_triangle_vertices
from sim_core.unique import compact_indices


DEVICE_INDEX_NAMES = ("geometry_vt", "geometry_ee")
"""The names of a list's int32 vertices (:meth:`CandidateVertices.int32_vertices`) in its device cache
(:attr:`CandidateVertices.device`), under which every kernel that reads them finds their device copies."""


class CandidateVertices:
    """The global vertices of candidate lists ``vt`` ``(p, 2)`` (``[vertex, triangle row]``) and ``ee`` ``(q, 2)``
    (``[edge row, edge row]``) over ``triangles`` ``(t, 3)`` and ``edges`` ``(e, 2)``.

    Attributes:
        vt, ee: the lists (the arrays given: :meth:`of` matches them by identity).
        vt_vertices: ``[p, a, b, c]`` int64 ``(p, 4)``; with ``device_vertices`` a
            :class:`~sim_core.energies.contact.reference.PairVertices` (rows gathered from the pairs when asked: no
            host gather of every candidate where the kernels read the device's).
        ee_vertices: ``[a0, a1, b0, b1]`` int64 ``(q, 4)``; likewise.
        device: the device copies of this list's index arrays (a :func:`~sim_core.ti_kernels.buffers.on_device`
            cache; empty off CUDA), shared by the kernels that read them.

    Args:
        vt, ee, triangles, edges: as above (int ``(p, 2)``, ``(q, 2)``, ``(t, 3)``, ``(e, 2)``).
        keys: the lists' packed keys ``first << 32 | second`` (int64 ``(p,)``, ``(q,)``, each list's or None) when
            the caller has them (the candidate search's sort: :meth:`~sim_core.ti_kernels.hash_grid.HashGrid.keys_of`),
            taken by :meth:`keys` instead of being made from the pairs again.
        vertex_count: the number of vertices (every index of ``vt``'s first column, ``triangles`` and ``edges`` lies in
            ``[0, vertex_count)``), or None; with it the compaction (:meth:`batch_layout`) sizes its table without a
            pass over the indices for their range.
        pool: where the vertex arrays are made (:class:`~sim_core.array_pool.ArrayPool`: the blocks of earlier lists
            that nothing holds any more, written again; a contact set's; for int64 lists and elements), or None: fresh
            arrays. The same values.
        device_vertices: the lists' int32 vertices ``(p, 4)`` and ``(q, 4)`` already in device memory (Taichi
            ndarrays, None for an empty list: the candidate search gathered them where its sort left the keys,
            :meth:`~sim_core.ti_kernels.hash_candidates.HashCandidates.device_vertices`), or None; the kernels then
            read them there (:meth:`index_arrays`) instead of :meth:`int32_vertices` sent from the host.

    Raises:
        IndexError: a triangle or edge row out of range (with ``device_vertices``: when its vertices are read).
    """

    def __init__(self, vt: np.ndarray, ee: np.ndarray, triangles: np.ndarray, edges: np.ndarray,
                 keys: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
                 vertex_count: int | None = None, pool: ArrayPool | None = None,
                 device_vertices: tuple | None = None) -> None:
        self.vt, self.ee = vt, ee
        self._device_vertices = device_vertices
        self._pool = pool
        self._edges = edges
        if device_vertices is not None:  # the kernels read the device's: the host's rows gathered when asked
            self.vt_vertices = PairVertices(vt, triangles, vertex_triangle_vertices)
            self.ee_vertices = PairVertices(ee, edges, edge_edge_vertices)
        elif pool is None or not all(a.dtype == np.int64 for a in (vt, ee, triangles, edges)):
            self.vt_vertices = vertex_triangle_vertices(vt, triangles)
            self.ee_vertices = edge_edge_vertices(ee, edges)
        else:
            self.vt_vertices, self.ee_vertices = _pooled_vertices(pool, vt, ee, triangles, edges)
        self._compact: tuple | None = None
        self._int32: tuple | None = None
        self._given_keys = keys
        self._keys: tuple | None = None
        self._vertex_count = vertex_count
        self.device: dict = {}

    def of(self, vt: np.ndarray, ee: np.ndarray) -> bool:
        """Whether these are the vertices of the lists ``vt`` and ``ee`` (the same array objects)."""
        return vt is self.vt and ee is self.ee

    def int32_vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """:attr:`vt_vertices` and :attr:`ee_vertices` as C-contiguous int32 arrays ``(p, 4)``, ``(q, 4)`` (the
        geometry kernel's indices, :func:`~sim_core.energies.contact.setup_kernel.pair_geometry`), made once."""
        if self._int32 is None:
            if self._pool is None:
                self._int32 = tuple(np.asarray(v, dtype=np.int32) for v in (self.vt_vertices, self.ee_vertices))
            else:
                self._int32 = tuple(self._pool.copy_of(name, np.asarray(v), np.int32)
                                    for name, v in (("vt_int32", self.vt_vertices), ("ee_int32", self.ee_vertices)))
        return self._int32

    def index_arrays(self) -> tuple[object, object]:
        """The lists' int32 vertices ``(p, 4)``, ``(q, 4)`` where the kernels read them: the device arrays the search
        gathered (``device_vertices``; a host :meth:`int32_vertices` array stands for an empty list), else
        :meth:`int32_vertices` (sent once per list through :attr:`device` on CUDA). The same values."""
        given = self._device_vertices
        if given is None:
            return self.int32_vertices()
        return tuple(g if g is not None else np.zeros((0, 4), dtype=np.int32) for g in given)

    def keys(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The lists' pairs as packed keys ``first << 32 | second``, int64 ``(p,)`` and ``(q,)``
        (:class:`~sim_core.collision.memory.ContactMemory`'s keys), made once; None for a list whose keys are not
        sorted and unique or whose indices are out of the keys' range (its pairs are then looked up one by one)."""
        if self._keys is None:
            self._keys = tuple(_sorted_keys(pairs) if given is None else _increasing(given)
                               for pairs, given in zip((self.vt, self.ee), self._given_keys))
        return self._keys

    def kept_edge_edge_vertices(self, ee_rows: np.ndarray, ee_kept: np.ndarray):
        """The vertices ``(r, 4)`` of the edge-edge candidates ``ee_rows`` (int ``(r,)``), whose pairs are ``ee_kept``
        (``ee[ee_rows]``, int ``(r, 2)``): the rows of :attr:`ee_vertices`, or where those are gathered by rows
        (:class:`~sim_core.energies.contact.reference.PairVertices`, the lists' vertices on the device) a
        :class:`~sim_core.energies.contact.reference.PairVertices` of ``ee_kept``: nothing gathered here. The same
        values."""
        if isinstance(self.ee_vertices, PairVertices):
            return PairVertices(ee_kept, self._edges, edge_edge_vertices)
        return np.take(self.ee_vertices, ee_rows, axis=0)

    def batch_layout(self, ee_rows: np.ndarray, rows: np.ndarray | None = None) -> "BatchLayout":
        """The :class:`BatchLayout` of a pair batch over every vertex-triangle candidate and the edge-edge candidates
        ``ee_rows`` (int ``(r,)``, increasing), in that order; the compaction of every candidate's vertices is made on
        first use and kept. ``rows``: the layout's rows where the caller has them (int32 ``(p + r,)``: ``0 .. p - 1``,
        then ``p + ee_rows``; the rows made on the device,
        :class:`~sim_core.energies.contact.sides_kernel.KeptRows`), taken as they are; None: made here.

        Raises:
            ValueError: ``rows`` not int32 of ``p + r`` rows."""
        if self._compact is None:
            self._compact = self._compaction()
        own, local = self._compact
        p = len(self.vt)
        ee_rows = np.asarray(ee_rows, dtype=np.int64)
        if rows is not None:
            if rows.shape != (p + len(ee_rows),) or rows.dtype != np.int32:
                raise ValueError(f"CandidateVertices.batch_layout: rows of shape {rows.shape} ({rows.dtype}) for "
                                 f"{p} + {len(ee_rows)} pairs, want int32")
            return BatchLayout(own, local, rows, ee_rows, self.device)
        rows = np.empty(p + len(ee_rows), dtype=np.int32)
        rows[:p] = np.arange(p, dtype=np.int32)
        np.add(ee_rows, p, out=rows[p:], casting="unsafe")
        return BatchLayout(own, local, rows, ee_rows, self.device)

    def _compaction(self) -> tuple[np.ndarray, object]:
        """``(own, local)`` of every candidate's vertices (:func:`~sim_core.unique.compact_indices`): on CUDA, with the
        vertex count known, made where the lists' int32 vertices are kept (:attr:`device`, under
        :data:`DEVICE_INDEX_NAMES`; :func:`~sim_core.ti_kernels.compaction.compact_on_device`: ``local`` stays there),
        else on the host. The same values."""
        if self._vertex_count is not None and len(self.vt) + len(self.ee):
            # optional heavy dependency: Taichi, loaded on a Taichi backend only (where pair batches are made)
            from sim_core.ti_backend import current_arch

            if current_arch() == "cuda":
                from sim_core.ti_kernels.compaction import compact_on_device

                return compact_on_device(*self.index_arrays(), self._vertex_count, self.device, DEVICE_INDEX_NAMES)
        return compact_indices((np.asarray(self.vt_vertices), np.asarray(self.ee_vertices)), dtype=np.int32,
                               size=self._vertex_count)


def _pooled_vertices(pool: ArrayPool, vt: np.ndarray, ee: np.ndarray, triangles: np.ndarray, edges: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~sim_core.energies.contact.reference.vertex_triangle_vertices` and
    :func:`~sim_core.energies.contact.reference.edge_edge_vertices` (int64 ``(p, 4)``, ``(q, 4)``; the same values)
    written into arrays of ``pool``; the rows checked to lie in ``triangles`` and ``edges`` first (the gathers into
    given arrays do not check them).

    Raises:
        IndexError: a triangle or edge row out of range."""
    for rows, count in ((vt[:, 1], len(triangles)), (ee, len(edges))):
        if len(rows) and (rows.min() < 0 or rows.max() >= count):
            raise IndexError(f"CandidateVertices: a row out of range [0, {count})")
    vt_vertices = pool.empty("vt_vertices", (len(vt), 4), np.int64)
    vt_vertices[:, 0] = vt[:, 0]
    np.take(triangles, vt[:, 1], axis=0, out=vt_vertices[:, 1:], mode="clip")  # (clip: no buffered copy; checked)
    ee_vertices = pool.empty("ee_vertices", (len(ee), 4), np.int64)
    np.take(edges, ee, axis=0, out=ee_vertices.reshape(-1, 2, 2), mode="clip")
    return vt_vertices, ee_vertices


def _sorted_keys(pairs: np.ndarray) -> np.ndarray | None:
    """:meth:`CandidateVertices.keys` of one list ``(p, 2)``."""
    pairs = np.asarray(pairs).reshape(-1, 2)
    if pairs.size and (pairs.min() < 0 or pairs.max() >= 1 << 31):
        return None
    keys = pairs[:, 0].astype(np.int64)  # (a new array, shifted and combined in place)
    keys <<= 32
    keys |= pairs[:, 1]
    return _increasing(keys)


def _increasing(keys: np.ndarray) -> np.ndarray | None:
    """``keys`` ``(p,)`` when strictly increasing (sorted and unique), else None."""
    return keys if len(keys) < 2 or bool(np.all(keys[1:] > keys[:-1])) else None


class BatchLayout(NamedTuple):
    """The indices of a pair batch (:class:`~sim_core.energies.contact.batch_kernel.PairBatch`, its argument
    ``layout``) over the kept compaction of candidate lists: pair ``k`` of the batch is row ``rows[k]`` of ``local``.

    Attributes:
        own: int64 ``(u,)``, the sorted distinct vertices every candidate names (a superset of the batch's).
        local: int32 ``(p + q, 4)``, every candidate's vertices (the vertex-triangle list's, then the edge-edge
            list's) as positions in ``own``: a NumPy array, or on CUDA a Taichi ndarray in device memory where the
            compaction was made there (:meth:`local_on_device`, :meth:`host_local`).
        rows: int32 ``(p + r,)``, the batch's pairs as rows of ``local`` (the vertex-triangle pairs ``0 .. p - 1``
            first: a row below ``p`` is a vertex-triangle pair).
        ee_rows: int64 ``(r,)``, the batch's edge-edge pairs as rows of the edge-edge list (``rows[p:] - p``).
        device: the lists' device cache (:attr:`CandidateVertices.device`), where ``local`` is kept on CUDA.
    """

    own: np.ndarray
    local: object
    rows: np.ndarray
    ee_rows: np.ndarray
    device: dict

    def local_on_device(self) -> object:
        """:attr:`local` where a launch reads it: on CUDA a Taichi ndarray in device memory (a NumPy ``local`` sent
        once per list, kept in :attr:`device`), elsewhere the NumPy array."""
        if not isinstance(self.local, np.ndarray):
            return self.local
        # optional heavy dependency: Taichi, loaded on a Taichi backend only (where pair batches are made)
        from sim_core.ti_kernels.buffers import on_device

        return on_device(self.device, "vertices", self.local)

    def host_local(self) -> np.ndarray:
        """:attr:`local` as a NumPy int32 array ``(p + q, 4)`` (one kept in device memory copied back once per
        list)."""
        if isinstance(self.local, np.ndarray):
            return self.local
        kept = self.device.get("host_local")
        if kept is None or kept[0] is not self.local:
            kept = self.device["host_local"] = (self.local, self.local.to_numpy())
        return kept[1]


def sheet_vertices_off_solids(vt: np.ndarray, keys: np.ndarray | None, sheet_vertex: np.ndarray,
                              solid_triangle: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """``(vt, keys)``: the vertex-triangle candidates ``vt`` ``(p, 2)`` (``[vertex, triangle row]``) without the pairs
    of a sheet's vertex and a solid's triangle (:class:`~sim_core.model.ContactSettings` ``sheet_vertices_vs_solids``
    off), new arrays in the same order, and their packed keys (``keys`` int64 ``(p,)`` of the same rows, or None)
    likewise. ``sheet_vertex``: bool ``(n,)``, whether each vertex is a sheet's; ``solid_triangle``: bool ``(t,)``,
    whether each triangle is a solid's (tables made once: two lookups a pair)."""
    rows = np.flatnonzero(~(np.take(sheet_vertex, vt[:, 0]) & np.take(solid_triangle, vt[:, 1])))
    return np.take(vt, rows, axis=0), None if keys is None else np.take(keys, rows)


def lookup_pairs(old: tuple | None, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(pos, found)`` of ``pairs`` ``(p, 2)`` in ``old`` (``(old pairs, old arrays)``, the old pairs sorted as
    candidate lists are): rows ``pos`` ``(p,)`` of the old arrays hold the pairs ``found`` (bool ``(p,)``). The same
    list (the same array object) is found row for row without a search."""
    if old is None or not len(old[0]) or not len(pairs):
        return np.zeros(len(pairs), dtype=np.int64), np.zeros(len(pairs), dtype=bool)
    old_pairs = old[0]
    if old_pairs is pairs:
        return np.arange(len(pairs), dtype=np.int64), np.ones(len(pairs), dtype=bool)
    keys = (pairs[:, 0] << 32) | pairs[:, 1]
    old_keys = (old_pairs[:, 0] << 32) | old_pairs[:, 1]
    pos = np.minimum(np.searchsorted(old_keys, keys), len(old_keys) - 1)
    return pos, old_keys[pos] == keys
