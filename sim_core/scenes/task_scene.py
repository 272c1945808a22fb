"""Scene schema ``kind: task``: ThinShellLab-style manipulation and inverse tasks as data.

A task scene lists sheets (grids, optionally pre-folded into a hairpin), boxes (frozen tables or
elastic blocks), effector-driven solids (a ThinShellLab dome sensor or a box-shaped tactile pad),
planes, Coulomb coefficients per body pair and contact settings. Every key is validated; an unknown
key raises :class:`ConfigError` naming the dotted key. Example: ``config/scenes/forming.yaml``.

Top-level keys (all required unless marked optional)::

    kind: task              version: 1 | 2         name: str
    dt: s                   gravity: [gx, gy, gz]  damping: 1/s (optional, 0)
    contact: {stiffness: N/m, eps: m, eps_v: m/s (optional), self_contact: bool (optional),
              broad_phase: spatial_hash | sweep | kdtree (optional, spatial_hash)}
    sheets:    {name: SHEET, ...}
    boxes:     {name: {size, resolution, origin, frozen: bool, material (if not frozen)}} (optional)
    effectors: {name: EFFECTOR, ...} (optional)
    planes:    {name: {normal, offset}} (optional)
    friction:  [{pair: [a, b], mu: float}, ...] (optional)
    task:      {type: manipulation|inverse, horizon: steps, identify: [parameter names] (optional)}

SHEET: ``size, resolution, origin, thickness, density | areal_density, membrane, bending,
yield_angle, clamped_edge`` and optional ``pattern``, ``initial_shape``, ``rest_angles``.

* ``membrane: {model: stvk, youngs_modulus, poisson_ratio}`` or ThinShellLab's spring form
  ``{model: spring, k_length, k_area}``. The spring form is recorded in
  ``model.meta["membrane"][sheet]`` for :class:`sim_core.elastic.ElasticTerms`; the sheet's StVK
  parameters are then a small-strain stand-in matching the spring network's response to uniform
  in-plane dilation on a grid of spacing dx: ``E t / (1 - nu) = K_l (2 + sqrt 2) / dx + 4 K_a`` with
  ``nu = 1/3`` (a triangulated spring grid's isotropic Poisson ratio).
* ``bending: {bending_stiffness: D}`` (N m) or ``{k_bend_thinshelllab: K_b}``: ThinShellLab's energy
  ``K_b dx^2 / 3 (theta - theta_bar)^2`` per hinge equals ours, ``(D / 2) 3 |e|^2 / (A1 + A2)
  (theta - theta_bar)^2``, on an axis-aligned grid edge (|e| = dx, A1 + A2 = dx^2) when
  ``D = 2 K_b dx^2 / 9``.
* ``initial_shape: {kind: flat}`` or ``{kind: hairpin, bottom_start_column: R, curve_segments: n}``:
  columns ``ix >= R`` stay flat, columns ``R - n < ix < R`` lie on a half circle of radius
  ``r = dx / (2 sin(pi / (2 n)))`` (chords equal dx, so the fold is an isometry of the flat sheet;
  ThinShellLab used arc length dx, which compresses the curved strip by 1.6 %), and columns
  ``ix <= R - n`` run back at height ``2 r`` above the bottom layer.
* ``rest_angles: flat | initial`` (default flat): rest dihedral angles 0 (ThinShellLab: the fold
  springs back elastically) or those of the initial shape (a set crease). ``initial`` is stored in
  ``model.meta["initial_hinge_theta_bar"]`` and applied by :func:`task_initial_state`.

EFFECTOR: ``shape: dome`` with ``outer_radius, inner_radius, mesh: {ring_step, ring_count,
layer_count}`` (mount = inner surface + base, as in ThinShellLab) or ``shape: pad`` with ``size:
[gx, gy, gt], resolution: [nx, ny, nz]`` (box ``[-gx/2, gx/2] x [-gy/2, gy/2] x [-gt, 0]`` in the
effector frame, mount = back face); plus ``material: {youngs_modulus, poisson_ratio, density}``,
``initial_pose: [x y z qx qy qz qw]``, optional ``max_translation_per_step`` (m, 1e-3) and
``max_rotation_per_step`` (rad, 0.02). The solid's body name is the effector's name.

Version 2 adds gripper effectors, rigid effectors, ``blocks``, ``meshes``, arched boxes, pinned
vertex sets and creases (:mod:`sim_core.scenes.task_scene_v2`; all documented in
``docs/scene_schema.md``); a version-1 file that uses one of these keys is rejected with a hint.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sim_core.builder import ModelBuilder
from sim_core.energies.hinge_bending.reference import dihedral_angle
from sim_core.errors import ConfigError
from sim_core.mesh.dome import dome_shell
from sim_core.mesh.sheet import grid_sheet
from sim_core.mesh.tet import TetMesh, box_face_vertices, tet_box
from sim_core.model import ContactSettings, Model, check_broad_phase
from sim_core.scenes import task_scene_v2 as v2
from sim_core.state import State
from sim_core.transforms import transform_points

TASK_SCENE_VERSION = 2
"""The newest version; version-1 files load unchanged (:data:`TASK_SCENE_VERSIONS`)."""
TASK_SCENE_VERSIONS = (1, 2)
SPRING_STANDIN_POISSON_RATIO = 1.0 / 3.0

_TOP = {"kind": True, "version": True, "name": True, "dt": True, "gravity": True, "contact": True, "sheets": True,
        "damping": False, "boxes": False, "effectors": False, "planes": False, "friction": False, "task": False,
        "fitted": False}  # fitted: the record of thinshell sysid --write-scene (sysid.fitted_scene), not read here
_CONTACT = {"stiffness": True, "eps": True, "eps_v": False, "self_contact": False, "broad_phase": False}
_SHEET = {"size": True, "resolution": True, "origin": True, "thickness": True, "membrane": True, "bending": True,
          "yield_angle": True, "clamped_edge": True, "density": False, "areal_density": False, "pattern": False,
          "initial_shape": False, "rest_angles": False}
_BOX = {"size": True, "resolution": True, "origin": True, "frozen": True, "material": False}
_SOLID_MATERIAL = {"youngs_modulus": True, "poisson_ratio": True, "density": True}
_EFFECTOR = {"shape": True, "material": True, "initial_pose": True, "outer_radius": False, "inner_radius": False,
             "mesh": False, "size": False, "resolution": False, "max_translation_per_step": False,
             "max_rotation_per_step": False}
_TASK = {"type": True, "horizon": True, "identify": False}
# keys that version 2 adds (sim_core.scenes.task_scene_v2)
_TOP_V2 = {**_TOP, "blocks": False, "meshes": False}
_SHEET_V2 = {**_SHEET, "pinned": False, "creases": False, "gravity_scale": False}
_BOX_V2 = {**_BOX, "arch_height": False}
_EFFECTOR_V2 = {**_EFFECTOR, "finger": False, "opening": False, "axis": False, "rigid": False, "gravity_scale": False}


# ----------------------------------------------------------------------------- validation helpers
def _block(value: Any, where: str, keys: dict[str, bool], v2_keys: dict[str, bool] | None = None) -> dict:
    """Check that ``value`` is a mapping with only ``keys`` and all required ones; returns it.

    ``v2_keys``: the keys of version 2, named in the error of a version-1 file that uses one."""
    if not isinstance(value, dict):
        raise ConfigError(f"task scene: {where} must be a mapping, got {type(value).__name__}")
    for k in value:
        if k not in keys:
            hint = " (a version-2 key: set version: 2)" if v2_keys is not None and k in v2_keys else ""
            raise ConfigError(f"task scene: unknown key {where}.{k}{hint} (known: {sorted(keys)})")
    for k, required in keys.items():
        if required and k not in value:
            raise ConfigError(f"task scene: missing key {where}.{k}")
    return value


def _number(value: Any, where: str, positive: bool = False, nonneg: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"task scene: {where} must be a number, got {value!r}") from err
    if not math.isfinite(v) and not (nonneg and v == math.inf):
        raise ConfigError(f"task scene: {where} must be finite, got {value!r}")
    if positive and not v > 0:
        raise ConfigError(f"task scene: {where} must be > 0, got {v}")
    if nonneg and not v >= 0:
        raise ConfigError(f"task scene: {where} must be >= 0, got {v}")
    return v


def _vector(value: Any, n: int, where: str, positive: bool = False) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigError(f"task scene: {where} must be a list of {n} numbers, got {value!r}")
    return np.array([_number(v, f"{where}[{i}]", positive=positive) for i, v in enumerate(value)])


def _ints(value: Any, n: int, where: str, minimum: int) -> tuple[int, ...]:
    vec = _vector(value, n, where)
    if np.any(vec != np.round(vec)) or np.any(vec < minimum):
        raise ConfigError(f"task scene: {where} must be {n} integers >= {minimum}, got {value!r}")
    return tuple(int(v) for v in vec)


# ----------------------------------------------------------------------------- geometry
def hairpin_fold(x_flat: np.ndarray, grid_shape: tuple[int, int], bottom_start_column: int,
                 curve_segments: int) -> tuple[np.ndarray, float]:
    """Fold a flat grid sheet (normal +z) into a hairpin about a line parallel to y.

    Args:
        x_flat: flat grid positions in m, shape ``(nx * ny, 3)``, vertex ``(ix, iy)`` at ``iy * nx + ix``,
            uniform spacing dx along x.
        grid_shape: ``(nx, ny)``.
        bottom_start_column: R, first column of the flat bottom layer (``1 <= R - n``, ``R <= nx - 1``).
        curve_segments: n, number of grid segments on the half circle (>= 1).

    Returns:
        ``(x, r)``: folded positions, shape ``(nx * ny, 3)``, and the fold radius in m.

    Raises:
        ConfigError: columns out of range.
    """
    nx, ny = grid_shape
    R, n = int(bottom_start_column), int(curve_segments)
    if n < 1 or R - n < 0 or R > nx - 1:
        raise ConfigError(f"hairpin: need curve_segments >= 1 and 0 <= R - n, R <= nx - 1; got R={R}, n={n}, nx={nx}")
    x = np.array(x_flat, dtype=float)
    u = x[:nx, 0] - x[0, 0]
    dx = float(u[1] - u[0])
    r = dx / (2.0 * math.sin(math.pi / (2 * n)))
    cx, z0 = x[0, 0] + R * dx, x[0, 2]
    col_x, col_z = np.empty(nx), np.empty(nx)
    for ix in range(nx):
        if ix >= R:
            col_x[ix], col_z[ix] = x[0, 0] + ix * dx, z0
        elif ix > R - n:
            a = (R - ix) / n * math.pi
            col_x[ix], col_z[ix] = cx - r * math.sin(a), z0 + r * (1.0 - math.cos(a))
        else:
            col_x[ix], col_z[ix] = cx + (R - n - ix) * dx, z0 + 2.0 * r
    ix_of = np.arange(nx * ny) % nx
    x[:, 0] = col_x[ix_of]
    x[:, 2] = col_z[ix_of]
    return x, r


def _edge_vertices(nx: int, ny: int, edge: str, where: str) -> np.ndarray:
    ix, iy = np.arange(nx * ny) % nx, np.arange(nx * ny) // nx
    sel = {"none": np.zeros(nx * ny, bool), "x0": ix == 0, "x1": ix == nx - 1, "y0": iy == 0, "y1": iy == ny - 1}
    if edge not in sel:
        raise ConfigError(f"task scene: {where} must be none|x0|x1|y0|y1, got {edge!r}")
    return np.flatnonzero(sel[edge])


def _solid_material(value: Any, where: str) -> dict[str, float]:
    m = _block(value, where, _SOLID_MATERIAL)
    out = {k: _number(m[k], f"{where}.{k}", positive=k != "poisson_ratio") for k in _SOLID_MATERIAL}
    if not -1.0 < out["poisson_ratio"] < 0.5:
        raise ConfigError(f"task scene: {where}.poisson_ratio must be in (-1, 0.5), got {out['poisson_ratio']}")
    return out


# ----------------------------------------------------------------------------- sheets
def _add_sheet(b: ModelBuilder, name: str, spec: Any, meta: dict, version: int = 1) -> tuple[np.ndarray, np.ndarray]:
    where = f"sheets.{name}"
    s = _block(spec, where, _SHEET_V2 if version >= 2 else _SHEET, _SHEET_V2)
    size = _vector(s["size"], 2, f"{where}.size", positive=True)
    nx, ny = _ints(s["resolution"], 2, f"{where}.resolution", 2)
    origin = _vector(s["origin"], 3, f"{where}.origin")
    mesh = grid_sheet(tuple(size), (nx, ny), tuple(origin), s.get("pattern", "alternating"))
    dx, dy = size[0] / (nx - 1), size[1] / (ny - 1)
    t = _number(s["thickness"], f"{where}.thickness", positive=True)
    if ("density" in s) == ("areal_density" in s):
        raise ConfigError(f"task scene: {where} needs exactly one of density (kg/m^3) or areal_density (kg/m^2)")
    rho = (_number(s["density"], f"{where}.density", positive=True) if "density" in s
           else _number(s["areal_density"], f"{where}.areal_density", positive=True) / t)
    mem = s["membrane"]
    model_kind = mem.get("model") if isinstance(mem, dict) else None
    if model_kind == "stvk":
        mem = _block(mem, f"{where}.membrane", {"model": True, "youngs_modulus": True, "poisson_ratio": True})
        E = _number(mem["youngs_modulus"], f"{where}.membrane.youngs_modulus", positive=True)
        nu = _number(mem["poisson_ratio"], f"{where}.membrane.poisson_ratio")
        if not -1.0 < nu < 0.5:
            raise ConfigError(f"task scene: {where}.membrane.poisson_ratio must be in (-1, 0.5), got {nu}")
    elif model_kind == "spring":
        mem = _block(mem, f"{where}.membrane", {"model": True, "k_length": True, "k_area": True})
        k_l = _number(mem["k_length"], f"{where}.membrane.k_length", positive=True)
        k_a = _number(mem["k_area"], f"{where}.membrane.k_area", nonneg=True)
        nu = SPRING_STANDIN_POISSON_RATIO
        E = (k_l * (2.0 + math.sqrt(2.0)) / min(dx, dy) + 4.0 * k_a) * (1.0 - nu) / t
        meta.setdefault("membrane", {})[name] = {"model": "spring", "k_length": k_l, "k_area": k_a}
    else:
        raise ConfigError(f"task scene: {where}.membrane.model must be stvk|spring, got {model_kind!r}")
    bend = s["bending"]
    if isinstance(bend, dict) and "k_bend_thinshelllab" in bend:
        bend = _block(bend, f"{where}.bending", {"k_bend_thinshelllab": True})
        D = 2.0 * _number(bend["k_bend_thinshelllab"], f"{where}.bending.k_bend_thinshelllab", nonneg=True) * dx * dy / 9.0
    else:
        bend = _block(bend, f"{where}.bending", {"bending_stiffness": True})
        D = _number(bend["bending_stiffness"], f"{where}.bending.bending_stiffness", nonneg=True)
    yield_angle = _number(s["yield_angle"], f"{where}.yield_angle", positive=True, nonneg=True)
    shape = s.get("initial_shape", {"kind": "flat"})
    kind = shape.get("kind") if isinstance(shape, dict) else None
    if kind == "flat":
        _block(shape, f"{where}.initial_shape", {"kind": True})
        x0 = mesh.x
    elif kind == "hairpin":
        shape = _block(shape, f"{where}.initial_shape", {"kind": True, "bottom_start_column": True, "curve_segments": True})
        x0, radius = hairpin_fold(mesh.x, (nx, ny), int(shape["bottom_start_column"]), int(shape["curve_segments"]))
        meta.setdefault("fold_radius", {})[name] = radius
    else:
        raise ConfigError(f"task scene: {where}.initial_shape.kind must be flat|hairpin, got {kind!r}")
    rest = s.get("rest_angles", "flat")
    if rest not in ("flat", "initial"):
        raise ConfigError(f"task scene: {where}.rest_angles must be flat|initial, got {rest!r}")
    fixed = _edge_vertices(nx, ny, s["clamped_edge"], f"{where}.clamped_edge")
    if "pinned" in s:
        fixed = np.union1d(fixed, v2.pinned_vertices(s["pinned"], x0, (nx, ny), f"{where}.pinned", _edge_vertices))
    body = b.add_sheet(
        name, mesh,
        {"youngs_modulus": E, "poisson_ratio": nu, "thickness": t, "bending_stiffness": D, "density": rho,
         "yield_angle": yield_angle},
        fixed=fixed, grid_shape=(nx, ny),
    )
    local = body.hinges - body.vertex_start
    theta_bar = dihedral_angle(x0[local]) if rest == "initial" else np.zeros(local.shape[0])
    if "creases" in s:
        theta_bar = v2.crease_rest_angles(s["creases"], local, nx, theta_bar, f"{where}.creases")
    if rest == "initial" or "creases" in s:
        meta.setdefault("initial_hinge_theta_bar", {})[name] = theta_bar
    return mesh.x, x0


# ----------------------------------------------------------------------------- solids
def _effector_solid(name: str, spec: dict, where: str) -> tuple[TetMesh, np.ndarray]:
    shape = spec["shape"]
    if shape == "dome":
        for k in ("outer_radius", "inner_radius", "mesh"):
            if k not in spec:
                raise ConfigError(f"task scene: missing key {where}.{k} (shape dome)")
        for k in ("size", "resolution"):
            if k in spec:
                raise ConfigError(f"task scene: key {where}.{k} does not apply to shape dome")
        m = _block(spec["mesh"], f"{where}.mesh", {"ring_step": True, "ring_count": True, "layer_count": True})
        dome = dome_shell(_number(spec["outer_radius"], f"{where}.outer_radius", positive=True),
                          _number(spec["inner_radius"], f"{where}.inner_radius", positive=True),
                          int(m["ring_step"]), int(m["ring_count"]), int(m["layer_count"]))
        return dome.mesh, dome.mount_vertices
    if shape == "pad":
        for k in ("size", "resolution"):
            if k not in spec:
                raise ConfigError(f"task scene: missing key {where}.{k} (shape pad)")
        for k in ("outer_radius", "inner_radius", "mesh"):
            if k in spec:
                raise ConfigError(f"task scene: key {where}.{k} does not apply to shape pad")
        gx, gy, gt = _vector(spec["size"], 3, f"{where}.size", positive=True)
        pad = tet_box((gx, gy, gt), _ints(spec["resolution"], 3, f"{where}.resolution", 2), (-gx / 2, -gy / 2, -gt))
        return pad, box_face_vertices(pad, 2, "min")
    raise ConfigError(f"task scene: {where}.shape must be dome|pad, got {shape!r}")


# ----------------------------------------------------------------------------- public API
def build_task_scene(scene: dict, base_dir: Path | None = None) -> Model:
    """Build the Model of a ``kind: task`` scene dictionary (schema in the module docstring and, for
    version 2, :mod:`sim_core.scenes.task_scene_v2` and ``docs/scene_schema.md``).

    Args:
        scene: the parsed YAML mapping.
        base_dir: directory that relative ``meshes.*.file`` paths are resolved against (default: the
            working directory).

    Returns:
        the Model. ``model.meta`` holds ``name``, ``dt``, ``task`` (type, horizon, identify),
        ``sheet_grid`` per sheet, ``effector_bodies`` (effector -> body), ``tactile_effectors``
        (effectors whose solid deforms: not rigid), ``version``, and where used
        ``membrane`` (spring form), ``fold_radius`` and ``initial_hinge_theta_bar``;
        ``model.initial_x`` is set when a sheet starts folded.

    Raises:
        ConfigError: unknown or missing key (named as a dotted path), a bad value, or a mesh error.
    """
    if not isinstance(scene, dict):
        raise ConfigError(f"task scene: the document must be a mapping, got {type(scene).__name__}")
    version = scene.get("version")
    if version not in TASK_SCENE_VERSIONS:
        raise ConfigError(f"task scene: version must be one of {TASK_SCENE_VERSIONS}, got {version!r}")
    _block(scene, "<top>", _TOP_V2 if version >= 2 else _TOP, _TOP_V2)
    if scene["kind"] != "task":
        raise ConfigError(f"task scene: kind must be 'task', got {scene['kind']!r}")
    dt = _number(scene["dt"], "dt", positive=True)
    gravity = _vector(scene["gravity"], 3, "gravity")
    c = _block(scene["contact"], "contact", _CONTACT)
    contact = ContactSettings(
        stiffness=_number(c["stiffness"], "contact.stiffness", positive=True),
        eps=_number(c["eps"], "contact.eps", positive=True),
        eps_v=_number(c.get("eps_v", 0.01), "contact.eps_v", positive=True),
        self_contact=bool(c.get("self_contact", True)),
        broad_phase=check_broad_phase(c.get("broad_phase", "spatial_hash"), "contact.broad_phase"),
    )
    meta: dict[str, Any] = {"name": str(scene["name"]), "dt": dt, "sheet_grid": {}, "effector_bodies": {},
                            "tactile_effectors": [], "version": int(version)}
    b = ModelBuilder()
    initial_parts = []
    sheets = scene["sheets"]
    if not isinstance(sheets, dict) or not sheets:
        raise ConfigError("task scene: sheets must be a non-empty mapping name -> sheet")
    moved = False
    for name, spec in sheets.items():
        x_flat, x0 = _add_sheet(b, name, spec, meta, version)
        meta["sheet_grid"][name] = tuple(int(v) for v in spec["resolution"])
        initial_parts.append(x0)
        moved |= not np.array_equal(x_flat, x0)
    for name, spec in (scene.get("boxes") or {}).items():
        where = f"boxes.{name}"
        s = _block(spec, where, _BOX_V2 if version >= 2 else _BOX, _BOX_V2)
        box = tet_box(tuple(_vector(s["size"], 3, f"{where}.size", positive=True)),
                      _ints(s["resolution"], 3, f"{where}.resolution", 2), tuple(_vector(s["origin"], 3, f"{where}.origin")))
        if "arch_height" in s:
            box = TetMesh(v2.arch(box.x, _number(s["arch_height"], f"{where}.arch_height")), box.tets)
            moved = True
        frozen = bool(s["frozen"])
        if not frozen and "material" not in s:
            raise ConfigError(f"task scene: missing key {where}.material (box not frozen)")
        mat = _solid_material(s["material"], f"{where}.material") if "material" in s else None
        b.add_solid(name, box, mat, frozen=frozen)
        initial_parts.append(box.x)
    for name, spec in (scene.get("blocks") or {}).items():
        where = f"blocks.{name}"
        s = _block(spec, where, v2.BLOCK_KEYS)
        initial_parts.append(v2.add_block(b, name, s, where, _number, _vector, _ints))
    for name, spec in (scene.get("meshes") or {}).items():
        initial_parts.append(_add_mesh_object(b, name, spec, base_dir))
    for name, spec in (scene.get("effectors") or {}).items():
        where = f"effectors.{name}"
        s = _block(spec, where, _EFFECTOR_V2 if version >= 2 else _EFFECTOR, _EFFECTOR_V2)
        finger_sign, axis, opening = None, (1.0, 0.0, 0.0), 0.0
        rigid = bool(s.get("rigid", False))
        if s["shape"] == "gripper":
            if version < 2:
                raise ConfigError(f"task scene: {where}.shape gripper needs version: 2")
            for k in v2.GRIPPER_KEYS:
                if k not in s:
                    raise ConfigError(f"task scene: missing key {where}.{k} (shape gripper)")
            if "rigid" in s:
                raise ConfigError(f"task scene: {where}.rigid: set finger.rigid for a gripper")
            local_mesh, mount, finger_sign, axis, opening, rigid = v2.gripper_solid(
                s, where, lambda f, w: _effector_solid(name, f, w), _block)
        else:
            for k in ("finger", "opening", "axis"):
                if k in s:
                    raise ConfigError(f"task scene: key {where}.{k} applies to shape gripper only")
            local_mesh, mount = _effector_solid(name, s, where)
            if rigid:
                mount = np.arange(local_mesh.x.shape[0])
        pose = _vector(s["initial_pose"], 7, f"{where}.initial_pose")
        world = TetMesh(transform_points(pose, local_mesh.x), local_mesh.tets)
        b.add_solid(name, world, _solid_material(s["material"], f"{where}.material"))
        b.add_effector(name, name, mount, pose,
                       _number(s.get("max_translation_per_step", 1e-3), f"{where}.max_translation_per_step", positive=True),
                       _number(s.get("max_rotation_per_step", 0.02), f"{where}.max_rotation_per_step", positive=True),
                       finger_sign=finger_sign, finger_axis=axis, initial_opening=opening)
        meta["effector_bodies"][name] = name
        if not rigid:
            meta["tactile_effectors"].append(name)
        initial_parts.append(world.x)
    for name, spec in (scene.get("planes") or {}).items():
        p = _block(spec, f"planes.{name}", {"normal": True, "offset": True})
        b.add_plane(name, _vector(p["normal"], 3, f"planes.{name}.normal"), _number(p["offset"], f"planes.{name}.offset"))
    friction = scene.get("friction") or []
    if not isinstance(friction, list):
        raise ConfigError("task scene: friction must be a list of {pair: [a, b], mu: value}")
    for i, entry in enumerate(friction):
        e = _block(entry, f"friction[{i}]", {"pair": True, "mu": True})
        if not isinstance(e["pair"], (list, tuple)) or len(e["pair"]) != 2:
            raise ConfigError(f"task scene: friction[{i}].pair must name two bodies/planes, got {e['pair']!r}")
        b.set_friction(str(e["pair"][0]), str(e["pair"][1]), _number(e["mu"], f"friction[{i}].mu", nonneg=True))
    task = _block(scene.get("task") or {"type": "manipulation", "horizon": 1}, "task", _TASK)
    if task["type"] not in ("manipulation", "inverse"):
        raise ConfigError(f"task scene: task.type must be manipulation|inverse, got {task['type']!r}")
    meta["task"] = {"type": task["type"], "horizon": int(_number(task["horizon"], "task.horizon", positive=True)),
                    "identify": [str(v) for v in task.get("identify", [])]}
    model = b.finalize(gravity=gravity, contact=contact, damping=_number(scene.get("damping", 0.0), "damping", nonneg=True),
                       meta=meta)
    if moved:
        model.initial_x = np.concatenate(initial_parts)
    _set_gravity_scale(model, scene)
    known = set(model.parameter_names)
    for p in meta["task"]["identify"]:
        if p not in known:
            raise ConfigError(f"task scene: task.identify names unknown parameter {p!r}; known: {sorted(known)}")
    return model


def _set_gravity_scale(model: Model, scene: dict) -> None:
    """``model.vertex_gravity_scale`` from the bodies' ``gravity_scale`` keys (version 2; None when all 1)."""
    scale = np.ones(model.vertex_count)
    for section in ("sheets", "blocks", "meshes", "effectors"):
        for name, spec in (scene.get(section) or {}).items():
            if isinstance(spec, dict) and "gravity_scale" in spec:
                value = _number(spec["gravity_scale"], f"{section}.{name}.gravity_scale", nonneg=True)
                body = model.bodies[name]
                scale[body.vertex_start:body.vertex_stop] = value
    model.vertex_gravity_scale = None if np.all(scale == 1.0) else scale


