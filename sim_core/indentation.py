"""Quasi-static indentation of a gel by a rigid indenter: model building and depth sweeps.

A gel (tetrahedral Stable Neo-Hookean solid, fixed on its back face) is pressed by a rigid
indenter: either a triangle surface whose every vertex is driven by one kinematic effector (so it
is a rigid, displacement-controlled body, like the fixed node set of a CalculiX indenter), or an
exact sphere (:class:`RigidSphere`: centre vertex driven by the effector, smooth signed distance,
:mod:`sim_core.energies.sphere_contact.reference`), which avoids the facets of a meshed sphere. The indenter
moves along -z in small increments with a large time step (inertia negligible), and after each
increment the net contact + friction force on the indenter is read from ``State.contact_force``.

Used to validate the gel against Hertz contact (:func:`hertz_force`) and to identify the gel modulus
from measured depth / force pairs (``sysid.indentation_fit``). Geometry helpers build a graded gel
block (fine near the contact, coarse away from it), a triangulated spherical cap, and split a
CalculiX/Abaqus mesh (FEATS, Helmut et al. 2024) into gel and indenter by node sets.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import Delaunay

from sim_core.builder import ModelBuilder
from sim_core.control import Control
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.sheet import TriMesh
from sim_core.mesh.tet import TetMesh, tet_box, tet_boundary_triangles
from sim_core.model import ContactSettings, Model
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig

GEL_BODY = "gel"
INDENTER_BODY = "indenter"
INDENTER_EFFECTOR = "indenter"

_RIGID_SHEET_MATERIAL = {"youngs_modulus": 1.0e9, "poisson_ratio": 0.3, "thickness": 1.0e-3, "density": 0.0}
"""Material of the indenter surface. Every indenter vertex is driven by the effector (Dirichlet),
so these values enter no equation; the sheet body only carries the contact triangles."""


@dataclass(frozen=True)
class RigidSphere:
    """An exact spherical indenter.

    Attributes:
        center: centre in m, shape ``(3,)``.
        radius: radius in m.
    """

    center: np.ndarray
    radius: float

    @property
    def lowest_point(self) -> np.ndarray:
        """The sphere's lowest point (its tip when pressing along -z), m, shape ``(3,)``."""
        return np.asarray(self.center, dtype=float) - np.array([0.0, 0.0, self.radius])


