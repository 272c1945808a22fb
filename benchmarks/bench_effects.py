"""Physics effects of the diagnosis benchmark (``python -m benchmarks.diagnose_bench``).

Each effect is a solver hook with its own terms and rules, written independently of the candidate
models of ``sim_core.candidates`` and ``sysid.diagnose`` (SYSID.md "Benchmark protocol"): a
rate-dependent Perzyna-type yield instead of the library's instantaneous return, drag on the sheet
only, a driver-level Stribeck law, a two-term Prony series for the gel instead of the finite-strain
SLS, cohesive-zone point bonds (Needleman's polynomial law with irreversible damage), orthotropic hinges with the grain 15 degrees off x, and,
outside the library, a thickness step (stiffer hinges on the far part of the card). The effect table
and the generation of the labelled set live in :mod:`benchmarks.diagnose_bench`.
"""

from __future__ import annotations

import copy
import math
from typing import Any, Sequence

import numpy as np

from sim_core.candidates.adhesion import adhesion_pairs
from sim_core.energies.base import HessianBlocks, scatter_gradient
from sim_core.energies.hinge_bending.reference import DiscreteShellBending, dihedral_angle

class PhysicsEffect:
    """Base of the hooks: no terms, no state; ``attach`` gives the simulation before the first step."""

    def attach(self, sim: Any) -> None:
        """Remember the simulation (model, initial state)."""
        self.sim = sim

    def terms(self, model: Any, state: Any, x_prev: np.ndarray, dt: float, elastic: Any,
              friction: Any) -> tuple[list, list]:
        """``(contact_like, body_like)`` potentials of a step (the solver's
        :class:`~sim_core.candidates.hook.StepHook` contract)."""
        return self.contact_terms(model, x_prev, friction, state), self.body_terms(model, state, elastic)

    def contact_terms(self, model: Any, x_prev: np.ndarray, friction: Any, state: Any = None) -> list:
        """Extra contact-like potentials of a step (count in the wrench); ``state``: the step's start state."""
        return []

    def body_terms(self, model: Any, state: Any, elastic: Any) -> list:
        """Extra body potentials of a step."""
        return []

    def update_state(self, model: Any, state_in: Any, x: np.ndarray, dt: float, elastic: Any) -> dict:
        """Internal variables after a step, stored in ``State.candidate_state``."""
        return dict(getattr(state_in, "candidate_state", None) or {})


class _Quadratic:
    """``E = 1/2 (x - x0)^T K (x - x0) + g0 . (x - x0)`` over element blocks (a generic helper)."""

    parameter_names: tuple[str, ...] = ()

    def __init__(self, vertices: np.ndarray, blocks: np.ndarray, x0: np.ndarray, g0: np.ndarray | None = None):
        self.vertices, self.blocks, self.x0 = vertices, blocks, x0
        self.g0 = np.zeros_like(x0) if g0 is None else g0

    def _element_dx(self, x: np.ndarray) -> np.ndarray:
        return (x - self.x0)[self.vertices].reshape(self.vertices.shape[0], -1)

    def energy(self, x: np.ndarray) -> float:
        d = self._element_dx(x)
        return float(0.5 * np.einsum("ki,kij,kj->", d, self.blocks, d) + np.sum(self.g0 * (x - self.x0)))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        d = self._element_dx(x)
        return scatter_gradient(x.shape[0], self.vertices, np.einsum("kij,kj->ki", self.blocks, d)) + self.g0

    def hessian(self, x: np.ndarray, projection: str = "clamp"):
        return HessianBlocks(self.vertices, self.blocks)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        raise KeyError(name)


class SheetDrag(PhysicsEffect):
    """Viscous drag ``-c m v`` on the sheet's vertices only (c in 1/s)."""

    def __init__(self, c: float) -> None:
        self.c = float(c)

    def body_terms(self, model, state, elastic) -> list:
        if getattr(self, "_vertices", None) is None:
            self._vertices = model.bodies["sheet"].vertices[:, None]
        k = self.c / self.sim.dt * model.vertex_mass()[self._vertices[:, 0]]
        return [_Quadratic(self._vertices, k[:, None, None] * np.eye(3)[None], state.x.copy())]


