"""What a Newton step reports (:class:`StepInfo`, summed over steps in :class:`StepTotals`) and what it
keeps for the adjoint (:class:`StepRecord`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from sim_core.linsolve import SymmetricExpansion


@dataclass
class StepRecord:
    """Everything the adjoint needs of one converged step (kept as ``NewtonSolver.last_record``).

    Attributes:
        dt: step size in s.
        x_prev: positions at the start ``x^n`` (m), shape ``(n, 3)``.
        v_prev: velocities at the start ``v^n`` (m/s), shape ``(n, 3)``.
        x: converged positions ``x^{n+1}``, shape ``(n, 3)``.
        fixed: Dirichlet vertices of the step (static + effector-driven), shape ``(n,)`` bool.
        x_target: prescribed positions of the fixed vertices, shape ``(n, 3)``.
        effector_pose: effector poses reached at the end of the step (after rate limiting).
        gripper_opening: finger openings of the step.
        limited_effectors: effectors whose command was rate-limited this step (their pose is then
            not differentiable w.r.t. the command in the usual sense).
        terms: the potentials of the incremental potential at the converged step, in the order
            inertia, gravity, [damping], elastic..., [friction], contact...
        hinge_theta_bar: rest angles used during the step (per sheet).
        hessian_upper: the upper triangle (CSR, sorted indices, ``(3 n, 3 n)``) of the constrained
            Newton matrix of the last iteration: the exact Hessian when it was positive definite,
            else the projected one. It is assembled at the last Newton iterate, which is ``x``
            except when ``SolverConfig.rate_stopping`` ended the step on an update, the step ended
            with its last update applied (``SolverConfig.apply_last_update``), or the simplified
            Newton test (``SolverConfig.simplified_newton_check``) ended it: then at the iterate
            before ``x``, within the Newton tolerance of ``x``. The full symmetric matrix is
            :attr:`hessian`.
        free_dofs: free DoF mask, shape ``(3 n,)`` bool.
        asleep: the bodies held asleep during the step (``SolverConfig.sleeping``): their vertices are
            in ``fixed`` and their elastic terms are not in ``terms`` (not the full system's linearisation).
        hessian_exact: ``hessian`` is the exact (unprojected) Hessian at ``x``, i.e. the matrix
            of the implicit-function-theorem linearisation (:mod:`sim_core.adjoint`).
        expansion: the :class:`~sim_core.linsolve.SymmetricExpansion` that builds :attr:`hessian`
            (the solver's, which keeps the index map of the current pattern); None: a new one.
    """

    dt: float
    x_prev: np.ndarray
    v_prev: np.ndarray
    x: np.ndarray
    fixed: np.ndarray
    x_target: np.ndarray
    effector_pose: dict
    gripper_opening: dict
    limited_effectors: list
    terms: list
    hinge_theta_bar: dict
    hessian_upper: sp.csr_matrix
    free_dofs: np.ndarray
    hessian_exact: bool = False
    asleep: tuple[str, ...] = ()
    expansion: SymmetricExpansion | None = field(default=None, repr=False, compare=False)

    @property
    def hessian(self) -> sp.csr_matrix:
        """The constrained Newton matrix of the last iteration (CSR, symmetric, sorted indices,
        ``(3 n, 3 n)``; see ``hessian_upper``), expanded from the upper triangle on first use and
        kept: a forward rollout never needs it, only the adjoint does."""
        full = self.__dict__.get("_hessian")
        if full is None:
            full = (self.expansion or SymmetricExpansion())(self.hessian_upper)
            self.__dict__["_hessian"] = full
        return full


STRICT_STOPS: tuple[str, ...] = ("velocity", "force", "simplified", "rate")
"""Stopping tests that accept a step at the strict tolerances: the Newton update below
``tol_velocity`` (``"velocity"``), the gradient below ``tol_force`` (``"force"``), the simplified
Newton correction below ``simplified_newton_check * tol_velocity`` (``"simplified"``), the rate
estimate of the remaining error below ``tol_velocity`` (``"rate"``)."""

RELAXED_STOPS: tuple[str, ...] = ("stalled", "line_search_relaxed", "line_search_roundoff")
"""Stopping tests that accept a step above ``tol_velocity`` (``StepInfo.relaxed_accepts``): a stalled
residual below ``stall_tolerance_factor * tol_velocity``; after a failed line search, a residual below
``line_search_tolerance_factor * tol_velocity`` or a predicted decrease below ``stationary_slope_rtol * |E|``."""


@dataclass
class StepInfo:
    """How one step ended. For a step taken as several substeps (``SolverConfig.dt_halvings_on_failure``)
    the counts and times are summed over its substeps, the residual and energy are the last substep's.

    Attributes:
        iterations: Newton iterations.
        residual_velocity: the accepted iterate's scaled Newton update ``max_i |dx_i| / dt``, m/s
            (for ``stop_reason == "rate"`` the estimated remaining error).
        energy: the incremental potential at the result, J.
        backtracks: line-search halvings.
        substeps: substeps the step was finally taken in (1, or ``2**retries``).
        retries: failed attempts redone with halved substeps (``SolverConfig.dt_halvings_on_failure``).
        limited_effectors: effectors whose command was rate-limited.
        time_assembly, time_linear_solve, time_total: s.
        projected_iterations: iterations whose Newton matrix had PSD-projected element blocks.
        released_sides: contact pairs whose side was released after a failed or very short line search
            (:meth:`ContactSet.release_stale_sides`).
        factorizations: Newton matrices factorised (a not positive definite exact Hessian and its
            projected fallback count two).
        simplified_stops: (sub-)steps that the simplified Newton test ended (their last iteration
            factorised nothing; ``SolverConfig.simplified_newton_check``).
        stop_reason: the test that accepted the step (:data:`STRICT_STOPS` or :data:`RELAXED_STOPS`;
            over substeps, the last relaxed one, else the last substep's).
        converged_strict: every (sub-)step was accepted by a strict test (:data:`STRICT_STOPS`).
        accepted_tolerance: the residual bound (m/s) the step was accepted under: ``tol_velocity`` for a
            strict test, ``stall_tolerance_factor * tol_velocity`` for a stalled step,
            ``line_search_tolerance_factor * tol_velocity`` after a failed line search, inf after a failed
            line search accepted on the round-off test alone; over substeps the largest.
        relaxed_accepts: (sub-)steps accepted by a relaxed test (:data:`RELAXED_STOPS`).
        stalled_accepts: of those, the stalled ones.
        line_search_failures: line searches that found no sufficient decrease in ``max_backtracks``
            halvings (accepted relaxed, followed by a released contact side, or raised).
        repeated: the step was not solved: its inputs were those of the step before, a fixed point
            (``SolverConfig.repeat_fixed_points``), whose result it took; ``residual_velocity``,
            ``energy``, ``stop_reason``, ``converged_strict`` and ``accepted_tolerance`` are that
            step's, the counts and times its own (no iteration, no factorisation).
        sleeping: the bodies held asleep during the step (``SolverConfig.sleeping``), sorted names.
        woken: the bodies woken at the step (before it, or during it: then the step was solved again), sorted.
        fell_asleep: the bodies that fell asleep after the step (they sleep from the next step on), sorted.
        wake_redos: times the step was solved again because a contact candidate pair joined a sleeping
            body to a moving vertex during the solve.
    """

    iterations: int = 0
    residual_velocity: float = 0.0
    energy: float = 0.0
    backtracks: int = 0
    substeps: int = 1
    limited_effectors: list[str] = field(default_factory=list)
    time_assembly: float = 0.0
    time_linear_solve: float = 0.0
    time_total: float = 0.0
    projected_iterations: int = 0
    released_sides: int = 0
    factorizations: int = 0
    simplified_stops: int = 0
    retries: int = 0
    stop_reason: str = ""
    converged_strict: bool = True
    accepted_tolerance: float = 0.0
    relaxed_accepts: int = 0
    stalled_accepts: int = 0
    line_search_failures: int = 0
    repeated: bool = False
    sleeping: tuple[str, ...] = ()
    woken: tuple[str, ...] = ()
    fell_asleep: tuple[str, ...] = ()
    wake_redos: int = 0

    def add_substep(self, info: "StepInfo") -> None:
        """Add substep ``info`` to this step's summary: its counts and times summed
        (:data:`SUMMED_COUNTS`), its residual and energy taken (the last substep's), the limited
        effectors merged, the stop reason the last relaxed one (else the last), strict only when
        every substep was, the accepted tolerance the largest."""
        for name in SUMMED_COUNTS:
            setattr(self, name, getattr(self, name) + getattr(info, name))
        self.residual_velocity = info.residual_velocity
        self.energy = info.energy
        self.limited_effectors = sorted(set(self.limited_effectors) | set(info.limited_effectors))
        if self.converged_strict or not info.converged_strict:
            self.stop_reason = info.stop_reason
        self.converged_strict = self.converged_strict and info.converged_strict
        self.accepted_tolerance = max(self.accepted_tolerance, info.accepted_tolerance)

    @property
    def needs_attention(self) -> bool:
        """Whether the step was accepted above the strict tolerance or needed substep retries."""
        return not self.converged_strict or self.retries > 0


SUMMED_COUNTS = ("iterations", "backtracks", "time_assembly", "time_linear_solve", "projected_iterations",
                  "released_sides", "factorizations", "simplified_stops", "relaxed_accepts", "stalled_accepts",
                  "line_search_failures")
"""The :class:`StepInfo` fields summed over the substeps of a step."""


@dataclass
class StepTotals:
    """How the steps since the last reset ended, summed over their :class:`StepInfo` (what a replay
    reports: :attr:`sim_core.simulation.Simulation.step_totals`).

    Attributes:
        steps: steps taken.
        substeps: substeps they were taken in (``steps`` when none was retried).
        retries: failed attempts redone with halved substeps, over all steps.
        retried_steps: steps that needed at least one retry.
        relaxed_steps: steps accepted above the strict tolerance (``not StepInfo.converged_strict``).
        relaxed_accepts, stalled_accepts, line_search_failures: summed as in :class:`StepInfo`.
        largest_accepted_tolerance: the largest ``StepInfo.accepted_tolerance``, m/s (0 before a step).
        first_relaxed_step: ``State.step_index`` at the start of the first relaxed or retried step, or None.
        repeated_steps: steps that repeated a fixed point instead of a solve (``StepInfo.repeated``).
        sleeping_steps: steps with at least one body asleep (``StepInfo.sleeping``).
        wake_redos: steps solved again after a sleeping body was reached (``StepInfo.wake_redos``), summed.
    """

    steps: int = 0
    substeps: int = 0
    retries: int = 0
    retried_steps: int = 0
    relaxed_steps: int = 0
    relaxed_accepts: int = 0
    stalled_accepts: int = 0
    line_search_failures: int = 0
    largest_accepted_tolerance: float = 0.0
    first_relaxed_step: int | None = None
    repeated_steps: int = 0
    sleeping_steps: int = 0
    wake_redos: int = 0

    def add(self, info: StepInfo, step_index: int) -> None:
        """Count the step that started at ``step_index`` and ended as ``info``."""
        self.steps += 1
        self.substeps += info.substeps
        self.retries += info.retries
        self.retried_steps += info.retries > 0
        self.relaxed_steps += not info.converged_strict
        self.relaxed_accepts += info.relaxed_accepts
        self.stalled_accepts += info.stalled_accepts
        self.line_search_failures += info.line_search_failures
        self.repeated_steps += info.repeated
        self.sleeping_steps += bool(info.sleeping)
        self.wake_redos += info.wake_redos
        self.largest_accepted_tolerance = max(self.largest_accepted_tolerance, info.accepted_tolerance)
        if info.needs_attention and self.first_relaxed_step is None:
            self.first_relaxed_step = int(step_index)
