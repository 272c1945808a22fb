"""Validation of vertex arrays, triangle meshes and tetrahedral meshes.

Every check raises :class:`~sim_core.errors.MeshError` with a message that names what was being
validated (``where``: a file, a body, a potential) and the index of the first offending vertex or
element, so that a bad mesh is found at load time instead of as a NaN in a Newton step.
"""

from __future__ import annotations

import numpy as np

from sim_core.errors import MeshError

RELATIVE_DEGENERACY_TOL = 1e-8
"""Default shape tolerance: a triangle with area <= tol * l_max^2 or a tet with |volume| <=
tol * l_max^3 (l_max its longest edge) is degenerate."""


def validate_vertices(x: np.ndarray, where: str) -> np.ndarray:
    """Check a vertex array.

    Args:
        x: positions in m, shape ``(n, 3)``.
        where: what is validated (file name, body name), used in the message.

    Returns:
        ``x`` as a float64 array of shape ``(n, 3)``.

    Raises:
        MeshError: wrong shape, or a NaN/inf coordinate (the message names the first vertex index).
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise MeshError(f"{where}: vertex array must have shape (n, 3), got {x.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(x), axis=1))
    if bad.size:
        i = int(bad[0])
        raise MeshError(f"{where}: vertex {i} has a non-finite coordinate {x[i].tolist()} ({bad.size} such vertices)")
    return x


def _check_indices(elements: np.ndarray, vertex_count: int, m: int, kind: str, where: str) -> np.ndarray:
    """Shape, integrality, range and distinctness of element vertex indices."""
    arr = np.asarray(elements)
    if arr.ndim != 2 or arr.shape[1] != m:
        raise MeshError(f"{where}: {kind} array must have shape (k, {m}), got {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise MeshError(f"{where}: {kind} vertex indices must be integers")
    arr = arr.astype(np.int64)
    if arr.size and (arr.min() < 0 or arr.max() >= vertex_count):
        e = int(np.flatnonzero(np.any((arr < 0) | (arr >= vertex_count), axis=1))[0])
        raise MeshError(
            f"{where}: {kind} {e} has vertex index out of range [0, {vertex_count}): {arr[e].tolist()}"
        )
    columns = arr.T.copy()  # (m, k): each pair of columns compared once
    same = np.zeros(arr.shape[0], dtype=bool)
    for i in range(m):
        for j in range(i + 1, m):
            same |= columns[i] == columns[j]
    repeated = np.flatnonzero(same)
    if repeated.size:
        e = int(repeated[0])
        raise MeshError(f"{where}: {kind} {e} repeats a vertex: {arr[e].tolist()}")
    return arr


def triangle_areas(x: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangle areas in m^2, shape ``(t,)``, from ``x`` ``(n, 3)`` and ``triangles`` ``(t, 3)``."""
    a, b, c = x[triangles[:, 0]], x[triangles[:, 1]], x[triangles[:, 2]]
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def tet_signed_volumes(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed tet volumes ``(x1-x0) x (x2-x0) . (x3-x0) / 6`` in m^3, shape ``(k,)``.

    Positive when vertex 3 lies on the side of face (0, 1, 2) that its right-hand normal points to.
    """
    x0 = x[tets[:, 0]]
    return np.einsum("ij,ij->i", np.cross(x[tets[:, 1]] - x0, x[tets[:, 2]] - x0), x[tets[:, 3]] - x0) / 6.0


def _max_edge_length(x: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """The longest edge of each element in m, ``(k,)``: the square root of the largest squared length (each a sum of
    the three squared coordinate differences in axis order, as ``np.linalg.norm`` sums them), by coordinate
    columns."""
    m = elements.shape[1]
    coords = [np.ascontiguousarray(x[:, a]) for a in range(3)]
    corners = [[c[elements[:, i]] for c in coords] for i in range(m)]
    longest = None
    for i in range(m):
        for j in range(i + 1, m):
            d = corners[i][0] - corners[j][0]
            squared = d * d
            for a in (1, 2):
                d = corners[i][a] - corners[j][a]
                squared += d * d
            longest = squared if longest is None else np.maximum(longest, squared, out=longest)
    return np.sqrt(longest) if longest is not None else np.zeros(elements.shape[0])


def validate_triangles(
    x: np.ndarray, triangles: np.ndarray, where: str, min_area: float | None = None
) -> np.ndarray:
    """Check a triangle mesh.

    Args:
        x: positions in m, shape ``(n, 3)``.
        triangles: vertex indices, shape ``(t, 3)``.
        where: what is validated, used in the message.
        min_area: triangles with area <= ``min_area`` (m^2) are degenerate. Default: area <=
            ``RELATIVE_DEGENERACY_TOL * l_max^2`` with ``l_max`` the triangle's longest edge.

    Returns:
        ``triangles`` as int64, shape ``(t, 3)``.

    Raises:
        MeshError: non-finite vertex, wrong shape, index out of range, repeated vertex or (near-)zero
            area; the message names the triangle index.
    """
    x = validate_vertices(x, where)
    tri = _check_indices(triangles, x.shape[0], 3, "triangle", where)
    if tri.shape[0] == 0:
        return tri
    area = triangle_areas(x, tri)
    limit = RELATIVE_DEGENERACY_TOL * _max_edge_length(x, tri) ** 2 if min_area is None else float(min_area)
    bad = np.flatnonzero(area <= limit)
    if bad.size:
        e = int(bad[0])
        raise MeshError(
            f"{where}: triangle {e} {tri[e].tolist()} is degenerate (area {area[e]:.3e} m^2, "
            f"{bad.size} such triangles)"
        )
    return tri


def validate_tets(x: np.ndarray, tets: np.ndarray, where: str, min_volume: float | None = None) -> np.ndarray:
    """Check a tetrahedral mesh: every tet must have positive signed volume.

    Args:
        x: positions in m, shape ``(n, 3)``.
        tets: vertex indices, shape ``(k, 4)``, positively oriented (see :func:`tet_signed_volumes`).
        where: what is validated, used in the message.
        min_volume: tets with |volume| <= ``min_volume`` (m^3) are degenerate. Default:
            ``RELATIVE_DEGENERACY_TOL * l_max^3`` with ``l_max`` the tet's longest edge.

    Returns:
        ``tets`` as int64, shape ``(k, 4)``.

    Raises:
        MeshError: non-finite vertex, wrong shape, index out of range, repeated vertex, inverted
            (negative volume) or degenerate tet; the message names the tet index and its signed volume.
    """
    return validated_tet_volumes(x, tets, where, min_volume)[0]


def validated_tet_volumes(x: np.ndarray, tets: np.ndarray, where: str,
                          min_volume: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`validate_tets` that also returns the signed volumes it checked: ``(tets, volumes)``, int64
    ``(k, 4)`` and m^3 ``(k,)`` (:func:`tet_signed_volumes`). Raises as :func:`validate_tets`."""
    x = validate_vertices(x, where)
    t = _check_indices(tets, x.shape[0], 4, "tet", where)
    if t.shape[0] == 0:
        return t, np.zeros(0)
    vol = tet_signed_volumes(x, t)
    if min_volume is None:
        limit = RELATIVE_DEGENERACY_TOL * _max_edge_length(x, t) ** 3
    else:
        limit = np.full(t.shape[0], float(min_volume))
    bad = np.flatnonzero(vol <= limit)
    if bad.size:
        e = int(bad[0])
        kind = "degenerate" if abs(vol[e]) <= limit[e] else "inverted"
        raise MeshError(
            f"{where}: tet {e} {t[e].tolist()} is {kind} (signed volume {vol[e]:.3e} m^3, "
            f"{bad.size} non-positive tets)"
        )
    return t, vol