class PronyGel(PhysicsEffect):
    """Two-term Prony series on the gel, small-strain linear branches with internal strains.

    Branch i: ``E_i = sum_t V_t g_i [mu |eps - q_i|^2 + lam/2 tr(eps - q_i)^2]`` with ``eps = sym(F) - I``;
    ``q_i <- q_i + (1 - exp(-dt/tau_i)) (eps - q_i)`` after each step.
    """

    def __init__(self, g: Sequence[float], tau: Sequence[float] = (0.05, 0.4)) -> None:
        self.g, self.tau = [float(v) for v in g], [float(v) for v in tau]

    def attach(self, sim) -> None:
        super().attach(sim)
        solid = next(iter(sim.solver.elastic.solids.values()))
        self.solid = solid
        material = sim.model.bodies[solid_name(sim.model)].material
        E, nu = material["youngs_modulus"], material["poisson_ratio"]
        mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
        # d eps_flat / d x_local = sym part of dF/dx: (k, 9, 12)
        M = solid.tet_dvecF_dx
        S = 0.5 * (M + M.reshape(-1, 3, 3, 12).transpose(0, 2, 1, 3).reshape(-1, 9, 12))
        C = 2 * mu * np.eye(9) + lam * np.outer(np.eye(3).ravel(), np.eye(3).ravel())
        self.S = S
        self.K = solid.tet_rest_volume[:, None, None] * np.einsum("kai,ab,kbj->kij", S, C, S)
        self.C = C

    def strain(self, x: np.ndarray) -> np.ndarray:
        F = self.solid.deformation_gradient(x)
        return (0.5 * (F + np.swapaxes(F, 1, 2)) - np.eye(3)).reshape(-1, 9)

    def body_terms(self, model, state, elastic) -> list:
        out = []
        q = (getattr(state, "candidate_state", None) or {}).get("prony", [np.zeros((self.K.shape[0], 9))] * 2)

        x_rest = model.x_rest
        for g, qi in zip(self.g, q):
            # E = 1/2 V (eps - q) C (eps - q) with eps = S (x - x_rest) linear in x: a quadratic about
            # x_rest with the linear term -V S^T C q.
            lin = -np.einsum("k,kai,ab,kb->ki", self.solid.tet_rest_volume, self.S, self.C, qi)
            g0 = scatter_gradient(x_rest.shape[0], self.solid.tets, g * lin)
            out.append(_Quadratic(self.solid.tets, g * self.K, x_rest, g0))
        return out

    def update_state(self, model, state_in, x, dt, elastic) -> dict:
        out = super().update_state(model, state_in, x, dt, elastic)
        q = out.get("prony", [np.zeros((self.K.shape[0], 9))] * 2)
        eps = self.strain(x)
        out["prony"] = [qi + (-math.expm1(-dt / t)) * (eps - qi) for qi, t in zip(q, self.tau)]
        return out


def solid_name(model) -> str:
    """Name of the (first) gel body."""
    return next(b.name for b in model.bodies.values() if b.kind == "solid")


