"""ModelBuilder: assemble bodies, planes, effectors and friction into one :class:`Model`.

Usage (Newton-style): ``b = ModelBuilder(); b.add_sheet(...); b.add_solid(...); model = b.finalize()``.
Every body is appended to one global vertex array; indices passed to the builder are local to
the body being added.
"""

from __future__ import annotations

import numpy as np

from sim_core.errors import ConfigError
from sim_core.mesh.sheet import TriMesh, sheet_topology
from sim_core.mesh.tet import TetMesh, tet_boundary_triangles
from sim_core.mesh.validate import validate_tets, validate_triangles, validate_vertices
from sim_core.model import SHEET_PARAMETERS, SOLID_PARAMETERS, Body, ContactSettings, Effector, Model, Plane
from sim_core.transforms import inverse_transform_points, quat_normalize


def unique_edges(triangles: np.ndarray) -> np.ndarray:
    """Unique undirected edges ``(e, 2)`` (sorted pairs) of triangles ``(t, 3)``."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    e = np.sort(e, axis=1)
    return np.unique(e, axis=0)


class ModelBuilder:
    """Collects bodies and boundaries; :meth:`finalize` produces the :class:`Model`."""

    def __init__(self) -> None:
        self._x: list[np.ndarray] = []
        self._fixed: list[np.ndarray] = []
        self._bodies: dict[str, Body] = {}
        self._planes: dict[str, Plane] = {}
        self._effectors: dict[str, Effector] = {}
        self._friction: dict[frozenset, float] = {}
        self._count = 0

    def _check_name(self, name: str) -> None:
        if name in self._bodies or name in self._planes:
            raise ConfigError(f"duplicate body/plane name {name!r}")

    def _fixed_mask(self, n: int, fixed, where: str) -> np.ndarray:
        mask = np.zeros(n, dtype=bool)
        if fixed is not None:
            idx = np.asarray(fixed)
            if idx.dtype == bool:
                if idx.shape != (n,):
                    raise ConfigError(f"{where}: fixed mask has shape {idx.shape}, expected ({n},)")
                mask = idx.copy()
            else:
                if idx.size and (idx.min() < 0 or idx.max() >= n):
                    raise ConfigError(f"{where}: fixed vertex index out of range [0, {n})")
                mask[idx] = True
        return mask

    def add_sheet(
        self, name: str, mesh: TriMesh, material: dict, fixed=None, grid_shape: tuple[int, int] | None = None
    ) -> Body:
        """Add a thin shell.

        Args:
            name: body name.
            mesh: triangle mesh (m).
            material: ``youngs_modulus`` (Pa), ``poisson_ratio``, ``thickness`` (m),
                ``bending_stiffness`` (N m; D = E t^3 / (12 (1 - nu^2)) when omitted), ``density``
                (kg/m^3), optional ``yield_angle`` (rad; inf = elastic).
            fixed: local vertex indices or a boolean mask of clamped vertices.
            grid_shape: ``(nx, ny)`` for grid sheets.

        Raises:
            ConfigError / MeshError: missing material keys, bad mesh.
        """
        self._check_name(name)
        where = f"sheet {name!r}"
        validate_vertices(mesh.x, where)
        validate_triangles(mesh.x, mesh.triangles, where)
        mat = dict(material)
        if "bending_stiffness" not in mat and {"youngs_modulus", "poisson_ratio", "thickness"} <= mat.keys():
            E, nu, t = mat["youngs_modulus"], mat["poisson_ratio"], mat["thickness"]
            mat["bending_stiffness"] = E * t**3 / (12.0 * (1.0 - nu**2))
        mat.setdefault("yield_angle", float("inf"))
        missing = [k for k in SHEET_PARAMETERS if k not in mat]
        unknown = [k for k in mat if k not in SHEET_PARAMETERS]
        if missing or unknown:
            raise ConfigError(f"{where}: material missing {missing} / unknown {unknown}")
        off = self._count
        tris = np.asarray(mesh.triangles, dtype=np.int64) + off
        topo = sheet_topology(np.asarray(mesh.triangles, dtype=np.int64))
        body = Body(
            name=name, kind="sheet", vertex_start=off, vertex_stop=off + len(mesh.x), triangles=tris,
            edges=np.asarray(topo.edges, dtype=np.int64) + off, hinges=np.asarray(topo.hinges, dtype=np.int64) + off,
            material={k: float(v) for k, v in mat.items()}, grid_shape=grid_shape,
        )
        self._append(body, mesh.x, self._fixed_mask(len(mesh.x), fixed, where))
        return body

    def add_solid(self, name: str, mesh: TetMesh, material: dict | None, fixed=None, frozen: bool = False) -> Body:
        """Add a tetrahedral elastomer (Stable Neo-Hookean) or a frozen obstacle.

        Args:
            name: body name.
            mesh: tetrahedral mesh (m), positive volumes.
            material: ``youngs_modulus`` (Pa), ``poisson_ratio``, ``density`` (kg/m^3); may be None
                when ``frozen``.
            fixed: local vertex indices or mask held fixed.
            frozen: all vertices fixed (a rigid obstacle such as ThinShellLab's table box).
        """
        self._check_name(name)
        where = f"solid {name!r}"
        validate_vertices(mesh.x, where)
        validate_tets(mesh.x, mesh.tets, where)
        mat = {k: float(v) for k, v in (material or {}).items()}
        if not frozen:
            missing = [k for k in SOLID_PARAMETERS if k not in mat]
            unknown = [k for k in mat if k not in SOLID_PARAMETERS]
            if missing or unknown:
                raise ConfigError(f"{where}: material missing {missing} / unknown {unknown}")
        off = self._count
        tets = np.asarray(mesh.tets, dtype=np.int64)
        tris = np.asarray(tet_boundary_triangles(tets, mesh.x), dtype=np.int64)
        body = Body(
            name=name, kind="frozen" if frozen else "solid", vertex_start=off, vertex_stop=off + len(mesh.x),
            triangles=tris + off, edges=unique_edges(tris) + off, tets=tets + off, material=mat,
        )
        mask = np.ones(len(mesh.x), dtype=bool) if frozen else self._fixed_mask(len(mesh.x), fixed, where)
        self._append(body, mesh.x, mask)
        return body

    def add_sphere(self, name: str, center, radius: float) -> Body:
        """Add a rigid sphere (e.g. a spherical indenter), represented exactly by its centre.

        The body has one vertex, the centre, always kinematic: fixed, or moved by an effector
        (:meth:`add_effector` with ``local_vertices=[0]``). Other bodies' surface vertices touch it
        through :class:`sim_core.energies.sphere_contact.reference.SphereContact` (smooth signed distance,
        no facets); the contact force on the sphere is the force on its centre vertex.

        Args:
            name: body name.
            center: centre position in m, shape ``(3,)``.
            radius: radius R in m (> 0).

        Raises:
            ConfigError: duplicate name, non-finite centre, non-positive radius.
        """
        self._check_name(name)
        c = np.asarray(center, dtype=float)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ConfigError(f"sphere {name!r}: center must be 3 finite numbers, got {center}")
        if not (np.isfinite(radius) and radius > 0):
            raise ConfigError(f"sphere {name!r}: radius must be finite and > 0 (m), got {radius}")
        off = self._count
        body = Body(
            name=name, kind="sphere", vertex_start=off, vertex_stop=off + 1, triangles=np.zeros((0, 3), np.int64),
            edges=np.zeros((0, 2), np.int64), material={"radius": float(radius)},
        )
        self._append(body, c[None, :], np.ones(1, dtype=bool))
        return body

    def _append(self, body: Body, x: np.ndarray, fixed: np.ndarray) -> None:
        self._bodies[body.name] = body
        self._x.append(np.asarray(x, dtype=float))
        self._fixed.append(fixed)
        self._count += len(x)

    def add_plane(self, name: str, normal, offset: float) -> Plane:
        """Add a rigid half-space ``n . x >= offset`` (``normal`` is normalised)."""
        self._check_name(name)
        n = np.asarray(normal, dtype=float)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) == 0:
            raise ConfigError(f"plane {name!r}: normal must be a non-zero 3-vector, got {normal}")
        plane = Plane(name, n / np.linalg.norm(n), float(offset))
        self._planes[name] = plane
        return plane

    def add_effector(
        self,
        name: str,
        body: str,
        local_vertices,
        initial_pose,
        max_translation_per_step: float = 1e-3,
        max_rotation_per_step: float = 0.02,
        finger_sign=None,
        finger_axis=(1.0, 0.0, 0.0),
        initial_opening: float = 0.0,
    ) -> Effector:
        """Drive vertices of ``body`` rigidly by an SE(3) frame with pose ``initial_pose`` now.

        The driven vertices' current positions define their effector-frame coordinates.

        Raises:
            ConfigError: unknown body, bad pose, non-positive limits.
        """
        if name in self._effectors:
            raise ConfigError(f"duplicate effector {name!r}")
        if body not in self._bodies:
            raise ConfigError(f"effector {name!r}: unknown body {body!r}")
        if max_translation_per_step <= 0 or max_rotation_per_step <= 0:
            raise ConfigError(f"effector {name!r}: per-step limits must be > 0")
        pose = np.asarray(initial_pose, dtype=float)
        if pose.shape != (7,) or not np.all(np.isfinite(pose)):
            raise ConfigError(f"effector {name!r}: initial_pose must be 7 finite numbers")
        pose[3:] = quat_normalize(pose[3:], f"effector {name!r} initial_pose")
        b = self._bodies[body]
        idx = b.vertex_start + np.asarray(local_vertices, dtype=np.int64)
        x_all = np.concatenate(self._x)
        local = inverse_transform_points(pose, x_all[idx])
        eff = Effector(
            name=name, vertices=idx, local_points=local, initial_pose=pose,
            max_translation_per_step=float(max_translation_per_step), max_rotation_per_step=float(max_rotation_per_step),
            finger_sign=None if finger_sign is None else np.asarray(finger_sign, dtype=float),
            finger_axis=np.asarray(finger_axis, dtype=float), initial_opening=float(initial_opening),
        )
        self._effectors[name] = eff
        return eff

    def set_friction(self, a: str, b: str, mu: float) -> None:
        """Coulomb coefficient between bodies/planes ``a`` and ``b`` (>= 0)."""
        for n in (a, b):
            if n not in self._bodies and n not in self._planes:
                raise ConfigError(f"friction: unknown body/plane {n!r}")
        if not np.isfinite(mu) or mu < 0:
            raise ConfigError(f"friction {a}-{b}: coefficient must be >= 0, got {mu}")
        self._friction[frozenset((a, b))] = float(mu)

    def finalize(
        self, gravity=(0.0, 0.0, -9.81), contact: ContactSettings | None = None, damping: float = 0.0, meta=None
    ) -> Model:
        """Produce the :class:`Model`."""
        if not self._bodies:
            raise ConfigError("model has no bodies")
        x = np.concatenate(self._x)
        fixed = np.concatenate(self._fixed)
        return Model(
            x_rest=x, vertex_fixed=fixed, bodies=dict(self._bodies), effectors=dict(self._effectors),
            planes=dict(self._planes), gravity=np.asarray(gravity, dtype=float), contact=contact or ContactSettings(),
            friction=dict(self._friction), damping=float(damping), meta=dict(meta or {}),
        )
