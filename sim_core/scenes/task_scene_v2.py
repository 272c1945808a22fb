"""Version-2 elements of ``kind: task`` scenes (documented in ``docs/scene_schema.md``).

* ``effectors.NAME.shape: gripper``: two fingers (each a ``dome`` or a ``pad``, rigid or tactile) on
  one effector, facing each other along ``axis`` (effector frame) at ``opening`` apart (m, between
  the finger frames' origins); the opening follows ``Control.gripper_target`` (``gripper_cmd``):
  finger ``s = +1/-1`` moves by ``s (opening - opening_0) / 2`` along the axis
  (:func:`sim_core.effector.driven_positions`). Both fingers form one solid body named by the effector.
* ``effectors.NAME.rigid: true`` (any shape): every vertex of the solid follows the effector (a rigid
  tool); false (default): only the mount (a tactile gel).
* ``blocks``: boxes that are ``free`` (an elastic box, stiff by default: ThinShellLab's
  ``Elastic`` with E = 5e5 Pa, nu = 0, standing in for a rigid body; mass from ``mass`` or
  ``density``) or ``kinematic`` (held in place: every vertex fixed).
* ``boxes.NAME.arch_height``: the box's vertices raised by ``h sin(pi (x - x0) / Lx)`` (ThinShellLab's
  ``init_arch``).
* ``sheets.NAME.pinned``: vertex sets held fixed (``{edge: x0|x1|y0|y1}``, ``{vertices: [...]}`` or
  ``{region: {min: [...], max: [...]}}``), in addition to ``clamped_edge``.
* ``sheets.NAME.creases``: rest angles set on grid lines (``{column: ix | row: iy, rest_angle: rad}``).
* ``gravity_scale`` (sheets, blocks, meshes, effectors): the fraction of the scene's gravity acting on
  the body (``Model.vertex_gravity_scale``; ThinShellLab's Lifting: 0 on the sheet, 1 on the block).
* ``meshes``: objects read from mesh files (``.obj``, ``.stl``, ``.msh`` ... through
  :mod:`sim_core.mesh.io`): ``kind: sheet`` (triangles), ``solid`` (tets) or ``frozen`` (tets, fixed);
  a degenerate mesh raises an error naming the file and the element.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sim_core.builder import ModelBuilder
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.sheet import TriMesh
from sim_core.mesh.tet import TetMesh, tet_box
from sim_core.transforms import quat_from_rotvec, quat_to_matrix

STIFF_BLOCK_YOUNGS_MODULUS = 5.0e5
"""Pa: ThinShellLab's ``Elastic`` default (``code/engine/model_elastic_offset.py``), used for free blocks."""
STIFF_BLOCK_POISSON_RATIO = 0.0

BLOCK_KEYS = {"size": True, "resolution": True, "origin": True, "mode": True, "mass": False, "density": False,
              "youngs_modulus": False, "poisson_ratio": False, "gravity_scale": False}
MESH_KEYS = {"file": True, "kind": True, "scale": False, "translation": False, "material": False, "pinned": False,
             "gravity_scale": False}
GRIPPER_KEYS = {"finger": True, "opening": True, "axis": True}
FINGER_KEYS = {"shape": True, "outer_radius": False, "inner_radius": False, "mesh": False, "size": False,
               "resolution": False, "rigid": False}
SHEET_MESH_MATERIAL = {"youngs_modulus": True, "poisson_ratio": True, "thickness": True, "density": True,
                       "bending_stiffness": True, "yield_angle": False}


