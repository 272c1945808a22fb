"""Import of triangle and tetrahedral meshes from files.

Formats:

- meshio (https://github.com/nschloe/meshio) for Gmsh ``.msh``, VTK ``.vtk``/``.vtu``, ``.obj``,
  ``.stl``, ``.ply``, ``.off``, Medit ``.mesh``;
- Abaqus / CalculiX keyword files (``.inp``, and ``.msh`` files whose first keyword line starts with
  ``*``) by the small reader below, because meshio drops the node labels that the node sets
  (``*NSET``, e.g. CalculiX ``.nam`` files) refer to;
- TetGen ``.node`` / ``.ele`` pairs (https://wias-berlin.de/software/tetgen/fformats.html).

Quadratic tets (``tetra10``/``C3D10``) are by default reduced to their 4 corners; with
``quadratic="split"`` each becomes 8 linear tets on its corner and mid-side nodes
(:func:`sim_core.mesh.tet.split_quadratic_tets`), which keeps the resolution the file was made for.
Quadratic triangles (``triangle6``) are reduced to their corners. Every reader drops unused nodes, compacts indices, orients
tets positively (a file whose tets all have negative volume is flipped as a whole; mixed signs are an
error) and validates the result with :mod:`sim_core.mesh.validate`. A file with tets gives a
:class:`TetMesh` (its triangles, usually boundary patches, are ignored); otherwise its triangles give
a :class:`TriMesh`.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.sheet import TriMesh
from sim_core.mesh.tet import TetMesh, split_quadratic_tets
from sim_core.mesh.validate import tet_signed_volumes, validate_tets, validate_triangles

MESHIO_SUFFIXES = (".msh", ".vtk", ".vtu", ".obj", ".stl", ".ply", ".off", ".mesh")
ABAQUS_SUFFIXES = (".inp", ".msh")
TETGEN_SUFFIXES = (".node", ".ele")

_ABAQUS_TET_PREFIXES = {"C3D4": 4, "C3D10": 10}
_ABAQUS_TRIANGLES = {
    **{t: 3 for t in ("S3", "S3R", "S3RS", "CPS3", "CPE3", "CAX3", "M3D3", "R3D3", "SFM3D3", "STRI3", "DS3")},
    **{t: 6 for t in ("STRI65", "CPS6", "CPE6", "CAX6", "M3D6", "SFM3D6", "DS6", "S6")},
}


class MeshImport(NamedTuple):
    """A mesh read from a file together with the file's node labels.

    Attributes:
        mesh: :class:`TriMesh` or :class:`TetMesh` (positions in m after ``scale``).
        node_ids: shape ``(n,)`` int64: label in the file of each vertex of ``mesh`` (Abaqus and
            TetGen node numbers; the 0-based point index for meshio formats).
    """

    mesh: TriMesh | TetMesh
    node_ids: np.ndarray


class _RawMesh(NamedTuple):
    labels: np.ndarray  # (N,) int64 node labels
    points: np.ndarray  # (N, 3)
    tets: np.ndarray  # (k, 4) labels of corner nodes
    tets10: np.ndarray  # (m, 10) labels of the nodes of quadratic tets (not in ``tets``)
    triangles: np.ndarray  # (t, 3) labels of corner nodes
    cell_types: tuple[str, ...]  # every element type seen, for messages


def _abaqus_options(line: str) -> tuple[str, dict[str, str]]:
    """``*ELEMENT, TYPE=C3D10, ELSET=Eall`` -> (``"ELEMENT"``, ``{"TYPE": "C3D10", ...}``)."""
    parts = [p.strip() for p in line[1:].split(",")]
    options: dict[str, str] = {}
    for p in parts[1:]:
        if p:
            key, _, value = p.partition("=")
            options[key.strip().upper()] = value.strip()
    return parts[0].upper(), options


def _int_tokens(line: str) -> list[int]:
    return [int(t) for t in line.split(",") if t.strip()]


def _parse_abaqus(path: Path) -> tuple[_RawMesh, dict[str, np.ndarray]]:
    """Nodes, tet/triangle elements and node sets (labels) of an Abaqus/CalculiX keyword file.

    Supports ``*NODE`` (with optional ``NSET=``), ``*ELEMENT, TYPE=`` (continuation lines allowed)
    and ``*NSET, NSET=`` (with optional ``GENERATE``); other keywords are skipped.
    """
    labels: list[int] = []
    points: list[list[float]] = []
    elements: dict[str, list[list[int]]] = {}
    node_sets: dict[str, list[int]] = {}
    block: str | None = None
    etype = ""
    nodes_per_element = 0
    set_name = ""
    generate = False
    pending: list[int] = []
    with open(path, encoding="utf-8", errors="replace") as stream:
        for line_number, raw in enumerate(stream, start=1):
            line = raw.strip()
            if not line or line.startswith("**"):
                continue
            if line.startswith("*"):
                keyword, options = _abaqus_options(line)
                block, pending, set_name = None, [], ""
                if keyword == "NODE":
                    block, set_name = "node", options.get("NSET", "")
                elif keyword == "ELEMENT":
                    etype = options.get("TYPE", "").upper()
                    elements.setdefault(etype, [])
                    block = "element"
                    nodes_per_element = next(
                        (n for p, n in _ABAQUS_TET_PREFIXES.items() if etype.startswith(p)),
                        _ABAQUS_TRIANGLES.get(etype, 0),
                    )
                elif keyword == "NSET" and "NSET" in options:
                    block, set_name, generate = "nset", options["NSET"], "GENERATE" in options
                if set_name:
                    node_sets.setdefault(set_name, [])
                continue
            try:
                if block == "node":
                    tokens = [t for t in line.split(",") if t.strip()]
                    labels.append(int(tokens[0]))
                    coords = [float(t) for t in tokens[1:4]]
                    points.append(coords + [0.0] * (3 - len(coords)))
                    if set_name:
                        node_sets[set_name].append(labels[-1])
                elif block == "element" and nodes_per_element:
                    pending += _int_tokens(line)
                    if len(pending) >= nodes_per_element + 1:
                        elements[etype].append(pending[1 : nodes_per_element + 1])
                        pending = []
                elif block == "nset":
                    values = _int_tokens(line)
                    if generate:
                        first, last, step = (values + [1])[:3]
                        values = list(range(first, last + 1, step))
                    node_sets[set_name] += values
            except (ValueError, IndexError) as err:
                raise MeshError(f"{path}:{line_number}: cannot parse {block} line {line!r}") from err
    tets = [np.asarray(v, dtype=np.int64)[:, :4] for t, v in elements.items() if v and t.startswith("C3D4")]
    tets10 = [np.asarray(v, dtype=np.int64)[:, :10] for t, v in elements.items() if v and t.startswith("C3D10")]
    tris = [np.asarray(v, dtype=np.int64)[:, :3] for t, v in elements.items() if v and t in _ABAQUS_TRIANGLES]
    raw_mesh = _RawMesh(
        np.asarray(labels, dtype=np.int64),
        np.asarray(points, dtype=float).reshape(-1, 3),
        np.concatenate(tets) if tets else np.zeros((0, 4), dtype=np.int64),
        np.concatenate(tets10) if tets10 else np.zeros((0, 10), dtype=np.int64),
        np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64),
        tuple(elements),
    )
    return raw_mesh, {k: np.asarray(v, dtype=np.int64) for k, v in node_sets.items()}


def _tetgen_rows(path: Path) -> list[list[str]]:
    """Non-empty rows of a TetGen file, ``#`` comments removed."""
    if not path.is_file():
        raise ConfigError(f"TetGen file {path} does not exist (a .node file needs its .ele file and vice versa)")
    rows = []
    with open(path, encoding="utf-8", errors="replace") as stream:
        for raw in stream:
            tokens = raw.split("#", 1)[0].split()
            if tokens:
                rows.append(tokens)
    return rows


