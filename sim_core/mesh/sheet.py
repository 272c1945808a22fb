"""Rectangular sheet grids and the edge / hinge topology of triangle sheets.

A thin shell is a triangle mesh. The membrane terms need its triangles and edges, the discrete-shell
bending term (Grinspun et al. 2003) its *hinges*: pairs of triangles sharing an interior edge,
stored as ``[e0, e1, opp0, opp1]`` where ``(e0, e1, opp0)`` is one triangle in its mesh orientation
and ``opp1`` the third vertex of the other one (ARCHITECTURE.md, "Hinges").
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np

from sim_core.errors import ConfigError, MeshError

GridPattern = Literal["alternating", "regular"]


class TriMesh(NamedTuple):
    """A triangle mesh.

    Attributes:
        x: vertex positions in m, shape ``(vertex_count, 3)``, float64.
        triangles: vertex indices, shape ``(triangle_count, 3)``, int64, counter-clockwise seen
            from the side the normal points to.
    """

    x: np.ndarray
    triangles: np.ndarray


class SheetTopology(NamedTuple):
    """Edges and hinges of a manifold, consistently oriented triangle mesh.

    Attributes:
        edges: unique undirected edges ``(a, b)`` with ``a < b``, shape ``(edge_count, 2)``, int64,
            sorted lexicographically.
        hinges: ``[e0, e1, opp0, opp1]`` per interior edge, shape ``(hinge_count, 4)``, int64.
        edge_triangles: the one or two triangles of each edge, shape ``(edge_count, 2)``, int64,
            ``-1`` in the second column for boundary edges.
        hinge_edges: index into ``edges`` of each hinge's edge, shape ``(hinge_count,)``, int64.
    """

    edges: np.ndarray
    hinges: np.ndarray
    edge_triangles: np.ndarray
    hinge_edges: np.ndarray


def grid_sheet(
    size: tuple[float, float],
    resolution: tuple[int, int],
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    pattern: GridPattern = "alternating",
) -> TriMesh:
    """A flat rectangular sheet triangulated on a regular vertex grid, in the plane z = origin z.

    Vertex ``(ix, iy)`` sits at ``origin + (ix Lx / (nx - 1), iy Ly / (ny - 1), 0)`` with index
    ``iy * nx + ix`` (row-major, y outer; INTERFACES.md). Every grid cell is split into two
    triangles, counter-clockwise seen from +z (normals +z). ``"regular"`` uses the same diagonal
    (ix, iy)-(ix+1, iy+1) in every cell; ``"alternating"`` flips it in a checkerboard, which makes
    the discrete bending stiffness less direction dependent.

    Args:
        size: ``(Lx, Ly)`` in m, both > 0.
        resolution: ``(nx, ny)`` vertices along x and y, both >= 2.
        origin: position of vertex 0 in m.
        pattern: ``"alternating"`` or ``"regular"`` diagonals.

    Returns:
        :class:`TriMesh` with ``nx * ny`` vertices and ``2 (nx - 1)(ny - 1)`` triangles.

    Raises:
        ConfigError: non-positive or non-finite size, resolution below 2, unknown pattern.
    """
    lx, ly = (float(v) for v in size)
    nx, ny = (int(v) for v in resolution)
    if not (np.isfinite(lx) and np.isfinite(ly) and lx > 0 and ly > 0):
        raise ConfigError(f"grid_sheet: size must be two finite lengths > 0, got {tuple(size)}")
    if nx < 2 or ny < 2:
        raise ConfigError(f"grid_sheet: resolution must be >= 2 vertices per side, got {tuple(resolution)}")
    if pattern not in ("alternating", "regular"):
        raise ConfigError(f"grid_sheet: unknown pattern {pattern!r}; use 'alternating' or 'regular'")
    o = np.asarray(origin, dtype=float).reshape(3)
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))  # shape (ny, nx): y outer
    x = np.zeros((ny * nx, 3))
    x[:, 0] = o[0] + ix.reshape(-1) * (lx / (nx - 1))
    x[:, 1] = o[1] + iy.reshape(-1) * (ly / (ny - 1))
    x[:, 2] = o[2]

    cx, cy = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    cx, cy = cx.reshape(-1), cy.reshape(-1)
    v00 = cy * nx + cx
    v10, v01, v11 = v00 + 1, v00 + nx, v00 + nx + 1
    # Diagonal v00-v11: (v00, v10, v11), (v00, v11, v01); diagonal v10-v01: (v00, v10, v01), (v10, v11, v01).
    main = np.stack([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)], 1)
    anti = np.stack([np.stack([v00, v10, v01], 1), np.stack([v10, v11, v01], 1)], 1)
    flip = ((cx + cy) % 2 == 1) if pattern == "alternating" else np.zeros(cx.shape, dtype=bool)
    triangles = np.where(flip[:, None, None], anti, main).reshape(-1, 3).astype(np.int64)
    return TriMesh(x, triangles)


def sheet_topology(triangles: np.ndarray) -> SheetTopology:
    """Unique edges and bending hinges of a triangle mesh.

    Each triangle ``(a, b, c)`` contributes the directed half-edges a->b, b->c, c->a. An edge with
    two half-edges is interior and yields one hinge ``[e0, e1, opp0, opp1]``: ``e0 -> e1`` is the
    half-edge of the lower-numbered triangle, ``opp0`` that triangle's third vertex and ``opp1``
    the third vertex of the other triangle.

    Args:
        triangles: vertex indices, shape ``(triangle_count, 3)``, non-negative integers.

    Returns:
        :class:`SheetTopology`.

    Raises:
        MeshError: wrong shape, negative index, a triangle repeating a vertex, an edge shared by
            three or more triangles (non-manifold), or two triangles traversing their common edge in
            the same direction (inconsistent orientation). The message names the edge / triangles.
    """
    tri = np.asarray(triangles)
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise MeshError(f"sheet_topology: triangles must have shape (t, 3), got {tri.shape}")
    if tri.size and not np.issubdtype(tri.dtype, np.integer):
        raise MeshError(f"sheet_topology: triangle indices must be integers, got dtype {tri.dtype}")
    tri = tri.astype(np.int64)
    t = tri.shape[0]
    if t == 0:
        empty2 = np.zeros((0, 2), dtype=np.int64)
        return SheetTopology(empty2, np.zeros((0, 4), dtype=np.int64), empty2, np.zeros(0, dtype=np.int64))
    if tri.min() < 0:
        bad = int(np.nonzero((tri < 0).any(axis=1))[0][0])
        raise MeshError(f"sheet_topology: triangle {bad} has a negative vertex index {tri[bad].tolist()}")
    repeated = (tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2]) | (tri[:, 2] == tri[:, 0])
    if repeated.any():
        bad = int(np.nonzero(repeated)[0][0])
        raise MeshError(f"sheet_topology: triangle {bad} repeats a vertex {tri[bad].tolist()}")

    # Half-edge k = 3 * triangle + j goes tri[:, j] -> tri[:, j+1], opposite vertex tri[:, j+2].
    src = tri.reshape(-1)
    dst = tri[:, [1, 2, 0]].reshape(-1)
    opp = tri[:, [2, 0, 1]].reshape(-1)
    he_tri = np.repeat(np.arange(t, dtype=np.int64), 3)
    keys = np.stack([np.minimum(src, dst), np.maximum(src, dst)], axis=1)
    edges, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    if counts.max() > 2:
        e = int(np.nonzero(counts > 2)[0][0])
        tris = sorted(set(he_tri[inverse == e].tolist()))
        raise MeshError(
            f"sheet_topology: non-manifold edge {edges[e].tolist()} is shared by {counts[e]} triangles {tris}"
        )
    order = np.argsort(inverse, kind="stable")  # half-edges grouped by edge, triangle order kept
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    he_first = order[first]
    edge_triangles = np.full((edges.shape[0], 2), -1, dtype=np.int64)
    edge_triangles[:, 0] = he_tri[he_first]
    interior = np.nonzero(counts == 2)[0]
    he_a = he_first[interior]
    he_b = order[first[interior] + 1]
    edge_triangles[interior, 1] = he_tri[he_b]
    same_direction = src[he_a] == src[he_b]
    if same_direction.any():
        i = int(np.nonzero(same_direction)[0][0])
        raise MeshError(
            f"sheet_topology: triangles {int(he_tri[he_a[i]])} and {int(he_tri[he_b[i]])} traverse edge "
            f"{edges[interior[i]].tolist()} in the same direction (inconsistent orientation)"
        )
    hinges = np.stack([src[he_a], dst[he_a], opp[he_a], opp[he_b]], axis=1).astype(np.int64)
    return SheetTopology(edges.astype(np.int64), hinges, edge_triangles, interior.astype(np.int64))
