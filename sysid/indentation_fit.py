"""Fit the gel's Young's modulus to measured indentation depth / force pairs.

For a fixed geometry, Poisson ratio and prescribed indenter displacement, every stress of a
hyperelastic gel scales with E, so the simulated force is (up to the penalty contact's own
stiffness) proportional to E: ``F_sim(E) = E g``. The fit minimises the relative least squares
``sum_i ((F_sim_i - F_i) / F_i)^2`` over ``log E`` by a secant/scaling iteration: with the ratios
``r_i = F_sim_i(E_k) / F_i``, the exact minimiser for a force proportional to E is
``E_{k+1} = E_k sum r_i / sum r_i^2``; the iteration stops when the update changes ``log E`` by less
than ``tol`` (one or two simulations beyond the first when F is close to proportional to E).

Conventions: the small-strain shear modulus ``mu = E / (2 (1 + nu))`` and the Neo-Hookean
``C10 = mu / 2`` (Abaqus/CalculiX ``*HYPERELASTIC, NEO HOOKE``: ``W = C10 (I1_bar - 3) + ...``).
CalculiX replaces a zero compressibility ``D1`` by the value of an initial Poisson ratio of 0.475
(CalculiX CrunchiX user's manual, "Hyperelastic and hyperfoam materials").
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from sim_core import indentation as ind
from sim_core.errors import CalibrationError, ConfigError
from sim_core.mesh import io
from sim_core.model import ContactSettings
from sim_core.scenes.scene_file import load_yaml
from sim_core.solver import SolverConfig

CONFIG_KEYS = {
    "version", "data_root", "mesh", "mesh_scale", "gel_volume_set", "gel_fixed_set", "indenter_volume_set",
    "poisson_ratio", "friction", "measurements", "reference", "simulation",
}


@dataclass
class ModulusFit:
    """Result of :func:`fit_youngs_modulus`.

    Attributes:
        youngs_modulus: fitted E in Pa.
        poisson_ratio: nu held fixed.
        mu: small-strain shear modulus E / (2 (1 + nu)) in Pa.
        c10: Neo-Hookean C10 = mu / 2 in Pa.
        force_model: simulated forces at the fitted E, N, shape ``(k,)``.
        relative_error: ``force_model / force_measured - 1``, shape ``(k,)``.
        history: ``(E, objective)`` of every simulation, in order.
        runtime: wall time in s.
    """

    youngs_modulus: float
    poisson_ratio: float
    mu: float
    c10: float
    force_model: np.ndarray
    relative_error: np.ndarray
    history: list
    runtime: float


def fit_youngs_modulus(
    simulate: Callable[[float], np.ndarray],
    force_measured,
    poisson_ratio: float,
    youngs_modulus_initial: float,
    tol: float = 1e-3,
    max_evaluations: int = 6,
) -> ModulusFit:
    """Least-squares fit of E (in log space) to measured forces.

    Args:
        simulate: E (Pa) -> simulated force magnitudes (N), shape ``(k,)`` (same order and sign
            convention as ``force_measured``).
        force_measured: measured force magnitudes in N, shape ``(k,)``, all > 0.
        poisson_ratio: nu (fixed), used for mu and C10.
        youngs_modulus_initial: starting E in Pa (> 0).
        tol: stop when ``|log E_{k+1} - log E_k| < tol``.
        max_evaluations: simulations allowed.

    Returns:
        :class:`ModulusFit` (the best E evaluated, with its forces).

    Raises:
        CalibrationError: non-positive measurements, a simulation returning a non-positive or
            non-finite force, or no convergence within ``max_evaluations``.
    """
    t0 = time.perf_counter()
    f_meas = np.asarray(force_measured, dtype=float).reshape(-1)
    if f_meas.size == 0 or not np.all(np.isfinite(f_meas)) or np.any(f_meas <= 0):
        raise CalibrationError(f"indentation fit: measured forces must be finite and > 0, got {f_meas.tolist()}")
    if not youngs_modulus_initial > 0:
        raise CalibrationError(f"indentation fit: initial Young's modulus must be > 0, got {youngs_modulus_initial}")
    E = float(youngs_modulus_initial)
    history: list[tuple[float, float]] = []
    best = None
    for _ in range(max_evaluations):
        f_sim = np.asarray(simulate(E), dtype=float).reshape(-1)
        if f_sim.shape != f_meas.shape or not np.all(np.isfinite(f_sim)) or np.any(f_sim <= 0):
            raise CalibrationError(
                f"indentation fit: simulation at E = {E:.6g} Pa returned forces {f_sim.tolist()} "
                f"(need {f_meas.size} finite positive values)"
            )
        r = f_sim / f_meas
        objective = float(np.sum((r - 1.0) ** 2))
        history.append((E, objective))
        if best is None or objective < best[1]:
            best = (E, objective, f_sim)
        scale = float(np.sum(r) / np.sum(r**2))
        if abs(np.log(scale)) < tol:
            break
        E *= scale
    else:
        raise CalibrationError(
            f"indentation fit: log E still moving after {max_evaluations} simulations (history {history})"
        )
    E_fit, _, f_fit = best
    mu = E_fit / (2.0 * (1.0 + poisson_ratio))
    return ModulusFit(E_fit, float(poisson_ratio), mu, mu / 2.0, f_fit, f_fit / f_meas - 1.0, history,
                      time.perf_counter() - t0)


@dataclass
class IndentationConfig:
    """The FEATS indentation data set (packaged ``sysid/data/feats_indentation.yaml``), paths resolved.

    Attributes:
        mesh: Abaqus/CalculiX mesh file holding gel and indenter.
        mesh_scale: factor to m (1e-3 for mm).
        gel_volume_set / gel_fixed_set / indenter_volume_set: ``.nam`` node-set files.
        poisson_ratio: gel nu used in the fit.
        friction: gel-indenter Coulomb coefficient.
        depth: prescribed indenter displacements in m, shape ``(k,)``.
        force: measured normal force magnitudes in N, shape ``(k,)``.
        reference_c10: the published C10 in Pa (for comparison only).
        simulation: free-form numerical settings (contact stiffness, eps, increment ...).
    """

    mesh: Path
    mesh_scale: float
    gel_volume_set: Path
    gel_fixed_set: Path
    indenter_volume_set: Path
    poisson_ratio: float
    friction: float
    depth: np.ndarray
    force: np.ndarray
    reference_c10: float
    simulation: dict


def load_indentation_config(path: str | Path, base: str | Path | None = None) -> IndentationConfig:
    """Read an indentation-fit YAML; data paths are relative to ``base / data_root``.

    Args:
        path: the YAML file.
        base: the folder a relative ``data_root`` is resolved against (default: the YAML file's folder).

    Returns:
        :class:`IndentationConfig`.

    Raises:
        ConfigError: missing file, unknown or missing key, mismatched measurement lengths, or a data
            file that does not exist (the message names the file and the key).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"indentation config {path} does not exist")
    raw = load_yaml(path.read_text(encoding="utf-8")) or {}
    unknown = sorted(set(raw) - CONFIG_KEYS)
    missing = sorted(CONFIG_KEYS - set(raw) - {"simulation", "reference"})
    if unknown or missing:
        raise ConfigError(f"{path}: unknown keys {unknown} / missing keys {missing}")
    root = Path(base) if base is not None else path.resolve().parent
    data_root = (root / raw["data_root"]).resolve()
    files = {}
    for key in ("mesh", "gel_volume_set", "gel_fixed_set", "indenter_volume_set"):
        f = data_root / raw[key]
        if not f.is_file():
            raise ConfigError(f"{path}: key {key!r}: data file {f} does not exist (data_root {raw['data_root']!r} "
                              f"is resolved against {root})")
        files[key] = f
    meas = raw["measurements"]
    depth = np.asarray(meas.get("depth_mm", []), dtype=float) * 1e-3
    force = np.abs(np.asarray(meas.get("force_n", []), dtype=float))
    if depth.size == 0 or depth.shape != force.shape:
        raise ConfigError(f"{path}: measurements.depth_mm and measurements.force_n must be equal-length lists")
    return IndentationConfig(
        files["mesh"], float(raw["mesh_scale"]), files["gel_volume_set"], files["gel_fixed_set"],
        files["indenter_volume_set"], float(raw["poisson_ratio"]), float(raw["friction"]), depth, force,
        float((raw.get("reference") or {}).get("c10_mpa", np.nan)) * 1e6, dict(raw.get("simulation") or {}),
    )


