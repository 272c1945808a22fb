"""A small gel block and deformed configurations shared by the solid elements' tests (nodal pressure, Green
strain)."""

from __future__ import annotations

import numpy as np

from sim_core.mesh.tet import tet_box

E_GEL, NU_GEL = 3e5, 0.45


def gel_block():
    """3 x 2 x 2 cells of an elongated gel-like box (72 tets, 36 vertices)."""
    return tet_box((0.0186, 0.0143, 0.004), (4, 3, 3), (0.0, 0.0, 0.0))


def deformed(x: np.ndarray, seed: int, amplitude: float = 1.5e-4) -> np.ndarray:
    """``x`` plus Gaussian noise of ``amplitude`` m (seeded)."""
    return x + amplitude * np.random.default_rng(seed).standard_normal(x.shape)
