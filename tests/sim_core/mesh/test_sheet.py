"""Sheet grids and their edge / hinge topology."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.sheet import grid_sheet, sheet_topology


def _normals(x, triangles):
    return np.cross(x[triangles[:, 1]] - x[triangles[:, 0]], x[triangles[:, 2]] - x[triangles[:, 0]])


@pytest.mark.parametrize("pattern", ["alternating", "regular"])
def test_grid_sheet_layout_and_orientation(pattern):
    (lx, ly), (nx, ny), origin = (0.3, 0.12), (7, 4), (0.1, -0.2, 0.05)
    mesh = grid_sheet((lx, ly), (nx, ny), origin, pattern)
    assert mesh.x.shape == (nx * ny, 3) and mesh.x.dtype == np.float64
    assert mesh.triangles.shape == (2 * (nx - 1) * (ny - 1), 3) and mesh.triangles.dtype == np.int64
    for iy in range(ny):
        for ix in range(nx):
            expected = [origin[0] + ix * lx / (nx - 1), origin[1] + iy * ly / (ny - 1), origin[2]]
            assert np.allclose(mesh.x[iy * nx + ix], expected)
    n = _normals(mesh.x, mesh.triangles)
    assert np.allclose(n[:, :2], 0.0) and np.all(n[:, 2] > 0)  # counter-clockwise seen from +z
    assert 0.5 * n[:, 2].sum() == pytest.approx(lx * ly)
    assert np.array_equal(np.unique(mesh.triangles), np.arange(nx * ny))


def test_alternating_pattern_flips_diagonals_in_a_checkerboard():
    nx, ny = 5, 4

    def diagonals(pattern):
        topo = sheet_topology(grid_sheet((1.0, 1.0), (nx, ny), pattern=pattern).triangles)
        ix, iy = topo.edges % nx, topo.edges // nx
        diag = (ix[:, 0] != ix[:, 1]) & (iy[:, 0] != iy[:, 1])
        e = topo.edges[diag]
        cell = np.minimum(ix[diag, 0], ix[diag, 1]) + np.minimum(iy[diag, 0], iy[diag, 1])
        main = (e % nx)[:, 0] < (e % nx)[:, 1]  # (ix, iy)-(ix+1, iy+1): lower index has the lower ix
        return cell, main

    cell, main = diagonals("regular")
    assert main.size == (nx - 1) * (ny - 1) and np.all(main)
    cell, main = diagonals("alternating")
    assert np.array_equal(main, cell % 2 == 0)


def test_grid_sheet_rejects_bad_arguments():
    with pytest.raises(ConfigError, match="resolution"):
        grid_sheet((1.0, 1.0), (1, 3))
    with pytest.raises(ConfigError, match="size"):
        grid_sheet((0.0, 1.0), (3, 3))
    with pytest.raises(ConfigError, match="pattern 'diamond'"):
        grid_sheet((1.0, 1.0), (3, 3), pattern="diamond")


@pytest.mark.parametrize("pattern", ["alternating", "regular"])
def test_sheet_topology_of_grid(pattern):
    nx, ny = 6, 4
    mesh = grid_sheet((0.5, 0.3), (nx, ny), pattern=pattern)
    topo = sheet_topology(mesh.triangles)
    cells = (nx - 1) * (ny - 1)
    edge_count = (nx - 1) * ny + nx * (ny - 1) + cells
    boundary = 2 * (nx - 1) + 2 * (ny - 1)
    assert topo.edges.shape == (edge_count, 2)
    assert np.all(topo.edges[:, 0] < topo.edges[:, 1])
    assert len(np.unique(topo.edges, axis=0)) == edge_count
    assert np.sum(topo.edge_triangles[:, 1] == -1) == boundary
    assert topo.hinges.shape == (edge_count - boundary, 4)
    assert np.array_equal(np.sort(topo.edges[topo.hinge_edges], 1), np.sort(topo.hinges[:, :2], 1))

    # (e0, e1, opp0) and (e1, e0, opp1) are triangles of the mesh with their orientation.
    rotations = {tuple(np.roll(t, k)) for t in mesh.triangles.tolist() for k in range(3)}
    for e0, e1, o0, o1 in topo.hinges.tolist():
        assert (e0, e1, o0) in rotations
        assert (e1, e0, o1) in rotations
    # Triangles of each edge contain it.
    for (a, b), (t0, t1) in zip(topo.edges.tolist(), topo.edge_triangles.tolist()):
        for t in (t0, t1):
            if t >= 0:
                assert {a, b} <= set(mesh.triangles[t].tolist())


def test_sheet_topology_rejects_non_manifold_edge():
    triangles = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(MeshError, match=r"non-manifold edge \[0, 1\] is shared by 3 triangles \[0, 1, 2\]"):
        sheet_topology(triangles)


def test_sheet_topology_rejects_inconsistent_orientation():
    triangles = np.array([[0, 1, 2], [2, 1, 3], [3, 1, 4], [0, 4, 1]])
    triangles[1] = [1, 2, 3]  # traverses 1 -> 2 like triangle 0
    with pytest.raises(MeshError, match=r"triangles 0 and 1 traverse edge \[1, 2\] in the same direction"):
        sheet_topology(triangles)


def test_sheet_topology_rejects_bad_triangles():
    with pytest.raises(MeshError, match="shape"):
        sheet_topology(np.zeros((3, 4), dtype=np.int64))
    with pytest.raises(MeshError, match=r"triangle 1 repeats a vertex \[2, 3, 2\]"):
        sheet_topology(np.array([[0, 1, 2], [2, 3, 2]]))
    with pytest.raises(MeshError, match="triangle 0 has a negative"):
        sheet_topology(np.array([[0, -1, 2]]))
    empty = sheet_topology(np.zeros((0, 3), dtype=np.int64))
    assert empty.edges.shape == (0, 2) and empty.hinges.shape == (0, 4)
