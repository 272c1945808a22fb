"""The band blocks of a stacked scene's batched CG: each copy's sheet, its vertices in a band-limiting order
(:func:`sheet_band_dofs`, the lockstep's), or each copy's whole free system in reverse Cuthill-McKee order
(:func:`copy_band_dofs`: measured in ``benchmarks/bench_copy_bands.py`` and docs/gpu_roofline.md, not the lockstep's:
its wider band costs more a factorisation than the CG iterations it saves with today's kernels).

A thin sheet's Newton matrix is the stiff part of a copy's system: its bending modes are slow under the 3x3 vertex
block-Jacobi preconditioner, and the CG's iterations go to them. Its own block, factorised exactly
(:class:`~sim_core.ti_kernels.band_cholesky.BandBlocks`), takes them out: on the Forming scene (a 16 x 8 sheet on a
gel dome, 825 free DoFs a copy) the CG to a relative residual of 1e-4 takes 28 iterations a solve (mean of 147
solves) instead of 256 (a SciPy study of the lockstep's matrices, docs/benchmarks_log.md, session 42). Ordered
along the sheet's long axis (the first principal axis of its rest positions), the grid's rows across the short side
follow each other, and the bending stencil (a hinge spans two rows) couples DoFs at most ``3 (2 r + 1) - 1`` apart
for rows of ``r`` vertices: 53 DoFs on the 16 x 8 grid, against 95 in the vertex order.

The block's factor is kept on the device as tiles (:mod:`~sim_core.ti_kernels.band_cholesky`: about ``3 m t``
entries a copy for ``m`` DoFs in tiles of ``t >= w`` rows, float64 or, in the batched CG's mixed precision, float32),
made at each factorisation by work (the banded elimination's ``m w^2 / 2`` multiply-adds and the tiles') that grows
faster than the CG work the block saves; sheets of more than :data:`MAX_BLOCK_DOFS` DoFs keep the vertex blocks
(measured: Forming's 384 DoFs, 360 of them free, and Folding's 192). The model's fixed vertices are left out of the
block: fixed at every step, they only enlarge it.
"""

from __future__ import annotations

import numpy as np

from sim_core.batch.stacked import StackedScene


MAX_BLOCK_DOFS = 512
"""The largest sheet (DoFs) taken as one band block."""


def long_axis_order(x: np.ndarray) -> np.ndarray:
    """The order of points along their first principal axis (stable: points at one coordinate keep their order).

    Args:
        x: points, shape ``(k, 3)`` (m).

    Returns:
        A permutation of ``0..k-1``, shape ``(k,)``.
    """
    centred = x - x.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0] if len(x) > 1 else np.zeros(3)
    return np.argsort(np.round(centred @ axis, 12), kind="stable")


def sheet_band_dofs(scene: StackedScene, max_dofs: int = MAX_BLOCK_DOFS) -> np.ndarray | None:
    """Each copy's sheet bodies as band blocks of the stacked DoFs, for
    :class:`~sim_core.ti_kernels.pcg.BatchedPCG`'s ``bands``.

    Args:
        scene: the stacked scene (the stacked model's sheet bodies hold whole copies' sheets).
        max_dofs: sheets of more DoFs are left out (module docstring).

    Returns:
        ``(blocks, m)`` int64: one row per copy and sheet, that sheet's stacked DoFs (its vertices in
        :func:`long_axis_order` of the rest positions, three DoFs each; the model's fixed vertices, ``vertex_fixed``,
        left out: fixed at every step, their rows are the identity's and the vertex blocks invert them), padded
        with -1 to the largest sheet's ``m``; None when the scene has no sheet with free vertices and at most
        ``max_dofs`` DoFs.
    """
    model = scene.model
    copy_of = np.full(model.vertex_count, -1, dtype=np.int64)
    local_of = np.full(model.vertex_count, -1, dtype=np.int64)
    copy_of[scene.index] = np.arange(scene.copies)[:, None]
    local_of[scene.index] = np.arange(scene.vertex_count)[None, :]
    rows = []
    for body in model.bodies.values():
        if body.kind != "sheet":
            continue
        vertices = body.vertices
        for c in np.unique(copy_of[vertices]):
            local = np.sort(local_of[vertices[(copy_of[vertices] == c) & ~model.vertex_fixed[vertices]]])
            if not local.size:
                continue
            if 3 * local.size > max_dofs:
                continue
            stacked = scene.index[c][local]
            ordered = stacked[long_axis_order(model.x_rest[stacked])]
            rows.append((3 * ordered[:, None] + np.arange(3)).reshape(-1))
    if not rows:
        return None
    out = np.full((len(rows), max(r.size for r in rows)), -1, dtype=np.int64)
    for k, r in enumerate(rows):
        out[k, : r.size] = r
    return out


def copy_band_dofs(scene: StackedScene, free: np.ndarray, indptr: np.ndarray, indices: np.ndarray,
                   pairs: np.ndarray | None = None) -> np.ndarray:
    """Each copy's free DoFs (its sheet and its gel together) as one band block, for
    :class:`~sim_core.ti_kernels.pcg.BatchedPCG`'s ``bands``: the free vertices of copy 0 in the reverse
    Cuthill-McKee order (Cuthill & McKee 1969; George & Liu, Computer Solution of Large Sparse Positive Definite
    Systems, 1981, Sec. 4.3) of the graph that couples two vertices where the assembled pattern or ``pairs`` does,
    the same local order for every copy.

    Args:
        scene: the stacked scene.
        free: the free-DoF mask, ``(3 N,)`` (a vertex with a free DoF is in its copy's block).
        indptr, indices: the assembled pattern's CSR arrays over the stacked DoFs (an upper triangle or both).
        pairs: None, or more coupled vertex pairs, int ``(K, 2)`` of stacked vertices (e.g. contact blocks' rows and
            columns): those of copy 0 join the graph.

    Returns:
        ``(B, m)`` int64: row ``c`` copy ``c``'s free DoFs, three a vertex, in that order (every copy has the same
        free vertices in a lockstep batch).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    n_local = scene.vertex_count
    local_of = np.full(scene.model.vertex_count, -1, dtype=np.int64)
    local_of[scene.index[0]] = np.arange(n_local)
    vertex_free = np.asarray(free, dtype=bool).reshape(-1, 3).any(axis=1)
    rows = np.repeat(np.arange(np.asarray(indptr).size - 1), np.diff(indptr)) // 3
    cols = np.asarray(indices)[: rows.size] // 3
    if pairs is not None and len(pairs):
        rows = np.concatenate([rows, np.asarray(pairs)[:, 0]])
        cols = np.concatenate([cols, np.asarray(pairs)[:, 1]])
    a, c = local_of[rows], local_of[cols]
    keep = (a >= 0) & (c >= 0)
    kept_local = np.flatnonzero(vertex_free[scene.index[0]])
    compact = np.full(n_local, -1, dtype=np.int64)
    compact[kept_local] = np.arange(kept_local.size)
    a, c = compact[a[keep]], compact[c[keep]]
    both = (a >= 0) & (c >= 0)
    k = kept_local.size
    graph = coo_matrix((np.ones(2 * int(both.sum())), (np.concatenate([a[both], c[both]]),
                                                      np.concatenate([c[both], a[both]]))), shape=(k, k)).tocsr()
    order = kept_local[reverse_cuthill_mckee(graph, symmetric_mode=True)]
    stacked = scene.index[:, order]  # (B, k)
    return (3 * stacked[:, :, None] + np.arange(3)).reshape(scene.copies, -1)
