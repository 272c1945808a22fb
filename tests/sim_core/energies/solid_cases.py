"""A small gel block, deformed configurations and the derivative checks shared by the solid elements' tests
(Stable Neo-Hookean variants: nodal pressure, Green strain)."""

from __future__ import annotations

import numpy as np

from sim_core.mesh.tet import tet_box
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

E_GEL, NU_GEL = 3e5, 0.45


def gel_block():
    """3 x 2 x 2 cells of an elongated gel-like box (72 tets, 36 vertices)."""
    return tet_box((0.0186, 0.0143, 0.004), (4, 3, 3), (0.0, 0.0, 0.0))


def deformed(x: np.ndarray, seed: int, amplitude: float = 1.5e-4) -> np.ndarray:
    """``x`` plus Gaussian noise of ``amplitude`` m (seeded)."""
    return x + amplitude * np.random.default_rng(seed).standard_normal(x.shape)


def derivative_errors(element, nu: float) -> tuple[float, float, float]:
    """``(gradient, Hessian, asymmetry)`` relative errors of ``element(tets, x, E, nu)`` on :func:`gel_block` against
    central differences of its energy and gradient (the asymmetry relative to the Hessian's largest entry)."""
    mesh = gel_block()
    pot = element(mesh.tets, mesh.x, E_GEL, nu)
    x = deformed(mesh.x, 1)
    H = dense_hessian(pot.hessian(x, "none"), x.shape[0])
    return (relative_error(pot.gradient(x), fd_gradient(pot.energy, x, h=1e-8)),
            relative_error(H, fd_hessian(pot.gradient, x, h=1e-9)), float(np.abs(H - H.T).max() / np.abs(H).max()))


def parameter_gradient_error(element, name: str) -> tuple[float, object, np.ndarray]:
    """``(relative error, potential, x)``: ``element``'s ``parameter_gradient(x, name)`` against a central difference
    of its gradient in ``name`` (relative step 1e-6) on :func:`gel_block`."""
    mesh = gel_block()
    x = deformed(mesh.x, 2)
    base = {"youngs_modulus": E_GEL, "poisson_ratio": NU_GEL}
    step = 1e-6 * base[name]

    def gradient_at(value: float) -> np.ndarray:
        return element(mesh.tets, mesh.x, **{**base, name: value}).gradient(x)

    fd = (gradient_at(base[name] + step) - gradient_at(base[name] - step)) / (2 * step)
    pot = element(mesh.tets, mesh.x, E_GEL, NU_GEL)
    return relative_error(pot.parameter_gradient(x, name), fd), pot, x