def build_indentation_setup(cfg: IndentationConfig, youngs_modulus: float, quadratic: str = "corners"):
    """The gel + rigid indenter model of an indentation data set (e.g. FEATS' CalculiX model).

    Reads the mesh (quadratic tets reduced to their corners, or split into 8 linear ones so that the
    gel keeps every node of the model it was made for), separates gel and indenter by their node sets, clamps the gel's
    fixed set and makes the indenter a rigid, effector-driven body lowered along -z: its surface
    mesh, or (``simulation.indenter_geometry: sphere``) the exact sphere fitted to the lower half
    of that surface (:func:`sim_core.indentation.fit_sphere`; smooth contact, no facets). The
    indenter is lifted by the contact offset ``eps`` plus its initial penetration (if any), so that
    depth 0 is first touch, as in the prescribed-displacement CalculiX model.

    Args:
        cfg: from :func:`load_indentation_config`.
        youngs_modulus: gel E in Pa (changed later by :func:`sim_core.indentation.run_depth_sweep`).
        quadratic: ``"corners"`` or ``"split"`` (see :func:`sim_core.mesh.io.read_mesh`).

    Returns:
        :class:`sim_core.indentation.IndentationSetup`.

    Raises:
        MeshError / ConfigError: unreadable mesh or node sets, a set with no tets (names the file).
    """
    mesh = io.read_mesh(cfg.mesh, scale=cfg.mesh_scale, quadratic=quadratic)
    gel_nodes = _single_set(io.load_node_sets(cfg.gel_volume_set, mesh.node_ids), cfg.gel_volume_set)
    fixed_nodes = _single_set(io.load_node_sets(cfg.gel_fixed_set, mesh.node_ids), cfg.gel_fixed_set)
    indenter_nodes = _single_set(io.load_node_sets(cfg.indenter_volume_set, mesh.node_ids), cfg.indenter_volume_set)
    parts = ind.split_by_node_sets(mesh.mesh, {"gel": gel_nodes, "indenter": indenter_nodes})
    gel, gel_index = parts["gel"]
    fixed = np.isin(gel_index, fixed_nodes)
    if not fixed.any():
        raise ConfigError(f"{cfg.gel_fixed_set}: no node of the fixed set belongs to the gel")
    surface = ind.surface_of(parts["indenter"][0])
    sim = cfg.simulation
    geometry = sim.get("indenter_geometry", "mesh")
    if geometry == "sphere":
        # the contacting lower half of the indenter (FEATS: a hemisphere under a flat top)
        z = surface.x[:, 2]
        indenter = ind.fit_sphere(surface.x[z <= 0.5 * (z.min() + z.max())])
    elif geometry == "mesh":
        indenter = surface
    else:
        raise ConfigError(f"indentation config: simulation.indenter_geometry must be mesh|sphere, got {geometry!r}")
    eps = float(sim.get("contact_eps", 2e-5))
    increment = float(sim.get("max_increment", 2.5e-4))
    contact = ContactSettings(stiffness=float(sim.get("contact_stiffness", 1e5)), eps=eps,
                              eps_v=float(sim.get("friction_eps_v", 1e-6)), self_contact=False,
                              candidate_margin=increment + eps)
    solver = SolverConfig(tol_velocity=float(sim.get("tol_velocity", 1e-7)), projection="abs",
                          max_iterations=int(sim.get("max_iterations", 100)))
    options = {"friction": cfg.friction, "solver_config": solver,
               "indenter_vertices_vs_gel": bool(sim.get("indenter_vertices_vs_gel", True))}
    return ind.build_indentation(gel, fixed, indenter, youngs_modulus, cfg.poisson_ratio, contact,
                                 indenter_lift=None, **options)


def _single_set(sets: dict[str, np.ndarray], path: Path) -> np.ndarray:
    """The node indices of a ``.nam`` file holding exactly one set (ConfigError naming the file)."""
    if len(sets) != 1:
        raise ConfigError(f"{path}: expected exactly one node set, found {sorted(sets)}")
    return next(iter(sets.values()))
