"""Build a Model from a scene v1 file (INTERFACES.md): sheet + tactile gel pads + table.

Geometry conventions (INTERFACES.md, shared/data/reference_bags/README.md):
- sheet vertex (ix, iy) is index ``iy * nx + ix``; vertex (0, 0) at ``sheet.origin`` (mid-surface);
  ``clamped_edge`` fixes one edge.
- each sensor's gel is a box ``[-gx/2, gx/2] x [-gy/2, gy/2] x [-gt, 0]`` in the sensor frame, whose
  face z = 0 is the contact surface (outward normal +z); its back face z = -gt is the mount that
  follows the effector rigidly. The sensor frame is ``effector pose * mount``.
- the table is the plane z = ``table.height``.

Optional extension block (not in INTERFACES.md v1; every key optional)::

    simulation:
      contact_stiffness: 2.0e4     # N/m penalty stiffness
      contact_eps_v: 0.01          # m/s, friction's stick speed (IPC mollifier)
      contact_eps: null            # m; default: half the sheet thickness
      gel_resolution: [8, 6, 5]    # gel tet-box vertices along sensor x, y, z (default_gel_resolution)
      gel_cut: kuhn                # or mirrored: how the gel's cells are cut into tets (sim_core.mesh.tet.TET_CUTS)
      gel_element: stable_neohookean   # or nodal_pressure_neohookean (does not lock; sim_core.energies.nodal_pressure)
                                       # or green_strain (Saint Venant-Kirchhoff; sim_core.energies.green_strain)
                                       # or modified_stvk (Green-strain shear, (ln J)^2 volume; sim_core.energies.modified_stvk)
      sheet_yield_angle: .inf      # rad, bending plasticity threshold
      damping: 0.0                 # 1/s, mass-proportional
      max_translation_per_step: 0.001   # m
      max_rotation_per_step: 0.02       # rad
      self_contact: true
      broad_phase: spatial_hash    # or sweep | kdtree (same pairs)
      candidates: {stiction: 0.4}  # missing-physics terms (sim_core.candidates): name -> beta, setting -> value
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_core.builder import ModelBuilder
from sim_core.candidates.parameters import validate_candidate_parameters
from sim_core.elastic import SOLID_ELEMENTS
from sim_core.errors import ConfigError
from sim_core.mesh.sheet import grid_sheet
from sim_core.mesh.tet import TET_CUTS, tet_box
from sim_core.model import ContactSettings, Model, check_broad_phase
from sim_core.sensors.camera import PinholeCamera
from sim_core.sensors.markers import embed_markers, marker_grid
from sim_core.sensors.tactile import TactileSensorSpec
from sim_core.transforms import compose_poses, transform_points

SIMULATION_KEYS = {
    "contact_stiffness": 2.0e4,
    "contact_eps_v": 0.01,
    "contact_eps": None,
    "gel_resolution": None,
    "gel_cut": "kuhn",
    "gel_element": "stable_neohookean",
    "sheet_yield_angle": float("inf"),
    "damping": 0.0,
    "max_translation_per_step": 1.0e-3,
    "max_rotation_per_step": 0.02,
    "self_contact": True,
    "broad_phase": "spatial_hash",
    "candidates": None,
}


@dataclass
class TactileSensorInstance:
    """A tactile sensor placed in a model.

    Attributes:
        name: sensor name.
        effector: effector name carrying the gel.
        gel_body: name of the gel's solid body.
        mount: sensor frame in the effector frame ``[x y z qx qy qz qw]``.
        contact_triangles: global triangles of the gel's contact face, shape ``(t, 3)``.
        spec: the sensor's scene block (dict or ``sim_core.sensors`` spec).
        camera: the camera model (``sim_core.sensors.camera.PinholeCamera``).
        embedding: marker embedding on ``contact_triangles``.
    """

    name: str
    effector: str
    gel_body: str
    mount: np.ndarray
    contact_triangles: np.ndarray
    spec: Any
    camera: Any
    embedding: Any


def _edge_vertices(nx: int, ny: int, edge: str) -> np.ndarray:
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))
    ix, iy = ix.reshape(-1), iy.reshape(-1)
    sel = {"x0": ix == 0, "x1": ix == nx - 1, "y0": iy == 0, "y1": iy == ny - 1}
    if edge == "none":
        return np.zeros(0, dtype=np.int64)
    if edge not in sel:
        raise ConfigError(f"sheet.clamped_edge must be none|x0|x1|y0|y1, got {edge!r}")
    return np.nonzero(sel[edge])[0]


GEL_LAYERS = 4
"""Tet layers through the gel's thickness in the default mesh (:func:`default_gel_resolution`)."""