def _add_mesh_object(b: ModelBuilder, name: str, spec: Any, base_dir: Path | None) -> np.ndarray:
    """Add a ``meshes`` entry (version 2); returns its initial positions ``(n, 3)``."""
    where = f"meshes.{name}"
    s = _block(spec, where, v2.MESH_KEYS)
    kind = s["kind"]
    if kind not in ("sheet", "solid", "frozen"):
        raise ConfigError(f"task scene: {where}.kind must be sheet|solid|frozen, got {kind!r}")
    mesh = v2.load_mesh_object(s, where, base_dir)
    pinned = None
    if "pinned" in s:
        pinned = v2.pinned_vertices(s["pinned"], mesh.x, None, f"{where}.pinned", _edge_vertices)
    if kind == "sheet":
        m = _block(s.get("material"), f"{where}.material", v2.SHEET_MESH_MATERIAL)
        mat = {k: _number(v, f"{where}.material.{k}", positive=k != "poisson_ratio") for k, v in m.items()}
        b.add_sheet(name, mesh, mat, fixed=pinned)
    elif kind == "solid":
        b.add_solid(name, mesh, _solid_material(s.get("material"), f"{where}.material"), fixed=pinned)
    else:
        if "material" in s:
            raise ConfigError(f"task scene: key {where}.material does not apply to kind frozen")
        b.add_solid(name, mesh, None, frozen=True)
    return mesh.x


def task_initial_state(model: Model) -> State:
    """The initial state of a task scene: ``model.state()`` with the sheets' initial rest angles.

    ``Model.state()`` starts every sheet with flat rest angles; a sheet with ``rest_angles: initial``
    gets the dihedral angles of its initial shape (``model.meta["initial_hinge_theta_bar"]``).
    """
    state = model.state()
    for name, theta_bar in model.meta.get("initial_hinge_theta_bar", {}).items():
        state.hinge_theta_bar[name] = np.array(theta_bar, dtype=float)
    return state


def load_task_scene(path) -> Model:
    """Read a ``kind: task`` YAML file and build its Model.

    Raises:
        ConfigError: missing file or YAML error (naming the file), or any error of :func:`build_task_scene`
            (re-raised with the file name).
    """
    path = Path(path)
    try:
        scene = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{path}: cannot read task scene ({err})") from err
    try:
        return build_task_scene(scene, path.parent)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from err