class HingeStiffness(PhysicsEffect):
    """Extra hinge bending ``sum_h c_h k_h (theta - theta_bar)^2`` with a per-hinge factor ``c_h``.

    ``kind="orthotropic"``: ``c_h = a cos(2 (phi_h - 15 deg))`` (grain off the x axis);
    ``kind="thickness_step"``: ``c_h = a`` on hinges whose rest midpoint lies in the far 40 % of the card.
    """

    def __init__(self, a: float, kind: str) -> None:
        self.a, self.kind = float(a), kind

    def attach(self, sim) -> None:
        super().attach(sim)
        model = sim.model
        hinges = sim.solver.elastic.hinges["sheet"]
        self.bending = DiscreteShellBending(hinges, model.x_rest, model.bodies["sheet"].material["bending_stiffness"])
        xr = model.x_rest
        if self.kind == "orthotropic":
            e = xr[hinges[:, 1]] - xr[hinges[:, 0]]
            phi = np.arctan2(e[:, 1], e[:, 0]) - np.deg2rad(15.0)
            c = self.a * np.cos(2 * phi)
        else:
            mid = 0.5 * (xr[hinges[:, 0], 0] + xr[hinges[:, 1], 0])
            x0, x1 = xr[model.bodies["sheet"].vertices, 0].min(), xr[model.bodies["sheet"].vertices, 0].max()
            c = self.a * (mid > x0 + 0.6 * (x1 - x0))
        self.c = c

    def body_terms(self, model, state, elastic) -> list:
        b = copy.copy(self.bending)
        b.hinge_theta_bar = np.asarray(state.hinge_theta_bar["sheet"], dtype=float)
        return [_SignedHinges(b, self.c)]


class _SignedHinges:
    """``sum_h c_h k_h (theta - theta_bar)^2`` with factors ``c_h`` of either sign; blocks ``max(c_h, 0) P(H_h)``."""

    parameter_names: tuple[str, ...] = ()

    def __init__(self, bending, c: np.ndarray) -> None:
        self.b, self.c = bending, c
        self.vertices = bending.hinges

    def energy(self, x):
        d = self.b.theta(x) - self.b.hinge_theta_bar
        return float(np.dot(self.c * self.b.hinge_stiffness, d * d))

    def gradient(self, x):
        return self.b._gradient_with(x, self.c * self.b.hinge_stiffness)

    def hessian(self, x, projection="clamp"):
        h = self.b.hessian(x, projection)
        c = self.c if projection == "none" else np.maximum(self.c, 0.0)
        return HessianBlocks(h.vertices, c[:, None, None] * h.blocks)

    def parameter_gradient(self, x, name):
        raise KeyError(name)


class RatePlasticity(PhysicsEffect):
    """Perzyna-type bending yield: ``theta_bar += f (1 - exp(-dt / t_p)) (|d| - y)_+ sign(d)``, ``d = theta - theta_bar``."""

    def __init__(self, f: float, yield_angle: float = 0.05, t_p: float = 0.05) -> None:
        self.f, self.y, self.t_p = float(f), float(yield_angle), float(t_p)

    def update_state(self, model, state_in, x, dt, elastic) -> dict:
        out = super().update_state(model, state_in, x, dt, elastic)
        hinges = elastic.hinges["sheet"]
        tb = np.asarray(self.sim_state_theta_bar(state_in), dtype=float)
        d = dihedral_angle(x[hinges]) - tb
        tb = tb + self.f * (-math.expm1(-dt / self.t_p)) * np.maximum(np.abs(d) - self.y, 0.0) * np.sign(d)
        out["rest_angles"] = tb
        return out

    @staticmethod
    def sim_state_theta_bar(state):
        return (getattr(state, "candidate_state", None) or {}).get("rest_angles", state.hinge_theta_bar["sheet"])

    def body_terms(self, model, state, elastic) -> list:
        # The rest angles live in candidate_state; the isotropic bending uses state.hinge_theta_bar,
        # so hand the difference over as a correction: E(theta_bar_new) - E(theta_bar_old) is linear
        # in theta and quadratic-free: -2 k (theta_bar_new - theta_bar_old) (theta - ...) -> use the
        # exact difference through a second bending potential pair.
        tb_new = self.sim_state_theta_bar(state)
        tb_old = np.asarray(state.hinge_theta_bar["sheet"], dtype=float)
        if np.allclose(tb_new, tb_old):
            return []
        return [_RestShift(elastic.bending("sheet", tb_new), elastic.bending("sheet", tb_old), elastic.hinges["sheet"])]