def default_gel_resolution(gel_size: tuple[float, float, float], marker_pitch: float) -> list[int]:
    """The gel's tet-box vertices ``[NX, NY, NZ]`` when the scene does not set ``simulation.gel_resolution``.

    A bonded gel layer pressed flat resists by the bulge of its free sides, whose lateral displacement is a
    parabola through the thickness (Gent and Lindley, Proc. Inst. Mech. Eng. 173, 1959). Two layers of linear
    tets cannot follow it and lock at the gel's nu = 0.45: the reference pad (18.6 x 14.3 x 4 mm) on
    ``[10, 8, 3]`` (two layers, lateral spacing = the marker pitch, the rule until session 51) is 1.30x
    (bonded face) / 1.21x (frictionless face) stiffer in compression than the converged mesh. So the default
    takes :data:`GEL_LAYERS` layers and widens the lateral spacing to ``2/3`` of the thickness (never below
    the marker pitch), which keeps the vertex count, and with it a replay's cost: ``[8, 6, 5]`` for the
    reference pad, 1.13x / 1.11x (``docs/known_answers.md``, "The tactile gel in compression";
    ``tests/sim_core/test_known_answers_gel_compression.py``).

    Args:
        gel_size: ``(gx, gy, gt)`` in m, the gel box along sensor x, y and its thickness.
        marker_pitch: marker spacing, m.

    Returns:
        ``[NX, NY, NZ]``, each >= 3 laterally, ``GEL_LAYERS + 1`` through the thickness.
    """
    gx, gy, gt = (float(v) for v in gel_size)
    spacing = max(float(marker_pitch), 2.0 * gt / 3.0)
    return [max(3, int(round(gx / spacing)) + 1), max(3, int(round(gy / spacing)) + 1), GEL_LAYERS + 1]


def simulation_options(scene: dict) -> dict:
    """The ``simulation:`` extension block with defaults filled in.

    Raises:
        ConfigError: unknown key (named).
    """
    block = dict(scene.get("simulation") or {})
    unknown = sorted(set(block) - set(SIMULATION_KEYS))
    if unknown:
        raise ConfigError(f"scene: unknown key(s) simulation.{unknown[0]} (known: {sorted(SIMULATION_KEYS)})")
    out = dict(SIMULATION_KEYS)
    out.update(block)
    return out


def _gel_element(name) -> str:
    """``simulation.gel_element``, checked: one of :data:`sim_core.elastic.SOLID_ELEMENTS`."""
    if name not in SOLID_ELEMENTS:
        raise ConfigError(f"scene: simulation.gel_element must be one of {SOLID_ELEMENTS}, got {name!r}")
    return name


def _gel_cut(name) -> str:
    """``simulation.gel_cut``, checked: one of :data:`sim_core.mesh.tet.TET_CUTS`."""
    if name not in TET_CUTS:
        raise ConfigError(f"scene: simulation.gel_cut must be one of {TET_CUTS}, got {name!r}")
    return name


