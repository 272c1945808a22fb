"""The clamped card's sheet (StVK membrane + discrete Kirchhoff bending) against plate and beam solutions.

Static equilibria of a strip clamped at x = 0 (vertex columns 0 and 1 fixed: the discrete clamp sits at
x = dx / 2, see ``test_kirchhoff_bending._cantilever_tip_ratio``) under loads on its free edge, found by
minimising the total potential ``membrane + bending - f . x`` with the exact (unprojected) Hessians in a
trust region, so that an unstable equilibrium (the flat strip above its buckling load) is left:

* Euler buckling of a clamped-free column, ``P_cr = pi^2 EI / (4 L^2)`` (Timoshenko & Gere, "Theory of
  Elastic Stability", 2nd ed., sec. 2.1): below it an initial tip deflection is amplified by
  ``1 / (1 - P / P_cr)`` (sec. 1.11, Southwell); above it the post-buckled elastica (sec. 2.7),
  ``sqrt(P / P_cr) = 2 K(k) / pi``, tip deflection ``2 k L / K(k)`` and tip shortening
  ``L (2 - 2 E(k) / K(k))``, ``k = sin(alpha / 2)``, alpha the tip rotation;
* uniaxial stretch ``u = F L / (E t W)`` and the in-plane tip deflection of the deep cantilever
  (Timoshenko beam: ``F L^3 / (3 E I) + F L / (kappa G A)``, ``I = t W^3 / 12``, kappa = 5/6);
* Saint-Venant torsion of a thin strip, twist rate ``T / (G J)``, ``G J = G W t^3 / 3`` (plate theory with
  Kirchhoff's edge forces, Timoshenko & Woinowsky-Krieger, "Theory of Plates and Shells", sec. 11),
  on the grid whose cells share one diagonal (the alternating grid reads twist about 2.8x too stiff:
  :mod:`sim_core.energies.kirchhoff_bending.reference`).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize as so
from scipy.special import ellipe, ellipk

from sim_core.energies.base import assemble_hessian
from sim_core.energies.kirchhoff_bending.reference import KirchhoffBending
from sim_core.energies.membrane.reference import StVKMembrane
from sim_core.mesh.sheet import grid_sheet, sheet_topology

E_CARD, T_CARD = 3.0e9, 3.0e-4  # the reference card: Pa, m


class ClampedStrip:
    """A ``length x width`` strip, ``resolution`` vertices, clamped at x = 0 (columns 0 and 1 fixed)."""

    def __init__(self, length: float, width: float, resolution: tuple[int, int], nu: float,
                 pattern: str = "alternating") -> None:
        self.mesh = grid_sheet((length, width), resolution, (0.0, -0.5 * width, 0.0), pattern)
        self.nx = resolution[0]
        self.ix = np.arange(len(self.mesh.x)) % self.nx
        D = E_CARD * T_CARD**3 / (12.0 * (1.0 - nu**2))
        hinges = sheet_topology(np.asarray(self.mesh.triangles)).hinges
        self.potentials = [StVKMembrane(self.mesh.triangles, self.mesh.x, E_CARD, nu, T_CARD),
                           KirchhoffBending(self.mesh.triangles, hinges, self.mesh.x, D, nu)]
        self.free_dofs = np.repeat(self.ix >= 2, 3)
        self.tip = self.ix == self.nx - 1
        self.free_length = length * (1.0 - 0.5 / (self.nx - 1))  # bending: the clamp at dx / 2
        self.stretched_length = length * (1.0 - 1.0 / (self.nx - 1))  # in plane: held up to column 1

    def tip_load(self, force) -> np.ndarray:
        """Force ``(3,)`` N spread over the free edge with trapezoidal weights, shape ``(n, 3)``."""
        y = self.mesh.x[self.tip, 1]
        weight = np.where(np.isclose(np.abs(y), np.abs(y).max()), 0.5, 1.0)
        f = np.zeros_like(self.mesh.x)
        f[self.tip] = np.outer(weight / weight.sum(), force)
        return f

    def equilibrium(self, f_ext: np.ndarray, start: np.ndarray) -> np.ndarray:
        """Positions ``(n, 3)`` m minimising the total potential from ``start`` (trust region, exact Hessian)."""
        x_all = self.mesh.x.reshape(-1).copy()

        def positions(q):
            x_all[self.free_dofs] = q
            return x_all.reshape(-1, 3)

        def fun(q):
            x = positions(q)
            return sum(p.energy(x) for p in self.potentials) - float(np.sum(f_ext * x))

        def jac(q):
            x = positions(q)
            return (sum(p.gradient(x) for p in self.potentials) - f_ext).reshape(-1)[self.free_dofs]

        def hess(q):
            x = positions(q)
            H = assemble_hessian([p.hessian(x, "none") for p in self.potentials], x_all.size)
            return H[self.free_dofs][:, self.free_dofs].toarray()

        q = so.minimize(fun, start.reshape(-1)[self.free_dofs], jac=jac, hess=hess, method="trust-exact",
                        options={"gtol": 1e-9, "maxiter": 400}).x
        tolerance = 1e-6 * np.abs(f_ext).max() + 1e-9
        for _ in range(10):  # Newton's steps at the (stable) minimum, to the force tolerance
            g = jac(q)
            if np.abs(g).max() < tolerance:
                break
            q = q - np.linalg.solve(hess(q), g)
        assert np.abs(jac(q)).max() < tolerance, np.abs(jac(q)).max()
        return positions(q).copy()


@pytest.fixture(scope="module")
def column():
    """A narrow strip (beam) with nu = 0, so that EI = D W exactly: 0.1 m x 6 mm, 21 x 3 vertices."""
    strip = ClampedStrip(0.1, 0.006, (21, 3), 0.0)
    EI = E_CARD * T_CARD**3 / 12.0 * 0.006
    return strip, np.pi**2 * EI / (4.0 * strip.free_length**2)


def _bent_column(strip: ClampedStrip, tip_rotation: float) -> np.ndarray:
    """The strip bent without stretch, its slope angle ``alpha sin(pi s / (2 L))`` at arc length s from
    the clamp (0 at the clamp, no moment at the tip): a start near the elastica of tip rotation alpha."""
    s = np.clip(strip.mesh.x[:, 0] - (strip.mesh.x[:, 0].max() - strip.free_length), 0.0, None)
    grid = np.linspace(0.0, strip.free_length, 2001)
    angle = tip_rotation * np.sin(0.5 * np.pi * grid / strip.free_length)
    slope = np.c_[np.cos(angle), np.sin(angle)]
    steps = np.diff(grid)[:, None] * 0.5 * (slope[1:] + slope[:-1])
    path = np.vstack([np.zeros(2), np.cumsum(steps, axis=0)])
    x = strip.mesh.x.copy()
    x[:, 0] += np.interp(s, grid, path[:, 0]) - s
    x[:, 2] = np.interp(s, grid, path[:, 1])
    return x


def test_compressed_column_amplifies_a_lateral_load_by_southwell_below_euler_load(column):
    """A small lateral tip load Q gives w_0 alone; with the compressive tip load P the tip deflection is
    w_0 / (1 - P / P_cr) (exact for the first-mode part, within 2 % for the tip load) at P / P_cr = 0.5
    and 0.8, and the strip stays straight (no buckling) below P_cr."""
    strip, p_cr = column
    q = 1e-3 * p_cr
    w0 = strip.equilibrium(strip.tip_load((0.0, 0.0, q)), strip.mesh.x)[strip.tip, 2].mean()
    for ratio in (0.5, 0.8):
        x = strip.equilibrium(strip.tip_load((-ratio * p_cr, 0.0, q)), strip.mesh.x)
        amplification = x[strip.tip, 2].mean() / w0
        assert amplification == pytest.approx(1.0 / (1.0 - ratio), rel=0.03), (ratio, amplification)


@pytest.mark.parametrize("ratio", [1.1, 1.5])
def test_post_buckled_column_follows_the_elastica(column, ratio):
    """Above P_cr the strip buckles; its tip deflection and shortening are the elastica's within 4 %."""
    strip, p_cr = column
    m = so.brentq(lambda m: 2.0 * ellipk(m) / np.pi - np.sqrt(ratio), 1e-9, 0.999)
    k, L = np.sqrt(m), strip.free_length
    deflection, shortening = 2.0 * k * L / ellipk(m), L * (2.0 - 2.0 * ellipe(m) / ellipk(m))
    start = _bent_column(strip, 2.0 * np.arcsin(k))
    x = strip.equilibrium(strip.tip_load((-ratio * p_cr, 0.0, 0.0)), start)
    tip = x[strip.tip].mean(axis=0) - strip.mesh.x[strip.tip].mean(axis=0)
    assert abs(tip[2]) == pytest.approx(deflection, rel=0.04), (tip, deflection)
    assert -tip[0] == pytest.approx(shortening, rel=0.04), (tip, shortening)