def _parse_tetgen(path: Path) -> _RawMesh:
    """A TetGen ``.node`` + ``.ele`` pair (either file may be given)."""
    node_path, ele_path = path.with_suffix(".node"), path.with_suffix(".ele")
    node_rows, ele_rows = _tetgen_rows(node_path), _tetgen_rows(ele_path)
    try:
        point_count, dim = int(node_rows[0][0]), int(node_rows[0][1])
        if dim != 3:
            raise MeshError(f"{node_path}: dimension must be 3, got {dim}")
        nodes = np.array([[float(t) for t in r[: 1 + dim]] for r in node_rows[1 : 1 + point_count]])
        tet_count, corners = int(ele_rows[0][0]), int(ele_rows[0][1])
        if corners not in (4, 10):
            raise MeshError(f"{ele_path}: nodes per tetrahedron must be 4 or 10, got {corners}")
        tets = np.array([[int(t) for t in r[1:5]] for r in ele_rows[1 : 1 + tet_count]], dtype=np.int64)
    except (ValueError, IndexError) as err:
        raise MeshError(f"cannot parse TetGen files {node_path} / {ele_path}: {err}") from err
    if nodes.shape[0] != point_count or tets.shape[0] != tet_count:
        raise MeshError(
            f"TetGen files {node_path} / {ele_path} are truncated: header promises {point_count} nodes and "
            f"{tet_count} tets, found {nodes.shape[0]} and {tets.shape[0]}"
        )
    no_triangles = np.zeros((0, 3), dtype=np.int64)
    return _RawMesh(nodes[:, 0].astype(np.int64), nodes[:, 1:4], tets.reshape(-1, 4), np.zeros((0, 10), dtype=np.int64), no_triangles, ("tetra",))


