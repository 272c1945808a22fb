"""Central finite-difference checks shared by the potential tests."""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, assemble_hessian


def fd_gradient(energy, x: np.ndarray, h: float = 1e-7) -> np.ndarray:
    """Central-difference gradient of ``energy(x)``, shape of ``x``."""
    g = np.zeros_like(x)
    flat = x.reshape(-1)
    gf = g.reshape(-1)
    for i in range(flat.size):
        xp = flat.copy()
        xm = flat.copy()
        xp[i] += h
        xm[i] -= h
        gf[i] = (energy(xp.reshape(x.shape)) - energy(xm.reshape(x.shape))) / (2 * h)
    return g


def fd_hessian(gradient, x: np.ndarray, h: float = 1e-7) -> np.ndarray:
    """Central-difference Hessian (dense, ``(3n, 3n)``) from ``gradient(x)``."""
    n = x.size
    H = np.zeros((n, n))
    flat = x.reshape(-1)
    for i in range(n):
        xp = flat.copy()
        xm = flat.copy()
        xp[i] += h
        xm[i] -= h
        H[:, i] = (gradient(xp.reshape(x.shape)).reshape(-1) - gradient(xm.reshape(x.shape)).reshape(-1)) / (2 * h)
    return 0.5 * (H + H.T)


def dense_hessian(blocks: HessianBlocks, vertex_count: int) -> np.ndarray:
    """Assembled Hessian as a dense array (test sizes only)."""
    return assemble_hessian([blocks], 3 * vertex_count).toarray()


def relative_error(a: np.ndarray, b: np.ndarray) -> float:
    """max|a - b| / max(max|b|, tiny)."""
    scale = max(float(np.max(np.abs(b))), 1e-300)
    return float(np.max(np.abs(a - b))) / scale
