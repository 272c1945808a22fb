"""Mesh import: meshio formats, Abaqus/CalculiX keyword files with node sets, TetGen pairs."""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np
import pytest

from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.io import load_mesh, load_node_sets, read_mesh
from sim_core.mesh.sheet import TriMesh
from sim_core.mesh.tet import TetMesh, split_quadratic_tets, tet_box, tet_boundary_triangles, tet_rest_volume
from sim_core.mesh.validate import tet_signed_volumes

FEATS_DIR = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "real" / "feats" / "calculix_templates"


@pytest.fixture()
def box() -> TetMesh:
    return tet_box((0.02, 0.01, 0.01), (3, 2, 2), (0.0, 0.0, 0.0))


@pytest.mark.parametrize("suffix,fmt", [(".vtu", None), (".vtk", None), (".msh", "gmsh22")])
def test_meshio_round_trip_drops_unused_nodes(tmp_path: Path, box: TetMesh, suffix: str, fmt) -> None:
    # an unused node first shifts every index by one; the reader must drop it and compact
    points = np.vstack([[9.0, 9.0, 9.0], box.x * 1e3])
    path = tmp_path / f"box{suffix}"
    meshio.write(path, meshio.Mesh(points, [("tetra", box.tets + 1)]), file_format=fmt)
    mesh = load_mesh(path, scale=1e-3)
    assert isinstance(mesh, TetMesh)
    assert np.allclose(mesh.x, box.x, atol=1e-12)
    assert np.array_equal(mesh.tets, box.tets)


def test_quadratic_tets_reduced_to_corners_and_orientation_fixed(tmp_path: Path, box: TetMesh) -> None:
    edges = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]  # tetra10 mid-side order
    mids = np.stack([(box.x[box.tets[:, a]] + box.x[box.tets[:, b]]) / 2 for a, b in edges], axis=1)
    n, k = box.x.shape[0], box.tets.shape[0]
    points = np.vstack([box.x, mids.reshape(-1, 3)])
    flipped = box.tets[:, [1, 0, 2, 3]]  # every tet negative: a file using the opposite convention
    tet10 = np.hstack([flipped, n + np.arange(6 * k).reshape(k, 6)])
    path = tmp_path / "quadratic.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra10", tet10)]))
    result = read_mesh(path)
    assert result.mesh.x.shape == box.x.shape  # mid-side nodes dropped
    assert np.array_equal(result.node_ids, np.arange(n))
    assert np.all(tet_rest_volume(result.mesh.tets, result.mesh.x) > 0)
    assert tet_rest_volume(result.mesh.tets, result.mesh.x).sum() == pytest.approx(2e-6)


def test_mixed_orientation_is_reported(tmp_path: Path, box: TetMesh) -> None:
    tets = box.tets.copy()
    tets[2] = tets[2][[1, 0, 2, 3]]
    path = tmp_path / "mixed.vtu"
    meshio.write(path, meshio.Mesh(box.x, [("tetra", tets)]))
    with pytest.raises(MeshError, match=r"mixed\.vtu: tets are not consistently oriented: tet 2 "):
        load_mesh(path)


@pytest.mark.parametrize("suffix", [".obj", ".stl"])
def test_surface_files_give_trimesh(tmp_path: Path, box: TetMesh, suffix: str) -> None:
    tri = tet_boundary_triangles(box.tets)
    path = tmp_path / f"surface{suffix}"
    options = {"binary": True} if suffix == ".stl" else {}
    meshio.write(path, meshio.Mesh(box.x, [("triangle", tri)]), **options)
    mesh = load_mesh(path)
    assert isinstance(mesh, TriMesh)
    assert mesh.triangles.shape == tri.shape
    a, b, c = (mesh.x[mesh.triangles[:, i]] for i in range(3))
    # orientation kept: divergence-theorem volume of the closed surface = box volume
    assert np.sum((a + b + c) / 3 * np.cross(b - a, c - a)) / 6 == pytest.approx(2e-6, rel=1e-6)


ABAQUS_INP = """** two C3D10 tets sharing face (1, 2, 3), in mm
*HEADING
test
*NODE, NSET=Nall
1, 0.0, 0.0, 0.0
2, 10.0, 0.0, 0.0
3, 0.0, 10.0, 0.0
4, 0.0, 0.0, 10.0
5, 0.0, 0.0, -10.0
11, 5.0, 0.0, 0.0
12, 5.0, 5.0, 0.0
13, 0.0, 5.0, 0.0
14, 0.0, 0.0, 5.0
15, 5.0, 0.0, 5.0
16, 0.0, 5.0, 5.0
17, 0.0, 0.0, -5.0
18, 5.0, 0.0, -5.0
19, 0.0, 5.0, -5.0
*ELEMENT, TYPE=C3D10, ELSET=Eall
1, 1, 2, 3, 4, 11, 12, 13, 14, 15,
16
2, 1, 3, 2, 5, 13, 12, 11, 17, 19, 18
*NSET, NSET=Ntop
4, 14, 15
*NSET, NSET=Nrange, GENERATE
1, 5, 2
*ELSET, ELSET=Eone
1
"""