def _parse_meshio(path: Path) -> _RawMesh:
    """Any meshio-readable file; point labels are the 0-based point indices."""
    import meshio  # optional dependency: meshio, for mesh files only

    try:
        data = meshio.read(path)
    except (Exception, SystemExit) as err:  # meshio raises ReadError, ValueError, ...; sys.exit on some formats
        raise MeshError(f"cannot read mesh file {path} with meshio: {err}") from err
    tets, tets10, tris = [], [], []
    for block in data.cells:
        if block.type == "tetra":
            tets.append(np.asarray(block.data, dtype=np.int64)[:, :4])
        elif block.type == "tetra10":
            tets10.append(np.asarray(block.data, dtype=np.int64)[:, :10])
        elif block.type in ("triangle", "triangle6"):
            tris.append(np.asarray(block.data, dtype=np.int64)[:, :3])
    points = np.asarray(data.points, dtype=float)
    if points.ndim == 2 and points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(points.shape[0])])
    return _RawMesh(
        np.arange(points.shape[0], dtype=np.int64),
        points,
        np.concatenate(tets) if tets else np.zeros((0, 4), dtype=np.int64),
        np.concatenate(tets10) if tets10 else np.zeros((0, 10), dtype=np.int64),
        np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64),
        tuple(block.type for block in data.cells),
    )


def _is_abaqus(path: Path) -> bool:
    """``.inp``, or a ``.msh`` whose first non-comment line is an Abaqus keyword (CalculiX export)."""
    if path.suffix.lower() == ".inp":
        return True
    with open(path, encoding="utf-8", errors="replace") as stream:
        for raw in stream:
            line = raw.strip()
            if line and not line.startswith("**"):
                return line.startswith("*")
    return False


def _labels_to_indices(labels: np.ndarray, query: np.ndarray, what: str) -> np.ndarray:
    """Positions of ``query`` labels in ``labels``; MeshError naming the element for unknown labels."""
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    pos = np.clip(np.searchsorted(sorted_labels, query), 0, max(len(labels) - 1, 0))
    found = (sorted_labels[pos] == query) if len(labels) else np.zeros(query.shape, bool)
    if not np.all(found):
        e = int(np.flatnonzero(~np.all(found.reshape(query.shape[0], -1), axis=1))[0])
        raise MeshError(f"{what} {e} refers to an undefined node: {query[e].tolist()}")
    return order[pos]


def _build(raw: _RawMesh, path: Path, scale: float, quadratic: str = "corners") -> MeshImport:
    """Compacted, oriented, validated mesh from parsed file contents (quadratic tets per ``quadratic``)."""
    if np.unique(raw.labels).size != raw.labels.size:
        raise MeshError(f"{path}: node labels are not unique")
    use_tets = raw.tets.shape[0] + raw.tets10.shape[0] > 0
    if not use_tets:
        cells = raw.triangles
    elif quadratic == "split" and raw.tets10.shape[0]:
        tet10 = _labels_to_indices(raw.labels, raw.tets10, f"{path}: tet")
        split = split_quadratic_tets(raw.points, tet10)
        cells = np.concatenate([raw.tets, raw.labels[split]])
    else:
        cells = np.concatenate([raw.tets, raw.tets10[:, :4]])
    if cells.shape[0] == 0:
        found = list(raw.cell_types) or "none"
        raise MeshError(f"{path} has no triangles or tetrahedra (element types found: {found})")
    kind = "tet" if use_tets else "triangle"
    index = _labels_to_indices(raw.labels, cells, f"{path}: {kind}")
    used, compact = np.unique(index, return_inverse=True)
    cells = compact.reshape(cells.shape).astype(np.int64)
    x = raw.points[used] * scale
    node_ids = raw.labels[used]
    where = str(path)
    if not use_tets:
        return MeshImport(TriMesh(x, validate_triangles(x, cells, where)), node_ids)
    volume = tet_signed_volumes(x, cells)
    negative = volume < 0
    if np.all(negative):
        cells = cells[:, [0, 2, 1, 3]]
    elif np.any(negative):
        minority = negative if negative.sum() <= (~negative).sum() else ~negative
        e = int(np.flatnonzero(minority)[0])
        raise MeshError(
            f"{where}: tets are not consistently oriented: tet {e} {cells[e].tolist()} has signed volume "
            f"{volume[e]:.3e} m^3 against the sign of {int(max(negative.sum(), (~negative).sum()))} others "
            f"(inverted element?)"
        )
    return MeshImport(TetMesh(x, validate_tets(x, cells, where)), node_ids)


