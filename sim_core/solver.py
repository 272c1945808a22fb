"""Newton's method on the incremental potential (implicit Euler), with Dirichlet boundaries.

One step minimises E(x) = inertia + gravity + damping + elastic + contact + friction
(DESIGN.md "Time stepping"), then sets v = (x - x^n)/dt. Each iteration assembles the projected
Hessian blocks of every potential into one sparse matrix, solves with a sparse direct solver
(PARDISO by default), and backtracks along the Newton direction until the Armijo condition
E(x + a d) <= E(x) + c a g.d holds (ThinShellLab accepted energy increases; we do not). The
matrix is the exact Hessian whenever its Cholesky factorisation succeeds (it is then positive
definite on the free DoFs and the Newton direction is a descent direction, with quadratic
convergence near the solution), else the Hessian with PSD-projected element blocks (on the fused
Taichi path, ``SolverConfig.backend`` ``taichi-cpu`` or ``taichi-cuda``, the elastic part of both comes from
:class:`~sim_core.fused_elastic.FusedElastic`: the exact values from the fused kernels, the
projected ones from :meth:`~sim_core.fused_elastic.FusedElastic.projected_hessian_values`). The step
is also capped so that no vertex moves more than ``max_displacement`` per iteration, which keeps
the contact candidate set of the iteration valid. A step that does not converge raises
:class:`SimulationDivergedError` naming the step (or retries with dt/2 when configured). The
stopping tests are in :mod:`sim_core.newton_stop`; a resting scene may repeat its fixed point
(``SolverConfig.repeat_fixed_points``, :mod:`sim_core.fixed_point`) and a resting body nothing moving
can reach may sleep out of the Newton system (``SolverConfig.sleeping``, :mod:`sim_core.sleeping`).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import scipy.sparse as sp

from sim_core.assembly import HessianAssembler
from sim_core.backend import resolve_backend, uses_taichi
from sim_core.candidates.hook import CandidateHook, StepHook, checked_hook
from sim_core.carried_start import carry_driven_bodies
from sim_core.contact_set import ContactSet, active_contacts, same_active_contacts
from sim_core.control import Control
from sim_core.drive_compression import CompressionPotential
from sim_core.fixed_point import FixedPoint, copy_state_into, same_array, same_arrays, same_resting_state
from sim_core.effector import driven_positions, limit_pose_step
from sim_core.elastic import ElasticTerms
from sim_core.energies.base import FrozenPositionsKey, KeepsDerivatives, PenaltyContact, declares
from sim_core.energies.damping.reference import ViscousDamping
from sim_core.energies.friction.reference import LaggedFriction
from sim_core.energies.gravity.reference import GravityPotential
from sim_core.energies.inertia.reference import InertiaPotential
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.fused_elastic import FusedElastic, fusable
from sim_core.linsolve import LinearSolver, SymmetricExpansion, SymmetricSolver, make_linear_solver, make_symmetric_solver
from sim_core.model import Model
from sim_core.solver_config import SolverConfig
from sim_core.sleeping import SleepSet, Woken
from sim_core.state import State
from sim_core.newton_stop import accept, largest_move, line_search_failure_acceptance, rate_stops, stop_reason
from sim_core.step_terms import FreeDofs, StepTerms, contact_force
from sim_core.step_info import RELAXED_STOPS, STRICT_STOPS, StepInfo, StepRecord, StepTotals
from sim_core.workspace import Workspace

__all__ = ["NewtonSolver", "SolverConfig", "StepInfo", "StepRecord", "StepTotals", "STRICT_STOPS", "RELAXED_STOPS"]


class NewtonSolver:
    """Implicit-Euler Newton solver (Model/State/Control/Solver seam as in NVIDIA Newton).

    Args:
        model: the scene model.
        config: :class:`SolverConfig`.
        hook: extra terms of each step and the state update after it
            (:class:`~sim_core.candidates.hook.StepHook`; e.g. the diagnosis benchmark's effects);
            None: the model's ``candidate.<name>`` parameters, if any, through a
            :class:`~sim_core.candidates.hook.CandidateHook`.

    Raises:
        ConfigError: ``config.backend`` cannot start here (:func:`sim_core.backend.resolve_backend`);
            a ``hook`` that is not a :class:`~sim_core.candidates.hook.StepHook`; a ``hook`` on a
            model with candidate parameters (:meth:`set_hook`).

    Attributes:
        backend: the concrete backend of ``config.backend`` (``numpy``, ``taichi-cpu`` or
            ``taichi-cuda``), resolved once at construction.
        step_hook: the hook the step calls: ``hook``, else a
            :class:`~sim_core.candidates.hook.CandidateHook` of the model's candidate parameters, else
            None (no extra terms).
        elastic_worker: an :class:`~sim_core.elastic_worker.ElasticWorker` that evaluates the largest
            fused elastic term (the gel's) in a second process while this one evaluates the others, on
            the fused CPU path; None (default) = everything here. The results are the same either way
            where the term's vertices are its own (:meth:`FusedElastic._evaluate_offloaded`).
    """

    def __init__(self, model: Model, config: SolverConfig | None = None, hook: StepHook | None = None) -> None:
        self.model = model
        self.config = config or SolverConfig()
        self.backend = resolve_backend(self.config.backend)
        self.linear_solver: SymmetricSolver = make_symmetric_solver(self.config.linear_solver)
        self._general_solver: LinearSolver | None = None  # LU for a non-PD projection="none" matrix
        self._full_from_upper = SymmetricExpansion()  # Newton matrix (upper triangle) -> full symmetric
        # evaluations the potentials' energy, gradient and Hessian calls share (sim_core.workspace)
        self.workspace = Workspace()
        self._revision = -1
        self._hook = checked_hook(hook)
        self.step_hook: StepHook | None = None
        # Optional worker process for the largest fused elastic term (sim_core.elastic_worker), None = off.
        self.elastic_worker = None
        self.notify_model_changed()  # the elastic terms, and the contact set and other caches (_new_caches)
        # Data of the last converged step, kept for the adjoint.
        self.last_record: StepRecord | None = None
        self.last_free_mask: np.ndarray | None = None
        # Solver holding the factorisation of last_hessian when that is the exact Hessian (valid
        # until the next step; forward sensitivities solve with it), else None.
        self.last_factorization: LinearSolver | SymmetricSolver | None = None

    @property
    def last_hessian(self) -> sp.csr_matrix | None:
        """The last converged step's Newton matrix (``last_record.hessian``; None before the first step)."""
        return None if self.last_record is None else self.last_record.hessian

    def reset_caches(self) -> None:
        """Forget what steps carry to the next besides the state: the workspace's evaluations
        (:mod:`sim_core.workspace`), the contact set's candidate lists and search state, the Newton matrix's union pattern (dynamic entries are kept until unused
        for 50 assemblies, so the pattern, PARDISO's ordering and the rounding of the solve depend
        on the steps before) and the last step's record. A rollout from a given state then gives
        the same result bit for bit whatever ran before it (the simulation's ``reset``, the sim
        node's ``~/reset``). The material terms (and their kernel backend) are kept.
        """
        self._new_caches()
        self.last_record = None
        self.last_free_mask = None
        self.last_factorization = None

    def _new_caches(self) -> None:
        """Fresh contact set, assembler (union pattern), fused-evaluator slot and an empty workspace."""
        self.workspace.clear()
        self.contact = ContactSet(self.model, backend=self.backend, workspace=self.workspace)
        self.assembler = HessianAssembler(self.model.dof_count)
        self._fused: FusedElastic | None = None
        self._fused_kept: dict[frozenset, FusedElastic] = {}  # by the sleeping bodies' names
        self._fixed_point: FixedPoint | None = None
        # the bodies asleep until now are woken (reported by the next step)
        self._woken_by_reset = getattr(self, "_sleep", None) and self._sleep.names or ()
        self._sleep = SleepSet(self.model, self.config.sleep_velocity)
        self._last_update: np.ndarray | None = None  # the last step's StepTerms.last_update
        self._last_contact_terms: list = []  # the contact terms at the last step's result
        # (step terms, accepted x) of the last step when its Newton matrix is not the exact Hessian at x,
        # and the assembler and solver that factorise that Hessian on request (exact_factorization)
        self._inexact_step: tuple[StepTerms, np.ndarray] | None = None
        self._exact_parts: tuple[HessianAssembler, SymmetricSolver] | None = None
        self._refactorised: SymmetricSolver | None = None
        self._free_dofs = FreeDofs()  # the step's free and fixed DoFs, kept for a read-only boundary mask

    def notify_model_changed(self) -> None:
        """Rebuild everything that depends on material parameters (call after ``set_parameter``)."""
        self.elastic = self._new_elastic_terms()
        self.vertex_mass = self.model.vertex_mass()
        self._new_caches()
        self.step_hook = self._resolve_hook()
        self._revision = self.model.revision

    def _new_elastic_terms(self) -> ElasticTerms:
        """The model's elastic terms (:meth:`notify_model_changed`; a subclass may make its own kind)."""
        return ElasticTerms(self.model, workspace=self.workspace)

    def set_hook(self, hook: StepHook | None) -> None:
        """Use ``hook`` for the extra terms of the next steps (None: the model's candidates, if any).

        Raises:
            ConfigError: ``hook`` is not a :class:`~sim_core.candidates.hook.StepHook`, or the model
                has candidate parameters (one source of extra terms at a time).
        """
        self._hook = checked_hook(hook)
        self.step_hook = self._resolve_hook()
        self._fixed_point = None
        self._sleep.wake_all()

    def _resolve_hook(self) -> StepHook | None:
        """The explicit hook, else a :class:`CandidateHook` of the model's candidates, else None.

        Raises:
            ConfigError: both an explicit hook and candidate parameters.
        """
        if self._hook is not None:
            if self.model.candidates:
                raise ConfigError(f"NewtonSolver: a step hook ({type(self._hook).__name__}) and the model's candidate "
                                  f"parameters {sorted(self.model.candidates)} are both set; use one of them")
            return self._hook
        return CandidateHook(self.model.candidates) if self.model.candidates else None

    # ------------------------------------------------------------------ step
    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> StepInfo:
        """Advance ``state_in`` by ``dt`` into ``state_out`` (only ``state_out`` is written).

        Raises:
            SimulationDivergedError: Newton did not converge (after the configured dt halvings),
                naming the step index and time.
            ConfigError: invalid control (non-finite pose, unknown effector).
        """
        if self._revision != self.model.revision:
            self.notify_model_changed()
        control = control or Control()
        for name in control.effector_pose_target:
            if name not in self.model.effectors:
                raise ConfigError(f"unknown effector {name!r} in control; known: {list(self.model.effectors)}")
        if not dt > 0:
            raise ConfigError(f"dt must be > 0, got {dt}")
        guess = control.position_guess
        if guess is not None:
            guess = np.asarray(guess, dtype=float)
            if guess.shape != state_in.x.shape or not np.all(np.isfinite(guess)):
                raise ConfigError(f"control position_guess must be finite positions of shape {state_in.x.shape}, "
                                  f"got shape {guess.shape}" + ("" if guess.shape != state_in.x.shape else " with NaN/inf"))
        t0 = time.perf_counter()
        joint = control.compression is not None  # a series spring's compression among the unknowns
        # a guess's positions of a sleeping body are replaced by its held ones (_set_up_step: its DoFs are fixed); a
        # joint step's compression ties the driven base only, which never sleeps (sleeping_eligible)
        sleeping = self.config.sleeping and self.step_hook is None
        woken = sorted(set(self._woken_by_reset) | set([] if sleeping else self._sleep.wake_all()))
        self._woken_by_reset = ()
        repeat = self.config.repeat_fixed_points and guess is None and self.step_hook is None and not joint
        if repeat and not woken:
            # a fixed point of this sleeping set (its Dirichlet mask holds them) from bitwise this state
            # and inputs: the wake test passed when it was solved and would pass again
            info = self._repeat_fixed_point(state_in, state_out, control, dt)
            if info is not None:
                info.sleeping = self._sleep.names
                info.time_total = time.perf_counter() - t0
                return info
        if sleeping and self._sleep.bodies:
            fixed, x_target = self.boundary(state_in, control)[:2]
            woken = sorted(set(woken) | set(self._sleep.wake_before_step(state_in, self._step_inputs(dt), x_target,
                                                                         fixed, dt)))
        self._fixed_point = None
        redos = 0
        while True:
            try:
                info = self._solve(state_in, state_out, control, dt, guess, repeat)
            except Woken as err:  # a sleeping body was reached during the solve: solve again with it awake
                self._sleep.wake(err.bodies)
                woken = sorted(set(woken) | set(err.bodies))
                redos += 1
                continue
            info.woken, info.wake_redos = tuple(woken), redos
            if sleeping and info.retries == 0 and info.converged_strict:
                info.fell_asleep = tuple(self._sleep.fall_asleep(
                    state_in, state_out, self._last_update, dt, self._last_contact_terms, self._step_inputs(dt),
                    lambda name, x: self.elastic.body_energy(name, x, state_out.hinge_theta_bar)))
            info.time_total = time.perf_counter() - t0
            return info

    def _solve(self, state_in: State, state_out: State, control: Control, dt: float, guess: np.ndarray | None,
               repeat: bool) -> StepInfo:
        """The step solved, retried in substeps as configured (``SolverConfig.dt_halvings_on_failure``);
        kept as the fixed point when ``repeat`` and it left the state at rest.

        Raises:
            SimulationDivergedError: see :meth:`step`.
            Woken: a contact candidate pair joined a sleeping body to a moving vertex.
        """
        retries = 0
        while True:
            n_sub = 2 ** retries
            try:
                info = self._step_substeps(state_in, state_out, control, dt, n_sub, guess if n_sub == 1 else None)
            except SimulationDivergedError as err:
                # no substeps with a compression among the unknowns: its damper and reach are the step's
                if retries < self.config.dt_halvings_on_failure and control.compression is None:
                    retries += 1
                    continue
                if retries == 0:
                    raise
                raise SimulationDivergedError(
                    f"step {state_in.step_index} (t = {state_in.t:.6g} s): Newton failed at dt = {dt:g} s and at "
                    f"every substep down to dt/{n_sub} = {dt / n_sub:.3g} s ({retries} retries, "
                    f"SolverConfig.dt_halvings_on_failure exhausted); last failure: {err}",
                    step_index=state_in.step_index, t=state_in.t) from err
            info.retries = retries
            info.sleeping = self._sleep.names
            if repeat and retries == 0:
                self._fixed_point = self._as_fixed_point(state_in, state_out, dt, info)
            return info

    def _step_inputs(self, dt: float) -> tuple:
        """What a step depends on besides its state and Dirichlet data: the model's revision, gravity,
        damping and friction table, ``dt`` and the solver settings (compared by value)."""
        model = self.model
        scale = model.vertex_gravity_scale
        return (model.revision, float(dt), np.asarray(model.gravity, dtype=float).tobytes(), float(model.damping),
                None if scale is None else np.asarray(scale, dtype=float).tobytes(),
                tuple(model.friction.items()), self.config)

    def _as_fixed_point(self, state_in: State, state_out: State, dt: float, info: StepInfo) -> FixedPoint | None:
        """The step just taken from ``state_in`` to ``state_out`` as a :class:`FixedPoint`, when it left
        the state unchanged (positions, zero velocity, poses, openings, rest angles, contact memory)
        and was accepted by a strict test in one (sub)step; else None."""
        rec = self.last_record
        if (rec is None or not info.converged_strict or info.substeps != 1 or np.any(state_in.v)
                or not same_resting_state(state_out, state_in, with_velocity=False)):
            return None
        # a copy of the settings: the kept ones compare by value with the solver's (a dataclass's ==)
        inputs = self._step_inputs(dt)[:-1] + (dataclasses.replace(self.config),)
        return FixedPoint(inputs=inputs, state=state_out.copy(), fixed=rec.fixed, x_target=rec.x_target,
                           poses=rec.effector_pose, openings=rec.gripper_opening, limited=list(rec.limited_effectors),
                           info=dataclasses.replace(info))

    def _repeat_fixed_point(self, state_in: State, state_out: State, control: Control, dt: float) -> StepInfo | None:
        """Take the kept fixed point's result into ``state_out`` when ``state_in``, the Dirichlet data
        ``control`` resolves to (with the sleeping bodies held) and the other inputs
        (:meth:`_step_inputs`) are bitwise its own (``SolverConfig.repeat_fixed_points``); its
        :class:`StepInfo` (``repeated``). None otherwise (nothing written)."""
        fp = self._fixed_point
        if fp is None or self._revision != self.model.revision:
            return None
        kept = fp.state
        if not (same_resting_state(state_in, kept, with_velocity=True) and self._step_inputs(dt) == fp.inputs):
            return None
        fixed, x_target, poses, openings, limited = self.boundary(state_in, control)
        if self._sleep.bodies:
            fixed = fixed | self._sleep.mask  # the step's Dirichlet mask holds the sleeping bodies
        if not (same_array(fixed, fp.fixed) and same_array(x_target, fp.x_target) and same_arrays(poses, fp.poses)
                and openings == fp.openings and limited == fp.limited):
            return None
        out = kept.copy()
        out.t = state_in.t + dt
        out.step_index = state_in.step_index + 1
        out.candidate_state = state_in.candidate_state
        copy_state_into(out, state_out)
        done = fp.info
        return StepInfo(residual_velocity=done.residual_velocity, energy=done.energy, limited_effectors=list(limited),
                        stop_reason=done.stop_reason, converged_strict=done.converged_strict,
                        accepted_tolerance=done.accepted_tolerance, repeated=True)

    def warm_up(self, state: State, control: Control | None = None) -> None:
        """Build, before the first step from ``state``, the per-model structures that step would build
        before its first Newton iteration and later steps reuse: on the fused path (``_fused_path``) the
        fused elastic evaluator bound to the assembler's static sparsity pattern of the state's Dirichlet
        mask with ``control`` (:meth:`_fused_elastic`; Forming: about 30 ms); with
        ``SolverConfig.sleeping``, also those of the steps with every body that may sleep asleep
        (their vertices held; the bundled press_slide scene's card: about 8 ms at its first sleeping
        step otherwise). Steps give the same results with or without it (the step finds the evaluator
        and pattern built); a missing-physics candidate body term with a fused part changes the
        pattern, which its first step then builds as before.

        Raises:
            ConfigError: invalid control (:meth:`boundary`).
        """
        if self._revision != self.model.revision:
            self.notify_model_changed()
        if not self._fused_path():
            return
        fixed = self.boundary(state, control or Control())[0]
        asleep = frozenset(self._sleep.bodies)
        if self.config.sleeping and self._sleep.eligible:
            # the evaluator and pattern of the steps with every body that may sleep asleep (a resting
            # scene's; sim_core.sleeping): the first such step would build them (Forming-sized: ms)
            every = frozenset(self._sleep.eligible)
            held = fixed | self._sleep.mask_of(every)
            self._fused_elastic(self.elastic.potentials(state.hinge_theta_bar, skip=every), state.x,
                                np.repeat(~held, 3), asleep=every)
        if asleep:
            fixed = fixed | self._sleep.mask
        self._fused_elastic(self.elastic.potentials(state.hinge_theta_bar, skip=asleep), state.x,
                            np.repeat(~fixed, 3), asleep=asleep)

    def _step_substeps(self, state_in: State, state_out: State, control: Control, dt: float, n_sub: int,
                       guess: np.ndarray | None = None) -> StepInfo:
        """The step of ``dt`` from ``state_in`` as ``n_sub`` substeps of ``dt / n_sub`` into ``state_out``
        (written only when every substep succeeds); their :class:`StepInfo` summed. Every substep
        keeps the step's index (so that a failure names it); ``state_out`` gets index + 1 and time
        ``t + dt``."""
        s = state_in.copy()
        total = StepInfo(substeps=n_sub)
        for _ in range(n_sub):
            nxt = s.copy()
            info = self._single_step(s, nxt, control, dt / n_sub, guess=guess)
            nxt.step_index = state_in.step_index
            total.add_substep(info)
            s = nxt
        s.step_index = state_in.step_index + 1
        s.t = state_in.t + dt
        copy_state_into(s, state_out)
        return total

    def boundary(self, state: State, control: Control) -> tuple[np.ndarray, np.ndarray, dict, dict, list[str]]:
        """Dirichlet data of the step: fixed-vertex mask, their target positions, new effector poses.

        Returns:
            ``(fixed (n,) bool, x_target (n,3), poses, openings, limited_effector_names)``.
        """
        model = self.model
        fixed = model.vertex_fixed.copy()
        x_target = state.x.copy()
        poses, openings, limited = {}, {}, []
        for name, eff in model.effectors.items():
            pose = state.effector_pose[name]
            target = control.effector_pose_target.get(name)
            if target is not None:
                pose, was_limited = limit_pose_step(pose, target, eff.max_translation_per_step, eff.max_rotation_per_step)
                if was_limited:
                    limited.append(name)
            opening = float(control.gripper_target.get(name, state.gripper_opening.get(name, eff.initial_opening)))
            poses[name] = pose
            openings[name] = opening
            fixed[eff.vertices] = True
            x_target[eff.vertices] = driven_positions(eff, pose, opening)
        return fixed, x_target, poses, openings, limited

    def general_solver(self) -> LinearSolver:
        """The solver's LU solver (general square matrices), created on first use and kept: PARDISO's
        set-up searches the disk for MKL (about 1 s), which each replay of a fit would repeat."""
        if self._general_solver is None:
            self._general_solver = make_linear_solver(self.config.linear_solver)
        return self._general_solver

    def _projections(self) -> tuple[str, ...]:
        """Element-Hessian projections to try in order each iteration (see ``exact_hessian_first``)."""
        cfg = self.config
        if cfg.exact_hessian_first and cfg.projection != "none" and self.linear_solver.detects_indefinite:
            return ("none", cfg.projection)
        return (cfg.projection,)

    def _fused_path(self) -> bool:
        """Whether the elastic terms go through :class:`FusedElastic` (a Taichi :attr:`backend`, and the
        exact Hessian is tried first)."""
        return uses_taichi(self.backend) and "none" in self._projections()

    def _fused_elastic(self, elastic_terms: list, x: np.ndarray, free: np.ndarray,
                       asleep: frozenset[str] | None = None) -> FusedElastic | None:
        """The step's fused elastic evaluator (Taichi kernels) bound to the assembler's static
        pattern, on a Taichi :attr:`backend` when the exact Hessian is tried first; else None (the
        reference potentials). One is kept per sleeping set: ``asleep`` (default: the bodies asleep
        now), whose elastic terms ``elastic_terms`` leave out and whose vertices ``free`` holds."""
        if not self._fused_path():
            return None
        key = frozenset(self._sleep.bodies) if asleep is None else asleep
        self._fused = self._fused_kept[key] = FusedElastic.for_terms(self._fused_kept.get(key), elastic_terms)
        self._fused.bind(self.assembler.static_pattern(self._fused.block_vertex_arrays(x), free))
        # the worker runs Taichi's CPU backend: only beside CPU kernels (the same kernels, the same values)
        self._fused.offload = self.elastic_worker if self.backend == "taichi-cpu" else None
        return self._fused

    def _single_step(self, state_in: State, state_out: State, control: Control, dt: float,
                     guess: np.ndarray | None = None) -> StepInfo:
        """One implicit-Euler step of ``dt`` from ``state_in`` into ``state_out`` (no dt halving).

        Sets up the step's incremental potential (:meth:`_set_up_step`), runs the Newton iterations
        (:meth:`_newton_iterations`) and writes the outputs (:meth:`_finish_step`).

        Raises:
            SimulationDivergedError: non-finite gradient or Newton update, a line search that failed
                with no relaxed acceptance and no stale contact side to release, or no convergence in
                ``max_iterations`` (the message names the step index and time).
        """
        info = StepInfo()
        step, x = self._set_up_step(state_in, control, dt, guess, info)
        x, H, projection, factorization = self._newton_iterations(step, x, guess is not None, info)
        self._finish_step(step, x, H, projection, factorization, state_out, info)
        self._last_update = step.last_update
        return info

    # -------------------------------------------------------------- the parts of one step
    def _set_up_step(self, state_in: State, control: Control, dt: float, guess: np.ndarray | None,
                     info: StepInfo) -> tuple[StepTerms, np.ndarray]:
        """The step's Dirichlet data and the terms of its incremental potential, and the first iterate
        (``guess`` or ``x^n``, with the fixed vertices at their targets), shape ``(n, 3)``."""
        cfg = self.config
        model = self.model
        fixed, x_target, poses, openings, info.limited_effectors = self.boundary(state_in, control)
        asleep = frozenset(self._sleep.bodies)
        if asleep:
            fixed = fixed | self._sleep.mask  # held at their positions (x_target is state_in.x there)
        compression, carried_poses = None, poses
        if control.compression is not None:  # the base kept free, tied to the compression (sim_core.drive_compression)
            compression = self._compression(state_in, control, fixed, x_target, poses, openings, info)
            carried_poses = compression.start_poses(poses)
        (free, fixed_dofs), x_n = self._free_dofs(fixed), state_in.x
        x = x_n.copy() if guess is None else guess.copy()
        if cfg.carried_start and guess is None:  # the effectors' solids moved with them (sim_core.carried_start)
            carry_driven_bodies(model, x_n, state_in.v, dt, state_in.effector_pose, state_in.gripper_opening,
                                carried_poses, openings, fixed, x_target, x)
        np.copyto(x, x_target, where=fixed_dofs)  # the fixed vertices at their targets (one pass, no gather)
        if compression is not None:  # the base at the start compression
            x[compression.base] = x_target[compression.base]
        x_hat, mass = x_n + dt * state_in.v, self.vertex_mass
        gravity_mass = mass if model.vertex_gravity_scale is None else mass * model.vertex_gravity_scale
        fixed_terms = [InertiaPotential(mass, x_hat, dt), GravityPotential(gravity_mass, model.gravity)]
        diag = fixed_terms[0].hessian_diagonal()
        if model.damping > 0:
            damp = ViscousDamping(mass, x_n, model.damping, dt)
            fixed_terms.append(damp)
            diag = diag + damp.hessian_diagonal()
        elastic_terms = self.elastic.potentials(state_in.hinge_theta_bar, skip=asleep)
        fixed_terms += elastic_terms
        fused = None
        if self.step_hook is None and self.elastic_worker is not None:
            # the fused terms are the elastic terms: the worker evaluates them at the first iterate
            # (FusedElastic.start) while the contact and friction terms are set up
            fused = self._fused_elastic(elastic_terms, x, free)
            if fused is not None:
                fused.start(x)
        self.contact.held = self._sleep.mask if asleep else None  # their pairs apart leave the candidates
        memory = self.contact.begin_step(x_n, state_in.contact_memory)
        friction = self.contact.friction(x_n, dt, memory, held=self._sleep.mask if asleep else None)
        if friction is not None:
            fixed_terms.append(friction)
        cand_contact, cand_body = ([], []) if self.step_hook is None else self.step_hook.terms(
            model, state_in, x_n, dt, self.elastic, friction)
        fixed_terms += cand_contact + cand_body
        # body terms with a fused part (the sheets' anisotropic bending; the gels' Maxwell branches, a
        # Stable Neo-Hookean on their relaxed rest state) join the fused kernels with the elastic terms
        fused_body = [p for p in cand_body if fusable(p)] if self._fused_path() else []
        if fused is None:
            fused = self._fused_elastic(elastic_terms + fused_body, x, free)
        if fused is not None:  # the friction and contact kernels read the positions it copies to the device
            fused.offer_positions(self.workspace)
        # the terms the Newton loop evaluates: the fused elastic evaluator in place of the elastic terms,
        # and no gravity term in zero gravity (its energy and gradient are zeros: the sums are the same)
        replaced = (elastic_terms + fused_body if fused is not None else []) + (
            [fixed_terms[1]] if not np.any(model.gravity) else [])
        loop_terms = [p for p in fixed_terms if not any(p is q for q in replaced)] + ([fused] if fused is not None else [])
        cand_dynamic = cand_contact + [p for p in cand_body if not any(p is q for q in fused_body)]
        # the simplified Newton test (SolverConfig.simplified_newton_check): only with penalty-like contacts
        # whose switches the test compares (the library's, a candidate's adhesion) and lagged friction (a
        # candidate's stiction may switch within a step; a body term is not compared); not where the last update
        # is applied (SolverConfig.apply_last_update: the correction of the previous matrix is not second order)
        if compression is not None:  # the spring's energy read with the step's (its Hessian: the border)
            loop_terms.append(compression)
        simplified = (cfg.simplified_newton_check > 0 and not cfg.apply_last_update and not cand_body
                      and all(declares(p, PenaltyContact) for p in cand_contact)
                      and (friction is None or isinstance(friction, LaggedFriction)))
        step = StepTerms(
            state_in=state_in, dt=dt, fixed=fixed, free=free, x_target=x_target, poses=poses, openings=openings,
            x_n=x_n, diag=diag, fixed_terms=fixed_terms, elastic_terms=elastic_terms, fused=fused,
            loop_terms=loop_terms, friction=friction, cand_contact=cand_contact,
            dynamic_terms=([friction] if friction is not None else []) + cand_dynamic, memory=memory,
            max_displacement=cfg.max_displacement or (0.5 * model.contact.eps + 2e-3), simplified=simplified,
            compression=compression,
        )
        return step, x

    def _compression(self, state_in: State, control: Control, fixed: np.ndarray, x_target: np.ndarray,
                     poses: dict, openings: dict, info: StepInfo) -> CompressionPotential:
        """The step's :class:`~sim_core.drive_compression.CompressionPotential` of ``control.compression``: its
        effector's vertices (the base) freed in ``fixed`` and at the start compression in ``x_target``; the
        effector's pose in ``poses`` its anchor (all written). The anchor is the target with the
        effector's rotation limit only: the tool ends the step where the spring's balance puts it, and the
        anchor runs ahead of it by the compression (``b = F / k_s``: a few mm for newtons on an arm's spring,
        which the per-step translation limit of a kinematic effector would clip).

        Raises:
            ConfigError: an unknown effector.
        """
        unknown = control.compression
        name = unknown.effector
        if name not in self.model.effectors or name not in control.effector_pose_target:
            raise ConfigError(f"control compression: effector {name!r} is not among the control's targets "
                              f"{list(control.effector_pose_target)} and the model's {list(self.model.effectors)}")
        eff = self.model.effectors[name]
        poses[name], rotated = limit_pose_step(state_in.effector_pose[name], control.effector_pose_target[name],
                                               np.inf, eff.max_rotation_per_step)
        info.limited_effectors = [n for n in info.limited_effectors if n != name] + ([name] if rotated else [])
        base = np.asarray(eff.vertices, dtype=np.int64)
        anchored = driven_positions(eff, poses[name], openings[name])
        scale = self.model.vertex_gravity_scale
        loads = np.asarray(unknown.load_vertices, dtype=np.int64)
        mass = self.vertex_mass[loads] * (1.0 if scale is None else np.asarray(scale, dtype=float)[loads])
        weight = float(np.dot(unknown.axis, float(np.sum(mass)) * np.asarray(self.model.gravity, dtype=float)))
        potential = CompressionPotential(unknown, base, anchored, weight, np.repeat(~fixed, 3))
        fixed[base] = False
        x_target[base] = potential.positions(unknown.start)
        return potential

    def _newton_iterations(self, step: StepTerms, x: np.ndarray, guessed: bool,
                           info: StepInfo) -> tuple[np.ndarray, sp.csr_matrix, str, LinearSolver | SymmetricSolver]:
        """Newton iterations from ``x`` until a stopping test accepts an iterate (:func:`~sim_core.newton_stop.stop_reason`,
        the simplified Newton test, rate stopping, or a failed line search at a relaxed tolerance).

        Records in ``info`` the iterations, the residual, how the step ended (``stop_reason``,
        ``accepted_tolerance``, ``converged_strict``) and the line-search and relaxed-acceptance counts.

        Returns:
            ``(x, H, projection, factorization)``: the accepted positions ``(n, 3)`` in m, the
            upper triangle of the last Newton matrix, its element-Hessian projection and the solver
            holding its factorisation.

        Raises:
            SimulationDivergedError: see :meth:`_single_step`.
        """
        cfg = self.config
        dt = step.dt
        residual = np.inf
        history: list[float] = []  # scaled Newton update sizes (m/s), one per iteration
        # the simplified Newton test runs only after an iteration that factorised the exact Hessian and
        # took its full step (simplified_ok), at the same touching contacts (active_before)
        simplified_ok = False
        active_before = None
        H, projection, factorization = None, cfg.projection, self.linear_solver
        for it in range(1, cfg.max_iterations + 1):
            contact_terms, x_search, g = self._gradient(step, x, it, info)
            if (simplified_ok and active_before is not None
                    and same_active_contacts(active_contacts(contact_terms + step.cand_contact, x), active_before)):
                residual_bar, d_bar = self._simplified_correction(step, g, info)
                if residual_bar < cfg.simplified_newton_check * cfg.tol_velocity:
                    info.simplified_stops = 1
                    step.last_update = d_bar
                    accept(self.config, info, it, residual_bar, "simplified")
                    return x, H, projection, factorization
            active_before = None
            d, H, projection, factorization = self._newton_direction(step, x, g, contact_terms, it, info)
            d3 = d.reshape(-1, 3)
            step_max = largest_move(d)
            residual = step_max / dt
            history.append(residual)
            reason = stop_reason(self.config, residual,
                                 g if step.compression is None else step.compression.reduced_gradient(g), history)
            if reason is not None:
                if cfg.apply_last_update and reason in STRICT_STOPS:
                    # the update just solved for, taken in full (no line search: a step this small is in the
                    # quadratic region); a stalled stop keeps x (its update is round-off;
                    # SolverConfig.apply_last_update)
                    step.last_update, step.applied = d, True
                    accept(self.config, info, it, residual, reason)
                    return x + d3, H, projection, factorization
                if not (guessed and it == 1):
                    step.last_update = d if reason in STRICT_STOPS else None
                    accept(self.config, info, it, residual, reason)
                    return x, H, projection, factorization
                # a guess already within the tolerance: take its Newton correction (no line search:
                # a step this small is in the quadratic region) and test again, so that the result
                # is the guess corrected to second order, not the guess itself (which would tie
                # nearby replays to the one the guess came from: finite differences would vanish)
                x = x + d3
                continue
            if step.simplified and projection == "none" and factorization is self.linear_solver:
                # the contacts touching at x (and the candidate's open adhesion pairs), for the simplified
                # test at the next iterate (which needs this iteration's exact factorisation)
                active_before = active_contacts(contact_terms + step.cand_contact, x)
            alpha = min(1.0, step.max_displacement / step_max) if step_max > 0 else 1.0
            e0 = self._energy(step, x, contact_terms, x_search)
            slope = float(g @ d)
            if slope >= 0:  # not a descent direction (should not happen with a PD matrix)
                d = -g
                d3 = d.reshape(-1, 3)
                slope = float(g @ d)
            # rate stopping ends the step on this update if it is taken in full
            rate_stop = cfg.rate_stopping and len(history) > 1 and rate_stops(history, cfg.tol_velocity)
            # the elastic terms' (and the Taichi friction's and the pair contacts') energy, gradient and
            # Hessian at the first trial point in one evaluation when, once accepted (backtracks are
            # rare), it is the next iterate
            prefetch = step.fused is not None and not (alpha == 1.0 and rate_stop)
            x_new, backtracks = self._line_search(step, x, d3, alpha, e0, slope, contact_terms, x_search,
                                                  prefetch, info)
            if x_new is None:
                info.line_search_failures += 1
                reason = line_search_failure_acceptance(self.config, slope, e0, residual)
                if reason is not None:
                    accept(self.config, info, it, residual, reason)
                    return x, H, projection, factorization
                released = self.contact.release_stale_sides(x, step.memory)
                if released:
                    # a pair gone round its partner kept a side that puts a step in the energy where
                    # x stands (ContactSet.release_stale_sides); unsigned, the energy at x is the same
                    # and the next iteration's Newton direction can descend
                    info.released_sides += released
                    simplified_ok = False  # x did not move, its energy did: no test at the next iteration
                    continue
                raise self._diverged(step, f"line search failed at Newton iteration {it} (no decrease along "
                                           f"the Newton direction; residual {residual:.3g} m/s)")
            x = x_new
            full_step = alpha == 1.0 and backtracks == 0
            simplified_ok = (step.simplified and full_step and projection == "none"
                             and factorization is self.linear_solver)
            if backtracks >= cfg.stale_side_backtracks:
                # a line search this short may be Newton creeping up to a step in the energy from a
                # stale side (ContactSet.release_stale_sides); nothing changes when there is none
                info.released_sides += self.contact.release_stale_sides(x, step.memory)
            if rate_stop and full_step:
                theta = residual / history[-2]
                accept(self.config, info, it, residual * (theta / (1.0 - theta)), "rate")  # the estimated remaining error
                return x, H, projection, factorization
        raise self._diverged(
            step, f"Newton did not converge in {cfg.max_iterations} iterations (residual {residual:.3g} m/s > "
                  f"tol {cfg.tol_velocity:g}; last residuals {', '.join(f'{r:.2g}' for r in history[-6:])}; "
                  f"{info.backtracks} backtracks)")

    def _gradient(self, step: StepTerms, x: np.ndarray, it: int,
                  info: StepInfo) -> tuple[list, np.ndarray | None, np.ndarray]:
        """The contact potentials at ``x``, the position their candidate search was made at, and the
        free-DoF gradient of the incremental potential at ``x`` (J/m, shape ``(3 n,)``, zero on fixed
        DoFs).

        Raises:
            SimulationDivergedError: the gradient is not finite.
        """
        ta = time.perf_counter()
        first = None if step.fused is None else step.fused.gradient(x)  # (x then on the device for the others)
        contact_terms = self.contact.potentials(x, step.x_n, step.memory)
        self._check_asleep_unreached(contact_terms, x)
        x_search = self.contact.search_position
        g = sum(first if p is step.fused else p.gradient(x) for p in step.loop_terms + contact_terms).reshape(-1)
        g[~step.free] = 0.0
        if not np.all(np.isfinite(g)):
            raise self._diverged(step, f"non-finite gradient at Newton iteration {it}")
        info.time_assembly += time.perf_counter() - ta
        return contact_terms, x_search, g

    def _simplified_correction(self, step: StepTerms, g: np.ndarray, info: StepInfo) -> tuple[float, np.ndarray]:
        """Scaled size (m/s) of the simplified Newton correction ``H(x_{k-1})^{-1} g(x_k)`` with the
        last factorisation (``SolverConfig.simplified_newton_check``), and the correction (m, ``(3 n,)``)."""
        tl = time.perf_counter()
        joint = step.compression
        if joint is None:
            d_bar = self.linear_solver.solve(g)
        else:  # the reduced system's, with the border of the factorised matrix (its Schur complement was positive)
            d_bar = -joint.direction(self.linear_solver.solve, g, *joint.last_border)
        d_bar[~step.free] = 0.0
        info.time_linear_solve += time.perf_counter() - tl
        return largest_move(d_bar) / step.dt, d_bar

    def _assemble_hessian(self, step: StepTerms, x: np.ndarray, projection: str,
                          dynamic_terms: list, assembler: HessianAssembler | None = None) -> sp.csr_matrix:
        """Upper triangle (CSR) of the constrained Newton matrix at ``x`` with element Hessians
        projected by ``projection`` ("none": exact), by ``assembler`` (default: the Newton loop's)."""
        assembler = self.assembler if assembler is None else assembler
        fused = step.fused
        if fused is not None:
            values = (fused.hessian_values(x) if projection == "none"
                      else fused.projected_hessian_values(x, projection))
            return assembler.assemble_upper_values(fused.pattern, values,
                                                   [p.hessian(x, projection) for p in dynamic_terms],
                                                   step.diag, step.free)
        return assembler.assemble_upper([p.hessian(x, projection) for p in step.elastic_terms],
                                        [p.hessian(x, projection) for p in dynamic_terms], step.diag, step.free)

    def exact_factorization(self) -> LinearSolver | SymmetricSolver | None:
        """A solver holding the factorisation of the constrained exact Hessian at the last step's accepted
        positions, the matrix forward tangents solve with (:mod:`sim_core.sensitivity`); valid until the next step.

        That is :attr:`last_factorization` where the step's last Newton matrix is that Hessian. Otherwise (a step
        ended by the simplified Newton test or with its last update applied holds the matrix of the iterate before
        ``x``; a projected matrix)
        the exact Hessian at ``x`` is assembled from the step's own terms (fused elastic kernels, contacts at
        ``x``) and Cholesky-factorised once, by an assembler and a solver of their own, so that the Newton
        loop's union pattern and PARDISO's ordering, and so the next steps, are those of a replay without
        tangents; the step's record and :attr:`last_factorization` are left as they are.

        Returns:
            the solver; None before a step, with a linear solver other than ``pardiso`` / ``scipy``, or where
            the exact Hessian at ``x`` is not positive definite (the caller factorises the general way).
        """
        if self.last_factorization is not None or self._inexact_step is None:
            return self.last_factorization or self._refactorised
        step, x = self._inexact_step
        self._inexact_step = None
        if self.config.linear_solver not in ("pardiso", "scipy"):
            return None
        if self._exact_parts is None:
            self._exact_parts = (HessianAssembler(self.model.dof_count), make_symmetric_solver(self.config.linear_solver))
        assembler, solver = self._exact_parts
        if step.fused is not None:  # its values are in the slots of the Newton loop's static pattern
            assembler.use_pattern(step.fused.pattern)
        H = self._assemble_hessian(step, x, "none", self._last_contact_terms + step.dynamic_terms, assembler)
        if step.compression is not None:  # the kinematic step's matrix: the base held
            H = step.compression.constrained(H)
        self._refactorised = solver if solver.factorize(H) else None
        return self._refactorised

    def _newton_direction(self, step: StepTerms, x: np.ndarray, g: np.ndarray, contact_terms: list, it: int,
                          info: StepInfo) -> tuple[np.ndarray, sp.csr_matrix, str, LinearSolver | SymmetricSolver]:
        """The Newton update ``d = -H^{-1} g`` (m, shape ``(3 n,)``, zero on fixed DoFs): the exact
        Hessian when it factorises as positive definite, else the projected one (:meth:`_projections`),
        else (``projection="none"``, indefinite) the general LU.

        Returns:
            ``(d, H, projection, factorization)``: the update, the upper triangle of the matrix it
            solved with, that matrix's projection and the solver holding its factorisation.

        Raises:
            SimulationDivergedError: the update is not finite.
        """
        dynamic_terms = contact_terms + step.dynamic_terms
        d = None
        factorization = self.linear_solver
        joint = step.compression
        for projection in self._projections():
            ta = time.perf_counter()
            H = self._assemble_hessian(step, x, projection, dynamic_terms)
            if joint is not None:  # the base tied to the compression: the kinematic step's matrix and its border
                H, column, corner = joint.border(H)
                joint.last_border = (column, corner)
            tl = time.perf_counter()
            info.time_assembly += tl - ta
            info.factorizations += 1
            if self.linear_solver.factorize(H):
                d = (-self.linear_solver.solve(g) if joint is None
                     else joint.direction(self.linear_solver.solve, g, column, corner))
                info.projected_iterations += projection != "none" and d is not None
            info.time_linear_solve += time.perf_counter() - tl
            if d is not None:
                break
        if d is None:  # projection="none" and not positive definite: the general LU
            tl = time.perf_counter()
            info.factorizations += 1
            factorization = self.general_solver()
            factorization.factorize(self._full_from_upper(H))
            d = (-factorization.solve(g) if joint is None
                 else joint.direction(factorization.solve, g, column, corner, definite=False))
            info.time_linear_solve += time.perf_counter() - tl
        d[~step.free] = 0.0
        if not np.all(np.isfinite(d)):
            raise self._diverged(step, f"linear solve produced NaN at iteration {it}")
        return d, H, projection, factorization

    def _energy(self, step: StepTerms, x: np.ndarray, contact_terms: list, x_search: np.ndarray | None) -> float:
        """The incremental potential at ``x`` (J): the loop terms' energy, kept for the same array
        object (the accepted line-search point is the next iteration's ``e0``), plus the contacts'."""
        if step.loop_energy_x is not x:  # the fused terms first (x then on the device for the others), summed in order
            first = None if step.fused is None else step.fused.energy(x)
            step.loop_energy_x = x
            step.loop_energy = sum(first if p is step.fused else p.energy(x) for p in step.loop_terms)
        if not self.contact.covers(x_search, x):
            # a trial point beyond the iterate's candidate list: search again, so that every
            # trial point is measured with the same energy (no pair left out)
            contact_terms = self.contact.potentials(x, step.x_n, step.memory)
        return step.loop_energy + sum(p.energy(x) for p in contact_terms)

    def _line_search(self, step: StepTerms, x: np.ndarray, d3: np.ndarray, alpha: float, e0: float, slope: float,
                     contact_terms: list, x_search: np.ndarray | None, prefetch: bool,
                     info: StepInfo) -> tuple[np.ndarray | None, int]:
        """Backtracking (halving) line search from ``alpha`` along ``d3`` ``(n, 3)`` until the Armijo
        condition ``E(x + a d) <= E(x) + c a g.d`` holds (``c = armijo_c``, ``slope = g.d``).

        ``prefetch``: evaluate the fused elastic terms, the Taichi friction and the pair contacts with
        their derivatives at the first trial point.

        Returns:
            ``(x_new, backtracks)``: the accepted point ``(n, 3)`` and the halvings it took, or
            ``(None, max_backtracks)`` when ``max_backtracks`` halvings found no decrease.
        """
        cfg = self.config
        for backtrack in range(cfg.max_backtracks):
            x_new = x + alpha * d3
            if prefetch and backtrack == 0:
                step.fused.evaluate(x_new)
                if declares(step.friction, KeepsDerivatives):
                    step.friction.keep_derivatives(x_new)
                if self.contact.covers(x_search, x_new):  # else _energy searches again: new pairs
                    for p in contact_terms:
                        if declares(p, KeepsDerivatives):
                            p.keep_derivatives(x_new)
            if self._energy(step, x_new, contact_terms, x_search) <= e0 + cfg.armijo_c * alpha * slope:
                return x_new, backtrack
            alpha *= 0.5
            info.backtracks += 1
        return None, cfg.max_backtracks

    def _check_asleep_unreached(self, contact_terms: list, x: np.ndarray) -> None:
        """Raise :class:`Woken` when a contact candidate pair of ``contact_terms`` joins a sleeping body
        to a moving vertex, or a moving sphere comes near one, at ``x`` (:meth:`SleepSet.reached_by_pairs`)."""
        reached = self._sleep.reached_by_pairs(contact_terms, x) if self._sleep.bodies else []
        if reached:
            raise Woken(reached)

    @staticmethod
    def _diverged(step: StepTerms, what: str) -> SimulationDivergedError:
        """A :class:`SimulationDivergedError` naming the step index and time of ``step``."""
        state = step.state_in
        return SimulationDivergedError(f"step {state.step_index} (t = {state.t:.6g} s): {what}",
                                       step_index=state.step_index, t=state.t)

    @staticmethod
    def _compression_result(step: StepTerms, x: np.ndarray) -> tuple:
        """A joint step's result as the kinematic step's with the tool at the compression ``b`` of ``x``: ``(x,
        fixed, free, x_target, poses)`` with the base rigidly at ``X_base - b n`` (new arrays; round-off of the
        tied updates removed), held, and the effector's pose ``b`` behind its target along the axis."""
        joint = step.compression
        b = joint.compression(x)
        x = x.copy()
        x[joint.base] = joint.positions(b)
        fixed = step.fixed.copy()
        fixed[joint.base] = True
        x_target = step.x_target.copy()
        x_target[joint.base] = x[joint.base]
        name = joint.unknown.effector
        pose = np.array(step.poses[name], dtype=float)
        pose[:3] -= b * joint.axis
        return x, fixed, joint.free, x_target, {**step.poses, name: pose}

    def _contact_force(self, x: np.ndarray, terms: list) -> np.ndarray:
        """:func:`~sim_core.step_terms.contact_force` of the step's contact ``terms`` at its result ``x``."""
        return contact_force(x, terms)

    def _velocities(self, x: np.ndarray, x_n: np.ndarray, dt: float) -> np.ndarray:
        """The step's velocities ``(x - x^n) / dt`` (m/s, a new ``(n, 3)`` array) from its result ``x`` and start
        ``x_n`` (m) and ``dt`` (s): implicit Euler's ``v^{n+1}``."""
        return (x - x_n) / dt

    def _finish_step(self, step: StepTerms, x: np.ndarray, H: sp.csr_matrix, projection: str,
                     factorization: LinearSolver | SymmetricSolver, state_out: State, info: StepInfo) -> None:
        """Write the step's outputs at the accepted positions ``x`` ``(n, 3)`` into ``state_out``, its
        energy into ``info``, and keep the adjoint's :class:`StepRecord` and factorisation."""
        model = self.model
        state_in, dt, x_n = step.state_in, step.dt, step.x_n
        # a step ended by the simplified Newton test or on an applied update has the matrix of the iterate before x:
        # its tangents take the exact Hessian at x (exact_factorization), where the lagged friction's stick
        # stiffness may differ on the scale of that last update (a joint step's is the kinematic step's at x, its
        # border eliminated)
        exact = projection == "none" and not info.simplified_stops and not step.applied
        fixed, free, x_target, poses = step.fixed, step.free, step.x_target, step.poses
        if step.compression is not None:  # recorded as the kinematic step with the tool at the compression found
            x, fixed, free, x_target, poses = self._compression_result(step, x)
        contact_terms = self.contact.potentials(x, x_n, step.memory)
        self._check_asleep_unreached(contact_terms, x)
        self._last_contact_terms = contact_terms
        self.last_free_mask = free
        self.last_factorization = factorization if exact else None
        self._inexact_step, self._refactorised = (None if exact else (step, x)), None
        info.energy = (self._energy(step, x, contact_terms, self.contact.search_position) + self._sleep.energy
                       + (self.contact.held_friction_energy if self._sleep.bodies else 0.0))
        x_prev, v_prev, x_kept = (a if FrozenPositionsKey.holds(a) else a.copy() for a in (x_n, state_in.v, x))
        self.last_record = StepRecord(
            dt=dt, x_prev=x_prev, v_prev=v_prev, x=x_kept, fixed=fixed, x_target=x_target,
            effector_pose={k: np.array(v) for k, v in poses.items()}, gripper_opening=dict(step.openings),
            limited_effectors=list(info.limited_effectors), terms=step.fixed_terms + contact_terms,
            hinge_theta_bar={k: np.array(v) for k, v in state_in.hinge_theta_bar.items()}, hessian_upper=H,
            free_dofs=free, hessian_exact=exact, asleep=self._sleep.names, expansion=self._full_from_upper,
        )
        state_out.t = state_in.t + dt
        state_out.step_index = state_in.step_index + 1
        state_out.x = x
        state_out.v = self._velocities(x, x_n, dt)
        state_out.effector_pose = {k: np.array(v) for k, v in poses.items()}
        state_out.gripper_opening = dict(step.openings)
        state_out.contact_force = self._contact_force(
            x, contact_terms + ([step.friction] if step.friction is not None else []) + step.cand_contact)
        state_out.contact_memory = self.contact.end_step(x, step.memory)
        state_out.hinge_theta_bar = self.elastic.plastic_update(x, state_in.hinge_theta_bar)
        if self.step_hook is not None:
            state_out.candidate_state = self.step_hook.update_state(model, state_in, x, dt, self.elastic)
