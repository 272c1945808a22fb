"""Differentiable rollouts: the linearisation of one implicit step and the reverse (adjoint) pass.

Each step solves ``x^{n+1} = argmin_x E(x; x^n, v^n, theta_bar^n, u^n, p)`` with Dirichlet vertices
(static clamps hold ``x^n``; effector-driven vertices follow ``driven_positions(pose^{n+1})``). At the
converged minimum the free rows of the gradient vanish, ``g_f(x^{n+1}; ...) = 0``, so by the implicit
function theorem (DESIGN.md "Backward")

    dx_f = -H_ff^{-1} (dg_f/dp dp + dg_f/dx^n dx^n + dg_f/dv^n dv^n + dg_f/dtheta_bar dtheta_bar^n + H_fd dx_d),

with H the EXACT Hessian at the converged ``x^{n+1}`` (element blocks with ``projection="none"``,
inertia/damping diagonals; not the projected Newton matrix), factorised once per step; then
``v^{n+1} = (x^{n+1} - x^n) / dt``. The reverse pass solves one system ``H_ff lambda = dL/dx_f`` per
step with that factorisation and pulls ``-lambda`` back through every right-hand side above.

What depends on what (and what is treated as constant):

- inertia ``m/(2 dt^2)|x - x^n - dt v^n|^2``: ``x^n``, ``v^n`` and the masses (``density``,
  ``thickness`` of sheets); gravity ``-m g.x``: the masses; damping ``c m/(2 dt)|x - x^n|^2``: ``x^n``,
  ``c`` and the masses.
- lagged friction (Li et al. 2020): besides ``x^n`` in the tangential displacement, the frozen normal
  force ``lam = k_c (eps - d(x^n))``, the contact normal (hence the tangent projector ``I - n n^T``)
  and the closest-point weights are functions of the pair's positions at ``x^n``; they are
  differentiated exactly (first-order forward-mode jets of the same closed forms the contact
  potentials use, per Voronoi region). ``lam`` is proportional to ``k_c`` (``contact.stiffness``).
  The friction energy only depends on the projector, so the piecewise choice of tangent basis does
  not enter. ``contact.eps_v`` (the mollifier width ``eps_u = eps_v dt``) enters only the step's
  friction gradient, not the frozen quantities.
- bending (hinge or Kirchhoff plate energy, both quadratic in ``theta - theta_bar``, see
  :func:`theta_stiffness`) and bending plasticity ``theta_bar^{n+1} = theta - Y sign(theta - theta_bar^n)`` where
  ``|theta - theta_bar^n| > Y`` (yielding branch: d/dx = dtheta/dx, d/dY = -sign), else
  ``theta_bar^n`` (identity); theta_bar enters the bending gradient as ``-(dtheta/dx)^T A``.
- a candidate's adhesion bonds (:class:`~sim_core.candidates.adhesion.LaggedAdhesion`): a contact term of the step
  (its Hessian in the contact-force tangent, as its force is in the step's contact force); the parameters it
  declares (``candidate_parameters``: the bond strength ``candidate.adhesion``, the compliant layer's
  ``candidate.adhesion.shear_stiffness``) enter through its ``parameter_gradient``; its lagged normals (an
  anchored bond's: its triangle's at ``x^n``) through ``normal_state_product`` in :meth:`StepLinearization.state_rhs`;
  its pair set and anchors are held like the contact pair set.
- non-differentiable, held fixed within a step: the contact pair set, the remembered sides, the
  Voronoi regions of the closest points, the active/inactive state of each penalty (the derivative
  is that of the branch the converged step is on), the yielding set.
- effector commands: an unlimited command reaches the pose ``[t, q / |q|]`` (derivative through the
  normalisation); a rate-limited command (``StepRecord.limited_effectors``) is differentiated
  through :func:`~sim_core.effector.limit_pose_step` by central differences of that 7 -> 7 map
  (it then also depends on the previous pose). A held effector (no target) keeps ``pose^n``.

Steps retried with dt halving (``SolverConfig.dt_halvings_on_failure``) are not differentiable here
(the record only holds the last sub-step): :func:`rollout` refuses them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence

import numpy as np
import scipy.sparse as sp

from sim_core.adjoint_effectors import (  # noqa: F401
    LIMITED_POSE_FD_STEP, command_jacobian, driven_jacobian, effector_pullback, rotation_derivative)
from sim_core.adjoint_friction import FrictionRows, friction_rows, friction_state_jacobian  # noqa: F401
from sim_core.candidates.adhesion import LaggedAdhesion
from sim_core.contact_set import ContactSet
from sim_core.control import Control
from sim_core.elastic import ElasticTerms
from sim_core.energies.base import ConstantDiagonalHessian, HingeBending, assemble_hessian, block_dof_indices
from sim_core.energies.contact.reference import EdgeEdgeContact, PlaneContact, VertexTriangleContact
from sim_core.energies.sphere_contact.reference import SphereContact
from sim_core.errors import ConfigError, ThinShellError
from sim_core.linsolve import LinearSolver, make_linear_solver
from sim_core.model import Model
from sim_core.energies.friction.reference import (
    LaggedFriction,
    smooth_friction_f1_over_x,
    smooth_friction_f2_x_minus_f1_over_x3,
)
from sim_core.state import State

# ============================================================================ records
@dataclass
class Trajectory:
    """A recorded rollout.

    Attributes:
        states: ``T + 1`` states (``states[0]`` the initial one), deep copies.
        records: the solver's ``StepRecord`` of each step (``T``), or None when not recorded.
        controls: the ``T`` controls that were applied (copies).
        model_revision: ``Model.revision`` during the rollout (parameters must not change before
            the gradient is taken).
    """

    states: list[State]
    records: list | None
    controls: list[Control]
    model_revision: int

    @property
    def step_count(self) -> int:
        """Number of steps ``T``."""
        return len(self.controls)

    @property
    def x(self) -> np.ndarray:
        """Positions of every state, m, shape ``(T + 1, n, 3)``."""
        return np.stack([s.x for s in self.states])


@dataclass
class Gradient:
    """Derivatives of a scalar loss of a rollout.

    Attributes:
        controls: per step, effector name -> dL/d(commanded target pose ``[x y z qx qy qz qw]``),
            shape ``(7,)`` (zeros for an effector without a target in that step's control).
        gripper: per step, effector name -> dL/d(commanded finger opening) (0 when not commanded).
        params: global parameter name -> dL/dp.
        x0: dL/d(initial positions), shape ``(n, 3)``.
        v0: dL/d(initial velocities), shape ``(n, 3)``.
        initial_pose: effector name -> dL/d(initial effector pose), shape ``(7,)``.
        theta_bar0: sheet name -> dL/d(initial rest angles), shape ``(h,)``.
        loss: the loss value when a callback gave it, else None.
    """

    controls: list[dict[str, np.ndarray]]
    gripper: list[dict[str, float]]
    params: dict[str, float]
    x0: np.ndarray
    v0: np.ndarray
    initial_pose: dict[str, np.ndarray] = field(default_factory=dict)
    theta_bar0: dict[str, np.ndarray] = field(default_factory=dict)
    loss: float | None = None


def rollout(sim, controls: Sequence[Control | None], record: bool = True) -> Trajectory:
    """Step a :class:`~sim_core.simulation.Simulation` from its current state through ``controls``.

    Args:
        sim: the simulation (its state advances; reset it first for a rollout from the start).
        controls: one control per step (None = hold every effector).
        record: keep the solver's ``StepRecord`` of every step (needed for gradients).

    Returns:
        the :class:`Trajectory`.

    Raises:
        ConfigError: a step was retried with a smaller dt (not differentiable; set
            ``SolverConfig.dt_halvings_on_failure = 0``), naming the step.
        SimulationDivergedError: from the solver.
    """
    states = [sim.state.copy()]
    records = [] if record else None
    applied = []
    for i, c in enumerate(controls):
        c = rollout_step(sim, c, i, differentiable=record)
        if record:
            records.append(sim.solver.last_record)
        states.append(sim.state.copy())
        applied.append(c)
    return Trajectory(states=states, records=records, controls=applied, model_revision=sim.model.revision)


def rollout_step(sim, control: Control | None, index: int, differentiable: bool = True) -> Control:
    """Advance ``sim`` one step of a rollout; returns the control applied (a copy; None = hold).

    Raises:
        ConfigError: ``differentiable`` and the solver halved dt (such a step has no implicit
            derivative) or held sleeping bodies (``SolverConfig.sleeping``), naming the step ``index``.
        SimulationDivergedError: from the solver.
    """
    c = control.copy() if control is not None else Control()
    info = sim.step(c)
    if differentiable and info.substeps != 1:
        raise ConfigError(
            f"rollout step {index}: the solver halved dt ({info.substeps} sub-steps); such steps are not "
            "differentiable, use SolverConfig(dt_halvings_on_failure=0) or a smaller dt"
        )
    if differentiable and info.sleeping:
        raise ConfigError(
            f"rollout step {index}: bodies {list(info.sleeping)} slept through the step (SolverConfig.sleeping): "
            "its record holds them as Dirichlet and lacks their elastic terms; use SolverConfig(sleeping=False) "
            "for gradients")
    return c


def theta_stiffness(pot) -> sp.csr_matrix:
    """``A = d^2 E / dtheta^2`` of a bending energy quadratic in ``theta - theta_bar``, shape ``(h, h)``.

    The bending gradient is ``(dtheta/dx)^T A (theta - theta_bar)``, so
    ``d gradient / d theta_bar = -(dtheta/dx)^T A``. Hinge energy (``DiscreteShellBending``):
    ``A = diag(2 k_h)``; Kirchhoff plate energy (``KirchhoffBending``, ``E = d^T M d``): ``A = 2 M``.

    Raises:
        ThinShellError: a bending potential that is not a :class:`~sim_core.energies.base.HingeBending`.
    """
    return _hinge_bending(pot).theta_stiffness()


def _theta_stiffness_product(pot, v: np.ndarray) -> np.ndarray:
    """``A v`` with ``A`` of :func:`theta_stiffness` (``2 K_h``), without copying ``K_h``; ``v`` ``(h, r)``.

    Equal to ``theta_stiffness(pot) @ v`` bit for bit (doubling is exact).
    """
    return _hinge_bending(pot).theta_stiffness_product(v)


def _hinge_bending(pot) -> HingeBending:
    """``pot`` if it declares :class:`~sim_core.energies.base.HingeBending`.

    Raises:
        ThinShellError: it does not.
    """
    if not isinstance(pot, HingeBending):
        raise ThinShellError(f"adjoint: bending potential {type(pot).__name__} is not a HingeBending "
                             "(no theta_stiffness)")
    return pot


# ============================================================================ parameters
def _mass_parameter_body(model: Model, name: str) -> tuple[str, float] | None:
    """Body whose masses scale linearly with parameter ``name`` (density, sheet thickness)."""
    body, _, key = name.partition(".")
    b = model.bodies.get(body)
    if b is None:
        return None
    if key == "density" or (key == "thickness" and b.kind == "sheet"):
        return body, model.get_parameter(name)
    return None


def check_parameters(model: Model, params: Sequence[str]) -> list[str]:
    """Validate parameter names against ``model.parameter_names`` and the model's candidate parameters that
    a step term differentiates (:attr:`~sim_core.candidates.adhesion.LaggedAdhesion.candidate_parameters`).

    Raises:
        ConfigError: unknown name (the known names are listed).
    """
    known = model.parameter_names + [name for name in LaggedAdhesion.candidate_parameters
                                     if name.partition(".")[2] in model.candidates]
    for p in params:
        if p not in known:
            raise ConfigError(f"adjoint: unknown parameter {p!r}; known: {known}")
    return list(params)


# ============================================================================ one step
class SupportTerms:
    """Which static terms of a rollout's steps have Hessian blocks touching a Dirichlet support
    (:meth:`StepLinearization.support_product`), so that the terms that touch none are not evaluated.

    A term is recognised across steps by itself, or by its hinge array where it is a bending term (the solver
    hands each step a copy of the sheet's bending potential with that step's rest angles, sharing its hinges,
    :meth:`sim_core.elastic.ElasticTerms.bending`). Its element vertex array is trusted to stay once its blocks
    came over the same array object at two steps: the rule the Newton matrix's static pattern already rests on
    (:meth:`sim_core.assembly.HessianAssembler.static_pattern`: elastic terms give the same ``vertices`` object
    every call). The terms are held while kept, so that their ids stay unique; one instance per rollout
    (:class:`sim_core.sensitivity.TangentPropagation` keeps one).
    """

    CONFIRMING_STEPS = 2
    """Evaluations over the same vertex array object after which a term's elements are trusted."""

    def __init__(self) -> None:
        # key -> [anchor (held), vertices array (held), evaluations over it, {support bytes: touching elements}]
        self._terms: dict[tuple[type, int], list] = {}

    @staticmethod
    def _key(p) -> tuple[tuple[type, int], object]:
        anchor = p.hinges if isinstance(p, HingeBending) else p
        return (type(p), id(anchor)), anchor

    def untouched(self, p, support: np.ndarray) -> bool:
        """Whether ``p``'s blocks are known to touch no vertex of ``support`` (``(n,)`` bool)."""
        touching = self.touching(p, support)
        return touching is not None and touching.size == 0

    def touching(self, p, support: np.ndarray) -> np.ndarray | None:
        """The elements of ``p`` (rows of its trusted vertex array) whose blocks touch a vertex of ``support``
        (``(n,)`` bool), ``(j,)`` int in increasing order; None while ``p``'s elements are not trusted."""
        entry = self._terms.get(self._key(p)[0])
        if entry is None or entry[2] < self.CONFIRMING_STEPS:
            return None
        mark = np.packbits(support).tobytes()
        touching = entry[3].get(mark)
        if touching is None:
            vertices = entry[1]
            touching = entry[3][mark] = (np.flatnonzero(support[vertices].any(axis=1)) if len(vertices)
                                         else np.zeros(0, dtype=np.int64))
        return touching

    def note(self, p, vertices: np.ndarray) -> None:
        """``p`` was evaluated and its blocks came over ``vertices`` ``(k, m)``."""
        key, anchor = self._key(p)
        entry = self._terms.get(key)
        if entry is not None and entry[1] is vertices:
            entry[2] += 1
        else:
            self._terms[key] = [anchor, vertices, 1, {}]


class StepLinearization:
    """The implicit-function-theorem linearisation of one converged step (module docstring).

    Args:
        model: the model (parameters as during the step).
        record: the solver's ``StepRecord`` of the step.
        state: the state the step started from (for the contact side memory of the friction frames).
        elastic: ``ElasticTerms(model)``.
        contact: a ``ContactSet(model)`` used to rebuild the friction frames.
        vertex_mass: ``model.vertex_mass()``, shape ``(n,)``.
        linear_solver: a :class:`~sim_core.linsolve.LinearSolver` to (re)factorise, or a name for
            :func:`~sim_core.linsolve.make_linear_solver` (creating one costs ~0.5 s with pypardiso:
            pass one solver for a whole rollout).
        factorize: factorise the exact free-DoF Hessian (False when only products are needed).
        factorization: a solver that already holds the factorisation of the constrained exact
            Hessian of this step (``NewtonSolver.last_factorization`` right after the step, when
            ``record.hessian_exact``); used instead of factorising again.

    The full Hessian ``H`` and its contact part ``H_contact`` are assembled on first use (the
    forward tangents only need them for products with non-zero Dirichlet tangents; the
    contact-force tangent multiplies the contact terms' element blocks directly,
    :meth:`contact_hessian_product`). When ``record.hessian_exact``, the record's Newton matrix is the
    constrained exact Hessian and is factorised as it is, without assembling it again.
    """

    def __init__(self, model: Model, record, state: State, elastic: ElasticTerms, contact: ContactSet,
                 vertex_mass: np.ndarray, linear_solver: LinearSolver | str = "pardiso",
                 factorize: bool = True, factorization: LinearSolver | None = None) -> None:
        self.model, self.record, self.elastic = model, record, elastic
        self.dt = float(record.dt)
        self.x, self.x_n = record.x, record.x_prev
        n = self.x.shape[0]
        self.n = n
        self.mass = vertex_mass
        self.free = np.asarray(record.free_dofs, dtype=bool)
        self.contact_terms = [p for p in record.terms if isinstance(
            p, (VertexTriangleContact, EdgeEdgeContact, PlaneContact, SphereContact, LaggedFriction, LaggedAdhesion))]
        self._H: sp.csr_matrix | None = None
        self._H_contact: sp.csr_matrix | None = None
        self._contact_rhs: dict[str, np.ndarray] = {}  # contact_parameter_rhs per parameter name
        self._friction_product: tuple[np.ndarray, np.ndarray] | None = None  # (dxn, _friction_apply(dxn))
        self.solver = factorization
        if factorize and factorization is None:
            if getattr(record, "hessian_exact", False) and getattr(record, "hessian_upper", None) is not None:
                Hc = sp.csr_matrix(record.hessian)  # a lockstep step solved by the batched CG keeps none
            else:
                D = sp.diags(self.free.astype(float))
                Hc = (D @ self.H @ D + sp.diags((~self.free).astype(float))).tocsr()
            self.solver = make_linear_solver(linear_solver) if isinstance(linear_solver, str) else linear_solver
            self.solver.factorize(Hc)
        self.friction = next((p for p in record.terms if isinstance(p, LaggedFriction)), None)
        self.adhesion = [p for p in self.contact_terms if isinstance(p, LaggedAdhesion)]
        self.rows = friction_rows(model, contact, state, self.friction) if self.friction is not None else None
        self.friction_J = friction_state_jacobian(self.rows, self.x) if self.rows is not None else None
        # bending: per sheet, hinge stiffness, dtheta/dx at x^{n+1}, plastic yielding set.
        self.bending = {}
        for name in elastic.hinges:
            tb = record.hinge_theta_bar.get(name)
            pot = _hinge_bending(elastic.bending(name, tb))
            theta, gt = pot.theta(self.x), pot.theta_gradient(self.x)  # Kirchhoff: kept angles, shared
            Y = model.bodies[name].material.get("yield_angle", np.inf)
            dev = theta - pot.hinge_theta_bar
            yielding = np.abs(dev) > Y if np.isfinite(Y) else np.zeros(len(theta), bool)
            self.bending[name] = (pot, gt, yielding, np.sign(dev))
        self.fixed = np.asarray(record.fixed, dtype=bool)
        self.driven = np.zeros(n, bool)
        for eff in model.effectors.values():
            self.driven[eff.vertices] = True
        self.static = self.fixed & ~self.driven

    # ------------------------------------------------------------ matrices
    @property
    def H(self) -> sp.csr_matrix:
        """Exact Hessian of the step's incremental potential at ``x^{n+1}``, ``(3 n, 3 n)`` CSR (all DoFs)."""
        if self._H is None:
            diag = np.zeros(3 * self.n)
            blocks = []
            for p in self.record.terms:
                if isinstance(p, ConstantDiagonalHessian):
                    diag += p.hessian_diagonal()
                else:
                    blocks.append(p.hessian(self.x, "none"))
            self._H = assemble_hessian(blocks, 3 * self.n, diag)
        return self._H

    def contact_hessian_product(self, dx: np.ndarray) -> np.ndarray:
        """``H_contact dx`` from the contact and friction terms' element blocks, without assembling
        :attr:`H_contact` (the same sum up to round-off); ``dx`` shape ``(n, 3, r)`` in and out."""
        if self._H_contact is not None:
            r = dx.shape[2]
            return (self._H_contact @ dx.reshape(3 * self.n, r)).reshape(self.n, 3, r)
        out = np.zeros(dx.shape)
        for p in self.contact_terms:
            if isinstance(p, LaggedFriction):
                out += _friction_hessian_product(p, self.x, dx)
                continue
            hb = p.hessian(self.x, "none")
            k, m = hb.vertices.shape
            if k == 0:
                continue
            prod = np.matmul(hb.blocks, dx[hb.vertices].reshape(k, 3 * m, -1))
            out += _scatter_vertex_rows(self.n, hb.vertices, prod.reshape(k, m, 3, -1))
        return out

    @property
    def H_contact(self) -> sp.csr_matrix:
        """Exact Hessian of the contact and friction terms alone, ``(3 n, 3 n)`` CSR."""
        if self._H_contact is None:
            self._H_contact = assemble_hessian([p.hessian(self.x, "none") for p in self.contact_terms], 3 * self.n)
        return self._H_contact

    # ------------------------------------------------------------ solves
    def solve(self, b: np.ndarray) -> np.ndarray:
        """``H_ff^{-1} b_f`` padded with zeros on fixed DoFs; ``b`` shape ``(3 n,)`` or ``(3 n, r)``."""
        b = np.array(b, dtype=float)
        b[~self.free] = 0.0
        out = np.asarray(self.solver.solve(b)).reshape(b.shape)
        out[~self.free] = 0.0
        return out

    # ------------------------------------------------------------ products with dg/d(state)
    def _friction_apply(self, dxn: np.ndarray) -> np.ndarray:
        """Friction part of (dg/dx^n) dx^n; dxn shape (n, 3, r) -> (n, 3, r).

        The last product is kept with its argument: the forward tangents ask for it twice per step
        with the same ``dx^n`` (:meth:`state_rhs`, :meth:`contact_force_tangent`). The result must
        not be modified in place.
        """
        kept = self._friction_product
        if kept is not None and kept[0] is dxn:
            return kept[1]
        if self.friction_J is None:
            out = np.zeros_like(dxn)
        else:
            v = self.rows.vertices
            local = dxn[v].reshape(v.shape[0], 12, -1)
            prod = np.matmul(self.friction_J, local).reshape(v.shape[0], 4, 3, -1)
            out = _scatter_vertex_rows(self.n, v, prod)
        self._friction_product = (dxn, out)
        return out

    def _friction_apply_T(self, w: np.ndarray) -> np.ndarray:
        out = np.zeros((self.n, 3))
        if self.friction_J is None:
            return out
        v = self.rows.vertices
        prod = np.einsum("kuv,ku->kv", self.friction_J, w[v].reshape(v.shape[0], 12))
        np.add.at(out, v.reshape(-1), prod.reshape(-1, 3))
        return out

    def _xn_coefficient(self) -> np.ndarray:
        """Diagonal part of dg/dx^n: ``-m/dt^2 - c m/dt`` per vertex, shape ``(n,)``."""
        return -self.mass / self.dt**2 - self.model.damping * self.mass / self.dt

    def state_rhs(self, dxn: np.ndarray, dvn: np.ndarray, dtb: dict[str, np.ndarray]) -> np.ndarray:
        """``dg/dx^n dx^n + dg/dv^n dv^n + dg/dtheta_bar dtheta_bar`` for ``r`` tangents.

        Args:
            dxn, dvn: shape ``(n, 3, r)``; dtb: sheet -> ``(h, r)``.

        Returns:
            shape ``(n, 3, r)``.
        """
        out = self._xn_coefficient()[:, None, None] * dxn - (self.mass / self.dt)[:, None, None] * dvn
        out += self._friction_apply(dxn)
        for p in self.adhesion:
            out += p.normal_state_product(self.x, self.x_n, dxn)
        for name, (pot, gt, _, _) in self.bending.items():
            if name in dtb:
                coef = -_theta_stiffness_product(pot, dtb[name])  # (h, r)
                contrib = gt[:, :, :, None] * coef[:, None, None, :]
                out += _scatter_vertex_rows(self.n, pot.hinges, contrib)
        return out

    def state_vjp(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Transpose of :meth:`state_rhs`: ``(w^T dg/dx^n, w^T dg/dv^n, {sheet: w^T dg/dtheta_bar})``."""
        ax = self._xn_coefficient()[:, None] * w + self._friction_apply_T(w)
        for p in self.adhesion:
            ax += p.normal_state_vjp(self.x, self.x_n, w)
        av = -(self.mass / self.dt)[:, None] * w
        atb = {}
        for name, (pot, gt, _, _) in self.bending.items():
            atb[name] = -(theta_stiffness(pot).T @ np.einsum("hvd,hvd->h", gt, w[pot.hinges]))
        return ax, av, atb

    def hessian_product(self, dx: np.ndarray) -> np.ndarray:
        """Full (unconstrained) exact Hessian times ``dx``; shape ``(n, 3, r)`` in and out."""
        r = dx.shape[2]
        return (self.H @ dx.reshape(3 * self.n, r)).reshape(self.n, 3, r)

    def support_product(self, dx: np.ndarray, kept: "SupportTerms | None" = None) -> np.ndarray:
        """The exact Hessian times ``dx`` (shape ``(n, 3, r)``) on the free rows, zeros on the fixed rows, from
        the element blocks that touch a vertex where ``dx`` is non-zero, without assembling :attr:`H` (unless
        it is assembled already): the right-hand side ``H_fd dx_d`` of a Dirichlet tangent supported on a few
        vertices (an effector's, :class:`sim_core.sensitivity.DriveStep`). Equal to :meth:`hessian_product` on
        the free rows up to round-off; the constant diagonal terms (inertia, damping) couple no two vertices
        and add nothing there.

        With ``kept`` (a rollout's :class:`SupportTerms`), a static term (every term but the contacts and the
        friction) whose blocks were found over the same vertex array at two earlier steps, none of them touching
        this support, is not evaluated at all (bit for bit the same product: its blocks added nothing). On a
        press-and-slide the effector's support touches the gel's tets only, so the card's membrane and Kirchhoff
        bending Hessians (the most costly NumPy Hessians of a step) are not built for a product of zeros. Of a
        static term that touches it and can be restricted to some of its elements (``restricted``: the gel's laws,
        :meth:`sim_core.energies.neohookean.reference.StableNeoHookean.restricted`), only the touching elements'
        blocks are built (the same blocks bit for bit; the gel's tets below the effector, not the whole gel)."""
        if self._H is not None:
            out = self.hessian_product(dx)
            out[self.fixed] = 0.0
            return out
        support = np.any(dx != 0.0, axis=(1, 2))
        out = np.zeros(dx.shape)
        for p in self.record.terms:
            if isinstance(p, ConstantDiagonalHessian):
                continue
            static = kept is not None and not any(p is q for q in self.contact_terms)
            touching = kept.touching(p, support) if static else None
            if touching is not None and touching.size == 0:
                continue
            restricted = getattr(p, "restricted", None)
            if touching is not None and restricted is not None:  # the touching elements' blocks alone
                hb = restricted(touching).hessian(self.x, "none")
                v, blocks = hb.vertices, hb.blocks
            else:
                hb = p.hessian(self.x, "none")
                if static:
                    kept.note(p, hb.vertices)
                touch = support[hb.vertices].any(axis=1) if len(hb.vertices) else np.zeros(0, bool)
                if not touch.any():
                    continue
                v, blocks = hb.vertices[touch], hb.blocks[touch]
            k, m = v.shape
            prod = np.matmul(blocks, dx[v].reshape(k, 3 * m, -1))
            out += _scatter_vertex_rows(self.n, v, prod.reshape(k, m, 3, -1))
        out[self.fixed] = 0.0
        return out

    def fixed_row_product(self, w: np.ndarray) -> np.ndarray:
        """The exact Hessian times ``w`` (shape ``(n, 3)``) on the rows of the fixed vertices, zeros on the
        other rows: the adjoint's Dirichlet pullback reads no other row. From the element blocks that touch
        a fixed vertex, without assembling :attr:`H` (unless it is assembled already); equal to
        :meth:`hessian_product` on those rows up to round-off."""
        if self._H is not None:
            out = self.hessian_product(w[:, :, None])[:, :, 0]
        else:
            diag = np.zeros(3 * self.n)
            out = np.zeros((self.n, 3, 1))
            for p in self.record.terms:
                if isinstance(p, ConstantDiagonalHessian):
                    diag += p.hessian_diagonal()
                    continue
                hb = p.hessian(self.x, "none")
                touch = self.fixed[hb.vertices].any(axis=1) if len(hb.vertices) else np.zeros(0, bool)
                if not touch.any():
                    continue
                v = hb.vertices[touch]
                k, m = v.shape
                prod = np.matmul(hb.blocks[touch], w[v].reshape(k, 3 * m, 1))
                out += _scatter_vertex_rows(self.n, v, prod.reshape(k, m, 3, 1))
            out = out[:, :, 0] + (diag * w.reshape(-1)).reshape(self.n, 3)
        out[~self.fixed] = 0.0
        return out

    # ------------------------------------------------------------ parameters
    def mass_gradient(self) -> np.ndarray:
        """d(inertia + gravity + damping gradient)/d m_i per vertex, shape ``(n, 3)``."""
        x_hat = self.x_n + self.dt * self.record.v_prev
        scale = self.model.vertex_gravity_scale
        g = self.model.gravity[None, :] if scale is None else scale[:, None] * self.model.gravity[None, :]
        return (self.x - x_hat) / self.dt**2 - g + self.model.damping * (self.x - self.x_n) / self.dt

    def parameter_rhs(self, name: str) -> np.ndarray:
        """dg/dp of global parameter ``name`` at the converged step, shape ``(n, 3)``.

        ``sheet.yield_angle`` does not enter the step's gradient (it acts through plasticity).
        ``contact.eps_v`` enters through the lagged friction's mollifier alone
        (:meth:`~sim_core.energies.friction.reference.LaggedFriction.eps_v_gradient`): the frozen normal forces,
        bases and weights are of ``x^n`` (their tangents are :meth:`state_rhs`'s).
        """
        x = self.x
        out = np.zeros((self.n, 3))
        body = name.partition(".")[0]
        for pot, local in self.elastic.parameter_terms(name, self.record.hinge_theta_bar):
            if body in self.bending and type(pot) is type(self.bending[body][0]):
                pot = self.bending[body][0]  # the step's bending term, same rest angles, kept kinematics
            out += pot.parameter_gradient(x, local)
        mb = _mass_parameter_body(self.model, name)
        if mb is not None:
            b = self.model.bodies[mb[0]]
            sl = slice(b.vertex_start, b.vertex_stop)
            out[sl] += (self.mass[sl] / mb[1])[:, None] * self.mass_gradient()[sl]
        if name == "damping":
            out += self.mass[:, None] * (x - self.x_n) / self.dt
        return out + self.contact_parameter_rhs(name)

    def contact_parameter_rhs(self, name: str) -> np.ndarray:
        """The contact + friction part of :meth:`parameter_rhs` (for the contact-force tangent).

        Kept per ``name`` (asked for by :meth:`parameter_rhs` and again for the contact-force
        tangent); the returned array must not be modified in place.
        """
        kept = self._contact_rhs.get(name)
        if kept is None:
            kept = self._contact_rhs[name] = self._contact_parameter_rhs(name)
        return kept

    def _contact_parameter_rhs(self, name: str) -> np.ndarray:
        out = np.zeros((self.n, 3))
        if name == "contact.stiffness":
            for p in self.contact_terms:
                if isinstance(p, LaggedFriction):
                    out += p.gradient(self.x) / self.model.contact.stiffness
                elif not isinstance(p, LaggedAdhesion):  # the bonds' law holds no contact stiffness
                    out += p.parameter_gradient(self.x, "stiffness")
        if name == "contact.eps_v" and self.friction is not None:
            out += self.friction.eps_v_gradient(self.x)
        for p in self.contact_terms:  # a candidate's bonds: the global parameters they declare
            local = getattr(p, "candidate_parameters", {}).get(name)
            if local is not None and local in p.parameter_names:
                out += p.parameter_gradient(self.x, local)
        if name.startswith("friction.") and self.rows is not None:
            key = self.model._friction_key(name)
            mask = np.array([pair == key for pair in self.rows.body_pairs])
            if np.any(mask):
                out += self.friction.mu_gradient(self.x, mask)
        return out

    def contact_force_tangent(self, dx_new: np.ndarray, dxn: np.ndarray, dparam: np.ndarray) -> np.ndarray:
        """Tangent of the end-of-step contact + friction force ``f = -(g_contact + g_friction)(x^{n+1})``.

        ``df = -(H_contact dx^{n+1} + d(g_friction + g_adhesion)/dx^n dx^n + dg_contact/dp dp)``.

        Args:
            dx_new, dxn: tangents of ``x^{n+1}`` and ``x^n``, shape ``(n, 3, r)``.
            dparam: ``dg_contact/dp`` columns times the parameter tangents, shape ``(n, 3, r)``.

        Returns:
            shape ``(n, 3, r)``, N per unit tangent.
        """
        out = -(self.contact_hessian_product(dx_new) + self._friction_apply(dxn) + dparam)
        for p in self.adhesion:
            out -= p.normal_state_product(self.x, self.x_n, dxn)
        return out

    # ------------------------------------------------------------ plasticity
    def plastic_tangent(self, dx_new: np.ndarray, dtb: dict[str, np.ndarray], dyield: dict[str, np.ndarray]):
        """Tangent of theta_bar^{n+1}: identity where elastic, ``dtheta.dx - sign dY`` where yielding.

        Args:
            dx_new: tangent of ``x^{n+1}``, ``(n, 3, r)``; dtb: sheet -> ``(h, r)``;
            dyield: sheet -> ``(r,)`` tangent of the sheet's yield angle.
        """
        out = {}
        for name, (pot, gt, yielding, sign) in self.bending.items():
            new = np.array(dtb[name])
            if np.any(yielding):
                dtheta = np.einsum("hvd,hvdr->hr", gt[yielding], dx_new[pot.hinges[yielding]])
                new[yielding] = dtheta - sign[yielding, None] * dyield.get(name, 0.0)
            out[name] = new
        return out


def _friction_hessian_product(friction: LaggedFriction, x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """``H_friction(x) dx`` without the per-pair ``(3m, 3m)`` blocks of :meth:`LaggedFriction.hessian`.

    The block of pair k is ``mu lam w_a w_b T Hu T^T`` (``Hu = (f1/y) I + ((f1' y - f1)/y^3) u u^T``,
    Li et al. 2020, as in :mod:`sim_core.energies.friction.reference`), so per pair
    ``(H dx)_a = w_a mu lam T Hu T^T sum_b w_b dx_b``: 2-D products instead of 12 x 12 ones.

    Args:
        friction: the step's lagged friction.
        x: positions (n, 3) m; dx: tangents ``(n, 3, r)``.

    Returns:
        shape ``(n, 3, r)``, N per unit tangent.
    """
    p, m = friction.vertices.shape
    if p == 0:
        return np.zeros(dx.shape)
    u = friction.tangential_displacement(x)
    y = np.linalg.norm(u, axis=1)
    Hu = smooth_friction_f1_over_x(y, friction.eps_u)[:, None, None] * np.eye(2)[None] + (
        smooth_friction_f2_x_minus_f1_over_x3(y, friction.eps_u)[:, None, None] * u[:, :, None] * u[:, None, :]
    )
    T = friction.tangent
    rel = np.einsum("kj,kjdr->kdr", friction.weights, dx[friction.vertices])  # sum_b w_b dx_b, (p, 3, r)
    back = np.matmul(T, np.matmul(Hu, np.matmul(np.swapaxes(T, 1, 2), rel)))  # (p, 3, r)
    back *= (friction.mu * friction.lam)[:, None, None]
    return _scatter_vertex_rows(x.shape[0], friction.vertices, friction.weights[:, :, None, None] * back[:, None])


def _scatter_vertex_rows(vertex_count: int, vertices: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Sum per-element vertex rows into global rows: ``out[vertices[k, a]] += values[k, a]``.

    Args:
        vertex_count: n.
        vertices: global vertex indices, shape ``(k, m)``.
        values: shape ``(k, m, 3, r)``.

    Returns:
        shape ``(n, 3, r)`` (``np.bincount`` over flat indices, summed in element order as
        ``np.add.at`` does).
    """
    k, m, _, r = values.shape
    flat = (3 * r * vertices.astype(np.int64))[:, :, None, None] + np.arange(3 * r).reshape(1, 1, 3, r)
    out = np.bincount(flat.reshape(-1), weights=values.reshape(-1), minlength=3 * r * vertex_count)
    return out.reshape(vertex_count, 3, r)


def _dof_vertices(eff) -> np.ndarray:
    return block_dof_indices(np.asarray(eff.vertices)[:, None]).reshape(-1)


# ============================================================================ reverse mode
class ParameterAdjoint(Protocol):
    """Where :func:`reverse_pass` accumulates the parameter derivatives ``sum_n w_n^T dg_n/dp``."""

    def add_step(self, lin: StepLinearization, w: np.ndarray) -> None:
        """Add ``w^T dg/dp`` of one step (``w = -lambda``, shape ``(n, 3)``) for every parameter."""

    def add_yield(self, sheet: str, yielding: np.ndarray, sign: np.ndarray, a: np.ndarray) -> None:
        """Add the plastic update's ``-sign . a`` over the ``yielding`` hinges of ``sheet`` (shape ``(h,)`` each)
        to the sheet's yield angle."""


class GlobalParameterAdjoint:
    """:class:`ParameterAdjoint` of one model: global parameter name -> dL/dp (:attr:`values`).

    Args:
        params: checked global parameter names (:func:`check_parameters`).
    """

    def __init__(self, params: Sequence[str]) -> None:
        self.values = {p: 0.0 for p in params}

    def add_step(self, lin: StepLinearization, w: np.ndarray) -> None:
        """As :meth:`ParameterAdjoint.add_step`."""
        for p in self.values:
            self.values[p] += float(np.sum(w * lin.parameter_rhs(p)))

    def add_yield(self, sheet: str, yielding: np.ndarray, sign: np.ndarray, a: np.ndarray) -> None:
        """As :meth:`ParameterAdjoint.add_yield`."""
        yname = f"{sheet}.yield_angle"
        if yname in self.values:
            self.values[yname] -= float(np.dot(sign[yielding], a[yielding]))


def rollout_gradient(sim_or_model, trajectory: Trajectory,
                     dL_dx: np.ndarray | Callable[[Trajectory], tuple[float, np.ndarray]],
                     params: Sequence[str] = (),
                     dL_dtheta_bar: dict[str, np.ndarray] | None = None) -> Gradient:
    """Reverse-mode derivative of a loss of the rollout's positions (adjoint method).

    One linear solve per step with the factorisation of the exact Hessian at the converged step
    (:func:`reverse_pass`).

    Args:
        sim_or_model: the Simulation (its solver's linear solver is used) or the Model of the rollout.
        trajectory: from :func:`rollout` with ``record=True``.
        dL_dx: dL/dx of every state, shape ``(T + 1, n, 3)``, or a callback
            ``loss(trajectory) -> (value, dL_dx)``.
        params: global parameter names (``Model.parameter_names``) to differentiate.
        dL_dtheta_bar: optional sheet name -> dL/d(rest dihedral angles of the FINAL state),
            shape ``(h,)`` (a loss that reads the plastic rest angles, e.g. a folding reward).

    Returns:
        the :class:`Gradient`.

    Raises:
        ConfigError: no records, parameters changed since the rollout, unknown parameter, bad shape
            (of ``dL_dx`` or of a ``dL_dtheta_bar`` entry), or a ``dL_dtheta_bar`` sheet without hinges.
    """
    model, solver_name, backend = _model_and_solver(sim_or_model)
    _check_trajectory(model, trajectory)
    params = check_parameters(model, params)
    loss = None
    if callable(dL_dx):
        loss, dL_dx = dL_dx(trajectory)
        loss = float(loss)
    T, n = trajectory.step_count, model.vertex_count
    dL_dx = np.asarray(dL_dx, dtype=float)
    if dL_dx.shape != (T + 1, n, 3):
        raise ConfigError(f"adjoint: dL_dx has shape {dL_dx.shape}, expected {(T + 1, n, 3)}")
    atb = rest_angle_adjoint(model, dL_dtheta_bar)
    parameters = GlobalParameterAdjoint(params)
    g = reverse_pass(model, trajectory, dL_dx, atb, parameters, make_linear_solver(solver_name), backend)
    g.params, g.loss = parameters.values, loss
    return g


def rest_angle_adjoint(model: Model, dL_dtheta_bar: dict[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """The final state's rest-angle adjoint: sheet -> dL/dtheta_bar, shape ``(h,)`` (zeros where not given).

    Raises:
        ConfigError: a sheet without hinges, or an entry of the wrong shape.
    """
    atb = {name: np.zeros(len(model.bodies[name].hinges)) for name in ElasticTerms(model).hinges}
    for name, value in (dL_dtheta_bar or {}).items():
        if name not in atb:
            raise ConfigError(f"adjoint: dL_dtheta_bar names {name!r}, not a sheet with hinges; sheets: {sorted(atb)}")
        value = np.asarray(value, dtype=float)
        if value.shape != atb[name].shape:
            raise ConfigError(f"adjoint: dL_dtheta_bar[{name!r}] has shape {value.shape}, expected {atb[name].shape}")
        atb[name] = value.copy()
    return atb


def reverse_pass(model: Model, trajectory: Trajectory, dL_dx: Sequence[np.ndarray], atb: dict[str, np.ndarray],
                 parameters: ParameterAdjoint, linear_solver: LinearSolver, backend: str,
                 fixed_rows: bool = False) -> Gradient:
    """The adjoint recursion of :func:`rollout_gradient` over a checked trajectory (module docstring).

    Per step, from the last: the plastic update's pullback, one solve ``H_ff lambda = a_f`` with the
    step's exact Hessian (:class:`StepLinearization`, factorised by ``linear_solver``), then the
    pullbacks of ``w = -lambda`` to the previous state, the parameters (``parameters``), the Dirichlet
    vertices and the effector commands.

    Args:
        model: the rollout's model (for a stacked batch, the stacked model: its copies' blocks are
            independent, so one factorisation and one solve serve all of them).
        trajectory: the rollout (records checked by the caller).
        dL_dx: ``T + 1`` arrays dL/dx of each state, shape ``(n, 3)`` each (indexable by step).
        atb: sheet -> dL/d(final rest angles), shape ``(h,)`` (:func:`rest_angle_adjoint`).
        parameters: where the parameter derivatives accumulate.
        linear_solver: the solver that factorises each step's exact Hessian (LU: it need not be
            positive definite).
        backend: the concrete backend of the contact set that rebuilds the friction frames.
        fixed_rows: the Dirichlet pullback's Hessian product from the element blocks touching a fixed vertex
            (:meth:`StepLinearization.fixed_row_product`) instead of the assembled Hessian (the same to
            round-off; no assembly when the step's record holds the exact Hessian).

    Returns:
        the :class:`Gradient` (``params`` empty: they are in ``parameters``; ``loss`` None).
    """
    T, n = trajectory.step_count, model.vertex_count
    elastic, contact, mass = ElasticTerms(model), ContactSet(model, backend=backend), model.vertex_mass()
    ax = np.array(dL_dx[T], dtype=float)
    av = np.zeros((n, 3))
    apose = {k: np.zeros(7) for k in model.effectors}
    aopen = {k: 0.0 for k in model.effectors}
    g_controls: list[dict] = [None] * T
    g_gripper: list[dict] = [None] * T
    for i in range(T - 1, -1, -1):
        rec, state, control = trajectory.records[i], trajectory.states[i], trajectory.controls[i]
        lin = StepLinearization(model, rec, state, elastic, contact, mass, linear_solver)
        dt = lin.dt
        a_hat = ax + av / dt
        ax_n = -av / dt
        # plasticity of this step: theta_bar^{n+1}(x^{n+1}, theta_bar^n, Y)
        atb_n = {}
        for name, (pot, gt, yielding, sign) in lin.bending.items():
            a = atb[name]
            if np.any(yielding):
                contrib = gt[yielding] * a[yielding, None, None]
                np.add.at(a_hat, pot.hinges[yielding].reshape(-1), contrib.reshape(-1, 3))
                parameters.add_yield(name, yielding, sign, a)
            atb_n[name] = np.where(yielding, 0.0, a)
        lam = lin.solve(a_hat.reshape(-1)).reshape(n, 3)
        w = -lam
        gx, gv, gtb = lin.state_vjp(w)
        ax_n += gx
        for name in atb_n:
            atb_n[name] = atb_n[name] + gtb[name]
        parameters.add_step(lin, w)
        a_fixed = a_hat + (lin.fixed_row_product(w) if fixed_rows else lin.hessian_product(w[:, :, None])[:, :, 0])
        ax_n[lin.static] += a_fixed[lin.static]
        g_controls[i], g_gripper[i] = {}, {}
        effector_pullback(model, rec, state, control, a_fixed, apose, aopen, g_controls[i], g_gripper[i])
        ax = ax_n + dL_dx[i]
        av = gv
        atb = atb_n
    return Gradient(controls=g_controls, gripper=g_gripper, params={}, x0=ax, v0=av,
                    initial_pose=apose, theta_bar0=atb)


def _model_and_solver(sim_or_model) -> tuple[Model, str, str]:
    """The model, the linear solver's name and the concrete backend of a Simulation (a Model: its
    defaults, ``pardiso`` and ``numpy``)."""
    if isinstance(sim_or_model, Model):
        return sim_or_model, "pardiso", "numpy"
    return sim_or_model.model, sim_or_model.solver.config.linear_solver, sim_or_model.solver.backend


def _check_trajectory(model: Model, trajectory: Trajectory) -> None:
    if trajectory.records is None:
        raise ConfigError("adjoint: the trajectory has no step records; use rollout(..., record=True)")
    if trajectory.model_revision != model.revision:
        raise ConfigError(
            f"adjoint: model parameters changed since the rollout (revision {trajectory.model_revision} -> "
            f"{model.revision}); roll out again"
        )
