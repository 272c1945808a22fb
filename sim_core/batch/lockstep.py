"""Lockstep Newton: one Newton iteration for all ``B`` copies of a stacked scene together.

:class:`LockstepSolver` is a :class:`~sim_core.solver.NewtonSolver` on the stacked model of
:mod:`sim_core.batch.stacked`: each iteration evaluates every energy term of every copy in one call
per term (one kernel launch per fused energy on a Taichi backend), assembles one sparse Newton matrix
(block diagonal by copy) and solves it once (one PARDISO factorisation, or SciPy's, per
``SolverConfig.linear_solver``). What is per copy:

* convergence: copy ``i``'s scaled Newton update ``max_v |d_iv| / dt`` and gradient are tested by
  the solver's stopping tests (:func:`sim_core.newton_stop.stop_reason`: velocity, force, stalled; the
  simplified Newton test, below), made over the copies' ``(B,)`` arrays with their acceptance records
  (:class:`~sim_core.batch.copy_outcomes.CopyOutcomes`: no loop over the copies in the iterations); a copy
  that has converged takes no further update (its right-hand side is zeroed, so its block of the
  solution is zero) while the others iterate; the envelope neither gathers nor factorises its matrix
  (:attr:`LockstepSolver.skip_closed_copies`; the other terms are still evaluated for every copy);
* step size: the displacement cap ``max_displacement`` and the backtracking line search act per copy:
  a copy keeps a step once it passes, the others halve theirs. The per-copy gradient is a slice of the
  stacked gradient, and each term's energy is split by copy (capability
  :class:`~sim_core.energies.base.CopyEnergies`), so each trial step is tested twice:
  first the Armijo condition with the energy change estimated by the trapezoidal rule of the
  directional derivatives, ``E_i(x + a d) - E_i(x) ~ a (g_i(x).d_i + g_i(x + a d).d_i) / 2`` (exact
  for a quadratic; Nocedal & Wright, Numerical Optimization, 2nd ed., Sec. 3.5), then, for the copies
  that pass, each copy's Armijo condition on its own measured energy change (one energy evaluation a trial
  point, :meth:`LockstepSolver._copy_energies`). Where a term cannot split its energy (the NumPy backend's elastic
  terms), the second test is the Armijo condition on the measured energy change of the group, split in halves
  (one energy evaluation a split; the energy being a sum over copies, the other half's change is the
  difference) down to single copies wherever a group fails (:meth:`LockstepSolver._armijo_groups`): there a copy
  whose own energy test fails while its group's holds (another copy's decrease covering it) is accepted.
  With one copy this is the separate run's line search; with several, a copy whose
  slope test fails while its own energy falls (a contact switching on near the trial point) halves its step
  where its separate run takes it (Forming: the lockstep's extra iterations, ``benchmarks/iterations_lockstep.py``);
* Newton matrix: the exact Hessian first as in a separate run, chosen per copy (a stacked matrix that
  is not positive definite is factorised again block by block, each copy taking the exact or the
  projected block its own run would take). With the batched CG it is never assembled into one sparse
  pattern: the fused elastic terms' values in their fixed static pattern plus the diagonal, and the
  contact and friction Hessians as vertex blocks applied matrix-free on the device
  (:meth:`LockstepSolver._device_operator`; the stacked step's ``StepRecord`` then holds no Hessian);
* failure: a copy whose gradient or update is not finite, whose line search fails with no relaxed
  acceptance and no stale contact side to release, or that has not converged in ``max_iterations``
  is reported with the reason, and the step is taken again from its start with that copy held fixed
  (Dirichlet at its positions), so that the others finish as they would without it.

Each copy's :class:`~sim_core.step_info.StepInfo` has its own iterations, residual, stop reason,
backtracks and line-search failures; its factorisations, projected iterations and assembly and
solve times are the stacked step's, ``time_total`` is the step's wall time divided among the stepped
copies, and ``energy`` is NaN (the incremental potential is one sum over all copies:
:attr:`LockstepSolver.last_stacked_info`).

The host's work over the stacked arrays: the iterates are read-only arrays of their own (the terms' caches key
them by identity, :func:`~sim_core.energies.base.positions_key`, not by their bytes), the stacked gradient takes
the contact and friction terms' rows at their vertices only (:class:`~sim_core.energies.base.SparseGradient`),
the effectors' Dirichlet data is computed for all copies at once (:mod:`sim_core.batch.effectors`) and the
plastic update after a step is one kernel on a Taichi backend (:mod:`sim_core.batch.plasticity`; with the batched CG
on the step's accepted iterate in device memory, no upload). With the batched
CG the Newton loop's iterate, update and stacked gradient stay in device memory (:mod:`sim_core.batch.iterates`,
:mod:`sim_core.batch.device_iterates`): trial points, per-copy dot products and norms, finiteness tests and copy
updates are kernels whose host side reads back ``(B,)`` arrays, the stacked gradient is summed there, the CG reads its
right-hand side and leaves its update there, and each trial point's positions come down once (the contact search and
the terms' caches); the direct solvers' path keeps NumPy vectors. A Newton iteration's reads around the batched solve:
none before it (the copies to solve are those whose gradient's largest entry, read with the last slope test, is not
0), the solver's per-copy flags (one int32 array a CG poll, :class:`~sim_core.ti_kernels.pcg.BatchedPCG`), then one
``(B,)`` read of ``g.d`` and the largest ``|d_v|`` a solve, which give the solve's finite and descent tests and the
loop's slope and step size. The line search is :mod:`sim_core.batch.line_search`.

The copies' contact sets are one stacked contact set whose candidates never pair two copies (they are
translated apart, :mod:`sim_core.batch.stacked`). With a direct linear solver a copy also stops on the simplified
Newton test (:mod:`sim_core.batch.simplified`); with the batched CG it does not (its correction would be a second CG
solve for the copies that fail it, to save the operator's assembly). Not done: the rate stopping test, substep
retries (``dt_halvings_on_failure``) and position guesses. Each copy's result is its separate run's to the
Newton tolerance, not bit for bit (on a scene with several equilibria within reach, a copy whose path
differs, e.g. by one more iteration, may settle in another one).
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import numpy as np

from sim_core.batch.effectors import StackedBoundary
from sim_core.batch.heap import keep_freed_memory
from sim_core.batch.copy_outcomes import CopyOutcomes
from sim_core.batch.iterates import HostIterates, Iterate, frozen
from sim_core.batch.line_search import CopyLineSearch
from sim_core.batch.lumped import LumpedQuadratic, lumped_loop_terms
from sim_core.batch.plasticity import StackedElasticTerms
from sim_core.batch.sheet_bands import sheet_band_dofs
from sim_core.batch.simplified import SimplifiedNewtonTest
from sim_core.batch.stacked import StackedScene
from sim_core.batch.subset_projection import projected_subset_blocks
from sim_core.backend import uses_taichi
from sim_core.control import Control
from sim_core.energies.base import DeviceGradient, DeviceHessian, SubsetHessian, declares
from sim_core.errors import ConfigError
from sim_core.solver import NewtonSolver
from sim_core.solver_config import SolverConfig
from sim_core.state import State
from sim_core.step_info import StepInfo


LOCKSTEP_CG_RTOL = 1e-4
"""Relative residual ``|r_c| <= rtol |g_c|`` at which the batched CG stops a copy's Newton solve: an inexact Newton
method (Dembo, Eisenstat & Steihaug, "Inexact Newton methods", SIAM J. Numer. Anal. 19, 1982: a forcing term
``eta`` adds at most a factor ``eta`` to each iteration's linear convergence). On the Forming scene (6 copies, 8
steps, CPU) the Newton iterations are those of ``rtol = 1e-10`` step by step, the states within 5e-8 m of its states
(a tenth of the Newton tolerance ``tol_velocity dt``), with a quarter fewer CG iterations (357 -> 267 a solve);
``1e-2`` adds Newton iterations. With each copy's sheet an exact block of the preconditioner
(:func:`~sim_core.batch.sheet_bands.sheet_band_dofs`) the CG reaches it in 31-34 iterations a solve (Forming, B = 4
on the CPU and 1024 on an H100), the Newton iterations step by step and the states within 5.5e-8 m of the vertex
block-Jacobi CG's."""