def build_tactile_scene(scene: dict) -> Model:
    """Build the Model of a validated scene v1 dictionary.

    Args:
        scene: the scene as a plain dict (``sim_core.scenes.load_scene`` validates it first).

    Returns:
        the Model; ``model.sensors`` holds :class:`TactileSensorInstance` objects and
        ``model.meta`` the scene name, dt and the sheet grid shape.
    """
    opts = simulation_options(scene)
    sheet = scene["sheet"]
    nx, ny = (int(v) for v in sheet["resolution"])
    mesh = grid_sheet(tuple(sheet["size"]), (nx, ny), tuple(sheet["origin"]))
    mat = dict(sheet["material"])
    thickness = float(sheet["thickness"])
    b = ModelBuilder()
    b.add_sheet(
        "sheet", mesh,
        {"youngs_modulus": mat["youngs_modulus"], "poisson_ratio": mat["poisson_ratio"], "thickness": thickness,
         "density": sheet["density"], "bending_stiffness": mat["bending_stiffness"],
         "yield_angle": opts["sheet_yield_angle"]},
        fixed=_edge_vertices(nx, ny, sheet.get("clamped_edge", "none")), grid_shape=(nx, ny),
    )
    table = scene.get("table")
    if table is not None:
        b.add_plane("table", (0.0, 0.0, 1.0), float(table["height"]))
        b.set_friction("sheet", "table", float(table["friction"]))
    sensors = {}
    effectors = scene.get("effectors", {})
    for i, (sname, s) in enumerate(scene.get("sensors", {}).items()):
        eff_name = s["effector"]
        if eff_name not in effectors:
            raise ConfigError(f"scene: sensors.{sname}.effector names unknown effector {eff_name!r}")
        gx, gy, gt = (float(v) for v in s["gel_size"])
        pitch = float(s["marker_pitch"])
        res = opts["gel_resolution"] or default_gel_resolution((gx, gy, gt), pitch)
        gel = tet_box((gx, gy, gt), tuple(int(r) for r in res), (-gx / 2, -gy / 2, -gt),
                      _gel_cut(opts["gel_cut"]))
        mount = np.asarray(s.get("mount") or [0, 0, 0, 0, 0, 0, 1], dtype=float)
        pose = np.asarray(effectors[eff_name]["initial_pose"], dtype=float)
        sensor_pose = compose_poses(pose, mount)
        x_local = gel.x.copy()
        gel_world = type(gel)(transform_points(sensor_pose, gel.x), gel.tets)
        gel_name = "gel" if i == 0 else f"gel_{sname}"
        gm = s["gel_material"]
        body = b.add_solid(gel_name, gel_world,
                           {"youngs_modulus": gm["youngs_modulus"], "poisson_ratio": gm["poisson_ratio"], "density": gm["density"]})
        back = np.nonzero(np.isclose(x_local[:, 2], -gt))[0]
        b.add_effector(eff_name, gel_name, back, pose, opts["max_translation_per_step"], opts["max_rotation_per_step"])
        b.set_friction(gel_name, "sheet", float(s["friction"]))
        if table is not None:
            b.set_friction(gel_name, "table", float(table["friction"]))
        # contact face: boundary triangles whose vertices all lie on z = 0 in the sensor frame
        local_tris = body.triangles - body.vertex_start
        on_face = np.all(np.isclose(x_local[local_tris, 2], 0.0), axis=1)
        face = local_tris[on_face]
        camera = PinholeCamera.from_dict(s["camera"], where=f"sensors.{sname}.camera")
        markers = marker_grid(tuple(int(v) for v in s["marker_grid"]), pitch)
        embedding = embed_markers(markers, x_local, face)
        sensors[sname] = TactileSensorInstance(
            name=sname, effector=eff_name, gel_body=gel_name, mount=mount,
            contact_triangles=face + body.vertex_start, spec=TactileSensorSpec.from_dict(s, sname), camera=camera, embedding=embedding,
        )
    eps = opts["contact_eps"] if opts["contact_eps"] is not None else 0.5 * thickness
    eps_v = float(opts["contact_eps_v"])
    if not (np.isfinite(eps_v) and eps_v > 0):
        raise ConfigError(f"scene: simulation.contact_eps_v must be a positive number (m/s), got {opts['contact_eps_v']!r}")
    contact = ContactSettings(stiffness=float(opts["contact_stiffness"]), eps=float(eps), eps_v=eps_v,
                              self_contact=bool(opts["self_contact"]),
                              broad_phase=check_broad_phase(opts["broad_phase"], "simulation.broad_phase"))
    model = b.finalize(gravity=scene.get("gravity", (0, 0, -9.81)), contact=contact, damping=float(opts["damping"]),
                       meta={"name": scene.get("name", ""), "dt": float(scene["dt"]), "sheet_grid": (nx, ny),
                             "solid_element": _gel_element(opts["gel_element"])})
    model.sensors = sensors
    if opts["candidates"]:
        if not isinstance(opts["candidates"], dict):
            raise ConfigError(f"scene: simulation.candidates must be a mapping of name -> value, got {opts['candidates']!r}")
        try:
            model.candidates = dict(validate_candidate_parameters(opts["candidates"]))
        except ConfigError as err:
            raise ConfigError(f"scene: simulation.candidates: {err}") from err
    return model
