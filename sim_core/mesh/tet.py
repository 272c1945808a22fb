"""Tetrahedral meshes: structured boxes, rest volumes and the oriented boundary surface.

Convention: a tet ``(i0, i1, i2, i3)`` is positively oriented when its signed volume
``(x1 - x0) x (x2 - x0) . (x3 - x0) / 6`` is positive. Every function here produces and expects
positively oriented tets.
"""

from __future__ import annotations

import itertools
from typing import Literal, NamedTuple, Sequence

import numpy as np

from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.validate import tet_signed_volumes, validate_tets

TET_FACES_OUTWARD = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)
"""Local vertex indices of the four faces of a positively oriented tet, ordered so that the
right-hand normal points out of the tet (face ``f`` is opposite local vertex ``3 - f``)."""


class TetMesh(NamedTuple):
    """A tetrahedral mesh.

    Attributes:
        x: vertex positions in m, shape ``(n, 3)``, float64.
        tets: vertex indices, shape ``(k, 4)``, int64, positive signed volume.
    """

    x: np.ndarray
    tets: np.ndarray


def _kuhn_cell_tets() -> np.ndarray:
    """The 6 tets of the unit cube split along its main diagonal (Kuhn / Freudenthal).

    For a permutation ``(p0, p1, p2)`` of the axes the tet is
    ``(000, e_p0, e_p0 + e_p1, 111)``; its signed volume is the sign of the permutation / 6, so odd
    permutations swap the middle vertices. Every square face is cut along the diagonal through its
    (lowest, highest) corners, so translated copies share faces exactly.

    Returns:
        shape ``(6, 4, 3)`` integer corner offsets.
    """
    cells = []
    for perm in itertools.permutations(range(3)):
        e = np.eye(3, dtype=np.int64)
        v1 = e[perm[0]]
        v2 = v1 + e[perm[1]]
        corners = [np.zeros(3, dtype=np.int64), v1, v2, np.ones(3, dtype=np.int64)]
        if round(np.linalg.det(np.stack([e[p] for p in perm]))) < 0:
            corners[1], corners[2] = corners[2], corners[1]
        cells.append(np.stack(corners))
    return np.stack(cells)


TetCut = Literal["kuhn", "mirrored"]
"""How :func:`tet_box` cuts its hexahedral cells (:data:`TET_CUTS`)."""

TET_CUTS = ("kuhn", "mirrored")
"""``"kuhn"``: every cell along its (0,0,0)-(1,1,1) diagonal, the same handedness everywhere (a mirror image of the
box is a different mesh); ``"mirrored"``: each cell is the Kuhn cell reflected along every axis on which its index
is odd in the box's lower half, and the mirror image of its partner's cut in the upper half
(:func:`mirrored_cut_flags`): the mesh is its own mirror image about the box's mid-planes wherever the cell count
along the mirrored axis is even, and, where it is odd, everywhere but the middle layer of cells."""


def mirrored_cut_flags(cells: int) -> np.ndarray:
    """Per cell along one axis, whether the ``"mirrored"`` cut reflects the Kuhn cell along that axis.

    Cells ``i`` and ``cells - 1 - i`` get opposite flags (the box's mirror image about its mid-plane maps the one
    cell's cut onto the other's), alternating from the first cell (``i mod 2``, the 3-D analogue of the card's
    checkerboard: every interior vertex plane is also a mirror plane); with an odd count the middle cell, its own
    image, keeps ``i mod 2``, the one cell whose cut a mirror image changes.

    Args:
        cells: cells along the axis, >= 1.

    Returns:
        shape ``(cells,)`` bool.
    """
    i = np.arange(int(cells))
    flags = i % 2 == 1
    upper = 2 * i > cells - 1
    flags[upper] = ~flags[cells - 1 - i[upper]]
    return flags