@pytest.fixture(scope="module")
def card():
    """The reference card's plan (0.1 m x 0.06 m, 21 x 13 vertices, nu = 0.3), clamped at x = 0."""
    return ClampedStrip(0.1, 0.06, (21, 13), 0.3)


def test_clamped_card_stretches_as_a_bar(card):
    """Tension F on the free edge: the mean tip displacement is F L / (E t W) within 2 %."""
    force = 10.0
    x = card.equilibrium(card.tip_load((force, 0.0, 0.0)), card.mesh.x)
    u = (x[card.tip, 0] - card.mesh.x[card.tip, 0]).mean()
    assert u == pytest.approx(force * card.stretched_length / (E_CARD * T_CARD * 0.06), rel=0.02), u


def test_clamped_card_sags_under_its_own_weight_between_the_beam_and_the_plate(card):
    """The card (700 kg/m^3, lumped masses) under gravity: the mean tip sag against the uniformly loaded cantilever
    ``q L^4 / (8 B)`` (q the weight per length). A strip of finite width bends between the beam (``B = E t^3 W / 12``,
    free anticlastic curvature) and the plate in cylindrical bending (``B = D W``, ``1 - nu^2`` = 0.91 of the beam's
    sag); measured 0.932 of the beam's, as under a tip load. The reference engine's flex card sags 1.074x the beam's
    (``benchmarks/mujoco_world/strip_answers.py gravity``): 15 % more than this card at the same E, so its card is
    the softer in bending, not the stiffer (docs/benchmarks_log.md, session 57, s57-49lift)."""
    L, W, nu, rho, g = 0.1, 0.06, 0.3, 700.0, 9.81
    nx, ny = 21, 13
    ix, iy = card.ix, np.arange(len(card.mesh.x)) // nx
    weight = (np.where((ix == 0) | (ix == nx - 1), 0.5, 1.0) * np.where((iy == 0) | (iy == ny - 1), 0.5, 1.0)
              * rho * T_CARD * (L / (nx - 1)) * (W / (ny - 1)) * g)
    f = np.zeros_like(card.mesh.x)
    f[:, 2] = -weight
    x = card.equilibrium(f, card.mesh.x)
    sag = -(x[card.tip, 2] - card.mesh.x[card.tip, 2]).mean()
    beam = rho * T_CARD * g * W * card.free_length**4 / (8.0 * E_CARD * T_CARD**3 * W / 12.0)
    assert (1.0 - nu**2) - 0.01 < sag / beam < 0.96, sag / beam