def fit_sphere(points: np.ndarray) -> RigidSphere:
    """Least-squares sphere through surface points (algebraic fit, then the mean radius).

    Solves ``|p|^2 = 2 c . p + (R^2 - |c|^2)`` for ``c`` and the constant in the least-squares
    sense (linear in the unknowns), then ``R`` = mean distance of the points to ``c``.

    Args:
        points: points on (part of) a sphere, m, shape ``(k, 3)``, ``k >= 4``, not coplanar.

    Returns:
        :class:`RigidSphere`.

    Raises:
        MeshError: fewer than 4 points, coplanar points, or points that deviate from the fitted
            sphere by more than 1 % of its radius (not a sphere).
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    if p.shape[0] < 4:
        raise MeshError(f"fit_sphere: need at least 4 points, got {p.shape[0]}")
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    sol, _, rank, _ = np.linalg.lstsq(a, np.sum(p * p, axis=1), rcond=None)
    if rank < 4:
        raise MeshError("fit_sphere: the points are coplanar (no unique sphere)")
    center = sol[:3]
    dist = np.linalg.norm(p - center, axis=1)
    radius = float(dist.mean())
    worst = float(np.max(np.abs(dist - radius)))
    if worst > 0.01 * radius:
        raise MeshError(f"fit_sphere: points deviate {worst:.3g} m from the fitted sphere (R = {radius:.4g} m)")
    return RigidSphere(center, radius)


# ---------------------------------------------------------------------------------- analytic
def hertz_force(depth, radius: float, youngs_modulus: float, poisson_ratio: float) -> np.ndarray:
    """Hertz normal force of a rigid sphere on an elastic half-space.

    ``F = 4/3 E* sqrt(R) d^(3/2)`` with ``E* = E / (1 - nu^2)`` (rigid indenter; Johnson, *Contact
    Mechanics*, 1985, eq. 4.22-4.23). Valid for contact radius ``a = sqrt(R d) << R`` and a body
    large compared with ``a``.

    Args:
        depth: indentation depth(s) d in m (>= 0), scalar or array.
        radius: sphere radius R in m.
        youngs_modulus: E of the half-space in Pa.
        poisson_ratio: nu of the half-space.

    Returns:
        force(s) in N, same shape as ``depth``.
    """
    d = np.clip(np.asarray(depth, dtype=float), 0.0, None)
    e_star = youngs_modulus / (1.0 - poisson_ratio**2)
    return 4.0 / 3.0 * e_star * np.sqrt(radius) * d**1.5


def flat_punch_force(depth, radius: float, youngs_modulus: float, poisson_ratio: float) -> np.ndarray:
    """Normal force of a rigid flat-ended cylindrical punch on an elastic half-space.

    ``F = 2 a E* d`` with ``E* = E / (1 - nu^2)`` (Sneddon 1965, Int. J. Eng. Sci. 3, 47-57;
    Boussinesq's problem, Johnson, *Contact Mechanics*, 1985, eq. 3.38 for the load of a flat punch),
    for a frictionless punch of radius ``a`` on a body large compared with ``a``.

    Args:
        depth: indentation depth(s) d in m (>= 0), scalar or array.
        radius: punch radius a in m.
        youngs_modulus: E in Pa.
        poisson_ratio: nu.

    Returns:
        force(s) in N, same shape as ``depth``.
    """
    d = np.clip(np.asarray(depth, dtype=float), 0.0, None)
    return 2.0 * radius * youngs_modulus / (1.0 - poisson_ratio**2) * d


def bonded_layer_coefficients(poisson_ratio: float) -> tuple[float, float]:
    """Dimitriadis et al.'s constants ``(alpha_0, beta_0)`` of a layer bonded to a rigid base.

    ``alpha_0 = -(1.2876 - 1.4678 nu + 1.3442 nu^2) / (1 - nu)``,
    ``beta_0 = (0.6387 - 1.0277 nu + 1.5164 nu^2) / (1 - nu)`` (Dimitriadis, Horkay, Maresca,
    Kachar & Chadwick, "Determination of elastic moduli of thin layers of soft material using the
    atomic force microscope", Biophys. J. 82, 2798-2810, 2002, eq. 12-13): the leading terms of the
    layer's surface kernel against the half-space's, fitted for 0 <= nu <= 0.5.
    """
    nu = float(poisson_ratio)
    return (-(1.2876 - 1.4678 * nu + 1.3442 * nu**2) / (1.0 - nu),
            (0.6387 - 1.0277 * nu + 1.5164 * nu**2) / (1.0 - nu))


def bonded_layer_sphere_factor(depth, radius: float, thickness: float, poisson_ratio: float) -> np.ndarray:
    """F / F_Hertz of a rigid sphere on an elastic layer of ``thickness`` bonded to a rigid base.

    With ``chi = sqrt(R d) / h`` (Dimitriadis et al. 2002, eq. 11; error < 1 % against the exact
    solution for ``chi <= 1``; see :func:`bonded_layer_coefficients`):
    ``1 - 2 a0/pi chi + 4 a0^2/pi^2 chi^2 - 8/pi^3 (a0^3 + 4 pi^2 b0/15) chi^3
    + 16 a0/pi^4 (a0^3 + 3 pi^2 b0/5) chi^4``.

    Args:
        depth: indentation depth(s) d in m, scalar or array.
        radius: sphere radius R in m.
        thickness: layer thickness h in m.
        poisson_ratio: nu of the layer.

    Returns:
        the factor (>= 1 for a bonded layer), same shape as ``depth``.
    """
    a0, b0 = bonded_layer_coefficients(poisson_ratio)
    chi = np.sqrt(radius * np.clip(np.asarray(depth, dtype=float), 0.0, None)) / thickness
    pi = np.pi
    return (1.0 - 2.0 * a0 / pi * chi + 4.0 * a0**2 / pi**2 * chi**2
            - 8.0 / pi**3 * (a0**3 + 4.0 * pi**2 * b0 / 15.0) * chi**3
            + 16.0 * a0 / pi**4 * (a0**3 + 3.0 * pi**2 * b0 / 5.0) * chi**4)


def bonded_layer_punch_factor(radius: float, thickness: float, poisson_ratio: float) -> float:
    """F / F_Sneddon of a frictionless flat punch of radius ``a`` on a layer bonded to a rigid base,
    to first order in ``a / h``: ``1 - 2 alpha_0 / pi (a / h)``.

    The layer's surface kernel differs from the half-space's, near the axis, by a constant (the
    ``alpha_0`` term of :func:`bonded_layer_coefficients`): a uniform extra compliance under any
    frictionless axisymmetric contact, which gives the first-order term of Dimitriadis et al.'s
    sphere expansion (:func:`bonded_layer_sphere_factor`, ``chi = a / h``) and the same term for a
    punch. Use only for ``a / h`` small enough that the neglected ``(a / h)^2`` term (about
    ``(2 alpha_0 / pi)^2 (a / h)^2``) is within the tolerance.
    """
    a0, _ = bonded_layer_coefficients(poisson_ratio)
    return float(1.0 - 2.0 * a0 / np.pi * radius / thickness)


# ---------------------------------------------------------------------------------- geometry
def graded_axis(extent: float, h_fine: float, fine_extent: float, growth: float) -> np.ndarray:
    """1-D coordinates from 0 to ``extent``: spacing ``h_fine`` up to ``fine_extent``, then geometric.

    Beyond ``fine_extent`` each interval is ``growth`` times the previous one; the last interval is
    merged into the one before when it would be shorter than half of that one, and the last
    coordinate is snapped to ``extent``.

    Args:
        extent: length in m (> 0).
        h_fine: spacing in the fine zone in m (> 0).
        fine_extent: length of the fine zone in m (>= 0, clipped to ``extent``).
        growth: ratio of consecutive intervals outside the fine zone (>= 1).

    Returns:
        increasing coordinates, shape ``(k,)``, ``k >= 2``, first 0 and last ``extent``.

    Raises:
        ConfigError: non-positive extent or spacing, growth below 1.
    """
    if not (extent > 0 and h_fine > 0 and fine_extent >= 0 and growth >= 1):
        raise ConfigError(
            f"graded_axis: need extent > 0, h_fine > 0, fine_extent >= 0, growth >= 1; got "
            f"{extent}, {h_fine}, {fine_extent}, {growth}"
        )
    coords = [0.0]
    h = h_fine
    while coords[-1] < extent - 1e-12 * extent:
        if coords[-1] >= fine_extent - 1e-12 * extent:
            h *= growth
        coords.append(min(coords[-1] + h, extent))
    if len(coords) > 2 and coords[-1] - coords[-2] < 0.5 * (coords[-2] - coords[-3]):
        del coords[-2]
    coords[-1] = extent
    return np.asarray(coords)


def graded_gel_block(
    half_width: float, depth: float, h_fine: float, fine_half_width: float, fine_depth: float, growth: float = 1.3
) -> TetMesh:
    """A gel block ``[-w, w]^2 x [-depth, 0]`` (top face at z = 0) refined around the top centre.

    A structured Kuhn-split box (:func:`sim_core.mesh.tet.tet_box`) whose axes are mapped by
    :func:`graded_axis` (symmetric in x and y about 0, z growing downwards from the top); a
    monotone map of each axis keeps every tet positively oriented.

    Args:
        half_width: w in m.
        depth: block thickness in m.
        h_fine: element size near the contact in m.
        fine_half_width: half width of the uniformly fine zone in x and y, m.
        fine_depth: thickness of the uniformly fine layer under the top face, m.
        growth: interval ratio outside the fine zone.

    Returns:
        :class:`TetMesh`.
    """
    half = graded_axis(half_width, h_fine, fine_half_width, growth)
    xy = np.concatenate([-half[:0:-1], half])
    z = -graded_axis(depth, h_fine, fine_depth, growth)[::-1]
    index = tet_box((len(xy) - 1, len(xy) - 1, len(z) - 1), (len(xy), len(xy), len(z)))
    ijk = np.rint(index.x).astype(np.int64)
    x = np.stack([xy[ijk[:, 0]], xy[ijk[:, 1]], z[ijk[:, 2]]], axis=1)
    return TetMesh(x, index.tets)


def ring_radii(rim: float, outer: float, h_rim: float, fine: float, growth: float) -> np.ndarray:
    """Radii of the node rings of a disc mesh graded towards a rim: spacing ``h_rim`` within ``fine`` of
    ``rim`` on both sides, then geometric (:func:`graded_axis`) inwards to the centre and outwards to
    ``outer``.

    Args:
        rim: radius to resolve (a ring lies on it), m (0 < rim < outer).
        outer: outermost radius, m.
        h_rim: ring spacing at the rim, m.
        fine: half width of the uniformly fine band about the rim, m.
        growth: ratio of consecutive spacings outside the band (>= 1).

    Returns:
        increasing radii, shape ``(k,)``, first 0 (the centre), one equal to ``rim``, last ``outer``.
    """
    if not 0 < rim < outer:
        raise ConfigError(f"ring_radii: need 0 < rim < outer, got {rim}, {outer}")
    inner = rim - graded_axis(rim, h_rim, fine, growth)[::-1]
    outside = rim + graded_axis(outer - rim, h_rim, fine, growth)
    return np.concatenate([inner, outside[1:]])


def ringed_gel_cylinder(
    outer_radius: float, thickness: float, rim: float, h_rim: float, fine: float, growth: float = 1.3,
    aspect: float = 4.0, min_segments: int = 6,
) -> TetMesh:
    """A gel cylinder ``r <= outer_radius``, ``-thickness <= z <= 0`` whose node rings follow a circle.

    A flat punch's contact edge is a circle of radius ``rim`` where the pressure has an inverse
    square-root singularity (Sneddon 1965): a Cartesian grid cannot follow it (the contact set is a
    staircase and its effective radius grows by about half a cell). Here the top face is a triangulation
    of concentric node rings (:func:`ring_radii`: one ring on ``rim``, spacing ``h_rim`` at it, geometric
    away from it), ``ceil(2 pi r / (aspect s))`` nodes on a ring of radial spacing ``s`` (at least
    ``min_segments``; the singular field is axisymmetric, so the tangential spacing may exceed the radial
    one by ``aspect``). The triangulation is Delaunay, which keeps the triangles' angles away from 180
    degrees (rings zipped chord by chord at aspect 8 pressed 15 % harder), so the rim ring's chords need
    not be edges: :func:`punch_face` takes the triangles within the rim. The surface is extruded along -z
    through layers graded from ``h_rim`` at the top (:func:`graded_axis` with the same ``fine`` and
    ``growth``), and each triangular prism is split into 3 tets by the global vertex order (the diagonal
    of a side face joins its lower-index bottom vertex to its higher-index top vertex, so neighbouring
    prisms share their faces' diagonals).

    Args:
        outer_radius: cylinder radius, m.
        thickness: cylinder height, m (the bottom ``z = -thickness`` is the face to clamp).
        rim: radius of the ring to resolve, m.
        h_rim: ring and layer spacing at the rim and the top, m.
        fine: half width of the band about ``rim`` (and depth of the top layer) at spacing ``h_rim``, m.
        growth: spacing ratio outside the band.
        aspect: largest tangential / radial spacing on a ring.
        min_segments: fewest nodes on a ring (the outer rings' tangential resolution; a punch's force at
            20 a against 48: +3.6 % with 6, +0.9 % with 12, +0.4 % with 24).

    Returns:
        :class:`TetMesh` (positively oriented tets).
    """
    radii = ring_radii(rim, outer_radius, h_rim, fine, growth)
    spacing = np.gradient(radii)
    pts = [np.zeros((1, 2))]
    for k in range(1, len(radii)):
        n = max(min_segments, int(np.ceil(2.0 * np.pi * radii[k] / (aspect * spacing[k]))))
        phi = 2.0 * np.pi * (np.arange(n) + 0.5 * (k % 2)) / n
        pts.append(radii[k] * np.stack([np.cos(phi), np.sin(phi)], axis=1))
    xy = np.concatenate(pts)
    tri = np.sort(Delaunay(xy).simplices.astype(np.int64), axis=1)
    e1, e2 = xy[tri[:, 1]] - xy[tri[:, 0]], xy[tri[:, 2]] - xy[tri[:, 0]]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    tri = tri[np.abs(area) > 1e-12 * np.max(np.abs(area))]
    z = -graded_axis(thickness, h_rim, fine, growth)
    m = len(xy)
    x = np.concatenate([np.column_stack([xy, np.full(m, zk)]) for zk in z])
    tets = []
    for layer in range(len(z) - 1):
        i, j, k = (tri + layer * m).T  # i < j < k, layer "layer" at the top
        ip, jp, kp = i + m, j + m, k + m
        tets += [np.stack([i, j, k, kp], 1), np.stack([i, j, jp, kp], 1), np.stack([i, ip, jp, kp], 1)]
    tets = np.concatenate(tets)
    e = x[tets[:, 1:]] - x[tets[:, :1]]
    negative = np.einsum("ij,ij->i", np.cross(e[:, 0], e[:, 1]), e[:, 2]) < 0
    tets[negative] = tets[negative][:, [0, 2, 1, 3]]
    return TetMesh(x, tets)


def _face_triangles(gel: TetMesh, rim: float) -> np.ndarray:
    """The gel's top-face triangles (gel vertex indices, ``(k, 3)``) with every corner within ``rim``."""
    tris = tet_boundary_triangles(gel.tets, gel.x)
    x = np.asarray(gel.x, dtype=float)
    top = np.isclose(x[:, 2], x[:, 2].max(), rtol=0.0, atol=1e-9 * np.ptp(x[:, 2]))
    inside = top & (np.hypot(x[:, 0], x[:, 1]) <= rim * (1.0 + 1e-9))
    face = tris[np.all(inside[tris], axis=1)]
    if face.shape[0] == 0:
        raise MeshError(f"punch_face: no top-face triangle of the gel lies within r = {rim} m")
    return face


def punch_face_vertices(gel: TetMesh, rim: float) -> np.ndarray:
    """Sorted gel vertex indices ``(k,)`` that a :func:`punch_face` of radius ``rim`` touches: the corners of
    the gel's top-face triangles within ``rim`` (a vertex with ``r <= rim`` that is no such triangle's corner
    is not touched)."""
    return np.unique(_face_triangles(gel, rim))


def punch_face(gel: TetMesh, rim: float, clearance: float) -> TriMesh:
    """The face of a rigid flat punch of radius ``rim`` triangulated as the gel's top face under it.

    The gel's top-face triangles (z = the mesh's maximum) whose corners all lie within ``rim`` (the rim
    ring of :func:`ringed_gel_cylinder` included), their corners moved radially out by ``clearance`` and
    put in the plane z = 0, normals down (-z). The face's edges are then parallel to the gel's (the
    contact's edge-edge pairs leave near-parallel pairs out) and no gel edge crosses the face's outline,
    so the contact set is exactly those triangles' vertices (:func:`punch_face_vertices`): the discrete
    punch problem that a linear-elastic solver can state on the same mesh. A face that is not the gel's
    own triangulation (a fan through the same rim vertices) has rim chords that the gel's edges joining
    the rings either side of the rim cross; the edge-edge contact holds those crossings at the face (a
    rigid rim on a piecewise-linear surface), which pulls the next ring down: 10 % more force on a
    ``ringed_gel_cylinder`` at 0.16 a rim spacing (session 51, docs/known_answers.md).

    Args:
        gel: gel mesh with a node ring on ``r = rim`` in its top face (m).
        rim: punch radius, m.
        clearance: radial offset of the face's rim beyond the gel's ring, m (small against the ring
            spacing, larger than the ring's inward displacement under the punch: about 1 % of it).

    Returns:
        :class:`TriMesh` (m).

    Raises:
        MeshError: no top-face triangle within ``rim``.
    """
    face = _face_triangles(gel, rim)
    x = np.asarray(gel.x, dtype=float)
    used, compact = np.unique(face, return_inverse=True)
    tri = compact.reshape(face.shape).astype(np.int64)
    fx = x[used].copy()
    fx[:, :2] *= 1.0 + clearance / rim
    fx[:, 2] = 0.0
    normal_z = np.cross(fx[tri[:, 1]] - fx[tri[:, 0]], fx[tri[:, 2]] - fx[tri[:, 0]])[:, 2]
    tri[normal_z > 0] = tri[normal_z > 0][:, [0, 2, 1]]
    return TriMesh(fx, tri)


def sphere_cap(radius: float, cap_radius: float, h: float) -> TriMesh:
    """Triangulated lower cap of a sphere whose lowest point is the origin.

    Vertices: the centre and rings of radius ``k h`` (``ceil(2 pi k)`` points each) up to
    ``cap_radius``, lifted to ``z = R - sqrt(R^2 - r^2)``; triangles: Delaunay triangulation of the
    planar points (nearly equilateral, edge ~ ``h``), oriented with normals pointing down (-z),
    out of the sphere.

    Args:
        radius: sphere radius R in m.
        cap_radius: planar radius of the cap in m (< R).
        h: target edge length in m.

    Returns:
        :class:`TriMesh`.

    Raises:
        ConfigError: ``cap_radius >= radius`` or non-positive sizes.
    """
    if not (radius > 0 and 0 < cap_radius < radius and h > 0):
        raise ConfigError(f"sphere_cap: need 0 < cap_radius < radius and h > 0, got {radius}, {cap_radius}, {h}")
    rings = max(1, int(np.ceil(cap_radius / h)))
    pts = [np.zeros((1, 2))]
    for k in range(1, rings + 1):
        r = cap_radius * k / rings
        n = int(np.ceil(2.0 * np.pi * r / (cap_radius / rings)))
        phi = 2.0 * np.pi * (np.arange(n) + 0.5 * (k % 2)) / n
        pts.append(np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1))
    xy = np.concatenate(pts)
    tri = Delaunay(xy).simplices.astype(np.int64)
    r2 = np.sum(xy**2, axis=1)
    x = np.column_stack([xy, radius - np.sqrt(radius**2 - r2)])
    normal_z = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])[:, 2]
    tri[normal_z > 0] = tri[normal_z > 0][:, [0, 2, 1]]
    return TriMesh(x, tri)