class _CopiesFailed(Exception):
    """Copies that failed in a lockstep attempt: ``failures`` maps copy -> reason."""

    def __init__(self, failures: dict[int, str]) -> None:
        super().__init__(", ".join(f"copy {i}: {why}" for i, why in failures.items()))
        self.failures = failures


@dataclass
class LockstepResult:
    """What one :meth:`LockstepSolver.step_copies` did.

    Attributes:
        infos: per copy, its :class:`StepInfo` (None for a copy that was held or failed).
        failures: copy -> reason, for the copies that failed in this step (their positions held).
        attempts: how many times the step was taken (1 + the attempts ended by failing copies).
    """

    infos: list[StepInfo | None]
    failures: dict[int, str] = field(default_factory=dict)
    attempts: int = 1


CUDA_DEVICE_SOLVER = "envelope"
"""The device solver a lockstep batch on ``taichi-cuda`` takes for the default ``linear_solver="pardiso"``: the envelope
Cholesky won against the batched CG at both sizes measured (Forming, H100, same call, session 52: steady 1,246 against
983 scene-steps/s at B = 256, 1,865 against 1,471 at B = 1024; docs/gpu_roofline.md)."""


class LockstepSolver(CopyLineSearch, NewtonSolver):
    """Newton's method on all copies of a :class:`StackedScene` at once (module docstring).

    Args:
        scene: the stacked scene.
        config: solver settings of every copy. The linear solver: ``linear_solver="pcg"`` is the batched
            block-Jacobi CG on the device (:class:`~sim_core.ti_kernels.pcg.BatchedPCG`, with the PSD-projected Newton
            matrix, each copy solved to the relative residual :data:`LOCKSTEP_CG_RTOL`); ``"envelope"``, and on
            ``taichi-cuda`` the default ``"pardiso"`` too (:data:`CUDA_DEVICE_SOLVER`), each copy's system solved
            directly on the device (:class:`~sim_core.ti_kernels.envelope_cholesky.BatchedEnvelope`, in the CG's
            place: the same operator, the same per-copy tests); else the named direct solver on the stacked matrix.

    Raises:
        ConfigError: ``linear_solver="pcg"`` on the NumPy backend.

    Attributes:
        scene: the stacked scene.
        held: copies held fixed in the current attempt, shape ``(B,)`` bool.
        subset_projection: how the projected retry projects the contact pair blocks of the retried copies:
            :data:`~sim_core.ti_kernels.block_projection.DEVICE_METHOD` on ``taichi-cuda``
            (:func:`projected_subset_blocks`), None elsewhere (the terms' own
            ``hessian_of_vertices``).
        last_stacked_info: the stacked :class:`StepInfo` of the last step (iterations of the slowest
            copy, factorisations, times), or None.
        copies_factorized: with a device solver, the copies whose Newton matrix it factorised, summed over its
            factorisations (``B`` a factorisation where it factorises every copy).
    """

    skip_closed_copies: bool = True
    """With a device solver that takes a device mask (the envelope, ``device_copies``), a Newton iteration's first
    factorisation and solve are those of the copies with an update to find only: the copies that have converged (and
    those with a zero gradient) are neither gathered into the envelope nor factorised nor substituted, at no extra
    transfer (:meth:`_copies_to_factorize`). Their update is 0 either way (their right-hand side is 0) and the open
    copies' arithmetic is unchanged: the results are those of factorising every copy (to the parallel kernels'
    run-to-run round-off of their atomic sums). The device solver's factors after a step then hold the matrices of
    the copies open at its last iteration only (``last_factorization``; no user of a lockstep batch solves with it:
    the batched adjoint factorises its own). False: every copy's matrix each iteration."""

    def __init__(self, scene: StackedScene, config: SolverConfig | None = None) -> None:
        config = config or SolverConfig()
        super().__init__(scene.model, config)
        self.pcg = self._block_rows = None
        device_solver = config.linear_solver if config.linear_solver in ("pcg", "envelope") else (
            CUDA_DEVICE_SOLVER if self.backend == "taichi-cuda" and config.linear_solver == "pardiso" else None)
        if device_solver == "pcg":
            if not uses_taichi(self.backend):
                raise ConfigError(f"linear_solver 'pcg' runs in Taichi: it needs a Taichi backend, not {self.backend!r}")
            from sim_core.ti_kernels.block_projection import BlockRowsProjector  # Taichi kernels: a Taichi backend
            from sim_core.ti_kernels.pcg import BatchedPCG

            segments = np.zeros(scene.model.vertex_count, dtype=np.int32)
            segments[scene.index] = np.arange(scene.copies)[:, None]
            self.pcg = self.linear_solver = BatchedPCG(np.repeat(segments, 3), rtol=LOCKSTEP_CG_RTOL,
                                                       bands=sheet_band_dofs(scene), precision=config.cg_precision)
            self._block_rows = BlockRowsProjector()  # the projected retry's pair blocks (projected_subset_blocks)
        elif device_solver == "envelope":  # (SolverConfig, or taichi-cuda: a Taichi backend)
            from sim_core.ti_kernels.block_projection import BlockRowsProjector
            from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

            segments = np.zeros(scene.model.vertex_count, dtype=np.int32)
            segments[scene.index] = np.arange(scene.copies)[:, None]
            self.pcg = self.linear_solver = BatchedEnvelope(np.repeat(segments, 3),
                                                            precision=config.envelope_precision)
            self._block_rows = BlockRowsProjector()  # the projected retry's pair blocks (projected_subset_blocks)
        self.scene = scene
        self._boundary = StackedBoundary(scene.model, scene.copies, scene.effector_names)
        # the projected retry's contact pair blocks by the device's projection kernel on the GPU (LAPACK on the host
        # took 68 ms a term at B = 256); None: the terms' own projection
        self.subset_projection = None
        if self.backend == "taichi-cuda":
            from sim_core.ti_kernels.block_projection import DEVICE_METHOD  # Taichi kernels: a Taichi backend

            self.subset_projection = DEVICE_METHOD
        self.held = np.zeros(scene.copies, dtype=bool)
        self._dofs = scene.dof_index  # (B, 3n)
        self._host_vectors = HostIterates(scene.index)  # per-copy sums and maxima over the stacked NumPy arrays
        self._device_vectors = None  # the same on the device with the batched CG (made at the first step: _vectors)
        self._direction_scalars = None  # (d, slope (B,), largest |d_v| (B,)) read by _direction_pcg with its tests
        self._direction_todo = None  # (B,) bool: the copies of the next _direction_pcg with a non-zero gradient
        self._copy_of_vertex = np.empty(scene.model.vertex_count, dtype=np.int64)
        self._copy_of_vertex[scene.index] = np.arange(scene.copies)[:, None]
        self._fixed: tuple | None = None  # (step.free, its fixed DoFs as indices): _fixed_dofs
        self._trial_energy: tuple | None = None  # (x, contact terms, J): the last trial point's measured energy
        self._copy_sums = None  # the line search's per-copy sums on the device (CopySums, made at the first use)
        self.last_stacked_info: StepInfo | None = None
        self.copies_factorized = 0  # copies whose matrix the device solver factorised, summed over its calls
        self._finish_iterate: Iterate | None = None  # the step's result while _finish_step runs
        self._made_velocities: tuple | None = None  # (host, device) velocities made by _velocities in _finish_step

    def _new_elastic_terms(self):
        """:meth:`NewtonSolver._new_elastic_terms`; on a Taichi backend the elastic terms' plastic update is one
        kernel over the stacked hinges (:class:`~sim_core.batch.plasticity.StackedElasticTerms`), made in their place
        (the terms of a stacked model are built once: 1.4 s at 256 Forming copies on the CPU)."""
        if uses_taichi(self.backend):
            return StackedElasticTerms(self.model, workspace=self.workspace)
        return super()._new_elastic_terms()

    def _projections(self) -> tuple[str, ...]:
        """:meth:`NewtonSolver._projections`; with the batched CG, which tells indefinite copies apart
        (:meth:`_direction_pcg`), the exact Hessian first too (and the fused elastic kernels with it)."""
        cfg = self.config
        if self.pcg is not None and cfg.exact_hessian_first and cfg.projection != "none":
            return ("none", cfg.projection)
        return super()._projections()

    def _set_up_step(self, state_in: State, control: Control, dt: float, guess: np.ndarray | None, info: StepInfo):
        """:meth:`NewtonSolver._set_up_step`, with the Newton loop's inertia, gravity and damping terms evaluated as
        one diagonal quadratic (:func:`~sim_core.batch.lumped.lumped_loop_terms`: one read of the stacked positions
        for the energy and one for the gradient; ``fixed_terms``, the step's record, keeps the terms)."""
        step, x = super()._set_up_step(state_in, control, dt, guess, info)
        step.loop_terms = lumped_loop_terms(step.loop_terms)
        lumped = next((p for p in step.loop_terms if isinstance(p, LumpedQuadratic)), None)
        if lumped is not None and lumped.predicted:  # y = x^n + dt v^n: made where the last step left x^n and v^n
            vectors = self._vectors
            x_n, v_n = vectors.resident(state_in.x), vectors.resident(state_in.v)
            if x_n is not None and v_n is not None:
                lumped.use_device_center(vectors.advanced(x_n, v_n, dt))
        return step, x

    def reset_caches(self) -> None:
        """:meth:`NewtonSolver.reset_caches`, and the device copies of the last step's result dropped
        (:meth:`~sim_core.batch.device_iterates.DeviceIterates.keep_resident`)."""
        super().reset_caches()
        self._vectors.forget_resident()

    def boundary(self, state: State, control: Control) -> tuple[np.ndarray, np.ndarray, dict, dict, list[str]]:
        """:meth:`NewtonSolver.boundary` vectorised over the copies
        (:class:`~sim_core.batch.effectors.StackedBoundary`), with the vertices of the :attr:`held` copies fixed at
        their positions in ``state``."""
        fixed, x_target, poses, openings, limited = self._boundary(state, control)
        if self.held.any():
            v = self.scene.index[self.held].ravel()
            fixed = fixed.copy()  # (the boundary's own mask is read-only, the same array every step)
            fixed[v] = True
            x_target[v] = state.x[v]
        return fixed, x_target, poses, openings, limited

    def step_copies(self, state_in: State, state_out: State, control: Control, dt: float, stepped: np.ndarray,
                    step_index: np.ndarray) -> LockstepResult:
        """One step of ``dt`` (s) of the copies in ``stepped`` (shape ``(B,)`` bool) from the stacked
        ``state_in`` into ``state_out``; the other copies are held at their positions.

        Args:
            state_in, state_out: stacked states (only ``state_out`` is written).
            control: the stacked control (:meth:`StackedScene.stack_controls`).
            dt: step size, s.
            stepped: copies to step.
            step_index: each copy's own step index, shape ``(B,)`` (named by failure reasons).

        Returns:
            the :class:`LockstepResult`; a failed copy's positions in ``state_out`` are those of
            ``state_in``.
        """
        t0 = time.perf_counter()
        failures: dict[int, str] = {}
        attempts = 0
        while True:
            attempts += 1
            self.held = ~np.asarray(stepped, dtype=bool).copy()
            for i in failures:
                self.held[i] = True
            if self.held.all():
                _copy_state(state_in, state_out, dt)
                return LockstepResult([None] * self.scene.copies, failures, attempts)
            attempt_in = state_in
            if self.held.any():  # held copies stand still: their velocities (maybe a failed copy's NaN) play no part
                attempt_in = state_in.copy()
                attempt_in.v[self.scene.index[self.held].ravel()] = 0.0
            try:
                infos = self._lockstep_step(attempt_in, state_out, control, dt, step_index)
            except _CopiesFailed as err:
                failures.update(err.failures)
                continue
            wall = time.perf_counter() - t0
            share = wall / max(1, int((~self.held).sum()))
            for info in infos:
                if info is not None:
                    info.time_total = share
            return LockstepResult(infos, failures, attempts)

    # ---------------------------------------------------------------------- the lockstep step
    def _lockstep_step(self, state_in: State, state_out: State, control: Control, dt: float,
                       step_index: np.ndarray) -> list[StepInfo | None]:
        """One attempt: Newton iterations of every copy not :attr:`held` until each has converged.

        Raises:
            _CopiesFailed: the copies that failed (a step without them is the next attempt).
        """
        cfg = self.config
        B = self.scene.copies
        vectors = self._vectors
        info = StepInfo()
        step, x = self._set_up_step(state_in, control, dt, None, info)
        # the first iterate is x^n but at the fixed DoFs (their targets), unless the solids are carried or the drive's
        # base is placed: then made on the device from x^n where the last step left it
        x = (vectors.start(x) if cfg.carried_start or step.compression is not None
             else vectors.start(x, step.x_n, self._fixed_dofs(step)))
        running = ~self.held
        # per copy how its iterations end, (B,) arrays decided over every copy (no loop over the copies until infos)
        outcomes = CopyOutcomes(cfg, running)
        for i, name in (self.scene.copy_of_effector(name) for name in info.limited_effectors):
            outcomes.limited.setdefault(i, []).append(name)
        done = outcomes.done  # (the same array: the acceptances set it)
        # row it - 1: the residuals of iteration it (a copy is open from the first iteration until it is done, so
        # its rows 0 .. it - 1 are its history)
        history = np.zeros((max(cfg.max_iterations, 1), B))
        residual = np.full(B, np.inf)

        def fail(mask: np.ndarray, what: str) -> _CopiesFailed:
            return _CopiesFailed({int(i): f"step {int(step_index[i])} (t = {state_in.t:.6g} s): {what}"
                                  for i in np.flatnonzero(mask)})

        self._trial_energy = None
        contact_terms, x_search, g = self._stacked_gradient(step, x, info)
        g_max = None  # per copy max |g|, where the line search read it with its slope test (one read back)
        H = projection = factorization = None
        simplified = SimplifiedNewtonTest(self._copy_of_vertex, B, step.simplified and self._kept_factorisation)
        for it in range(1, cfg.max_iterations + 1):
            open_ = running & ~done
            if g_max is None:
                g_max = vectors.largest_abs(g)  # NaN or infinite where a copy's gradient is not finite
            bad = open_ & ~np.isfinite(g_max)
            if bad.any():
                raise fail(bad, f"non-finite gradient at Newton iteration {it}")
            # on the device a test that cannot end the step saves nothing (the envelope's time does not depend on the
            # copies it factorises) and costs a substitution: made only where every open copy may pass (their
            # contacts compared only until one of them is found to differ)
            test = simplified.candidates(open_, contact_terms + step.cand_contact, x.host, every=self.pcg is not None)
            if self.pcg is not None and not np.array_equal(test, open_):
                test[:] = False
            if test.any():  # the simplified Newton test of these copies: one solve with the kept factorisation
                residual_bar = vectors.largest_norm(self._simplified_correction(step, g, test)) / dt
                outcomes.accept(test & (residual_bar < cfg.simplified_newton_check * cfg.tol_velocity), it,
                                residual_bar, "simplified")
                open_ = running & ~done
                if not open_.any():
                    info.simplified_stops = 1  # the kept matrix is the last iterate's, not x's
                    break
            # converged copies take no update: their block of the solution is 0 (a held copy's DoFs are fixed, so its
            # gradient is 0 already; the solvers do not write the right-hand side)
            rhs = vectors.zero_copies(vectors.copy(g), done) if done.any() else g
            factorizations = info.factorizations
            # the copies with an update to find: those whose gradient has a non-zero (or NaN) entry, from g_max, read
            # already (the batched solvers' direction then reads nothing before its solve)
            self._direction_todo = open_ & (g_max != 0.0)
            d, H, projection, factorization = self._direction(step, x, rhs, contact_terms, info)
            simplified.after_direction(projection == "none" and info.factorizations == factorizations + 1,
                                       contact_terms + step.cand_contact, x.host)
            vectors.zero_copies(d, ~open_)
            # NaN where a copy's update is not finite (or its squares overflow); the slope g.d read with it (the
            # batched solvers' direction read both with its own tests: no read here; the closed copies' d is 0)
            kept, self._direction_scalars = self._direction_scalars, None
            if kept is not None and kept[0] is d:
                slope, step_max = np.where(open_, kept[1], 0.0), np.where(open_, kept[2], 0.0)
            else:
                slope, step_max = vectors.slope_and_norm(g, d)
            bad = open_ & ~np.isfinite(step_max)
            if bad.any():
                raise fail(bad, f"linear solve produced NaN at iteration {it}")
            if self.pcg is not None and (self.pcg.unconverged | self.pcg.indefinite)[open_].any():
                raise fail(open_ & (self.pcg.unconverged | self.pcg.indefinite),
                           f"conjugate gradient did not converge at Newton iteration {it} "
                           f"({self.pcg.max_iterations} iterations)")
            residual[open_] = step_max[open_] / dt
            history[it - 1, open_] = residual[open_]
            outcomes.stop_tests(it, open_, residual, g_max, history[:it])
            open_ = running & ~done
            if not open_.any():
                break
            alpha = np.where(open_ & (step_max > 0),
                             np.minimum(1.0, step.max_displacement / np.maximum(step_max, 1e-300)), 0.0)
            uphill = open_ & (slope >= 0)
            if uphill.any():  # not a descent direction (should not happen with a PD matrix): steepest descent
                vectors.take_steepest(d, g, uphill)
                slope[uphill] = -vectors.dot(g, g)[uphill]
            released_before = info.released_sides
            x_new, g_new, contact_new, x_search_new, accepted, backtracks = self._line_search_copies(
                step, x, d, alpha, slope, open_, contact_terms, x_search, info)
            outcomes.backtracks[open_] += np.asarray(backtracks, dtype=np.int64)[open_]
            failed_ls = open_ & ~accepted
            if failed_ls.any():
                outcomes.line_search_failures[failed_ls] += 1
                relaxed = failed_ls & (residual < cfg.line_search_tolerance_factor * cfg.tol_velocity)
                outcomes.accept(relaxed, it, residual, "line_search_relaxed")
                stuck = failed_ls & ~relaxed
                if stuck.any():
                    self._trial_energy = None  # a released side changes the energies
                    released = self.contact.release_stale_sides(x_new.host, step.memory)
                    info.released_sides += released
                    if not released:
                        raise fail(stuck, f"line search failed at Newton iteration {it} (no decrease along the "
                                          f"Newton direction; residual {', '.join(f'{residual[i]:.3g}' for i in np.flatnonzero(stuck))} m/s)")
                    outcomes.released_sides[stuck] += released
                    # the stacked energy changed where the stuck copies stand: their gradient again
                    x_new = Iterate(frozen(x_new.host.copy()), x_new.device)
            if np.any(open_ & (backtracks >= cfg.stale_side_backtracks)):
                self._trial_energy = None
                info.released_sides += self.contact.release_stale_sides(x_new.host, step.memory)
            # the full steps taken along the kept factorisation (none once a released side changed the energies)
            simplified.after_line_search(open_ & accepted & (alpha == 1.0) & (backtracks == 0)
                                         & (info.released_sides == released_before))
            x = x_new
            if g_new[1] is None or x is not g_new[0]:
                contact_terms, x_search, g = self._stacked_gradient(step, x, info)
                g_max = None
            else:
                contact_terms, x_search, g = contact_new, x_search_new, g_new[1]
                g_max = g_new[2]
        else:
            raise fail(running & ~done, f"Newton did not converge in {cfg.max_iterations} iterations")
        elastic = self.elastic
        if isinstance(elastic, StackedElasticTerms) and x.device is not None:  # the plastic update reads x there
            elastic.device_positions = (x.host, x.device)
        self._finish_iterate = x  # the contact force summed and the velocities made where x is (_contact_force)
        self._made_velocities = None
        try:
            self._finish_step(step, x.host, H, projection, factorization, state_out, info)
        finally:
            self._finish_iterate = None
            if isinstance(elastic, StackedElasticTerms):
                elastic.device_positions = None
        # the result and its velocities kept on the device for the next step from this state (its inertia's centre,
        # its first iterate, its velocities)
        if state_out.x is x.host and x.device is not None:
            kept = [(x.host, x.device)]
            made = self._made_velocities
            if made is not None and made[0] is state_out.v:
                kept.append(made)
            force = vectors.last_force
            if force is not None and force[1] is not None and force[0] is state_out.contact_force:
                kept.append((frozen(force[0]), force[1]))  # (the engine copies a frozen force before writing it)
            vectors.keep_resident(*kept)
        self._made_velocities = None
        if x.device is not None:
            vectors.last_force = None
        frozen(state_out.v)  # a new array of the step's: the next step's record keeps it without a copy
        infos = outcomes.infos(info)
        info.iterations = int(outcomes.iteration[running].max(initial=0))
        self.last_stacked_info = info
        return infos

    @property
    def _kept_factorisation(self) -> bool:
        """Whether the linear solver keeps each copy's factors of the last factorisation, so that the simplified
        Newton test (:mod:`sim_core.batch.simplified`) is one substitution: a host direct solver, or the device's
        envelope Cholesky in double precision (:attr:`~sim_core.ti_kernels.envelope_cholesky.BatchedEnvelope.direct`;
        its ``"mixed"`` refinements would read the operator of the last factorisation, whose values the fused
        kernels may have overwritten since). Not the batched CG (no factors)."""
        pcg = self.pcg
        return pcg is None or (pcg.direct and not pcg.refinements)

    def _simplified_correction(self, step, g, test: np.ndarray):
        """The simplified Newton correction ``H(x_{k-1})^-1 g(x_k)`` of the copies in ``test`` (bool ``(B,)``; 0 in the
        others) with the kept factorisation (:attr:`_kept_factorisation`), the solver's vector (m); on the device the
        right-hand side and the solve stay there (its flags' one read, as a direction's solve)."""
        vectors = self._vectors
        rhs = vectors.zero_copies(vectors.copy(g), ~test)
        if self.pcg is None:
            return self.linear_solver.solve(rhs)
        d_bar = vectors.new()
        self.pcg.solve_on_device(rhs, d_bar)
        return vectors.zero_dofs(d_bar, self._fixed_dofs(step))

    def resident_rows(self, state: State, copies: np.ndarray) -> dict | None:
        """The rows of ``copies`` (int ``(k,)``) of the stacked ``state``'s positions (translated back by the copies'
        offsets), velocities and contact forces, each a new ``(k, n, 3)`` host array gathered on the device from the
        copies kept there by the last step (:meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors.copy_rows`: the
        values of :meth:`StackedScene.copy_states`' host gathers bit for bit), as ``{"x": .., "v": .., "force": ..}``
        for that method; None where any of the three is not kept for ``state``'s arrays (a held copy's rows written
        on the host, a host term's force, the host solvers)."""
        vectors = self._vectors
        kept = [vectors.resident(a) for a in (state.x, state.v, state.contact_force)]
        if any(a is None for a in kept) or not len(copies):
            return None
        x, v, force = vectors.copy_rows([(kept[0], True), (kept[1], False), (kept[2], False)], copies,
                                        self.scene.offset)
        return {"x": x, "v": v, "force": force}

    def _velocities(self, x: np.ndarray, x_n: np.ndarray, dt: float) -> np.ndarray:
        """:meth:`NewtonSolver._velocities`; with the step's result on the device (its :class:`Iterate`) and ``x_n`` kept
        there by the last step, made there and downloaded once
        (:meth:`~sim_core.batch.device_iterates.DeviceIterates.velocities`: the same values; the pair kept for
        :meth:`_lockstep_step` to keep resident)."""
        it = self._finish_iterate
        if it is not None and it.host is x:
            made = self._vectors.velocities(it, x_n, dt)
            if made is not None:
                self._made_velocities = made
                return made[0]
        return super()._velocities(x, x_n, dt)

    def _contact_force(self, x: np.ndarray, terms: list) -> np.ndarray:
        """:meth:`NewtonSolver._contact_force`; with the step's result on the device (the batched CG) and a first term
        declaring :class:`~sim_core.energies.base.DeviceGradient`, the leading such terms summed there and downloaded
        once (:meth:`~sim_core.batch.device_iterates.DeviceIterates.contact_force`: the same values)."""
        it = self._finish_iterate
        if it is None or it.device is None or it.host is not x or not terms or not declares(terms[0], DeviceGradient):
            return super()._contact_force(x, terms)
        return self._vectors.contact_force(terms, it)

    @property
    def _vectors(self):
        """The Newton loop's vectors and per-copy operations (:mod:`sim_core.batch.iterates`): on the device with the
        batched CG (:class:`~sim_core.batch.device_iterates.DeviceIterates`, made at the first use), else on the
        host."""
        if self.pcg is None:
            return self._host_vectors
        if self._device_vectors is None:
            from sim_core.batch.device_iterates import DeviceIterates  # Taichi kernels: a Taichi backend only

            self._device_vectors = DeviceIterates(self.scene.index)
        return self._device_vectors

    def _stacked_gradient(self, step, x: Iterate, info: StepInfo, segment_start: np.ndarray | None = None
                          ) -> tuple[list, np.ndarray | None, object]:
        """The contact potentials at ``x``, their search position and the free-DoF gradient of the stacked
        incremental potential (J/m; :attr:`_vectors`'s: ``(3 N,)`` on the host, ``(N, 3)`` on the device), non-finite
        entries kept (a copy's own failure); ``segment_start``: the line search's start where ``x`` is its trial point
        (:meth:`~sim_core.contact_set.ContactSet.potentials`)."""
        ta = time.perf_counter()
        contact_terms = self.contact.potentials(x.host, step.x_n, step.memory, x.device,  # covers on the device
                                                segment_start)
        x_search = self.contact.search_position
        terms = step.loop_terms + contact_terms
        g = self._vectors.gradient(terms, x, self._fixed_dofs(step),
                                   fresh_first=bool(terms) and isinstance(terms[0], LumpedQuadratic))
        info.time_assembly += time.perf_counter() - ta
        return contact_terms, x_search, g

    def _fixed_dofs(self, step) -> np.ndarray:
        """The step's fixed DoFs (``~step.free``) as indices, shape ``(f,)`` int64, made once per step."""
        kept = self._fixed
        if kept is None or kept[0] is not step.free:
            kept = self._fixed = (step.free, np.flatnonzero(~step.free))
        return kept[1]

    def _direction(self, step, x: Iterate, g, contact_terms: list, info: StepInfo):
        """The stacked Newton update ``d = -H^{-1} g`` (m, :attr:`_vectors`'s vector, zero on fixed DoFs), non-finite
        entries kept (a copy's NaN fails that copy alone). With a direct solver: one factorisation of the
        stacked matrix (the exact Hessian first, :meth:`NewtonSolver._projections`) when it is positive
        definite, else each copy's block on its own (:meth:`_direction_per_copy`), so that every copy
        takes the matrix its separate run takes. With the batched CG (:attr:`pcg`) the choice is per copy: the exact Hessian's solution for every
        copy whose CG met no negative curvature and whose update descends, the projected Hessian's for
        the others (the blocks are independent, so each copy's update is the one its own solve gives)."""
        if self.pcg is not None:
            return self._direction_pcg(step, x, g, contact_terms, info)
        x = x.host
        dynamic_terms = contact_terms + step.dynamic_terms
        projections = self._projections()
        ta = time.perf_counter()
        H = self._assemble_hessian(step, x, projections[0], dynamic_terms)
        tl = time.perf_counter()
        info.time_assembly += tl - ta
        info.factorizations += 1
        ok = self.linear_solver.factorize(H)
        d = -self.linear_solver.solve(g) if ok else None
        info.time_linear_solve += time.perf_counter() - tl
        if d is not None:
            info.projected_iterations += projections[0] != "none"
            d[~step.free] = 0.0
            return d, H, projections[0], self.linear_solver
        return self._direction_per_copy(step, x, g, H, projections, dynamic_terms, info)

    def _direction_per_copy(self, step, x: np.ndarray, g: np.ndarray, H_first, projections: tuple[str, ...],
                            dynamic_terms: list, info: StepInfo):
        """The update when the stacked matrix of ``projections[0]`` is not positive definite: each copy's
        block factorised on its own, in the order of ``projections`` (the exact Hessian, then the projected
        one, then the general LU for ``projection="none"``), so that each copy takes the matrix its
        separate run takes. A copy's DoFs are increasing in the stacked order, so its block of the upper
        triangle is the upper triangle of its block."""
        from sim_core.linsolve import make_symmetric_solver

        dofs = self._dofs
        d = np.zeros_like(g)
        todo = np.any(g[dofs] != 0.0, axis=1)
        matrices = {projections[0]: H_first}
        projection = projections[0]
        for projection in projections:  # ends at the last projection a copy's block was factorised with
            if projection not in matrices:
                ta = time.perf_counter()
                matrices[projection] = self._assemble_hessian(step, x, projection, dynamic_terms)
                info.time_assembly += time.perf_counter() - ta
            H = matrices[projection].tocsr()
            tl = time.perf_counter()
            for i in np.flatnonzero(todo):
                block = H[dofs[i]][:, dofs[i]].tocsr()
                block.sort_indices()
                solver = make_symmetric_solver(self.config.linear_solver)
                info.factorizations += 1
                if solver.factorize(block):
                    d[dofs[i]] = -solver.solve(g[dofs[i]])
                    todo[i] = False
                    info.projected_iterations += projection != "none"
            info.time_linear_solve += time.perf_counter() - tl
            if not todo.any():
                break
        if todo.any():  # projection="none" and not positive definite: the general LU of each such block
            H = matrices[projections[-1]]
            full = self._full_from_upper(H)
            for i in np.flatnonzero(todo):
                lu = self.general_solver()
                info.factorizations += 1
                lu.factorize(full[dofs[i]][:, dofs[i]].tocsr())
                d[dofs[i]] = -lu.solve(g[dofs[i]])
        d[~step.free] = 0.0
        return d, matrices[projection], projection, self.linear_solver

    def _direction_pcg(self, step, x: Iterate, g, contact_terms: list, info: StepInfo):
        """:meth:`_direction` with the batched CG, exact Hessian first, per copy (see there): the right-hand side
        ``-g`` and each solve's update stay on the device (:meth:`~sim_core.ti_kernels.pcg.BatchedPCG.solve_on_device`),
        the per-copy tests read back as ``(B,)`` arrays."""
        dynamic_terms = contact_terms + step.dynamic_terms
        vectors = self._vectors
        pcg = self.pcg
        projections = self._projections()
        fixed = self._fixed_dofs(step)
        d = None  # the update: the first solve's own array when every copy keeps that solve's update
        todo, self._direction_todo = self._direction_todo, None  # copies with an update to find (the Newton loop's)
        if todo is None:
            todo = vectors.any_dof(g)
        rhs = vectors.new()
        H, projection = None, self.config.projection
        for k, projection in enumerate(projections):
            ta = time.perf_counter()
            if step.fused is not None:  # the static part's values in its fixed pattern, contacts as blocks
                H = None
                marked = None
                if k > 0:  # the projected matrix is solved for the copies in todo only (the others' rhs is 0)
                    marked = np.zeros(self.scene.model.vertex_count, dtype=bool)
                    marked[self.scene.index[todo]] = True
                upper, blocks, diagonal = self._device_operator(step, x.host, projection, dynamic_terms, marked)
            else:
                H = upper = self._assemble_hessian(step, x.host, projection, dynamic_terms)
                blocks = diagonal = None
            tl = time.perf_counter()
            info.time_assembly += tl - ta
            info.factorizations += 1
            # -g on the copies to solve, 0 elsewhere: its per-copy values uploaded before the factorisation is queued
            # (a synchronous upload waits for every kernel queued before it), so that the host waits once, for the
            # factorisation and the CG together
            vectors.blend(rhs, g, todo, ~todo, scale=-1.0)
            copies = self._copies_to_factorize(k, todo)
            pcg.factorize(upper, blocks, diagonal, copies)
            self.copies_factorized += self.scene.copies if copies is None else int(todo.sum())
            dk = vectors.new()
            pcg.solve_on_device(rhs, dk)
            info.time_linear_solve += time.perf_counter() - tl
            vectors.zero_dofs(dk, fixed)
            # the slope g.dk and the largest |dk_v| (NaN where dk is not finite) in one read: the finite test, the
            # descent test and the Newton loop's slope and step size (kept in _direction_scalars)
            slope_k, norm_k = vectors.slope_and_norm(g, dk)
            ok = todo & ~pcg.indefinite & ~pcg.unconverged & np.isfinite(norm_k)
            if k + 1 < len(projections):  # the exact Hessian's update must descend to be kept
                ok &= slope_k < 0.0
            if d is None and np.array_equal(ok, todo):
                d = dk  # every copy with an update keeps this one; the others' right-hand side was 0, so is their dk
                slope, norm = slope_k, norm_k
            else:
                if d is None:
                    d, slope, norm = vectors.new(), np.zeros(len(ok)), np.zeros(len(ok))
                d = vectors.copy_where(d, dk, ok)
                slope, norm = np.where(ok, slope_k, slope), np.where(ok, norm_k, norm)
            info.projected_iterations += projection != "none" and bool(ok.any())
            todo &= ~ok
            if not todo.any() or k + 1 == len(projections):
                if todo.any():  # last try: keep what it gave (a NaN or a CG failure fails the copy)
                    vectors.copy_where(d, dk, todo)
                    slope, norm = np.where(todo, slope_k, slope), np.where(todo, norm_k, norm)
                break
        self._direction_scalars = (d, slope, norm)
        return d, H, projection, pcg

    def _copies_to_factorize(self, k: int, todo: np.ndarray):
        """The ``copies`` of the device solver's ``k``-th factorisation of a Newton iteration: a retry's, ``todo``
        (bool ``(B,)``); the first's, every copy (None), or where the solver takes a device mask
        (``device_copies``) and :attr:`skip_closed_copies` is set, the copies with an update to find as the right-hand
        side's blend left them on the device (:meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors.blend_actions`:
        nothing travels), so that the copies that have converged are neither gathered nor factorised nor solved."""
        if k:
            return todo  # a retry: its copies' band blocks only
        if self.pcg.device_copies and self.skip_closed_copies:
            return self._vectors.blend_actions(todo, ~todo)
        return None

    def _device_operator(self, step, x: np.ndarray, projection: str, dynamic_terms: list,
                         vertices: np.ndarray | None = None):
        """The Newton matrix at ``x`` as the batched CG's operator, never merged into one sparse pattern:
        ``(upper, blocks, diagonal)`` for :meth:`~sim_core.ti_kernels.pcg.BatchedPCG.factorize`:
        ``upper = (indptr, indices, data)``, the upper triangle (CSR) of the fused elastic terms' Hessian
        values in their static pattern (fixed for the step's elements and free mask: its index arrays travel
        to the device once; the exact and the projected values stay on the device where the fused kernels ran
        there), to which the CG adds ``diagonal``, the inertia / damping diagonal, and sets 1 on fixed DoFs; and the
        contact and friction Hessians (``dynamic_terms``, projected by ``projection``) as
        :class:`~sim_core.ti_kernels.pcg.VertexBlocks`, applied matrix-free by the CG (the exact blocks of
        the contact pairs left in device memory where the pair kernel wrote them, :meth:`_term_hessian`).
        The sum is the matrix :meth:`_assemble_hessian` assembles (the same entries, summed in another order). With
        ``vertices`` (bool ``(N,)``, whole copies) the projected elastic blocks are those of the marked
        copies only (:meth:`~sim_core.fused_elastic.FusedElastic.projected_hessian_values`), and so are the
        contact pair blocks (terms declaring :class:`~sim_core.energies.base.SubsetHessian`, projected for
        the marked copies only): the matrix is then right in the marked copies' rows and columns, which is
        all a solve with a zero right-hand side elsewhere reads (the CG stops a copy with ``b = 0`` at once)."""
        from sim_core.ti_kernels.pcg import VertexBlocks

        fused = step.fused
        pattern = fused.pattern
        # the contact and friction blocks first: a projected retry's pair blocks send their rows to the device before
        # the projected elastic Hessian's kernels are queued, so that the copy does not wait for those
        blocks = VertexBlocks.from_element_blocks(
            [self._term_hessian(p, x, projection, vertices) for p in dynamic_terms], step.free)
        values = (fused.hessian_values_device(x) if projection == "none"  # the values where the kernels wrote them
                  else fused.projected_hessian_values_device(x, projection, vertices, closed=True))
        if values is None:
            values = (fused.hessian_values(x) if projection == "none"
                      else fused.projected_hessian_values(x, projection, vertices))
        indptr, indices = pattern.csr()  # the same objects for the pattern: they travel once
        return (indptr, indices, values), blocks, (pattern.diag_slots, step.diag, pattern.fixed_diag_slots)

    def _term_hessian(self, term, x: np.ndarray, projection: str, vertices: np.ndarray | None):
        """A contact or friction term's Hessian blocks at ``x`` for :meth:`_device_operator`: the exact blocks
        left on the device where the term declares :class:`~sim_core.energies.base.DeviceHessian` and has them
        there (for every projection and every copy where the term's Hessian is PSD by construction, its
        ``psd_hessian``: the friction's, as ``term.hessian(x, projection)`` gives them), the marked copies' blocks of
        a :class:`~sim_core.energies.base.SubsetHessian` term (projected by :attr:`subset_projection` where set,
        :func:`projected_subset_blocks`), else ``term.hessian(x, projection)``."""
        if declares(term, DeviceHessian) and (projection == "none" and vertices is None
                                              or getattr(term, "psd_hessian", False)):
            kept = term.hessian_on_device(x)
            if kept is not None:
                return kept
        if vertices is not None and declares(term, SubsetHessian):
            if projection == "none" or self.subset_projection is None:
                return term.hessian_of_vertices(x, projection, vertices)
            return projected_subset_blocks(term, x, projection, vertices, self.subset_projection, self._block_rows)
        return term.hessian(x, projection)


