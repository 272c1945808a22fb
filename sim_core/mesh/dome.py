"""Tetrahedral meshes of a hollow spherical cap (a dome-shaped tactile sensor).

ThinShellLab's dome sensor is a hemispherical gel shell (outer radius 15 mm, inner radius 7.5 mm at
full scale) whose base and inner surface are mounted on the effector; its mesh has 276 nodes. This
module builds a structured mesh of the same kind from a few integers:

* a *ring mesh* of the unit cap: the pole plus ``ring_count`` rings at polar angles
  ``phi_j = cap_angle * j / ring_count`` with ``ring_step * j`` vertices on ring ``j``, triangulated
  ring to ring by merging the two rings in angular order;
* ``layer_count`` copies of that surface at radii evenly spaced from ``inner_radius`` to
  ``outer_radius``;
* every prism between two layers split into 3 tets with the sorted-vertex rule (for a surface
  triangle with vertex ids a < b < c: ``(a, b, c, a')``, ``(b, c, a', b')``, ``(c, a', b', c')``), whose
  diagonal on each quadrilateral face depends only on the face's own vertex ids, so neighbouring
  prisms share faces exactly (a conforming mesh).

Vertex count ``layer_count * (1 + ring_step * ring_count (ring_count + 1) / 2)``; the default
``ring_step = 3, ring_count = 5, layer_count = 6`` gives ThinShellLab's 276 nodes.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim_core.errors import ConfigError
from sim_core.mesh.tet import TetMesh
from sim_core.mesh.validate import tet_signed_volumes


class DomeMesh(NamedTuple):
    """A hollow spherical-cap tet mesh with its mount vertices.

    Attributes:
        mesh: :class:`~sim_core.mesh.tet.TetMesh`; the cap's axis is +z, the sphere centre at the
            origin, the pole at ``(0, 0, outer_radius)``.
        inner_vertices: vertices of the inner spherical surface, shape ``(s,)``.
        base_vertices: vertices on the rim ring (the base, ``phi = cap_angle``), shape ``(b,)``.
        outer_vertices: vertices of the outer (contact) surface, shape ``(s,)``.
    """

    mesh: TetMesh
    inner_vertices: np.ndarray
    base_vertices: np.ndarray
    outer_vertices: np.ndarray

    @property
    def mount_vertices(self) -> np.ndarray:
        """Inner surface and base together (ThinShellLab drives these with the effector), sorted."""
        return np.union1d(self.inner_vertices, self.base_vertices)


def dome_vertex_count(ring_step: int, ring_count: int, layer_count: int) -> int:
    """Number of vertices of :func:`dome_shell` for the given integers."""
    return layer_count * (1 + ring_step * ring_count * (ring_count + 1) // 2)


def _ring_surface(ring_step: int, ring_count: int, cap_angle: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit-sphere cap points ``(s, 3)``, triangles ``(t, 3)`` (outward, i.e. away from the centre), ring id ``(s,)``."""
    points = [np.array([[0.0, 0.0, 1.0]])]
    ring_id = [np.zeros(1, dtype=np.int64)]
    starts = [0]
    azimuths = [np.zeros(1)]
    count = 1
    for j in range(1, ring_count + 1):
        k = ring_step * j
        phi = cap_angle * j / ring_count
        # stagger successive rings by half a spacing so the merge below produces no slivers
        az = 2.0 * np.pi * (np.arange(k) + 0.5 * (j % 2)) / k
        points.append(np.stack([np.sin(phi) * np.cos(az), np.sin(phi) * np.sin(az), np.full(k, np.cos(phi))], 1))
        ring_id.append(np.full(k, j, dtype=np.int64))
        starts.append(count)
        azimuths.append(az)
        count += k
    tris: list[tuple[int, int, int]] = []
    for j in range(1, ring_count + 1):
        inner_ids = starts[j - 1] + np.arange(len(azimuths[j - 1]))
        outer_ids = starts[j] + np.arange(len(azimuths[j]))
        if j == 1:
            for i in range(len(outer_ids)):
                tris.append((0, int(outer_ids[i]), int(outer_ids[(i + 1) % len(outer_ids)])))
            continue
        a_in, a_out = azimuths[j - 1], azimuths[j]
        n_in, n_out = len(a_in), len(a_out)
        # merge the two rings in angular order: each triangle advances one ring by one vertex
        i_in = i_out = 0
        while i_in < n_in or i_out < n_out:
            next_in = a_in[(i_in + 1) % n_in] + 2 * np.pi * ((i_in + 1) // n_in)
            next_out = a_out[(i_out + 1) % n_out] + 2 * np.pi * ((i_out + 1) // n_out)
            p_in, p_out = int(inner_ids[i_in % n_in]), int(outer_ids[i_out % n_out])
            if i_out < n_out and (i_in >= n_in or next_out <= next_in):
                tris.append((p_in, p_out, int(outer_ids[(i_out + 1) % n_out])))
                i_out += 1
            else:
                tris.append((p_in, p_out, int(inner_ids[(i_in + 1) % n_in])))
                i_in += 1
    return np.concatenate(points), np.asarray(tris, dtype=np.int64), np.concatenate(ring_id)


def dome_shell(
    outer_radius: float,
    inner_radius: float,
    ring_step: int = 3,
    ring_count: int = 5,
    layer_count: int = 6,
    cap_angle: float = 0.5 * np.pi,
) -> DomeMesh:
    """A hollow spherical cap meshed with positively oriented tetrahedra (see the module docstring).

    Args:
        outer_radius: radius of the contact surface in m.
        inner_radius: radius of the mounted inner surface in m, ``0 < inner_radius < outer_radius``.
        ring_step: vertices added per ring (ring ``j`` has ``ring_step * j``), >= 3.
        ring_count: rings from the pole to the rim, >= 1.
        layer_count: spherical layers through the thickness, >= 2.
        cap_angle: polar angle of the rim in rad, in ``(0, pi)`` (``pi / 2``: hemisphere).

    Returns:
        :class:`DomeMesh` with :func:`dome_vertex_count` vertices (vertex of layer ``l`` (0 = inner)
        and surface point ``p`` at index ``l * s + p``) and ``3 (layer_count - 1) t`` tets, ``t`` the
        ring-surface triangle count ``ring_step * ring_count^2``.

    Raises:
        ConfigError: a radius not finite/positive, inner >= outer, or a count out of range.
    """
    ro, ri, cap = float(outer_radius), float(inner_radius), float(cap_angle)
    if not (np.isfinite(ro) and np.isfinite(ri) and 0.0 < ri < ro):
        raise ConfigError(f"dome_shell: need 0 < inner_radius < outer_radius, got {ri}, {ro}")
    if int(ring_step) != ring_step or ring_step < 3:
        raise ConfigError(f"dome_shell: ring_step must be an integer >= 3, got {ring_step}")
    if int(ring_count) != ring_count or ring_count < 1:
        raise ConfigError(f"dome_shell: ring_count must be an integer >= 1, got {ring_count}")
    if int(layer_count) != layer_count or layer_count < 2:
        raise ConfigError(f"dome_shell: layer_count must be an integer >= 2, got {layer_count}")
    if not (np.isfinite(cap) and 0.0 < cap < np.pi):
        raise ConfigError(f"dome_shell: cap_angle must be in (0, pi) rad, got {cap_angle}")
    unit, tris, ring_id = _ring_surface(int(ring_step), int(ring_count), cap)
    s = unit.shape[0]
    radii = np.linspace(ri, ro, int(layer_count))
    x = np.concatenate([r * unit for r in radii])
    sorted_tris = np.sort(tris, axis=1)
    a, b, c = sorted_tris[:, 0], sorted_tris[:, 1], sorted_tris[:, 2]
    tets = []
    for layer in range(int(layer_count) - 1):
        lo, hi = layer * s, (layer + 1) * s
        tets += [
            np.stack([a + lo, b + lo, c + lo, a + hi], 1),
            np.stack([b + lo, c + lo, a + hi, b + hi], 1),
            np.stack([c + lo, a + hi, b + hi, c + hi], 1),
        ]
    tets = np.concatenate(tets).astype(np.int64)
    negative = tet_signed_volumes(x, tets) < 0
    tets[negative] = tets[negative][:, [0, 2, 1, 3]]
    layer_of = np.repeat(np.arange(int(layer_count)), s)
    ring_of = np.tile(ring_id, int(layer_count))
    return DomeMesh(
        mesh=TetMesh(x, tets),
        inner_vertices=np.flatnonzero(layer_of == 0),
        base_vertices=np.flatnonzero(ring_of == int(ring_count)),
        outer_vertices=np.flatnonzero(layer_of == int(layer_count) - 1),
    )