def split_by_node_sets(mesh: TetMesh, node_sets: dict[str, np.ndarray]) -> dict[str, tuple[TetMesh, np.ndarray]]:
    """Split a multi-body tet mesh into parts whose tets have all corners in one node set.

    Args:
        mesh: the whole mesh.
        node_sets: part name -> vertex indices of ``mesh`` (e.g. from
            :func:`sim_core.mesh.io.load_node_sets` with ``node_ids``).

    Returns:
        part name -> ``(TetMesh of the part, original vertex index of each part vertex (k,))``.

    Raises:
        MeshError: a part with no tet, naming the set.
    """
    out = {}
    for name, nodes in node_sets.items():
        inside = np.zeros(len(mesh.x), dtype=bool)
        inside[np.asarray(nodes, dtype=np.int64)] = True
        tets = mesh.tets[np.all(inside[mesh.tets], axis=1)]
        if tets.shape[0] == 0:
            raise MeshError(f"node set {name!r}: no tetrahedron has all four corners in the set")
        used, compact = np.unique(tets, return_inverse=True)
        out[name] = (TetMesh(mesh.x[used], compact.reshape(tets.shape).astype(np.int64)), used)
    return out


def surface_of(mesh: TetMesh) -> TriMesh:
    """Boundary surface of a tet mesh as a compact :class:`TriMesh` (outward normals)."""
    tris = tet_boundary_triangles(mesh.tets, mesh.x)
    used, compact = np.unique(tris, return_inverse=True)
    return TriMesh(mesh.x[used], compact.reshape(tris.shape).astype(np.int64))