def test_abaqus_quadratic_tets_and_node_sets(tmp_path: Path) -> None:
    path = tmp_path / "two.inp"
    path.write_text(ABAQUS_INP)
    result = read_mesh(path, scale=1e-3)
    mesh = result.mesh
    assert isinstance(mesh, TetMesh)
    assert np.array_equal(result.node_ids, [1, 2, 3, 4, 5])
    assert np.array_equal(mesh.tets, [[0, 1, 2, 3], [0, 2, 1, 4]])
    assert np.allclose(tet_rest_volume(mesh.tets, mesh.x), (0.01**3) / 6)
    labels = load_node_sets(path)
    assert set(labels) == {"Nall", "Ntop", "Nrange"}
    assert np.array_equal(labels["Nrange"], [1, 3, 5])
    vertices = load_node_sets(path, result.node_ids)
    assert np.array_equal(vertices["Ntop"], [3])  # mid-side labels 14, 15 are not mesh vertices
    assert np.array_equal(vertices["Nrange"], [0, 2, 4])
    # the same file with the .msh suffix used by CalculiX is recognised as Abaqus, not Gmsh
    msh = tmp_path / "two.msh"
    msh.write_text(ABAQUS_INP)
    assert np.array_equal(load_mesh(msh).tets, mesh.tets)


def test_abaqus_errors_name_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.inp"
    path.write_text(ABAQUS_INP.replace("5, 0.0, 0.0, -10.0", "5, 0.0, zero, -10.0"))
    with pytest.raises(MeshError, match=r"bad\.inp:9: cannot parse node line"):
        load_mesh(path)
    path.write_text(ABAQUS_INP.replace("2, 1, 3, 2, 5,", "2, 1, 3, 2, 6,"))
    with pytest.raises(MeshError, match=r"bad\.inp: tet 1 refers to an undefined node"):
        load_mesh(path)
    path.write_text("*NODE\n1, 0, 0, 0\n2, 1, 0, 0\n*ELEMENT, TYPE=B31\n1, 1, 2\n")
    with pytest.raises(MeshError, match=r"bad\.inp has no triangles or tetrahedra .*B31"):
        load_mesh(path)
    with pytest.raises(MeshError, match=r"bad\.inp defines no node set"):
        load_node_sets(path)


TETGEN_NODE = """# cube corner + apexes; 1-based labels, one attribute, boundary markers
5 3 1 1
1  0.0 0.0 0.0  7.0  1
2  1.0 0.0 0.0  7.0  1
3  0.0 1.0 0.0  7.0  1
4  0.0 0.0 1.0  7.0  1
5  0.0 0.0 -1.0 7.0  1
"""
TETGEN_ELE = """2 4 1
# tet  n1 n2 n3 n4  region
1  1 2 3 4  1
2  1 3 2 5  2
"""


def test_tetgen_pair_read_from_either_file(tmp_path: Path) -> None:
    (tmp_path / "cube.1.node").write_text(TETGEN_NODE)
    (tmp_path / "cube.1.ele").write_text(TETGEN_ELE)
    for name in ("cube.1.node", "cube.1.ele"):
        result = read_mesh(tmp_path / name)
        assert np.array_equal(result.node_ids, [1, 2, 3, 4, 5])
        assert np.array_equal(result.mesh.tets, [[0, 1, 2, 3], [0, 2, 1, 4]])
        assert np.allclose(result.mesh.x[4], [0.0, 0.0, -1.0])
    (tmp_path / "cube.1.ele").unlink()
    with pytest.raises(ConfigError, match=r"cube\.1\.ele does not exist"):
        load_mesh(tmp_path / "cube.1.node")
    (tmp_path / "cube.1.ele").write_text("3 4 0\n1 1 2 3 4\n")
    with pytest.raises(MeshError, match="truncated"):
        load_mesh(tmp_path / "cube.1.node")


def test_missing_unsupported_and_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nothere\.vtu does not exist"):
        load_mesh(tmp_path / "nothere.vtu")
    (tmp_path / "a.xyz").write_text("1 2 3\n")
    with pytest.raises(ConfigError, match=r"a\.xyz: unsupported suffix"):
        load_mesh(tmp_path / "a.xyz")
    (tmp_path / "junk.vtu").write_text("this is not a VTU file")
    with pytest.raises(MeshError, match=r"cannot read mesh file .*junk\.vtu"):
        load_mesh(tmp_path / "junk.vtu")
    (tmp_path / "ok.vtu").write_text("")
    with pytest.raises(ConfigError, match="scale"):
        load_mesh(tmp_path / "ok.vtu", scale=0.0)
    with pytest.raises(ConfigError, match=r"sets\.nam does not exist"):
        load_node_sets(tmp_path / "sets.nam")


