"""Small sheet meshes and deformed configurations shared by the membrane and bending tests."""

from __future__ import annotations

import numpy as np

from sim_core.mesh.sheet import TriMesh, grid_sheet

SHEET_SIZE = (0.3, 0.2)
SHEET_RESOLUTION = (4, 3)  # dx = dy = 0.1 m
FOLD_ANGLE = 2.0  # rad


def small_sheet(pattern: str = "alternating") -> TriMesh:
    """The 4 x 3 vertex grid of 0.3 m x 0.2 m in the plane z = 0 (normals +z)."""
    return grid_sheet(SHEET_SIZE, SHEET_RESOLUTION, (0.0, 0.0, 0.0), pattern)


def folded_sheet(mesh: TriMesh, angle_left: float = FOLD_ANGLE, angle_right: float = -FOLD_ANGLE) -> np.ndarray:
    """Fold the grid about the lines x = 0.1 and x = 0.2 (rigidly, no stretch).

    The column ix = 0 is rotated about the line x = 0.1 so that it rises towards +z (the normal
    side) for a positive angle; the column ix = 3 about x = 0.2 likewise. Hinges on the two fold
    lines then have dihedral angles ``angle_left`` and ``angle_right``.
    """
    x = mesh.x.copy()
    left = x[:, 0] < 0.05
    right = x[:, 0] > 0.25
    for mask, pivot, angle, direction in ((left, 0.1, angle_left, -1.0), (right, 0.2, angle_right, 1.0)):
        r = np.abs(x[mask, 0] - pivot)
        x[mask, 0] = pivot + direction * r * np.cos(angle)
        x[mask, 2] = r * np.sin(angle)
    return x


def deformed_configurations(mesh: TriMesh, seed: int = 0) -> dict[str, np.ndarray]:
    """Random perturbations of ~20 % of dx of the flat sheet and of the folded sheet (theta ~ +-2 rad)."""
    rng = np.random.default_rng(seed)
    dx = SHEET_SIZE[0] / (SHEET_RESOLUTION[0] - 1)
    return {
        "perturbed": mesh.x + 0.2 * dx * rng.standard_normal(mesh.x.shape),
        "folded": folded_sheet(mesh) + 0.05 * dx * rng.standard_normal(mesh.x.shape),
    }


def random_rigid_motion(x: np.ndarray, seed: int = 1) -> np.ndarray:
    """``R x + t`` with a random proper rotation R and translation t."""
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return x @ q.T + rng.standard_normal(3)