# ---------------------------------------------------------------------------------- model
@dataclass
class IndentationSetup:
    """An indentation model and what a depth sweep needs to know about it.

    Attributes:
        model: the model (bodies ``gel`` and ``indenter``, effector ``indenter``).
        gel_body: name of the gel body.
        indenter_body: name of the indenter body.
        effector: name of the effector driving every indenter vertex.
        tip_vertex: global index of the gel surface vertex under the indenter's lowest point.
        initial_gap: vertical distance from the indenter's lowest vertex to the gel surface below
            it, minus the contact offset eps, at depth 0 (m; 0 = the offset surface just touches).
        solver_config: Newton settings for the sweep.
    """

    model: Model
    gel_body: str
    indenter_body: str
    effector: str
    tip_vertex: int
    initial_gap: float
    solver_config: SolverConfig = field(default_factory=SolverConfig)

    def simulation(self, dt: float = 1.0) -> Simulation:
        """A fresh :class:`Simulation` of this setup (large ``dt``: quasi-static)."""
        return Simulation(self.model, dt=dt, solver_config=self.solver_config)


def build_indentation(
    gel: TetMesh,
    gel_fixed: np.ndarray,
    indenter: TriMesh | RigidSphere,
    youngs_modulus: float,
    poisson_ratio: float,
    contact: ContactSettings,
    friction: float = 0.0,
    gel_density: float = 1000.0,
    indenter_lift: float | None = 0.0,
    solver_config: SolverConfig | None = None,
    indenter_vertices_vs_gel: bool = True,
    gel_element: str = "stable_neohookean",
) -> IndentationSetup:
    """Build a gel + rigid indenter model, no gravity.

    Args:
        gel: gel tet mesh (m).
        gel_fixed: local gel vertex indices (or mask) clamped (the back face).
        indenter: indenter surface (m; rigid: every vertex effector-driven), or an exact
            :class:`RigidSphere` (its centre effector-driven).
        youngs_modulus: gel E in Pa.
        poisson_ratio: gel nu.
        contact: penalty contact settings (stiffness k_c N/m, offset eps m, friction eps_v m/s).
            ``self_contact`` must be False (the indenter surface is a sheet body).
        friction: Coulomb coefficient gel-indenter.
        gel_density: kg/m^3 (irrelevant for quasi-static sweeps with a large dt).
        indenter_lift: z shift applied to the indenter before building, m; ``None``: just enough to
            put the indenter's lowest point at the contact offset above the gel (depth 0 = first
            touch, as in a prescribed-displacement FE model), 0 when it already starts above.
        solver_config: Newton settings (default: PARDISO, max |dx| / dt < 1e-7 m/s, i.e. 0.1 um at
            dt = 1 s, and absolute-value eigenvalue projection, which needs fewer iterations here).
        indenter_vertices_vs_gel: also pair the indenter's vertices with the gel's surface
            triangles (needed when the indenter is coarser than the gel, e.g. a sphere cap whose tip
            is one vertex; a gel surface finer than the indenter is sampled by its own vertices,
            and testing both directions there makes Newton's active set chatter).
        gel_element: the gel's element, one of :data:`sim_core.elastic.SOLID_ELEMENTS`.

    Returns:
        :class:`IndentationSetup`.

    Raises:
        ConfigError: self contact enabled, indenter not above the gel, bad materials.
    """
    if contact.self_contact:
        raise ConfigError("indentation: contact.self_contact must be False (the rigid indenter is a sheet body)")
    # a coarse rigid indenter's vertices (the sphere's tip is one) must test the gel's triangles,
    # unlike a compliant sheet that the gel's denser surface samples
    contact = replace(contact, sheet_vertices_vs_solids=indenter_vertices_vs_gel)
    sphere = isinstance(indenter, RigidSphere)
    ind_x = indenter.lowest_point[None, :] if sphere else np.asarray(indenter.x, dtype=float)
    if indenter_lift is None:
        gel_surface = np.unique(tet_boundary_triangles(gel.tets))
        indenter_lift = max(0.0, -_initial_gap(gel.x, gel_surface, ind_x, contact.eps)[0])
    ind_x = ind_x + np.array([0.0, 0.0, indenter_lift])
    b = ModelBuilder()
    b.add_solid(GEL_BODY, gel, {"youngs_modulus": youngs_modulus, "poisson_ratio": poisson_ratio,
                                "density": gel_density}, fixed=gel_fixed)
    if sphere:
        b.add_sphere(INDENTER_BODY, np.asarray(indenter.center, dtype=float) + [0.0, 0.0, indenter_lift],
                     indenter.radius)
        driven = np.arange(1)
    else:
        b.add_sheet(INDENTER_BODY, TriMesh(ind_x, indenter.triangles), dict(_RIGID_SHEET_MATERIAL))
        driven = np.arange(len(ind_x))
    b.add_effector(INDENTER_EFFECTOR, INDENTER_BODY, driven, [0, 0, 0, 0, 0, 0, 1], max_translation_per_step=1.0)
    if friction > 0:
        b.set_friction(GEL_BODY, INDENTER_BODY, friction)
    model = b.finalize(gravity=(0.0, 0.0, 0.0), contact=contact, meta={"solid_element": gel_element})
    gel_b = model.bodies[GEL_BODY]
    surface = np.unique(gel_b.triangles)
    gap, tip_vertex = _initial_gap(model.x_rest, surface, ind_x, contact.eps)
    if gap < -contact.eps:
        raise ConfigError(f"indentation: the indenter starts {-gap:.3g} m inside the gel surface")
    cfg = solver_config or SolverConfig(tol_velocity=1e-7, max_iterations=100, projection="abs")
    return IndentationSetup(model, GEL_BODY, INDENTER_BODY, INDENTER_EFFECTOR, tip_vertex, gap, cfg)


