"""Settings of the Newton solver (:class:`sim_core.solver.NewtonSolver`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_core.backend import check_backend
from sim_core.errors import ConfigError

CG_PRECISIONS = ("double", "mixed")
"""The batched CG's storage precisions (``SolverConfig.cg_precision``, :mod:`sim_core.ti_kernels.precision`)."""


@dataclass
class SolverConfig:
    """Newton settings.

    Attributes:
        tol_velocity: converged when ``max |dx_newton| / dt`` < this (m/s); 1e-4 m/s = 0.5 um per
            5 ms step, well below marker noise. Gradient checks use 1e-9. ThinShellLab: 1e-7.
        stall_iterations: accept (relaxed, counted in ``StepInfo.stalled_accepts``) a step whose
            residual is below ``stall_tolerance_factor * tol_velocity`` and has not dropped by 10 %
            over this many iterations (round-off-limited).
        stall_tolerance_factor: the relaxed tolerance of a stalled step, as a multiple of
            ``tol_velocity`` (>= 1; 1 never accepts a stalled step).
        line_search_tolerance_factor: a step whose line search fails (``max_backtracks`` halvings
            without sufficient decrease) is accepted (relaxed, counted in
            ``StepInfo.relaxed_accepts``) when its residual is below this multiple of
            ``tol_velocity`` (>= 1; 1 never accepts on the residual).
        stationary_slope_rtol: a step whose line search fails is also accepted (relaxed, counted)
            when the predicted decrease ``|g.d|`` is below this fraction of ``|E|``: x is then
            stationary to working precision (the gradient is zero up to floating-point error).
            0 never accepts on this test.
        tol_force: or when the free-DoF gradient infinity norm is below this (N).
        max_iterations: Newton iterations per step before failing.
        armijo_c: sufficient-decrease constant.
        max_backtracks: line-search halvings before failing.
        max_displacement: cap on any vertex's move per iteration, m (None: 0.5 * contact eps + 2 mm).
        projection: PSD projection of element Hessians ("clamp", "abs", "none").
        exact_hessian_first: each iteration, first factorise the exact (unprojected) Hessian and
            use it if it is positive definite; assemble the ``projection`` one only when it is not.
            Needs a solver that detects indefinite matrices (PARDISO's Cholesky); with SciPy, or
            ``projection="none"``, the ``projection`` Hessian is always used. Per-element projection
            discards negative curvature the neighbours would compensate, so projected Newton only
            converges linearly where it matters (Forming: 8.7 -> 4.9 iterations per step).
        linear_solver: "pardiso" or "scipy"; in a lockstep batch also "pcg" (the batched conjugate
            gradient on the Taichi device, :mod:`sim_core.ti_kernels.pcg`) and "envelope" (each copy's system
            solved directly on the device by the envelope Cholesky, :mod:`sim_core.ti_kernels.envelope_cholesky`;
            ``envelope_precision``; a lockstep batch on ``taichi-cuda`` takes it for "pardiso" since session 52).
        backend: the compute backend (:mod:`sim_core.backend`): ``"numpy"`` (the NumPy reference,
            the default: no Taichi, no kernel compilation), ``"taichi-cpu"``, ``"taichi-cuda"`` (the
            fused Taichi kernels: what ``thinshell bench forming`` measures), or ``"auto"`` (the
            fastest available; the sim node's and the command-line tools' default). Resolved once,
            when the solver is built (:attr:`NewtonSolver.backend`), which initialises Taichi.
        rate_stopping: also stop after a full (``alpha = 1``) Newton step ``dx_k`` whose estimated
            remaining error ``theta / (1 - theta) * |dx_k| / dt`` is below ``tol_velocity``, with
            the contraction rate ``theta = |dx_k| / |dx_{k-1}|`` (Hairer & Wanner, Solving ODEs
            II, Sec. IV.8, eq. 8.10-8.11). It saves the last factorisation of a step that
            converges (super)linearly (Forming: 4.94 -> 3.92 iterations per step); the Newton
            matrix kept for the adjoint is then the one of the iterate before that last step,
            within ``|dx_k|`` of the solution. Off by default: the default test stops on an
            update it does not apply, whose size is usually far below ``tol_velocity``, while
            this one stops with an error close to the tolerance; on contact scenes at a
            stick/slip or lift-off threshold that looser solution flips events (the diagnosis
            bench's generated damping and stiction effects lost their graded strengths, and
            its naming accuracy fell from 1.0 / 1.0 to 0.6 / 0.7 at 2 / 4 sigma;
            docs/benchmarks_log.md, 2026-11-22).
        simplified_newton_check: also stop at an iterate ``x_k`` whose simplified Newton correction
            ``H(x_{k-1})^{-1} g(x_k)`` (the last factorisation, one extra solve) has scaled size
            below this fraction of ``tol_velocity`` (Deuflhard, Newton Methods for Nonlinear
            Problems, 2004, Sec. 2.1: the simplified correction estimates the error of ``x_k`` as
            the ordinary one does). It saves the assembly and factorisation that only test
            convergence (Forming: a step takes about four Newton updates and a fifth, tiny one
            that is not applied). The test runs only after an iteration that factorised the
            exact Hessian and took its full step, when the same contacts touch at ``x_{k-1}``
            and ``x_k`` (:func:`sim_core.contact_set.active_contacts`; a candidate's adhesion pairs
            count with them, open or closed) and the model has no other candidate term (stiction,
            body terms): a contact switching on or off between the two iterates changes the
            matrix, and the simplified correction then underestimates the ordinary one (Forming:
            by up to 28x). With the same contacts it underestimated by up to 3.6x (Forming, 49
            steps, every iteration after the first; the lagged friction's stiffness
            ``mu lam f1(y)/y`` in the stick zone alone varies by 2x with ``y``), hence the
            factor 0.25: a step it ends is within the tolerance for an underestimate of up to 4x.
            On Forming it ends 31 of the 49 steps, each at the iterate the ordinary test ends
            it at (the same states bit for bit). ``x_k`` is the step's result; the kept Newton
            matrix is the one at ``x_{k-1}`` (``StepRecord.hessian_exact`` False: the adjoint
            assembles the exact Hessian at ``x``). 0 turns it off; ``apply_last_update`` too.
        apply_last_update: end a step that a strict test accepts (``"velocity"``, ``"force"``) at ``x_k + d_k``,
            its last Newton update applied, instead of at ``x_k``. The default test measures ``d_k`` and stops
            without it, so the result is off the step's minimiser by about ``|d_k|`` (up to ``tol_velocity * dt``),
            and whether a step stops one iteration earlier or later jumps with the parameters (nominal_s101's
            sliding card amplifies such a jump 10x a step: docs/benchmarks_log.md, session 55). Applied, the
            error is second order: ``O(|d_k|^2)`` with the exact Hessian (the full step is the Newton step) and a
            contraction of ``|d_k|`` with a projected one. No line search (``|d_k| <= tol_velocity * dt``, the
            quadratic region, as for a guess already within the tolerance). The kept Newton matrix is that of
            ``x_k``; the step's record says so (``StepRecord.hessian_exact`` False), so the tangents and the
            adjoint take the exact Hessian at the result ``x_k + d_k`` (``NewtonSolver.exact_factorization``:
            the lagged friction's stick stiffness changes on the scale of ``d_k``). The simplified Newton test
            (``simplified_newton_check``) is then not run: its correction, solved with the previous iterate's
            matrix, is not second order where the lagged friction's stiffness changes between iterates (the
            press-slide card of tests/sim_core/test_applied_update.py, first pressed step: 9.4e-9 m off the
            minimiser applied, 6.6e-9 m not, 0 with the ordinary update). Not applied: a ``"stalled"`` stop (a
            residual that no longer drops is round-off, its update noise) and a failed line search's acceptances
            (the update did not lower the energy). Off by default (the simulator's own results as before);
            sysid's replays keep it off (:data:`sysid.observation.REPLAY_APPLY_LAST_UPDATE` says why). A lockstep batch
            (``lockstep``) ignores it: its copies stop as by default.
        dt_halvings_on_failure: a step whose Newton solve fails (:class:`SimulationDivergedError`)
            is redone from its start as 2, 4, ... substeps of dt/2, dt/4, ..., at most this many
            times, so the smallest substep is ``dt / 2**dt_halvings_on_failure``; the step raises
            only when that one fails too. 0: a failure raises at once. The retries are counted in
            ``StepInfo.retries`` and ``StepInfo.substeps``.
        stale_side_backtracks: after a line search that needed this many halvings, release the
            contact sides gone stale at the new iterate (:meth:`ContactSet.release_stale_sides`,
            which a failed line search always tries). Newton creeping up to a step in the energy
            takes ever shorter steps for ~20 iterations before its line search fails outright
            (folding.yaml, dome dragging the fold: 53 iterations in one step; 10 halvings make it
            21 iterations). Where no side is stale this changes nothing.
        lockstep: how a :class:`~sim_core.batch.BatchedSimulation` of copies with these settings
            steps them: False (default) one copy after another, each with its own solver; True all
            together, one Newton iteration for all copies on their stacked model
            (:mod:`sim_core.batch.lockstep`: one evaluation per energy term and one linear solve for
            all copies, per-copy convergence, line search and failure). A single
            :class:`~sim_core.simulation.Simulation` ignores it.
        repeat_fixed_points: a step whose inputs are bitwise those of the step before (positions,
            velocities, effector poses and openings, rest angles, contact memory, the Dirichlet data
            its control resolves to, ``dt``, the model and these settings), when that step left
            its state unchanged (zero velocity in and out: a scene at rest) and was accepted by a
            strict test, is not solved again: it takes that step's result and outcome (its residual,
            energy and stop reason) and says so (``StepInfo.repeated``; ``iterations`` and
            ``factorizations`` 0). The step is a deterministic function of those inputs, so the
            result is the one a solve would give; only the rounding of the solve's residual may
            differ in its last bits, as the Newton matrix's union pattern and PARDISO's ordering
            depend on the steps before (which decides nothing unless that residual is within a few
            ulps of the tolerance). Off by default; the sim node turns it on (a scene at rest then
            costs a comparison of the inputs per step; docs/benchmarks_log.md, 2026-11-25 "the sim
            node's step"). Never with a step hook (candidate terms carry their own state).
        sleeping: let a body at rest that nothing moving can reach sleep (:mod:`sim_core.sleeping`):
            after a strictly converged step that left an eligible body (a sheet or solid not driven
            by an effector) with velocities in and out and its part of the last Newton update all
            below ``sleep_velocity``, with no contact candidate pair shared with a moving vertex and
            no moving vertex within reach, its DoFs are held (Dirichlet at its positions) and its
            elastic terms are not evaluated until it is woken: before a step whose inputs (model
            revision, gravity, damping, friction table, dt, these settings) or whose state of the
            body differ from those it fell asleep with, or that a moving vertex may reach it in;
            during a step (solved again with it awake, ``StepInfo.wake_redos``) as soon as a contact
            candidate pair joins it to a moving vertex. A never-sleeping solve would move such a body
            by its sub-threshold Newton updates only, so the trajectories differ by about
            ``sleep_velocity * dt`` per step it sleeps (tests/sim_core/test_sleeping.py: below 1e-9 m
            on the bundled scene with the pad pressing near, then onto, the card).
            Reported in ``StepInfo.sleeping`` / ``woken``. Off by default; the sim node and the plain
            replays of recordings (:meth:`sysid.observation.ObservationModel.simulate`) turn it on. With a
            position guess (``Control.position_guess``) the sleeping bodies keep their held positions and
            the guess is taken for the others; with a series spring's compression among the unknowns
            (``Control.compression``) the driven base, which never sleeps, is tied to it as without
            sleepers. Not with a step hook (the step solves every body), nor for gradients: a sleeping
            step's ``StepRecord`` holds the body as Dirichlet and lacks its elastic terms
            (:func:`sim_core.adjoint.rollout_step` refuses it), nor with ``lockstep``.
        sleep_velocity: the rest threshold of ``sleeping``, m/s (> 0; 1e-7 m/s = 0.5 nm per 5 ms step).
        carried_start: start each step's Newton iterations with the free vertices of every solid an
            effector drives (a tactile pad) and that is clear of contact reach moved by the effector's
            rigid motion over the step (:mod:`sim_core.carried_start`) instead of at ``x^n``: the step
            minimises the same potential, and its accepted iterate differs by less than
            ``tol_velocity * dt`` per step from the one reached from ``x^n`` (the bundled scene's pad
            moved 0.2 mm in the air: 1 Newton iteration instead of 3). Off by default (the benchmarks'
            and the replays' steps are those from ``x^n``); the sim node turns it on. Not with
            ``lockstep``; ignored with a position guess (``Control.position_guess``).
        cg_precision: the storage of a lockstep batch's batched CG (``linear_solver="pcg"``): ``"mixed"`` (default)
            keeps its operator's values and its preconditioner as float32 on the device, its vectors, sums and
            factorisations float64 (:mod:`sim_core.ti_kernels.precision`); ``"double"`` everything float64. Its solves
            stop at the relative residual ``LOCKSTEP_CG_RTOL`` (1e-4), far above float32's rounding, so a solve meets
            that tolerance as in ``"double"`` and a lockstep batch's copies give their separate runs' states (tests:
            ``tests/sim_core/ti_kernels/test_pcg.py``). Other solvers ignore it.
        envelope_precision: the factors of a lockstep batch's envelope Cholesky (``linear_solver="envelope"``, or
            ``"pardiso"`` on ``taichi-cuda``):
            ``"double"`` (default) float64; ``"mixed"`` float32, each solve refined twice in float64 against the
            float64 operator. Other solvers ignore it.
    """

    tol_velocity: float = 1e-4
    tol_force: float = 1e-9
    max_iterations: int = 60
    stall_iterations: int = 4
    stall_tolerance_factor: float = 10.0
    line_search_tolerance_factor: float = 100.0
    stationary_slope_rtol: float = 1e-12
    armijo_c: float = 1e-4
    max_backtracks: int = 40
    max_displacement: float | None = None
    projection: str = "clamp"
    exact_hessian_first: bool = True
    linear_solver: str = "pardiso"
    backend: str = "numpy"
    rate_stopping: bool = False
    dt_halvings_on_failure: int = 0
    apply_last_update: bool = False
    stale_side_backtracks: int = 10
    simplified_newton_check: float = 0.25
    lockstep: bool = False
    repeat_fixed_points: bool = False
    sleeping: bool = False
    sleep_velocity: float = 1e-7
    carried_start: bool = False
    cg_precision: str = "mixed"
    envelope_precision: str = "double"

    def __post_init__(self) -> None:
        check_backend(self.backend, "solver backend")
        if self.linear_solver in ("pcg", "envelope") and self.backend == "numpy":
            raise ConfigError(f"solver linear_solver {self.linear_solver!r} runs in Taichi: it needs a Taichi backend, "
                              f"not 'numpy'")
        if self.tol_velocity <= 0 or self.max_iterations < 1:
            raise ConfigError("solver tol_velocity must be > 0 and max_iterations >= 1")
        if self.stale_side_backtracks < 1:
            raise ConfigError(f"solver stale_side_backtracks must be >= 1, got {self.stale_side_backtracks}")
        if self.projection not in ("clamp", "abs", "none"):
            raise ConfigError(f"solver projection must be clamp|abs|none, got {self.projection!r}")
        for name in ("stall_tolerance_factor", "line_search_tolerance_factor"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 1.0):
                raise ConfigError(f"solver {name} must be a finite number >= 1, got {value!r}")
        if not (np.isfinite(self.stationary_slope_rtol) and self.stationary_slope_rtol >= 0.0):
            raise ConfigError(f"solver stationary_slope_rtol must be a finite number >= 0, got {self.stationary_slope_rtol!r}")
        if not (np.isfinite(self.sleep_velocity) and self.sleep_velocity > 0.0):
            raise ConfigError(f"solver sleep_velocity must be a finite number > 0 m/s, got {self.sleep_velocity!r}")
        if self.carried_start and self.lockstep:
            raise ConfigError("solver carried_start is not available with lockstep "
                              "(a lockstep batch starts every copy at x^n)")
        if self.sleeping and self.lockstep:
            raise ConfigError("solver sleeping is not available with lockstep (a lockstep batch solves every copy's bodies)")
        if self.cg_precision not in CG_PRECISIONS:
            raise ConfigError(f"solver cg_precision must be {'|'.join(CG_PRECISIONS)}, got {self.cg_precision!r}")
        if self.envelope_precision not in CG_PRECISIONS:
            raise ConfigError(f"solver envelope_precision must be {'|'.join(CG_PRECISIONS)}, "
                              f"got {self.envelope_precision!r}")
        if self.dt_halvings_on_failure < 0:
            raise ConfigError(f"solver dt_halvings_on_failure must be >= 0, got {self.dt_halvings_on_failure}")
