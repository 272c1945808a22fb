"""Mesh validation: every error names the offending vertex/element and the mesh."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import MeshError
from sim_core.mesh.validate import validate_tets, validate_triangles, validate_vertices

X_TET = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])


def test_vertices_nan_and_inf_name_vertex() -> None:
    x = X_TET.copy()
    x[3, 1] = np.nan
    with pytest.raises(MeshError, match=r"gel\.msh: vertex 3 has a non-finite"):
        validate_vertices(x, "gel.msh")
    x[3, 1] = 0.0
    x[4, 2] = np.inf
    with pytest.raises(MeshError, match="vertex 4"):
        validate_vertices(x, "gel.msh")
    with pytest.raises(MeshError, match=r"shape \(n, 3\)"):
        validate_vertices(np.zeros((4, 2)), "gel.msh")
    assert validate_vertices(X_TET.tolist(), "ok").dtype == np.float64


def test_triangles_errors_name_triangle() -> None:
    good = np.array([[0, 1, 2], [0, 1, 3]])
    assert validate_triangles(X_TET, good, "sheet").dtype == np.int64
    with pytest.raises(MeshError, match=r"sheet: triangle 1 has vertex index out of range \[0, 5\)"):
        validate_triangles(X_TET, np.array([[0, 1, 2], [0, 1, 7]]), "sheet")
    with pytest.raises(MeshError, match="triangle 1 .*out of range"):
        validate_triangles(X_TET, np.array([[0, 1, 2], [-1, 1, 2]]), "sheet")
    with pytest.raises(MeshError, match="triangle 0 repeats a vertex"):
        validate_triangles(X_TET, np.array([[0, 2, 2]]), "sheet")
    x = X_TET.copy()
    x[4] = [2.0, 0.0, 0.0]  # collinear with 0 and 1
    with pytest.raises(MeshError, match=r"triangle 1 \[0, 1, 4\] is degenerate \(area 0"):
        validate_triangles(x, np.array([[0, 1, 2], [0, 1, 4]]), "sheet")
    x[4] = [2.0, 1e-9, 0.0]  # near-zero area relative to its size
    with pytest.raises(MeshError, match="triangle 1 .*degenerate"):
        validate_triangles(x, np.array([[0, 1, 2], [0, 1, 4]]), "sheet")
    with pytest.raises(MeshError, match="triangle 0 .*degenerate"):
        validate_triangles(X_TET, good, "sheet", min_area=0.6)
    with pytest.raises(MeshError, match=r"shape \(k, 3\)"):
        validate_triangles(X_TET, np.array([0, 1, 2]), "sheet")


def test_tets_inverted_and_degenerate_name_tet_and_volume() -> None:
    assert validate_tets(X_TET, np.array([[0, 1, 2, 3], [1, 2, 3, 4]]), "box").shape == (2, 4)
    with pytest.raises(MeshError, match=r"box: tet 1 \[1, 3, 2, 4\] is inverted \(signed volume -3\.333e-01 m\^3"):
        validate_tets(X_TET, np.array([[0, 1, 2, 3], [1, 3, 2, 4]]), "box")
    x = X_TET.copy()
    x[3] = [0.3, 0.3, 0.0]  # coplanar with 0, 1, 2
    with pytest.raises(MeshError, match=r"tet 0 .*degenerate \(signed volume 0"):
        validate_tets(x, np.array([[0, 1, 2, 3]]), "box")
    with pytest.raises(MeshError, match="tet 0 repeats a vertex"):
        validate_tets(X_TET, np.array([[0, 1, 1, 3]]), "box")
    with pytest.raises(MeshError, match="tet 0 has vertex index out of range"):
        validate_tets(X_TET, np.array([[0, 1, 2, 5]]), "box")
    with pytest.raises(MeshError, match="integers"):
        validate_tets(X_TET, np.array([[0, 1, 2, 3.5]]), "box")
    x = X_TET.copy()
    x[0, 0] = np.nan
    with pytest.raises(MeshError, match="vertex 0"):
        validate_tets(x, np.array([[0, 1, 2, 3]]), "box")