def _initial_gap(x: np.ndarray, surface: np.ndarray, indenter_x: np.ndarray, eps: float) -> tuple[float, int]:
    """Gap (m) from the indenter's lowest point to the contact offset above the gel surface vertex
    nearest to it (the top vertex right below it), and that vertex's index into ``x``."""
    tip = indenter_x[np.argmin(indenter_x[:, 2])]
    vertex = int(surface[np.argmin(np.sum((x[surface] - tip) ** 2, axis=1))])
    return float(tip[2] - x[vertex, 2] - eps), vertex


# ---------------------------------------------------------------------------------- sweep
@dataclass
class IndentationResult:
    """Forces of a quasi-static depth sweep.

    Attributes:
        depth: prescribed indenter displacement along -z at each record, m, shape ``(k,)``.
        force: normal (+z) force of the gel on the indenter, N, shape ``(k,)`` (>= 0 when pressing).
        force_vector: net contact + friction force on the indenter, N, shape ``(k, 3)``.
        surface_depth: downward displacement of the gel surface vertex under the tip, m, ``(k,)``.
        steps: solver steps taken.
        newton_iterations: total Newton iterations.
        runtime: wall time of the sweep, s.
    """

    depth: np.ndarray
    force: np.ndarray
    force_vector: np.ndarray
    surface_depth: np.ndarray
    steps: int
    newton_iterations: int
    runtime: float