def rotation_z_to(u: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[x y z w]`` of the smallest rotation taking +z to the unit vector ``u``."""
    u = np.asarray(u, dtype=float) / np.linalg.norm(u)
    c = float(np.clip(u[2], -1.0, 1.0))
    if c < -1.0 + 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    axis = np.cross([0.0, 0.0, 1.0], u)
    n = float(np.linalg.norm(axis))
    if n < 1e-15:
        return np.array([0.0, 0.0, 0.0, 1.0])
    return quat_from_rotvec(axis / n * math.acos(c))


def gripper_solid(spec: dict, where: str, finger_solid: Callable[[dict, str], tuple[TetMesh, np.ndarray]],
                  check: Callable) -> tuple[TetMesh, np.ndarray, np.ndarray, np.ndarray, float, bool]:
    """The two fingers of a gripper effector in its frame.

    Args:
        spec: the effector's mapping (``finger``, ``opening``, ``axis``).
        where: dotted key for errors.
        finger_solid: builds one finger's local mesh and mount from a ``dome``/``pad`` mapping
            (pointing +z, mount first).
        check: ``(value, where, keys)`` key validator of the task scene.

    Returns:
        ``(mesh, driven, finger_sign, axis, opening, rigid)``: both fingers' tet mesh in the effector
        frame, driven local vertex indices ``(k,)``, their finger signs ``(k,)``, the unit opening axis
        ``(3,)``, the initial opening in m and whether the fingers are rigid.

    Raises:
        ConfigError: bad keys or values.
    """
    finger = check(spec["finger"], f"{where}.finger", FINGER_KEYS)
    if finger["shape"] not in ("dome", "pad"):
        raise ConfigError(f"task scene: {where}.finger.shape must be dome|pad, got {finger['shape']!r}")
    rigid = bool(finger.get("rigid", False))
    local, mount = finger_solid({k: v for k, v in finger.items() if k != "rigid"}, f"{where}.finger")
    axis = np.asarray(spec["axis"], dtype=float)
    if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
        raise ConfigError(f"task scene: {where}.axis must be a non-zero 3-vector, got {spec['axis']!r}")
    axis = axis / np.linalg.norm(axis)
    opening = float(spec["opening"])
    if not (math.isfinite(opening) and opening > 0):
        raise ConfigError(f"task scene: {where}.opening must be > 0 (m), got {spec['opening']!r}")
    xs, tets, driven, signs = [], [], [], []
    offset = 0
    for sign in (1.0, -1.0):
        R = quat_to_matrix(rotation_z_to(-sign * axis))  # each finger faces the other
        xs.append(local.x @ R.T + sign * 0.5 * opening * axis)
        tets.append(local.tets + offset)
        ids = np.arange(local.x.shape[0]) if rigid else np.asarray(mount)
        driven.append(ids + offset)
        signs.append(np.full(ids.shape[0], sign))
        offset += local.x.shape[0]
    return (TetMesh(np.concatenate(xs), np.concatenate(tets)), np.concatenate(driven), np.concatenate(signs),
            axis, opening, rigid)


def add_block(b: ModelBuilder, name: str, spec: dict, where: str, number: Callable, vector: Callable,
              ints: Callable) -> np.ndarray:
    """Add a ``blocks`` entry (free: a stiff elastic box; kinematic: all vertices fixed).

    Returns:
        its initial positions in m, shape ``(n, 3)``.

    Raises:
        ConfigError: bad mode, both or neither of mass/density for a free block, bad values.
    """
    size = vector(spec["size"], 3, f"{where}.size", positive=True)
    box = tet_box(tuple(size), ints(spec["resolution"], 3, f"{where}.resolution", 2),
                  tuple(vector(spec["origin"], 3, f"{where}.origin")))
    mode = spec["mode"]
    if mode not in ("free", "kinematic"):
        raise ConfigError(f"task scene: {where}.mode must be free|kinematic, got {mode!r}")
    if mode == "kinematic":
        for k in ("mass", "density", "youngs_modulus", "poisson_ratio"):
            if k in spec:
                raise ConfigError(f"task scene: key {where}.{k} does not apply to a kinematic block")
        b.add_solid(name, box, None, frozen=True)
        return box.x
    if ("mass" in spec) == ("density" in spec):
        raise ConfigError(f"task scene: {where} (free) needs exactly one of mass (kg) or density (kg/m^3)")
    volume = float(np.prod(size))
    rho = (number(spec["mass"], f"{where}.mass", positive=True) / volume if "mass" in spec
           else number(spec["density"], f"{where}.density", positive=True))
    nu = number(spec.get("poisson_ratio", STIFF_BLOCK_POISSON_RATIO), f"{where}.poisson_ratio")
    if not -1.0 < nu < 0.5:
        raise ConfigError(f"task scene: {where}.poisson_ratio must be in (-1, 0.5), got {nu}")
    material = {"youngs_modulus": number(spec.get("youngs_modulus", STIFF_BLOCK_YOUNGS_MODULUS), f"{where}.youngs_modulus",
                                         positive=True), "poisson_ratio": nu, "density": rho}
    b.add_solid(name, box, material)
    return box.x


def arch(x: np.ndarray, height: float) -> np.ndarray:
    """Raise box vertices by ``height sin(pi (x - x_min) / (x_max - x_min))`` (m); returns a copy."""
    out = np.array(x, dtype=float)
    u = (out[:, 0] - out[:, 0].min()) / (out[:, 0].max() - out[:, 0].min())
    out[:, 2] += float(height) * np.sin(np.pi * u)
    return out


def pinned_vertices(spec: Any, x: np.ndarray, grid_shape: tuple[int, int] | None, where: str,
                    edge_vertices: Callable) -> np.ndarray:
    """Local vertex indices of a ``pinned`` list.

    Args:
        spec: list of ``{edge}``, ``{vertices}`` or ``{region: {min, max}}`` items.
        x: the object's initial positions, shape ``(n, 3)``.
        grid_shape: ``(nx, ny)`` for grid sheets (needed by ``edge``), else None.
        where: dotted key for errors.
        edge_vertices: ``(nx, ny, edge, where) -> indices``.

    Raises:
        ConfigError: bad item, index out of range, an empty region.
    """
    if not isinstance(spec, list) or not spec:
        raise ConfigError(f"task scene: {where} must be a non-empty list of {{edge}} | {{vertices}} | {{region}}")
    n = x.shape[0]
    out = []
    for i, item in enumerate(spec):
        w = f"{where}[{i}]"
        if not isinstance(item, dict) or len(item) != 1 or next(iter(item)) not in ("edge", "vertices", "region"):
            raise ConfigError(f"task scene: {w} must be one of {{edge: ...}}, {{vertices: [...]}}, {{region: {{min, max}}}}")
        key, value = next(iter(item.items()))
        if key == "edge":
            if grid_shape is None:
                raise ConfigError(f"task scene: {w}.edge needs a grid sheet")
            out.append(edge_vertices(grid_shape[0], grid_shape[1], value, f"{w}.edge"))
        elif key == "vertices":
            idx = np.asarray(value)
            if idx.ndim != 1 or idx.size == 0 or not np.issubdtype(idx.dtype, np.integer) or idx.min() < 0 or idx.max() >= n:
                raise ConfigError(f"task scene: {w}.vertices must be integers in [0, {n}), got {value!r}")
            out.append(idx.astype(np.int64))
        else:
            if not isinstance(value, dict) or set(value) != {"min", "max"}:
                raise ConfigError(f"task scene: {w}.region must be {{min: [x y z], max: [x y z]}}")
            lo, hi = np.asarray(value["min"], dtype=float), np.asarray(value["max"], dtype=float)
            sel = np.flatnonzero(np.all((x >= lo) & (x <= hi), axis=1))
            if sel.size == 0:
                raise ConfigError(f"task scene: {w}.region contains no vertex")
            out.append(sel)
    return np.unique(np.concatenate(out))


def crease_rest_angles(spec: Any, hinges_local: np.ndarray, nx: int, theta_bar: np.ndarray, where: str) -> np.ndarray:
    """Rest angles with grid creases set (``{column: ix | row: iy, rest_angle: rad}`` items).

    Args:
        spec: the ``creases`` list.
        hinges_local: the sheet's hinges, local indices, shape ``(h, 4)``.
        nx: vertices along x.
        theta_bar: rest angles before, rad, shape ``(h,)``.
        where: dotted key for errors.

    Returns:
        the new rest angles, shape ``(h,)``.

    Raises:
        ConfigError: bad item or a line with no interior hinge.
    """
    if not isinstance(spec, list) or not spec:
        raise ConfigError(f"task scene: {where} must be a non-empty list of {{column | row, rest_angle}}")
    out = np.array(theta_bar, dtype=float)
    h = np.asarray(hinges_local)
    for i, item in enumerate(spec):
        w = f"{where}[{i}]"
        if not isinstance(item, dict) or "rest_angle" not in item or len(item.keys() & {"column", "row"}) != 1 \
                or len(item) != 2:
            raise ConfigError(f"task scene: {w} must be {{column: ix | row: iy, rest_angle: rad}}, got {item!r}")
        angle = float(item["rest_angle"])
        if not (math.isfinite(angle) and abs(angle) < math.pi):
            raise ConfigError(f"task scene: {w}.rest_angle must be in (-pi, pi) rad, got {item['rest_angle']!r}")
        if "column" in item:
            line = int(item["column"])
            on = (h[:, 0] % nx == line) & (h[:, 1] % nx == line)
        else:
            line = int(item["row"])
            on = (h[:, 0] // nx == line) & (h[:, 1] // nx == line)
        if not on.any():
            raise ConfigError(f"task scene: {w}: grid line {line} has no interior hinge")
        out[on] = angle
    return out


def load_mesh_object(spec: dict, where: str, base_dir: Path | None) -> TriMesh | TetMesh:
    """Read a ``meshes`` entry's file (scaled, translated).

    Raises:
        ConfigError: missing file, or a kind that does not match the file's elements.
        MeshError: a degenerate or unreadable mesh; the message names the file and the element.
    """
    from sim_core.mesh.io import load_mesh

    path = Path(str(spec["file"]))
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    scale = float(spec.get("scale", 1.0))
    try:
        mesh = load_mesh(path, scale)
    except MeshError as err:
        msg = str(err)
        raise MeshError(msg if str(path) in msg else f"mesh file {path}: {msg}") from err
    t = np.asarray(spec.get("translation", [0.0, 0.0, 0.0]), dtype=float)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ConfigError(f"task scene: {where}.translation must be 3 finite numbers (m)")
    kind = spec["kind"]
    if kind == "sheet" and not isinstance(mesh, TriMesh):
        raise ConfigError(f"task scene: {where}: kind sheet needs a triangle mesh; {path} has tetrahedra")
    if kind in ("solid", "frozen") and not isinstance(mesh, TetMesh):
        raise ConfigError(f"task scene: {where}: kind {kind} needs a tetrahedral mesh; {path} has only triangles")
    return type(mesh)(mesh.x + t, mesh.triangles if isinstance(mesh, TriMesh) else mesh.tets)