class _RestShift:
    """``E_new - E_old`` of the same bending potential with moved rest angles (Hessians cancel)."""

    parameter_names: tuple[str, ...] = ()

    def __init__(self, new, old, hinges: np.ndarray) -> None:
        self.new, self.old, self.hinges = new, old, hinges

    def energy(self, x):
        return self.new.energy(x) - self.old.energy(x)

    def gradient(self, x):
        return self.new.gradient(x) - self.old.gradient(x)

    def hessian(self, x, projection="clamp"):
        return HessianBlocks(self.hinges, np.zeros((self.hinges.shape[0], 12, 12)))

    def parameter_gradient(self, x, name):
        raise KeyError(name)


CRITICAL_OPENING = 1.15e-4
"""Critical opening ``delta_c`` (m) of the bench's cohesive bonds, from the physics of a tacky gel
pad (not fitted to the diagnosis). A bond lumps the interface patch of one coarse gel-face vertex
(about 3.7 mm x 3.6 mm over a 4 mm layer in two element layers), which the mesh cannot resolve down
to the crack tip; its opening at detachment is that of a soft confined layer pulled off a flat
surface, ``delta_c ~ sqrt(G h / E)`` (Kendall 1971; Shull, Mater. Sci. Eng. R 36, 1-45, 2002), with the
bench gel's ``E = 0.3 MPa``, ``h = 4 mm`` and the tack energy ``G ~ 1 J/m^2`` of a weakly dissipative
silicone gel at mm/s: 115 um. (The interface-scale ``G / E ~ 10 um`` was tried first: the 0.2 mm
lift steps then skip the whole cohesive zone in one step and the response is set by the buckling
branch the card takes, not monotone in the magnitude; docs/benchmarks_log.md, 2026-11-22.)"""