def read_mesh(path: str | Path, scale: float = 1.0, quadratic: str = "corners") -> MeshImport:
    """Read a triangle or tetrahedral mesh and the file's node labels.

    Args:
        path: mesh file (see module docstring for formats; for TetGen pass the ``.node`` or the
            ``.ele`` file of the pair).
        scale: factor applied to the coordinates (e.g. ``1e-3`` for a file in mm), > 0.
        quadratic: ``"corners"`` (keep the 4 corners of a 10-node tet) or ``"split"`` (8 linear
            tets on all 10 nodes).

    Returns:
        :class:`MeshImport` ``(mesh, node_ids)``.

    Raises:
        ConfigError: missing file, unsupported suffix, bad ``scale`` or ``quadratic``.
        MeshError: unreadable file, no triangles/tets, undefined node, inconsistent orientation,
            degenerate element, non-finite coordinate (messages name the file and element).
    """
    path = Path(path)
    if not (np.isfinite(scale) and scale > 0):
        raise ConfigError(f"mesh scale must be finite and > 0, got {scale!r} (for {path})")
    if quadratic not in ("corners", "split"):
        raise ConfigError(f"mesh {path}: quadratic must be 'corners' or 'split', got {quadratic!r}")
    suffix = path.suffix.lower()
    if suffix in TETGEN_SUFFIXES:
        return _build(_parse_tetgen(path), path, float(scale), quadratic)
    if not path.is_file():
        raise ConfigError(f"mesh file {path} does not exist")
    if suffix not in MESHIO_SUFFIXES + ABAQUS_SUFFIXES:
        raise ConfigError(
            f"mesh file {path}: unsupported suffix {suffix!r}; use one of "
            f"{sorted(set(MESHIO_SUFFIXES + ABAQUS_SUFFIXES + TETGEN_SUFFIXES))}"
        )
    raw = _parse_abaqus(path)[0] if _is_abaqus(path) else _parse_meshio(path)
    return _build(raw, path, float(scale), quadratic)


def load_mesh(path: str | Path, scale: float = 1.0) -> TriMesh | TetMesh:
    """Read a mesh file into a :class:`TriMesh` or :class:`TetMesh` (see :func:`read_mesh`)."""
    return read_mesh(path, scale).mesh


def load_node_sets(path: str | Path, node_ids: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Node sets (``*NSET``, and ``*NODE, NSET=``) of an Abaqus/CalculiX keyword file (e.g. ``.nam``).

    Args:
        path: the keyword file.
        node_ids: optional ``MeshImport.node_ids`` of a mesh read with :func:`read_mesh`. When given,
            labels are converted to vertex indices of that mesh and labels it does not contain
            (e.g. mid-side nodes of quadratic elements) are dropped.

    Returns:
        ``{set name: sorted unique int64 array}`` of node labels, or of vertex indices with ``node_ids``.

    Raises:
        ConfigError: missing file.
        MeshError: unparsable line or no node set in the file.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"node-set file {path} does not exist")
    sets = _parse_abaqus(path)[1]
    if not sets:
        raise MeshError(f"{path} defines no node set (*NSET)")
    out: dict[str, np.ndarray] = {}
    for name, labels in sets.items():
        labels = np.unique(labels)
        if node_ids is not None:
            ids = np.asarray(node_ids, dtype=np.int64)
            order = np.argsort(ids)
            pos = np.clip(np.searchsorted(ids[order], labels), 0, max(ids.size - 1, 0))
            keep = ids[order][pos] == labels if ids.size else np.zeros(labels.shape, bool)
            labels = np.sort(order[pos[keep]]).astype(np.int64)
        out[name] = labels
    return out
