"""Model: the static description of a scene (topology, rest shape, materials, boundaries).

Built once by :class:`sim_core.builder.ModelBuilder`. Material parameters can be edited through
:meth:`Model.set_parameter` (system identification); solvers notice through ``Model.revision``
(Newton's ``notify_model_changed`` idea).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_core.candidates.parameters import CANDIDATE_NAMES, CANDIDATE_SETTINGS, validate_candidate_parameters
from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.state import State

SHEET_PARAMETERS = ("youngs_modulus", "poisson_ratio", "thickness", "bending_stiffness", "density", "yield_angle")
SOLID_PARAMETERS = ("youngs_modulus", "poisson_ratio", "density")
BROAD_PHASES = ("spatial_hash", "sweep", "kdtree")
"""Broad-phase searches of the contact set (``ContactSettings.broad_phase``; all give the same pairs)."""


@dataclass
class Body:
    """One deformable or frozen body in the global vertex array.

    Attributes:
        name: unique name (``sheet``, ``gel``, ``table_box`` ...).
        kind: ``"sheet"`` (triangle shell), ``"solid"`` (tetrahedra), ``"frozen"`` (all vertices fixed)
            or ``"sphere"`` (a rigid sphere: one kinematic vertex, its centre; ``material["radius"]``).
        vertex_start, vertex_stop: global vertex range ``[start, stop)``.
        triangles: surface triangles, global indices, shape ``(t, 3)`` (a sheet's own triangles;
            a solid's outward boundary faces).
        edges: surface edges, global indices, shape ``(e, 2)``.
        tets: tetrahedra, global indices, shape ``(k, 4)`` (solids), else None.
        hinges: bending hinges ``[e0, e1, opp0, opp1]``, global, shape ``(h, 4)`` (sheets), else None.
        material: parameter name -> value (SI), see ``SHEET_PARAMETERS`` / ``SOLID_PARAMETERS``.
        grid_shape: ``(nx, ny)`` for grid sheets (vertex ``iy * nx + ix``), else None.
    """

    name: str
    kind: str
    vertex_start: int
    vertex_stop: int
    triangles: np.ndarray
    edges: np.ndarray
    tets: np.ndarray | None = None
    hinges: np.ndarray | None = None
    material: dict[str, float] = field(default_factory=dict)
    grid_shape: tuple[int, int] | None = None

    @property
    def vertices(self) -> np.ndarray:
        """Global vertex indices, shape ``(vertex_stop - vertex_start,)``."""
        return np.arange(self.vertex_start, self.vertex_stop)


@dataclass
class Effector:
    """A kinematic effector: driven vertices follow a rigid SE(3) frame.

    Attributes:
        name: effector name (``ee``).
        vertices: driven global vertex indices, shape ``(k,)``.
        local_points: their coordinates in the effector frame at zero gripper opening change, m,
            shape ``(k, 3)``.
        initial_pose: ``[x y z qx qy qz qw]`` in ``world``.
        max_translation_per_step: m per step (ThinShellLab: 1 mm); targets farther away are
            approached at this rate.
        max_rotation_per_step: rad per step.
        finger_sign: per driven vertex -1/+1 for the two fingers of a gripper (0 = palm), shape ``(k,)``,
            or None for a single pad.
        finger_axis: opening direction in the effector frame, shape ``(3,)``.
        initial_opening: finger opening at ``local_points``, m.
    """

    name: str
    vertices: np.ndarray
    local_points: np.ndarray
    initial_pose: np.ndarray
    max_translation_per_step: float = 1e-3
    max_rotation_per_step: float = 0.02
    finger_sign: np.ndarray | None = None
    finger_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    initial_opening: float = 0.0


@dataclass
class Plane:
    """A rigid half-space boundary ``n . x >= offset`` (table, ground)."""

    name: str
    normal: np.ndarray
    offset: float


def check_broad_phase(name: str, where: str) -> str:
    """``name`` if it is one of :data:`BROAD_PHASES`.

    Raises:
        ConfigError: naming ``where`` (the key) and the accepted values.
    """
    if name not in BROAD_PHASES:
        raise ConfigError(f"{where}: unknown broad phase {name!r}; use one of {', '.join(BROAD_PHASES)}")
    return name


@dataclass
class ContactSettings:
    """Penalty contact and friction settings (DESIGN.md "Contact", "Friction").

    Attributes:
        stiffness: penalty stiffness k_c in N/m.
        eps: contact offset in m (distance below which a pair is active).
        eps_v: friction velocity threshold in m/s (IPC mollifier).
        self_contact: whether sheets collide with themselves.
        candidate_margin: extra broad-phase radius in m beyond ``eps``.
        sheet_vertices_vs_solids: also pair a sheet's vertices with elastomer (solid) surface
            triangles. Off by default: the gel's denser surface samples the sheet (gel vertices
            against sheet triangles, plus edge-edge pairs for the sheet's edges); testing both
            directions between a coarse stiff card and a soft gel makes the card's vertices
            indent the gel as point loads, and Newton's active set oscillates.
        broad_phase: the box-pair search of the candidates (:data:`BROAD_PHASES`, same pairs):
            ``spatial_hash`` (default; Teschner et al. 2003: the Taichi kernel
            :mod:`sim_core.ti_kernels.hash_grid` on the Taichi backend,
            :class:`sim_core.collision.spatial_hash.SpatialHash` on the NumPy one), ``sweep`` (sort
            and sweep, :mod:`sim_core.ti_kernels.broad_phase`; on the NumPy backend its reference,
            the k-d trees) or ``kdtree`` (SciPy k-d trees per body pair, the reference).

    Raises:
        ConfigError: an unknown ``broad_phase``.
    """

    stiffness: float = 2.0e4
    eps: float = 4.0e-4
    eps_v: float = 0.01
    self_contact: bool = True
    candidate_margin: float = 1.0e-3
    sheet_vertices_vs_solids: bool = False
    broad_phase: str = "spatial_hash"

    def __post_init__(self) -> None:
        check_broad_phase(self.broad_phase, "contact.broad_phase")


@dataclass
class Model:
    """Static scene description plus editable material parameters.

    Attributes:
        x_rest: rest positions in m, shape ``(vertex_count, 3)``.
        vertex_fixed: statically fixed vertices (Dirichlet), shape ``(vertex_count,)`` bool.
        bodies: name -> :class:`Body`, in vertex order.
        effectors: name -> :class:`Effector`.
        planes: name -> :class:`Plane`.
        sensors: sensor name -> sensor instance (``sim_core.sensors``), built by the scene loader.
        gravity: m/s^2, shape ``(3,)``.
        vertex_gravity_scale: fraction of ``gravity`` acting on each vertex, shape ``(vertex_count,)``,
            or None (1 everywhere). Task scenes v2 set it per body (``gravity_scale``): ThinShellLab
            gives bodies of one scene different gravity (Lifting: none on the sheet, g on the block).
        contact: :class:`ContactSettings`.
        friction: Coulomb coefficients per unordered pair of body/plane names.
        damping: mass-proportional damping coefficient in 1/s (0 = off).
        initial_x: positions of the initial state (may differ from ``x_rest``), shape ``(n, 3)``.
        candidates: parameters of optional missing-physics candidates (``sim_core.candidates``),
            ``{"stiction": beta, "gel_viscoelasticity.tau": s, ...}``; empty = none active. Set
            with ``set_parameter("candidate.<name>", value)``.
        revision: incremented by every parameter change.
        meta: free-form information from the scene file (name, dt, ...).
    """

    x_rest: np.ndarray
    vertex_fixed: np.ndarray
    bodies: dict[str, Body]
    effectors: dict[str, Effector] = field(default_factory=dict)
    planes: dict[str, Plane] = field(default_factory=dict)
    sensors: dict[str, Any] = field(default_factory=dict)
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    contact: ContactSettings = field(default_factory=ContactSettings)
    friction: dict[frozenset, float] = field(default_factory=dict)
    damping: float = 0.0
    initial_x: np.ndarray | None = None
    candidates: dict[str, float] = field(default_factory=dict)
    revision: int = 0
    meta: dict[str, Any] = field(default_factory=dict)
    vertex_gravity_scale: np.ndarray | None = None

    # ------------------------------------------------------------------ sizes
    @property
    def vertex_count(self) -> int:
        """Number of vertices."""
        return int(self.x_rest.shape[0])

    @property
    def dof_count(self) -> int:
        """Number of degrees of freedom, ``3 * vertex_count``."""
        return 3 * self.vertex_count

    def body_of_vertex(self) -> np.ndarray:
        """Index (in ``bodies`` order) of the body owning each vertex, shape ``(vertex_count,)``."""
        out = np.empty(self.vertex_count, dtype=np.int64)
        for i, b in enumerate(self.bodies.values()):
            out[b.vertex_start : b.vertex_stop] = i
        return out

    def tracked_sheets(self) -> list[Body]:
        """The sheet bodies whose vertices are the tracked ``sheet/points`` (INTERFACES.md): the body
        named ``sheet`` when there is one, else every body of kind ``sheet`` in ``bodies`` order (a
        stack of cards)."""
        if "sheet" in self.bodies:
            return [self.bodies["sheet"]]
        return [b for b in self.bodies.values() if b.kind == "sheet"]

    def tracked_sheet_vertices(self) -> np.ndarray:
        """Global indices of the tracked sheet points in their published order, shape ``(p,)`` int64."""
        parts = [np.arange(b.vertex_start, b.vertex_stop, dtype=np.int64) for b in self.tracked_sheets()]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)

    # ------------------------------------------------------------------ mass
    def vertex_mass(self) -> np.ndarray:
        """Lumped vertex masses in kg, shape ``(vertex_count,)``.

        Sheets: density * thickness * triangle area / 3 per corner; solids: density * volume / 4
        per corner; frozen bodies get the mass of a solid if they have tets, else 0.
        """
        m = np.zeros(self.vertex_count)
        for b in self.bodies.values():
            rho = b.material.get("density", 0.0)
            if b.kind == "sheet":
                a, bb, c = (self.x_rest[b.triangles[:, i]] for i in range(3))
                area = 0.5 * np.linalg.norm(np.cross(bb - a, c - a), axis=1)
                w = rho * b.material["thickness"] * area / 3.0
                for i in range(3):
                    np.add.at(m, b.triangles[:, i], w)
            elif b.tets is not None:
                p = [self.x_rest[b.tets[:, i]] for i in range(4)]
                vol = np.abs(np.einsum("ij,ij->i", np.cross(p[1] - p[0], p[2] - p[0]), p[3] - p[0])) / 6.0
                for i in range(4):
                    np.add.at(m, b.tets[:, i], rho * vol / 4.0)
        return m

    # ------------------------------------------------------------------ parameters
    @property
    def parameter_names(self) -> list[str]:
        """Global names of the editable scalar parameters (``body.key``, ``friction.a_b``, ...)."""
        names = []
        for b in self.bodies.values():
            if b.kind in ("frozen", "sphere"):
                continue
            keys = SHEET_PARAMETERS if b.kind == "sheet" else SOLID_PARAMETERS
            names += [f"{b.name}.{k}" for k in keys if k in b.material]
        names += [f"friction.{self._pair_name(p)}" for p in self.friction]
        names += ["contact.stiffness", "contact.eps_v", "damping"]
        return names

    @staticmethod
    def _pair_name(pair: frozenset) -> str:
        a, b = sorted(pair)
        return f"{a}_{b}"

    def _friction_key(self, name: str) -> frozenset:
        label = name.split(".", 1)[1]
        for pair in self.friction:
            a, b = sorted(pair)
            if label in (f"{a}_{b}", f"{b}_{a}"):
                return pair
        raise ConfigError(f"unknown friction pair {name!r}; known: {[self._pair_name(p) for p in self.friction]}")

    def get_parameter(self, name: str) -> float:
        """Value of a global parameter.

        Raises:
            ConfigError: unknown name (the message lists the known names).
        """
        if name.startswith("candidate."):
            key = name.split(".", 1)[1]
            if key in self.candidates:
                return float(self.candidates[key])
            if key in CANDIDATE_SETTINGS and CANDIDATE_SETTINGS[key] is not None:
                return float(CANDIDATE_SETTINGS[key])
            if key in _candidate_names():
                return 0.0
            raise ConfigError(f"unknown candidate parameter {name!r}; known: {sorted(_candidate_names())}")
        if name == "damping":
            return float(self.damping)
        if name == "contact.stiffness":
            return float(self.contact.stiffness)
        if name == "contact.eps_v":
            return float(self.contact.eps_v)
        if name.startswith("friction."):
            return float(self.friction[self._friction_key(name)])
        body, _, key = name.partition(".")
        if body in self.bodies and key in self.bodies[body].material:
            return float(self.bodies[body].material[key])
        raise ConfigError(f"unknown parameter {name!r}; known: {self.parameter_names}")

    def set_parameter(self, name: str, value: float) -> None:
        """Set a global parameter and bump ``revision`` (solvers rebuild what depends on it).

        Raises:
            ConfigError: unknown name, or a value that is non-finite or out of its physical range.
        """
        value = float(value)
        if not np.isfinite(value):
            raise ConfigError(f"parameter {name!r} must be finite, got {value}")
        if name.startswith("candidate."):
            trial = dict(self.candidates)
            trial[name.split(".", 1)[1]] = value
            self.candidates = dict(validate_candidate_parameters(trial))
            self.revision += 1
            return
        positive = not (name.endswith("poisson_ratio") or name == "damping" or name.startswith("friction.")
                        or name.endswith("yield_angle"))
        if positive and value <= 0:
            raise ConfigError(f"parameter {name!r} must be > 0, got {value}")
        if name.endswith("poisson_ratio") and not -1.0 < value < 0.5:
            raise ConfigError(f"parameter {name!r} must be in (-1, 0.5), got {value}")
        if (name == "damping" or name.startswith("friction.") or name.endswith("yield_angle")) and value < 0:
            raise ConfigError(f"parameter {name!r} must be >= 0, got {value}")
        if name == "damping":
            self.damping = value
        elif name == "contact.stiffness":
            self.contact.stiffness = value
        elif name == "contact.eps_v":
            self.contact.eps_v = value
        elif name.startswith("friction."):
            self.friction[self._friction_key(name)] = value
        else:
            body, _, key = name.partition(".")
            if body not in self.bodies or key not in self.bodies[body].material:
                raise ConfigError(f"unknown parameter {name!r}; known: {self.parameter_names}")
            self.bodies[body].material[key] = value
        self.revision += 1

    def friction_coefficient(self, a: str, b: str) -> float:
        """Coulomb coefficient between bodies/planes ``a`` and ``b`` (0 when not listed)."""
        return float(self.friction.get(frozenset((a, b)), 0.0))

    # ------------------------------------------------------------------ per-step data
    def state(self) -> State:
        """A fresh initial state: rest (or initial) positions, zero velocity, initial effector poses."""
        x0 = self.x_rest if self.initial_x is None else self.initial_x
        seeded = self.meta.get("initial_hinge_theta_bar", {})
        theta_bar = {
            b.name: np.array(seeded.get(b.name, np.zeros(b.hinges.shape[0])), dtype=float)
            for b in self.bodies.values() if b.hinges is not None
        }
        return State(
            t=0.0,
            x=np.array(x0, dtype=float),
            v=np.zeros_like(x0, dtype=float),
            hinge_theta_bar=theta_bar,
            effector_pose={k: np.array(e.initial_pose, dtype=float) for k, e in self.effectors.items()},
            gripper_opening={k: float(e.initial_opening) for k, e in self.effectors.items()},
            contact_force=np.zeros_like(x0, dtype=float),
        )

    def control(self) -> Control:
        """An empty control (every effector holds its pose)."""
        return Control()


def _candidate_names() -> set[str]:
    """Names of the physics-level candidates (``candidate.<name>`` parameters)."""
    return set(CANDIDATE_NAMES)