def test_nan_coordinate_in_file_names_vertex(tmp_path: Path, box: TetMesh) -> None:
    x = box.x.copy()
    x[4, 0] = np.nan
    path = tmp_path / "nan.vtu"
    meshio.write(path, meshio.Mesh(x, [("tetra", box.tets)]))
    with pytest.raises(MeshError, match=r"nan\.vtu: vertex 4 has a non-finite"):
        load_mesh(path)


@pytest.mark.skipif(not (FEATS_DIR / "all.msh").is_file(), reason=f"FEATS CalculiX templates not found at {FEATS_DIR}")
def test_feats_calculix_gel_and_indenter() -> None:
    """The real FEATS mesh (mm, C3D10) splits into the gel and indenter bodies via its .nam sets."""
    result = read_mesh(FEATS_DIR / "all.msh", scale=1e-3)
    mesh = result.mesh
    # independent oracle: meshio's Abaqus reader (node labels there are file positions)
    reference = meshio.read(FEATS_DIR / "all.msh", file_format="abaqus")
    corners = reference.cells_dict["tetra10"][:, :4]
    assert mesh.tets.shape == corners.shape
    assert mesh.x.shape[0] == np.unique(corners).size
    assert np.allclose(mesh.x[mesh.tets], 1e-3 * reference.points[corners])
    volume = tet_rest_volume(mesh.tets, mesh.x)  # raises on any inverted tet
    gel = load_node_sets(FEATS_DIR / "gelsight_miniVolume.nam", result.node_ids)["Ngelsight_miniVolume"]
    indenter = load_node_sets(FEATS_DIR / "indenterVolume.nam", result.node_ids)["NindenterVolume"]
    assert np.intersect1d(gel, indenter).size == 0
    assert gel.size + indenter.size == mesh.x.shape[0]
    in_gel = np.isin(mesh.tets, gel)
    assert np.all(in_gel.all(axis=1) | ~in_gel.any(axis=1))  # every tet belongs to one body
    gel_lo, gel_hi = mesh.x[gel].min(axis=0), mesh.x[gel].max(axis=0)
    ind_lo, ind_hi = mesh.x[indenter].min(axis=0), mesh.x[indenter].max(axis=0)
    print(
        f"\nFEATS all.msh: {mesh.x.shape[0]} corner nodes, {mesh.tets.shape[0]} tets, volume "
        f"{volume.sum() * 1e9:.1f} mm^3; gel {gel.size} nodes bbox {gel_lo} .. {gel_hi} m; "
        f"indenter {indenter.size} nodes bbox {ind_lo} .. {ind_hi} m"
    )
    assert gel_hi[2] <= ind_lo[2]  # the indenter sits above the gel surface
    fixed = load_node_sets(FEATS_DIR / "gelsight_miniFixed.nam", result.node_ids)["Ngelsight_miniFixed"]
    assert np.all(np.isin(fixed, gel)) and np.allclose(mesh.x[fixed, 2], gel_lo[2])


def test_split_quadratic_tets_tiles_each_parent_with_eight_positive_children() -> None:
    rng = np.random.default_rng(3)
    edges = [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]
    for _ in range(10):
        c = rng.normal(size=(4, 3))
        x = np.vstack([c] + [(c[a] + c[b]) / 2 for a, b in edges])
        parent = np.arange(10)[None]
        children = split_quadratic_tets(x, parent)
        v = tet_signed_volumes(x, children)
        V = tet_signed_volumes(x, parent[:, :4])[0]
        assert children.shape == (8, 4)
        assert np.all(np.sign(v) == np.sign(V))  # orientation of the parent kept
        assert v.sum() == pytest.approx(V, rel=1e-12)  # the children tile the parent
        assert np.allclose(v, V / 8, rtol=1e-9)  # red refinement: eight children of equal volume
        assert np.array_equal(np.unique(children), np.arange(10))
    with pytest.raises(MeshError, match=r"shape \(k, 10\)"):
        split_quadratic_tets(x, np.zeros((1, 4), dtype=int))


def test_abaqus_quadratic_tets_split_into_linear_ones_keep_volume_and_node_sets(tmp_path: Path) -> None:
    path = tmp_path / "two.inp"
    path.write_text(ABAQUS_INP)
    corners = read_mesh(path, scale=1e-3)
    split = read_mesh(path, scale=1e-3, quadratic="split")
    assert split.mesh.tets.shape == (16, 4)
    assert split.node_ids.size > corners.node_ids.size  # mid-side nodes are vertices now
    assert tet_rest_volume(split.mesh.tets, split.mesh.x).sum() == pytest.approx(
        tet_rest_volume(corners.mesh.tets, corners.mesh.x).sum(), rel=1e-12)
    assert load_node_sets(path, split.node_ids)["Ntop"].size == 3  # node 4 and mid-sides 14, 15
    with pytest.raises(ConfigError, match="quadratic must be"):
        read_mesh(path, quadratic="drop")