def tet_box(
    size: Sequence[float],
    resolution: Sequence[int],
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    cut: TetCut = "kuhn",
) -> TetMesh:
    """A structured tetrahedral box, each hexahedral cell split into 6 tets along a main diagonal.

    With ``cut="kuhn"`` every cell is split along its (0,0,0)-(1,1,1) diagonal (Kuhn / Freudenthal,
    :func:`_kuhn_cell_tets`); with ``cut="mirrored"`` the cell ``(ix, iy, iz)`` is that split reflected along the
    axes whose :func:`mirrored_cut_flags` are set. Both are conforming: a cell's square faces normal to an axis are
    cut along the diagonal the other two axes' flags set, which the neighbour across that face shares (cf. the 2-D
    "Union Jack" grid; Bey, "Simplicial grid refinement", Numer. Math. 85, 2000, on Freudenthal's split and its
    reflections).

    Args:
        size: edge lengths ``(Lx, Ly, Lz)`` in m, each > 0.
        resolution: vertices per axis ``(nx, ny, nz)``, each >= 2.
        origin: position of the minimum corner in m.
        cut: ``"kuhn"`` or ``"mirrored"`` (:data:`TET_CUTS`).

    Returns:
        :class:`TetMesh` with ``nx * ny * nz`` vertices (vertex ``(ix, iy, iz)`` at index
        ``(iz * ny + iy) * nx + ix``) and ``6 (nx-1)(ny-1)(nz-1)`` positively oriented tets.

    Raises:
        ConfigError: non-positive size, resolution below 2 or an unknown cut.
    """
    size_arr = np.asarray(size, dtype=float)
    res = np.asarray(resolution)
    if size_arr.shape != (3,) or not np.all(np.isfinite(size_arr)) or np.any(size_arr <= 0):
        raise ConfigError(f"tet_box size must be 3 positive lengths, got {size!r}")
    if res.shape != (3,) or np.any(res != np.round(res)) or np.any(res < 2):
        raise ConfigError(f"tet_box resolution must be 3 integers >= 2 (vertices per axis), got {resolution!r}")
    if cut not in TET_CUTS:
        raise ConfigError(f"tet_box cut must be one of {TET_CUTS}, got {cut!r}")
    nx, ny, nz = (int(r) for r in res)
    axes = [np.linspace(0.0, size_arr[d], int(res[d])) + float(origin[d]) for d in range(3)]
    zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    x = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)

    iz, iy, ix = np.meshgrid(np.arange(nz - 1), np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    base = np.stack([ix.ravel(), iy.ravel(), iz.ravel()], axis=1)  # (cells, 3)
    offsets = np.broadcast_to(_kuhn_cell_tets()[None], (len(base), 6, 4, 3)).copy()  # (cells, 6, 4, 3)
    if cut == "mirrored":
        flips = np.stack([mirrored_cut_flags(n - 1)[base[:, d]] for d, n in enumerate((nx, ny, nz))], axis=1)
        offsets = np.where(flips[:, None, None, :], 1 - offsets, offsets)
        # a reflection along an odd number of axes turns every tet inside out: swap two vertices back
        odd = flips.sum(axis=1) % 2 == 1
        offsets[odd] = offsets[odd][:, :, [0, 2, 1, 3]]
    corner = base[:, None, None, :] + offsets
    tets = (corner[..., 2] * ny + corner[..., 1]) * nx + corner[..., 0]
    return TetMesh(x, tets.reshape(-1, 4).astype(np.int64))


def tet_rest_volume(tets: np.ndarray, x: np.ndarray, where: str = "tet mesh") -> np.ndarray:
    """Rest volumes of positively oriented tets.

    Args:
        tets: shape ``(k, 4)``.
        x: rest positions in m, shape ``(n, 3)``.
        where: name of the mesh for error messages.

    Returns:
        volumes in m^3, shape ``(k,)``, all > 0.

    Raises:
        MeshError: an inverted or degenerate tet (named by index), bad indices, non-finite vertices.
    """
    tets = validate_tets(x, tets, where)
    return tet_signed_volumes(np.asarray(x, dtype=float), tets)


def tet_boundary_triangles(tets: np.ndarray, x: np.ndarray | None = None) -> np.ndarray:
    """Boundary faces of a tet mesh, oriented with outward normals.

    A face is on the boundary when exactly one tet has it. Orientation is combinatorial
    (:data:`TET_FACES_OUTWARD`) and relies on positively oriented tets; pass ``x`` to check that.

    Args:
        tets: shape ``(k, 4)``, positively oriented.
        x: optional positions ``(n, 3)``; when given the tets are validated first.

    Returns:
        triangles, shape ``(f, 3)``, int64, ordered by (tet index, local face).

    Raises:
        MeshError: a face shared by more than two tets (non-manifold), or (with ``x``) an
            inverted/degenerate tet.
    """
    tets = np.asarray(tets, dtype=np.int64)
    if x is not None:
        tets = validate_tets(x, tets, "tet_boundary_triangles")
    if tets.shape[0] == 0:
        return np.zeros((0, 3), dtype=np.int64)
    faces = tets[:, TET_FACES_OUTWARD].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    if np.any(counts > 2):
        f = int(np.flatnonzero(counts[inverse] > 2)[0])
        raise MeshError(
            f"tet mesh is non-manifold: face {key[f].tolist()} of tet {f // 4} is shared by more than two tets"
        )
    return faces[counts[inverse] == 1]


def box_face_vertices(
    mesh: TetMesh, axis: int, side: Literal["min", "max"], rel_tol: float = 1e-9
) -> np.ndarray:
    """Indices of the vertices on one face of a mesh's axis-aligned bounding box.

    Args:
        mesh: any mesh with positions ``mesh.x`` of shape ``(n, 3)``.
        axis: 0, 1 or 2 (x, y, z).
        side: ``"min"`` or ``"max"`` face along ``axis``.
        rel_tol: tolerance relative to the bounding-box extent along ``axis``.

    Returns:
        sorted vertex indices, shape ``(m,)``, int64.

    Raises:
        ConfigError: bad ``axis`` or ``side``.
    """
    if axis not in (0, 1, 2):
        raise ConfigError(f"axis must be 0, 1 or 2, got {axis!r}")
    if side not in ("min", "max"):
        raise ConfigError(f"side must be 'min' or 'max', got {side!r}")
    c = np.asarray(mesh.x, dtype=float)[:, axis]
    lo, hi = float(c.min()), float(c.max())
    tol = rel_tol * max(hi - lo, np.finfo(float).tiny)
    target = lo if side == "min" else hi
    return np.flatnonzero(np.abs(c - target) <= tol).astype(np.int64)


# mid-side node slots of a 10-node tet (Abaqus C3D10 / VTK tetra10 order): 4 (0,1), 5 (1,2), 6 (2,0),
# 7 (0,3), 8 (1,3), 9 (2,3)
_CORNER_CHILDREN = np.array([[0, 4, 6, 7], [4, 1, 5, 8], [6, 5, 2, 9], [7, 8, 9, 3]])
# the inner octahedron, split along one of its three diagonals (opposite mid-side pairs) into four
# tets around it; ring = the other four mid-side nodes in cyclic order
_OCTAHEDRON_SPLITS = (
    ((4, 9), (6, 5, 8, 7)),  # diagonal (0,1)-(2,3)
    ((6, 8), (4, 5, 9, 7)),  # diagonal (2,0)-(1,3)
    ((7, 5), (4, 8, 9, 6)),  # diagonal (0,3)-(1,2)
)


def split_quadratic_tets(x: np.ndarray, tet10: np.ndarray) -> np.ndarray:
    """Split each 10-node tet into 8 linear tets on its corner and mid-side nodes.

    The standard red refinement (Bey 1995, "Tetrahedral grid refinement", Computing 55): four corner
    tets and an inner octahedron cut along its shortest diagonal (best shape). Each child keeps
    its parent's orientation. The linear tets use exactly the nodes of the quadratic mesh, so a
    model made for quadratic elements (e.g. CalculiX C3D10) keeps its geometry and node sets with
    twice the linear resolution instead of dropping the mid-side nodes.

    Args:
        x: node positions, shape ``(n, 3)``.
        tet10: node indices, shape ``(k, 10)``, order: 4 corners, then mid-sides of edges
            (0,1), (1,2), (2,0), (0,3), (1,3), (2,3) (Abaqus C3D10 = VTK tetra10).

    Returns:
        shape ``(8 k, 4)`` int64, children of tet ``e`` in rows ``8 e .. 8 e + 7``.

    Raises:
        MeshError: ``tet10`` not of shape ``(k, 10)`` or an index out of range.
    """
    tet10 = np.asarray(tet10, dtype=np.int64)
    if tet10.ndim != 2 or tet10.shape[1] != 10:
        raise MeshError(f"quadratic tets must have shape (k, 10), got {tet10.shape}")
    if tet10.size and (tet10.min() < 0 or tet10.max() >= len(x)):
        raise MeshError(f"quadratic tets reference node {int(tet10.max())} of {len(x)} nodes")
    k = tet10.shape[0]
    diag_len = np.stack([np.linalg.norm(x[tet10[:, a]] - x[tet10[:, b]], axis=1) for (a, b), _ in _OCTAHEDRON_SPLITS],
                        axis=1)
    choice = np.argmin(diag_len, axis=1) if k else np.zeros(0, dtype=np.int64)
    octa = np.zeros((k, 4, 4), dtype=np.int64)
    for c, ((a, b), ring) in enumerate(_OCTAHEDRON_SPLITS):
        rows = choice == c
        local = np.array([[a, b, ring[i], ring[(i + 1) % 4]] for i in range(4)])
        octa[rows] = tet10[rows][:, local]
    children = np.concatenate([tet10[:, _CORNER_CHILDREN], octa], axis=1)  # (k, 8, 4)
    parent_sign = np.sign(tet_signed_volumes(x, tet10[:, :4]))
    flat = children.reshape(-1, 4)
    flip = np.sign(tet_signed_volumes(x, flat)) != np.repeat(parent_sign, 8)
    flat[flip] = flat[flip][:, [0, 2, 1, 3]]
    return flat