def test_tangential_pull_bends_the_clamped_card_in_its_plane_as_a_timoshenko_beam(card):
    """A tangential pull F along y on the free edge (below the lateral-torsional buckling load): the mean
    in-plane tip deflection is the deep beam's bending + shear deflection within 10 % (L / W = 1.6: the
    clamp also holds the root's Poisson contraction, which the beam solution ignores)."""
    force, W, nu = 0.05, 0.06, 0.3
    x = card.equilibrium(card.tip_load((0.0, force, 0.0)), card.mesh.x)
    v = (x[card.tip, 1] - card.mesh.x[card.tip, 1]).mean()
    L, G = card.stretched_length, E_CARD / (2.0 * (1.0 + nu))
    beam = force * L**3 / (3.0 * E_CARD * T_CARD * W**3 / 12.0) + force * L / (5.0 / 6.0 * G * T_CARD * W)
    assert v == pytest.approx(beam, rel=0.10), (v, beam)
    assert np.abs(x[:, 2]).max() < 1e-9  # stays in its plane


def test_twisted_strip_has_saint_venant_torsion_stiffness():
    """A torque T on the free edge (z forces proportional to y) of a 0.1 x 0.06 m strip on the regular grid:
    the twist rate over the middle of the strip is T / (G J) within 15 % (the discrete clamp and free
    end hold the warping near both ends)."""
    nu = 0.3
    strip = ClampedStrip(0.1, 0.06, (21, 13), nu, pattern="regular")
    torque = 1e-4  # N m: twist rate about 0.16 rad/m
    y = strip.mesh.x[:, 1]
    f = np.zeros_like(strip.mesh.x)
    f[strip.tip, 2] = torque * y[strip.tip] / np.sum(y[strip.tip] ** 2)
    x = strip.equilibrium(f, strip.mesh.x)
    column_x = strip.mesh.x[strip.ix == 0, 0][0] + np.arange(strip.nx) * 0.1 / (strip.nx - 1)
    rotation = np.array([np.polyfit(y[strip.ix == i], x[strip.ix == i, 2], 1)[0] for i in range(strip.nx)])
    middle = slice(6, 15)
    rate = np.polyfit(column_x[middle], rotation[middle], 1)[0]
    GJ = E_CARD / (2.0 * (1.0 + nu)) * 0.06 * T_CARD**3 / 3.0
    assert rate == pytest.approx(torque / GJ, rel=0.15), (rate, torque / GJ)