def run_depth_sweep(
    setup: IndentationSetup, depths, max_increment: float, dt: float = 1.0, youngs_modulus: float | None = None
) -> IndentationResult:
    """Press the indenter to each depth in turn (increasing), quasi-statically.

    The indenter's effector pose is lowered by at most ``max_increment`` per step; the state after
    the step that reaches each requested depth is recorded. With ``dt`` large the inertia term
    ``m / dt^2`` is negligible against the gel stiffness, so each step is a static equilibrium.

    Args:
        setup: from :func:`build_indentation`.
        depths: increasing displacements from the initial pose, m, shape ``(k,)``.
        max_increment: largest displacement per step, m.
        dt: time step, s.
        youngs_modulus: if given, set ``gel.youngs_modulus`` (Pa) before the sweep.

    Returns:
        :class:`IndentationResult`.

    Raises:
        ConfigError: depths not increasing / non-positive increment.
        SimulationDivergedError: a step did not converge (from the solver).
    """
    depths = np.asarray(depths, dtype=float).reshape(-1)
    if depths.size == 0 or np.any(np.diff(depths) <= 0) or depths[0] <= 0 or not max_increment > 0:
        raise ConfigError(f"depth sweep: depths must be positive and increasing and max_increment > 0, got "
                          f"{depths.tolist()}, {max_increment}")
    t0 = time.perf_counter()
    if youngs_modulus is not None:
        setup.model.set_parameter(f"{setup.gel_body}.youngs_modulus", youngs_modulus)
    sim = setup.simulation(dt)
    ind = setup.model.bodies[setup.indenter_body]
    z_tip0 = sim.state.x[setup.tip_vertex, 2]
    pose0 = sim.state.effector_pose[setup.effector].copy()
    control = Control()
    forces, surf = [], []
    steps = iterations = 0
    current = 0.0
    for target in depths:
        n = int(np.ceil((target - current) / max_increment - 1e-9))
        for i in range(1, n + 1):
            pose = pose0.copy()
            pose[2] -= current + (target - current) * i / n
            control.effector_pose_target[setup.effector] = pose
            info = sim.step(control)
            steps += 1
            iterations += info.iterations
        current = target
        forces.append(sim.state.contact_force[ind.vertex_start : ind.vertex_stop].sum(axis=0))
        surf.append(z_tip0 - sim.state.x[setup.tip_vertex, 2])
    fv = np.asarray(forces)
    return IndentationResult(depths, fv[:, 2].copy(), fv, np.asarray(surf), steps, iterations,
                             time.perf_counter() - t0)


