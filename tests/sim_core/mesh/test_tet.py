"""Structured tet boxes, rest volumes, boundary surfaces and box-face selection."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.tet import (TET_CUTS, box_face_vertices, mirrored_cut_flags, tet_box, tet_boundary_triangles,
                               tet_rest_volume)

SIZE = (0.02, 0.03, 0.005)
RES = (4, 5, 3)
ORIGIN = (-0.01, 0.2, 1.0)


@pytest.fixture(params=TET_CUTS)
def box(request):
    return tet_box(SIZE, RES, ORIGIN, cut=request.param)


def test_volumes_positive_and_sum_to_box(box) -> None:
    nx, ny, nz = RES
    assert box.x.shape == (nx * ny * nz, 3)
    assert box.tets.shape == (6 * (nx - 1) * (ny - 1) * (nz - 1), 4)
    assert box.tets.dtype == np.int64
    v = tet_rest_volume(box.tets, box.x)
    assert np.all(v > 0)
    assert v.sum() == pytest.approx(np.prod(SIZE), rel=1e-12)


def test_vertex_index_convention(box) -> None:
    nx, ny, _ = RES
    ix, iy, iz = 2, 3, 1
    i = (iz * ny + iy) * nx + ix
    spacing = np.array(SIZE) / (np.array(RES) - 1)
    assert np.allclose(box.x[i], np.array(ORIGIN) + spacing * [ix, iy, iz])


def test_faces_match_between_cells(box) -> None:
    """Each face is shared by at most 2 tets and the boundary has the box's triangle count."""
    faces = np.sort(box.tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() == 2
    cx, cy, cz = (r - 1 for r in RES)
    expected_boundary = 2 * 2 * (cx * cy + cy * cz + cx * cz)
    assert np.sum(counts == 1) == expected_boundary
    assert tet_boundary_triangles(box.tets).shape == (expected_boundary, 3)


def test_boundary_is_closed_outward_surface(box) -> None:
    tri = tet_boundary_triangles(box.tets, box.x)
    a, b, c = (box.x[tri[:, k]] for k in range(3))
    area_normal = 0.5 * np.cross(b - a, c - a)  # |.| = area, direction = right-hand normal
    # closed surface: sum of area-weighted normals vanishes
    assert np.allclose(area_normal.sum(axis=0), 0.0, atol=1e-15)
    # divergence theorem: V = 1/3 sum (centroid . n) A  (positive only for outward normals)
    centroid = (a + b + c) / 3
    assert np.sum(centroid * area_normal) / 3 == pytest.approx(np.prod(SIZE), rel=1e-10)
    # every boundary triangle of a convex box points away from the centre
    centre = np.array(ORIGIN) + 0.5 * np.array(SIZE)
    assert np.all(np.einsum("ij,ij->i", centroid - centre, area_normal) > 0)
    # watertight and consistently oriented: every directed edge appears once, its reverse once
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    directed = {tuple(e) for e in edges.tolist()}
    assert len(directed) == edges.shape[0]
    assert all((j, i) in directed for i, j in directed)


def test_boundary_of_single_tet_is_outward() -> None:
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tri = tet_boundary_triangles(np.array([[0, 1, 2, 3]]))
    n = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    outward = x[tri].mean(axis=1) - x.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", n, outward) > 0)


def test_boundary_rejects_non_manifold_and_inverted() -> None:
    tets = np.array([[0, 1, 2, 3], [0, 1, 2, 4], [0, 1, 2, 5]])
    with pytest.raises(MeshError, match="non-manifold"):
        tet_boundary_triangles(tets)
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    with pytest.raises(MeshError, match="tet 0 .*inverted"):
        tet_boundary_triangles(np.array([[0, 2, 1, 3]]), x)


def test_box_face_vertices(box) -> None:
    nx, ny, nz = RES
    top = box_face_vertices(box, 2, "max")
    assert top.shape == (nx * ny,)
    assert np.allclose(box.x[top, 2], ORIGIN[2] + SIZE[2])
    left = box_face_vertices(box, 0, "min")
    assert left.shape == (ny * nz,)
    assert np.allclose(box.x[left, 0], ORIGIN[0])
    assert np.array_equal(left, np.arange(0, nx * ny * nz, nx))
    with pytest.raises(ConfigError, match="axis"):
        box_face_vertices(box, 3, "max")
    with pytest.raises(ConfigError, match="side"):
        box_face_vertices(box, 0, "top")


@pytest.mark.parametrize(
    "size,res,match",
    [((0.0, 1, 1), (2, 2, 2), "size"), ((1, 1, 1), (1, 2, 2), "resolution"), ((1, 1), (2, 2, 2), "size")],
)
def test_tet_box_rejects_bad_arguments(size, res, match) -> None:
    with pytest.raises(ConfigError, match=match):
        tet_box(size, res)
    with pytest.raises(ConfigError, match="cut"):
        tet_box((1, 1, 1), (2, 2, 2), cut="diagonal")


def _tet_set(tets: np.ndarray) -> set[tuple[int, ...]]:
    return {tuple(t) for t in np.sort(tets, axis=1).tolist()}


def _mirror(res: tuple[int, int, int], axis: int) -> np.ndarray:
    """Vertex index -> the index of its mirror image about the box's mid-plane normal to ``axis``."""
    nx, ny, nz = res
    iz, iy, ix = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    ijk = [ix.ravel(), iy.ravel(), iz.ravel()]
    ijk[axis] = res[axis] - 1 - ijk[axis]
    return (ijk[2] * ny + ijk[1]) * nx + ijk[0]


@pytest.mark.parametrize("res", [(3, 3, 3), (5, 7, 3), (9, 7, 5)])
def test_the_mirrored_cut_is_its_own_mirror_image_where_the_cells_are_even(res) -> None:
    """With an even cell count along x and y the mirrored cut maps onto itself tet for tet under either mirror (the
    Kuhn cut onto none of its tets: every cell's diagonal changes)."""
    mirrored, kuhn = (tet_box((0.02, 0.015, 0.004), res, cut=cut) for cut in ("mirrored", "kuhn"))
    for axis in (0, 1):
        image = _mirror(res, axis)
        assert _tet_set(image[mirrored.tets]) == _tet_set(mirrored.tets)
        assert not _tet_set(image[kuhn.tets]) & _tet_set(kuhn.tets)


def test_with_an_odd_cell_count_only_the_middle_layer_changes_in_the_mirror_image() -> None:
    """``[8, 6, 5]`` (7 x 5 x 4 cells): the mirror image along x changes the 4 x 5 middle cells' 6 tets each, along y
    the 7 x 4 middle cells'."""
    res = (8, 6, 5)
    mesh = tet_box((0.0186, 0.0143, 0.004), res, cut="mirrored")
    own = _tet_set(mesh.tets)
    assert len(own - _tet_set(_mirror(res, 0)[mesh.tets])) == 6 * 5 * 4
    assert len(own - _tet_set(_mirror(res, 1)[mesh.tets])) == 6 * 7 * 4


@pytest.mark.parametrize("cells", range(1, 10))
def test_mirrored_cut_flags_alternate_and_are_opposite_in_mirror_partners(cells) -> None:
    flags = mirrored_cut_flags(cells)
    assert flags.shape == (cells,) and flags.dtype == bool
    partners = [(i, cells - 1 - i) for i in range(cells) if i != cells - 1 - i]
    assert all(flags[i] != flags[j] for i, j in partners)
    lower = flags[: (cells + 1) // 2]
    assert np.array_equal(lower, np.arange(len(lower)) % 2 == 1)


def test_the_kuhn_cut_is_the_default() -> None:
    a, b = tet_box(SIZE, RES, ORIGIN), tet_box(SIZE, RES, ORIGIN, cut="kuhn")
    assert np.array_equal(a.tets, b.tets)
    assert not np.array_equal(a.tets, tet_box(SIZE, RES, ORIGIN, cut="mirrored").tets)