class _CohesiveBonds:
    """Point bonds with Needleman's (1987) polynomial cohesive law in the normal direction and
    irreversible damage with unloading to the origin (Ortiz & Pandolfi 1999).

    Per bond ``s = max(0, n . (r - r0))`` (m), ``r = sum_j w_j x_j``, ``u = s / delta_c``; the
    envelope traction is ``T(s) = 27/4 f_max u (1 - u)^2`` for ``u < 1`` and 0 beyond (peak
    ``f_max`` N at ``u = 1/3``, fracture energy ``9/16 f_max delta_c`` J), with potential
    ``psi(s) = 27/4 f_max delta_c (u^2/2 - 2u^3/3 + u^4/4)`` (constant ``9/16 f_max delta_c`` past
    ``delta_c``). Damage is the largest opening reached in earlier steps, ``s_max`` (fixed within a
    step): below it the bond unloads along the secant ``k_d = T(s_max) / s_max`` (energy
    ``k_d s^2 / 2``), beyond it the envelope applies (energy continuous, force continuous). The whole
    law is linear in ``f_max``, so the bond's work and force scale with the magnitude. Shear is
    friction's business; compression the contact barrier's."""

    parameter_names: tuple[str, ...] = ()

    def __init__(self, vertices: np.ndarray, weights: np.ndarray, normal: np.ndarray, r0: np.ndarray,
                 s_max: np.ndarray, f_max: float, delta_c: float = CRITICAL_OPENING):
        """``vertices`` (b, 4) int, ``weights`` (b, 4), ``normal`` (b, 3) unit, ``r0`` (b, 3) m,
        ``s_max`` (b,) m (damage), ``f_max`` N, ``delta_c`` m.

        Raises:
            ValueError: ``f_max`` negative or ``delta_c`` not positive.
        """
        if f_max < 0 or delta_c <= 0:
            raise ValueError(f"cohesive bonds need f_max >= 0 and delta_c > 0 (got {f_max}, {delta_c})")
        self.vertices, self.weights, self.normal, self.r0 = vertices, weights, normal, r0
        self.s_max = np.minimum(np.asarray(s_max, dtype=float), delta_c)
        self.f_max, self.delta_c = float(f_max), float(delta_c)
        u = self.s_max / self.delta_c
        # secant stiffness of the damaged bond (N/m); its limit 27/4 f_max / delta_c when undamaged
        self.k_d = 6.75 * self.f_max / self.delta_c * (1.0 - u) ** 2

    def opening(self, x: np.ndarray) -> np.ndarray:
        """Normal opening ``s`` of every bond in m, shape ``(b,)``."""
        r = np.einsum("kj,kjd->kd", self.weights, x[self.vertices])
        return np.maximum(np.einsum("kd,kd->k", self.normal, r - self.r0), 0.0)

    def _envelope(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Envelope potential (J), traction (N) and its slope (N/m) at openings ``s`` (m)."""
        u = np.minimum(s / self.delta_c, 1.0)
        c = 6.75 * self.f_max
        psi = c * self.delta_c * (u * u / 2 - 2 * u ** 3 / 3 + u ** 4 / 4)
        return psi, c * u * (1 - u) ** 2, c / self.delta_c * (1 - u) * (1 - 3 * u)

    def _law(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Damaged-bond potential (J), force (N) and stiffness (N/m) at openings ``s``, shape ``(b,)``."""
        psi, t, k = self._envelope(s)
        psi0, _, _ = self._envelope(self.s_max)
        below = s <= self.s_max
        energy = np.where(below, 0.5 * self.k_d * s * s, 0.5 * self.k_d * self.s_max ** 2 + psi - psi0)
        return energy, np.where(below, self.k_d * s, t), np.where(below, self.k_d, k)

    def energy(self, x: np.ndarray) -> float:
        """Bond energy in J."""
        return float(np.sum(self._law(self.opening(x))[0]))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``: ``T(s) w_j n`` (the bond pulls the gel vertex back)."""
        f = self._law(self.opening(x))[1]
        return scatter_gradient(x.shape[0], self.vertices, f[:, None, None] * self.weights[:, :, None] * self.normal[:, None, :])

    def hessian(self, x: np.ndarray, projection: str = "clamp"):
        """Blocks ``k(s) (w w^T) (x) n n^T`` of the open bonds, shape ``(b, 12, 12)``; ``k`` is the
        traction's slope, negative on the softening branch: ``"clamp"`` sets it to 0 there (PSD),
        ``"abs"`` flips it, ``"none"`` keeps it (exact Hessian).

        Raises:
            ValueError: unknown ``projection``.
        """
        if projection not in ("none", "clamp", "abs"):
            raise ValueError(f"unknown PSD projection {projection!r}; use 'none', 'clamp' or 'abs'")
        s = self.opening(x)
        k = np.where(s > 0, self._law(s)[2], 0.0)
        k = np.maximum(k, 0.0) if projection == "clamp" else (np.abs(k) if projection == "abs" else k)
        wn = (self.weights[:, :, None] * self.normal[:, None, :]).reshape(len(self.vertices), 12)
        return HessianBlocks(self.vertices, k[:, None, None] * wn[:, :, None] * wn[:, None, :])

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """No identifiable parameters (a bench effect).

        Raises:
            KeyError: always.
        """
        raise KeyError(name)


class BondAdhesion(PhysicsEffect):
    """Point bonds of a tacky gel with a cohesive-zone law: a gel contact-face vertex within the
    contact offset of the sheet bonds to the sheet point below it; the bond resists only opening along
    the sheet normal with Needleman's polynomial traction-separation law (peak ``strength`` N at a
    third of :data:`CRITICAL_OPENING`, zero beyond it) and irreversible damage (the largest opening of
    the earlier steps; unloading to the origin), see :class:`_CohesiveBonds`. A bond whose opening
    reached the critical opening has failed: it is dropped, and its vertex does not bond again while it
    stays within the contact offset (no re-healing in contact), but it re-adheres on its next contact
    once it has left the sheet (a tacky gel sticks on every touch). Shear is left to friction, so the
    bonds survive the slides and act at lift-off (the candidate model is a different law: a lagged
    tensile traction, :mod:`sim_core.candidates.adhesion`).

    State (``State.candidate_state``): ``bonds`` gel vertex -> (sheet triangle vertices, barycentric
    weights, gap at formation (m, (3,)), unit normal from the sheet towards the gel vertex, damage
    ``s_max`` m); ``broken`` the gel vertices whose bond failed and that have not yet left contact."""

    def __init__(self, strength: float, delta_c: float = CRITICAL_OPENING) -> None:
        """``strength``: peak traction per bond in N; ``delta_c``: critical opening in m."""
        self.strength, self.delta_c = float(strength), float(delta_c)

    def _bonds(self, state) -> dict:
        return (getattr(state, "candidate_state", None) or {}).get("bonds", {})

    def _terms(self, bonds: dict) -> _CohesiveBonds:
        v = np.array([[g, *bond[0]] for g, bond in bonds.items()], dtype=np.int64)
        w = np.array([[1.0, *(-np.asarray(bond[1]))] for bond in bonds.values()])
        r0 = np.array([bond[2] for bond in bonds.values()])
        n = np.array([bond[3] for bond in bonds.values()])
        s_max = np.array([bond[4] if len(bond) > 4 else 0.0 for bond in bonds.values()])
        return _CohesiveBonds(v, w, n, r0, s_max, self.strength, self.delta_c)

    def contact_terms(self, model, x_prev, friction, state=None) -> list:
        bonds = self._bonds(state)
        return [self._terms(bonds)] if bonds else []

    def update_state(self, model, state_in, x, dt, elastic) -> dict:
        out = super().update_state(model, state_in, x, dt, elastic)
        bonds = dict(self._bonds(state_in))
        broken = set(out.get("broken", ()))
        if bonds:
            terms = self._terms(bonds)
            s_max = np.maximum(terms.opening(x), terms.s_max)
            for g, s in zip(list(bonds), s_max):
                if s >= self.delta_c:
                    del bonds[g]
                    broken.add(g)
                else:
                    bonds[g] = (*bonds[g][:4], float(s))
        face = np.unique(model.sensors["tactile"].contact_triangles)
        sheet = model.bodies["sheet"].triangles
        v, w, normal = adhesion_pairs(x, face, sheet, model.contact.eps, 1e-12)
        broken &= {int(g) for g in v[:, 0]}  # left contact: may bond again on the next touch
        for row, wr, nr in zip(v, w, normal):
            g = int(row[0])
            if g not in bonds and g not in broken:
                b = -wr[1:]
                gap = x[g] - b @ x[row[1:]]
                n = nr if float(nr @ gap) >= 0.0 else -nr  # from the sheet towards the gel vertex
                bonds[g] = (tuple(int(t) for t in row[1:]), tuple(b), tuple(gap), tuple(n), 0.0)
        out["bonds"], out["broken"] = bonds, tuple(sorted(broken))
        return out


class StribeckFriction(PhysicsEffect):
    """Driver-level stiction: before each step the gel-sheet coefficient is set to
    ``mu_k (1 + a exp(-(v / v_s)^2))`` with v the previous step's gel-over-sheet slip speed."""

    def __init__(self, a: float, v_s: float = 0.01) -> None:
        self.a, self.v_s = float(a), float(v_s)

    def attach(self, sim) -> None:
        super().attach(sim)
        self.key = next(k for k in sim.model.friction if k == frozenset(("sheet", solid_name(sim.model))))
        self.mu_k = sim.model.friction[self.key]
        self.face = np.unique(sim.model.sensors["tactile"].contact_triangles)
        sim.model.friction[self.key] = self.mu_k * (1 + self.a)

    def update_state(self, model, state_in, x, dt, elastic) -> dict:
        out = super().update_state(model, state_in, x, dt, elastic)
        sheet = model.bodies["sheet"].vertices
        v_gel = (x[self.face] - state_in.x[self.face])[:, :2].mean(axis=0) / dt
        near = sheet[np.linalg.norm(x[sheet, None, :2] - x[None, self.face, :2], axis=2).min(axis=1) < 4e-3]
        v_sheet = (x[near] - state_in.x[near])[:, :2].mean(axis=0) / dt if near.size else np.zeros(2)
        v = float(np.linalg.norm(v_gel - v_sheet))
        model.friction[self.key] = self.mu_k * (1 + self.a * math.exp(-((v / self.v_s) ** 2)))
        return out