# ---------------------------------------------------------------------------------- slide
@dataclass
class SlideResult:
    """Forces of a quasi-static press-then-slide at constant depth.

    Attributes:
        depth: prescribed indenter displacement along -z held during the slide, m.
        pressed_force: net contact + friction force on the indenter at the end of the press, N, ``(3,)``.
        displacement: tangential displacement of the indenter from the pressed pose along
            ``direction``, m, shape ``(k,)``.
        force_vector: net contact + friction force on the indenter after each slide step, N,
            shape ``(k, 3)`` (``[:, 2]`` is the normal force, +z).
        direction: unit slide direction in the plane, shape ``(2,)``.
        steps: solver steps taken (press and slide).
        newton_iterations: total Newton iterations.
        runtime: wall time, s.
    """

    depth: float
    pressed_force: np.ndarray
    displacement: np.ndarray
    force_vector: np.ndarray
    direction: np.ndarray
    steps: int
    newton_iterations: int
    runtime: float

    @property
    def tangential_force(self) -> np.ndarray:
        """Force of the gel on the indenter along ``-direction`` (resisting the slide), N, ``(k,)``."""
        return -self.force_vector[:, :2] @ self.direction


def run_slide(
    setup: IndentationSetup, depth: float, displacements, press_increment: float, dt: float = 1.0,
    direction=(1.0, 0.0),
) -> SlideResult:
    """Press the indenter to ``depth``, then move it tangentially at that depth, quasi-statically.

    The press lowers the effector pose by at most ``press_increment`` per step (as
    :func:`run_depth_sweep`); then each step moves it to the next of ``displacements`` along
    ``direction`` in the plane, z held. With ``dt`` large and the friction's ``eps_v dt`` small
    against the slide increments, each step is a static equilibrium of the lagged Coulomb friction
    of :mod:`sim_core.energies.friction.reference`.

    Args:
        setup: from :func:`build_indentation` (with ``friction`` > 0 for a frictional slide).
        depth: indentation depth held during the slide, m (> 0).
        displacements: increasing tangential displacements from the pressed pose, m, shape ``(k,)``.
        press_increment: largest depth increment per press step, m (> 0).
        dt: time step, s.
        direction: slide direction in the plane (normalised here), shape ``(2,)``.

    Returns:
        :class:`SlideResult`.

    Raises:
        ConfigError: non-positive depth or increment, displacements not increasing from > 0, a zero
            direction.
    """
    steps_to = np.asarray(displacements, dtype=float).reshape(-1)
    direction = np.asarray(direction, dtype=float).reshape(2)
    norm = float(np.linalg.norm(direction))
    if not (depth > 0 and press_increment > 0 and steps_to.size and steps_to[0] > 0
            and np.all(np.diff(steps_to) > 0) and norm > 0):
        raise ConfigError(f"slide: need depth > 0, press_increment > 0, displacements positive and increasing and "
                          f"a non-zero direction; got {depth}, {press_increment}, {steps_to.tolist()}, "
                          f"{direction.tolist()}")
    direction = direction / norm
    t0 = time.perf_counter()
    sim = setup.simulation(dt)
    ind = setup.model.bodies[setup.indenter_body]
    pose0 = sim.state.effector_pose[setup.effector].copy()
    control = Control()
    steps = iterations = 0

    def step_to(z: float, s: float) -> np.ndarray:
        nonlocal steps, iterations
        pose = pose0.copy()
        pose[2] -= z
        pose[:2] += s * direction
        control.effector_pose_target[setup.effector] = pose
        info = sim.step(control)
        steps += 1
        iterations += info.iterations
        return sim.state.contact_force[ind.vertex_start : ind.vertex_stop].sum(axis=0)

    n_press = int(np.ceil(depth / press_increment - 1e-9))
    for i in range(1, n_press + 1):
        pressed = step_to(depth * i / n_press, 0.0)
    pressed = step_to(depth, 0.0)  # a second step at rest: the friction's lagged state settles
    forces = np.array([step_to(depth, s) for s in steps_to])
    return SlideResult(float(depth), pressed, steps_to, forces, direction, steps, iterations,
                       time.perf_counter() - t0)