def _copy_state(state_in: State, state_out: State, dt: float) -> None:
    """``state_out`` = ``state_in`` a step later with nothing moved (every copy held)."""
    for k, v in vars(state_in.copy()).items():
        setattr(state_out, k, v)
    state_out.v = np.zeros_like(state_in.v)
    state_out.t = state_in.t + dt
    state_out.step_index = state_in.step_index + 1


class LockstepEngine:
    """The lockstep stepping of a :class:`~sim_core.batch.BatchedSimulation`: its copies' models stacked
    (:func:`~sim_core.batch.stacked.stack_models`), one :class:`LockstepSolver`, and the stacked state,
    which it writes back into each copy's ``Simulation.state`` after every step.

    The stacked scene is built again when a copy's model changes (``Model.revision``), and the stacked
    state when a copy's state object was replaced from outside (a reset, a caller's initial state;
    the contact side memories then start afresh).

    Args:
        sims: the batch's copies (:class:`~sim_core.simulation.Simulation` objects).

    Making one sets the process's C heap to keep freed memory (:func:`~sim_core.batch.heap.keep_freed_memory`).

    Raises:
        ConfigError: copies with different ``dt`` or solver settings, or what :func:`stack_models` refuses.
    """

    def __init__(self, sims) -> None:
        from sim_core.batch.stacked import stack_models

        ref = sims[0]
        for i, sim in enumerate(sims):
            if sim.dt != ref.dt:
                raise ConfigError(f"batch copy {i}: dt {sim.dt:g} s differs from copy 0's {ref.dt:g} s; a lockstep "
                                  f"batch steps every copy by one dt")
            if sim.solver_config != ref.solver_config:
                raise ConfigError(f"batch copy {i}: solver settings differ from copy 0's; a lockstep batch has one "
                                  f"solver")
        keep_freed_memory()  # the iterations' stacked temporaries reuse the heap (sim_core.batch.heap)
        self.sims = sims
        self.scene = stack_models([s.model for s in sims])
        self.solver = LockstepSolver(self.scene, ref.solver_config)
        self._fresh = True  # the solver has not stepped since it was built: its caches are empty
        self._revisions = [s.model.revision for s in sims]
        self.state: State | None = None
        self._written: list = [None] * len(sims)

    def _sync(self) -> None:
        """Rebuild the stacked scene (changed model) and the stacked state (replaced copy state); a new stacked
        state clears the caches of a solver that has stepped (:meth:`NewtonSolver.reset_caches`; a solver built
        since has none). The solver is then used: the caller steps or warms it up."""
        from sim_core.batch.stacked import stack_models

        revisions = [s.model.revision for s in self.sims]
        if revisions != self._revisions:
            self.scene = stack_models([s.model for s in self.sims])
            self.solver = LockstepSolver(self.scene, self.sims[0].solver_config)
            self._fresh = True
            self._revisions = revisions
            self.state = None
        if self.state is None or any(s.state is not w for s, w in zip(self.sims, self._written)):
            self.state = self.scene.stack_states([s.state for s in self.sims])
            self._written = [s.state for s in self.sims]
            if not self._fresh:
                self.solver.reset_caches()
        self._fresh = False

    def warm_up(self) -> None:
        """:meth:`NewtonSolver.warm_up` of the stacked solver at the stacked state."""
        self._sync()
        self.solver.warm_up(self.state)

    def reset(self) -> None:
        """Forget the stacked state (the copies' reset states are stacked at the next step)."""
        self.state = None

    def step(self, controls: list, run: np.ndarray) -> tuple[list[StepInfo | None], dict[int, str]]:
        """Step the copies in ``run`` (shape ``(B,)`` bool) with their ``controls`` (None entries: none).

        Returns:
            ``(infos, failures)``: per copy its :class:`StepInfo` (None: not stepped or failed) and
            copy -> reason for the copies that failed (their states are kept).
        """
        self._sync()
        sims, scene = self.sims, self.scene
        state_in = self.state
        control = scene.stack_controls([c if run[i] else None for i, c in enumerate(controls)])
        # the step's outputs: _finish_step binds every field the step changes to new arrays (and _copy_state
        # every field when all copies are held), so the stacked state's arrays are not copied first
        out = copy.copy(state_in)
        out.candidate_state = copy.deepcopy(state_in.candidate_state)  # the candidates' variables: own copies
        step_index = np.array([s.state.step_index for s in sims])
        res = self.solver.step_copies(state_in, out, control, sims[0].dt, run, step_index)
        advanced = np.array([info is not None for info in res.infos])
        if not advanced.all():  # the solver's iterate, velocities and force are frozen (iterates.frozen): written below
            out.x, out.v, out.contact_force = (a if a is None or a.flags.writeable else a.copy()
                                               for a in (out.x, out.v, out.contact_force))
        for i in np.flatnonzero(~advanced):  # held and failed copies: as they were
            idx = scene.index[i]
            out.x[idx] = state_in.x[idx]
            out.v[idx] = state_in.v[idx]
            out.contact_force[idx] = state_in.contact_force[idx]
            g, k = int(scene.group_of_copy[i]), int(scene.slot_in_group[i])
            for sheet, h in scene.hinge_counts.items():
                name = scene.group_names[g][sheet]
                out.hinge_theta_bar[name][k * h:(k + 1) * h] = state_in.hinge_theta_bar[name][k * h:(k + 1) * h]
            for e in scene.effector_names:
                out.effector_pose[f"{e}#{i}"] = np.array(state_in.effector_pose[f"{e}#{i}"])
        self.state = out
        stepped = np.flatnonzero(advanced)
        before = [sims[i].state for i in stepped]
        states = scene.copy_states(out, stepped, np.array([b.t + sims[i].dt for i, b in zip(stepped, before)]),
                                   np.array([b.step_index + 1 for b in before], dtype=np.int64),
                                   self.solver.resident_rows(out, stepped))
        for i, b, st in zip(stepped, before, states):
            sim = sims[i]
            sim.state = st
            sim.step_totals.add(res.infos[i], b.step_index)
            sim.last_info = res.infos[i]
            self._written[i] = sim.state
        return res.infos, res.failures
