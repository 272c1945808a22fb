"""Fit simulator parameters to a recording: weighted least squares on whitened residuals.

Problem (SYSID.md "Fitting"): minimise ``C(theta) = 1/2 sum_i r_i(theta)^2`` with
``r = (y_data - y_sim(theta)) / sigma`` over the fitted channels (:mod:`sysid.observation`), i.e.
weighted least squares with ``W = diag(sigma^-2)`` and sigma the per-channel, per-axis noise level
estimated from the recording.

Coordinates: a positive scale parameter is searched in log space, ``u = ln(theta / theta_0)``
(``theta_0`` the initial value, so ``u_0 = 0`` and a unit step is a factor e); a parameter that may
be zero or is bounded on both sides (Poisson ratio, damping) is searched linearly,
``u = (theta - theta_0) / s``.

Local phase: ``scipy.optimize.least_squares`` (trust-region reflective, Branch, Coleman & Li 1999)
with a pluggable Jacobian provider: ``"fd"`` (central finite differences over the parameters) or
``"sensitivity"`` (forward sensitivities of ``sim_core.sensitivity``). Optional global phase before it
when the start may be poor: CMA-ES (Hansen 2016, the ``cma`` package) or a Latin-hypercube
multi-start screening; the best point found starts the local phase. ``thinshell sysid`` gives the local phase
a first trust region of :data:`FIRST_STEP` per coordinate (:func:`first_region_scale`) and holds a parameter
that the data do not identify at its start (``hold_unidentified``): a step along a direction the residual
barely sees is set by the trust region's size, not by the data.

Uncertainty: Gauss-Newton covariance ``Cov(u) = (J^T W J)^-1 = (J_r^T J_r)^-1`` at the optimum
(``J_r`` the Jacobian of the whitened residual); 1-sigma of a log parameter is ``theta sigma_u``
(first order) and the correlation matrix is the same in both coordinates. It assumes white noise
of the estimated level and a correct model; ``reduced_chi2`` > 1 says by how much that fails, and
``sigma_scaled = sigma sqrt(reduced_chi2)`` is the usual inflated estimate. Beside it the fit reports
a robust covariance (:mod:`sysid.covariance`, ``robust="hac"`` by default: the Newey-West sandwich
``H^-1 S H^-1`` with the residuals' time correlation; or ``"block_bootstrap"``), whose sigma
(``sigma_robust``) holds when the residual is a structured, time-correlated model misfit rather
than white noise.
"""

from __future__ import annotations

import math
import multiprocessing
import time
import warnings as _warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.stats import qmc

from sim_core.errors import CalibrationError, ConfigError, SimulationDivergedError
from sysid.covariance import (DEFAULT_ROBUST_METHOD, ROBUST_METHODS, RobustCovariance, model_residual_times,
                              model_robust_covariance, nuisance_covariance)
from sysid.identifiability import (Interval, judge, lower_cost_note, not_identified_note, profile_intervals,
                                   split_verdict)
from sysid.split_sample import model_phases, split_test
from sysid.jacobians import (JACOBIAN_KINDS, FiniteDifferenceJacobian, JacobianProvider,  # noqa: F401 (re-exported)
                             DIFFERENCE_PARAMETERS, SensitivityJacobian, load_sensitivity, make_jacobian,
                             tangent_columns)
from sysid.fit_region import (first_region_scale, held_jacobian, robust_sigma, sigma_of, unidentified_coordinates,
                               unseen_columns)
from sysid.observation import SENSOR_PARAMETERS, ObservationModel
from sysid.replay_batch import simulate_batch
from sim_core.parameter_coordinates import LOG_SPAN, ParameterSpec, bounded_spec  # noqa: F401 (re-exported)
from sim_core.parameter_coordinates import parameter_spec as coordinate_spec

DEFAULT_PARAMETERS = ("sheet.bending_stiffness", "gel.youngs_modulus", "friction.gel_sheet")
GLOBAL_METHODS = ("cma", "multistart")
STOP_SIGMA = 0.01
"""Default stop fraction of :func:`fit`: the local phase ends once the Gauss-Newton step is below
1 % of the 1-sigma uncertainty in every coordinate."""
STOP_TRIAL_SIGMA = 1.0
"""Default trial-step stop of :func:`fit`: the local phase ends when a trial step shorter than the
reported 1-sigma (scaled by the residual, ``sigma_scaled``) in every coordinate does not lower the
cost."""
STOP_RMS = 5.0e-4
"""Default RMS stop of :func:`fit`: the local phase ends at an accepted point that lowered the whitened
RMS by less than 0.05 % from the previous accepted point: a coarse precision stop for fits without the robust step
rule (the calibration's fits of the contact parameters; a replay stopped at 1e-4 m/s scatters by up to 6e-4 of its
cost). ``thinshell sysid``, whose robust step rule (:data:`STOP_ROBUST_SIGMA`) decides where the fit is known well
enough, stops on the RMS only at the replays' resolution: :data:`SYSID_STOP_RMS`."""
SYSID_STOP_RMS = 1.0e-5
"""Default RMS stop of ``thinshell sysid`` (:func:`fit` ``stop_rms``): a gain below 0.001 %, ten times the resolution
of two replays' RMS, is a cost flat to the replays' resolution.

A replay solved as sysid's are (:data:`sysid.observation.REPLAY_TOL_VELOCITY`) differs from one solved to 1e-8 m/s by
1e-6 / 5e-6 / 3e-6 whitened RMS (markers / wrench / sheet points, per channel RMS 1.2-1.9) and its cost is converged
to 1e-6 of itself (nominal_s101, docs/benchmarks_log.md, session 55), so the RMS of a replay is resolved to ~5e-7 of
itself and a gain between two to ~1e-6. At :data:`STOP_RMS` a fit of replays this smooth stopped on a gain of 0.003 %
with its Gauss-Newton step still 0.33 robust sigma (docs/benchmarks_log.md, session 56, s56-49applied)."""
STOP_ROBUST_SIGMA = 0.2
"""Default robust stop of ``thinshell sysid`` (:func:`fit` ``stop_robust_sigma``): the local phase ends
once the Gauss-Newton step is below 20 % of the robust 1-sigma (:mod:`sysid.covariance`) in every
coordinate.

The step is the distance left to the optimum: the replays are smooth and the tangents exact, so a Gauss-Newton step
is taken in full and lands where it said (nominal_s101 from the scene: every accepted step after the first within
1 % of the step predicted, the next step 5-35 % of it; from +30 % one full step was followed by one 1.5x as long
where the cost is flat to the replays' resolution, and :data:`SYSID_STOP_RMS` ended the fit; docs/benchmarks_log.md,
session 56). Where consecutive steps shrink, stopping leaves a bias of about 0.2 robust sigma (the HAC sigma; the
reported one adds the nuisance part and is larger), so the reported 2-sigma interval still covers the optimum's value
with ``P(|Z + 0.2| < 2)`` = 95.0 % (95.4 % unbiased; 94.7 % for the step and a following 35 % of it), and the bias
adds about 2 % to the sigma in quadrature (``sqrt(1 + 0.2^2)``)."""
FIRST_STEP = 0.5
"""Default first trust region of ``thinshell sysid`` (:func:`fit` ``first_step``), in search-coordinate units: a
factor e^0.5 = 1.65 on a log parameter, more than the 30 % a data sheet may be off, where least_squares' own
first region with the default bounds is a factor 13.8 (:func:`first_region_scale`)."""
DEFAULT_NUISANCE = {"friction.sheet_table": 0.3, "gel.poisson_ratio": 0.03, "contact.stiffness": 0.5}
"""Default nuisance priors of ``thinshell sysid`` (:func:`fit` ``nuisance``; names the scene lacks or the fit
fits are left out): parameters a cell's data sheet does not give and the default fit holds fixed. The
sheet-table friction to +-30 % (1-sigma; paper and card on a table range over 0.2-0.5), the gel's
Poisson ratio to +-0.03 (silicone gels 0.42-0.49, rarely on a data sheet) and the contact's penalty
stiffness to a factor 1.65 (a numerical compliance with no physical value to look up)."""


# ====================================================================================== parameters
def parameter_spec(name: str, initial: float) -> ParameterSpec:
    """The search coordinate of parameter ``name`` starting at ``initial``
    (:func:`sim_core.parameter_coordinates.parameter_spec`, the replay's sensor offsets
    :data:`sysid.observation.SENSOR_PARAMETERS` searched as length offsets).

    Raises:
        CalibrationError: non-finite start (e.g. an infinite yield angle) or a negative one.
    """
    return coordinate_spec(name, initial, offsets=SENSOR_PARAMETERS)


# ====================================================================================== problem
class _OutOfTime(Exception):
    """The time budget is spent (internal: ends the current phase)."""


class _OutOfReplays(_OutOfTime):
    """The replay budget cannot afford the next replay (internal: ends the current phase)."""


class _WithinNoise(Exception):
    """The Gauss-Newton step at an accepted point is below the stop fraction of 1-sigma (internal)."""


class _AllHeld(Exception):
    """Every fitted parameter is held at an accepted point: none is identified there (internal)."""


_WORKER: dict[str, Any] = {}
"""Per-process cache of the worker's FitProblem (set by the pool initializer; process-local)."""


def _worker_init(problem: "FitProblem") -> None:
    _WORKER["problem"] = problem


def _worker_residual(u: np.ndarray) -> tuple[np.ndarray | None, float]:
    problem: FitProblem = _WORKER["problem"]
    t = time.perf_counter()
    try:
        r = problem.model.residuals(problem.model.predict(problem.model.simulate(problem.values(u))))
    except SimulationDivergedError:
        r = None
    return r, time.perf_counter() - t


@dataclass
class Evaluation:
    """One replay: coordinates, cost ``0.5 |r|^2`` (inf on failure), phase, time since start."""

    u: np.ndarray
    cost: float
    phase: str
    time_s: float


class FitProblem:
    """Residuals of an :class:`ObservationModel` as a function of the search coordinates u.

    Args:
        model: the observation model.
        specs: one :class:`ParameterSpec` per fitted parameter.
        workers: processes for batches of replays (finite differences, CMA populations); 1 = serial.
        deadline: ``time.perf_counter()`` value after which optimisation phases stop (None: none).
        max_replays: most replays (:attr:`sim_runs`) of the problem; a replay of any phase but
            ``initial`` and ``final`` that would exceed it is not started (:meth:`reserve`). None: no
            limit. Unlike ``deadline`` it does not depend on the machine's speed or load.
        on_eval: called with each :class:`Evaluation`.
        joint: optional ``joint(problem, u) -> (r, J, prediction)`` computing the whitened residual
            ``(m,)``, its Jacobian ``(m, p)`` and the aligned prediction in one replay; used by the
            serial evaluations of the ``initial`` and ``local`` phases (where a Jacobian is asked
            for at almost every accepted point), the Jacobian kept for :meth:`cached_jacobian`.
            Divergence gives ``r = None`` as in a plain replay. It may set :attr:`last_positions`.
        warm_start: start the Newton solves of every serial replay from the vertex positions of
            the best replay so far (``ObservationModel.warm_start``), step by step: nearby
            parameters give nearby trajectories, so each step starts close to its solution.
        batched, batch_size: :meth:`evaluate_many` steps its replays together in this process as copies of
            the scene, at most ``batch_size`` at a time (an integer, ``"auto"`` or None: all;
            :func:`sysid.replay_batch.simulate_batch`, which says what runs serially instead); before ``workers``.
        extra: specs of parameters held at their nominal (``u = 0``; a fit's nuisance parameters) whose whitened
            Jacobian columns every joint replay also computes from its tangents and keeps beside its Jacobian
            (:meth:`extra_jacobian`): where the replays are cold, the fit's optimum then needs no replay of its own
            for them (:func:`_nuisance_jacobian`).
        made: a replay with tangents made before the fit (:class:`sysid.jacobians.TangentReplay`), which the first
            joint evaluation at its parameters takes instead of replaying (then dropped); None: none.

    Attributes:
        last_positions: vertex positions ``(K + 1, n, 3)`` of the last serial replay (None when
            it diverged or did not keep them).
    """

    JOINT_PHASES = ("initial", "local")
    JACOBIANS_KEPT = 2
    """Jacobians of the most recent joint replays kept (plus the best point's); ``(m, p)`` each."""

    def __init__(self, model: ObservationModel, specs: Sequence[ParameterSpec], workers: int = 1,
                 deadline: float | None = None, on_eval: Callable[[Evaluation], None] | None = None,
                 joint: Callable[["FitProblem", np.ndarray], tuple] | None = None, warm_start: bool = False,
                 max_replays: int | None = None, batched: bool = False, batch_size: int | str | None = None,
                 extra: Sequence[ParameterSpec] = (), made: Any = None) -> None:
        self.model = model
        self.made = made
        self.extra_specs = tuple(extra)
        self._extra: dict[bytes, np.ndarray] = {}
        self.batched, self.batch_size = bool(batched), batch_size
        self.max_replays = max_replays
        self.warm_start = bool(warm_start)
        self.last_positions: np.ndarray | None = None
        self.specs = tuple(specs)
        self.names = tuple(s.name for s in specs)
        b = np.array([s.u_bounds for s in specs], dtype=float).reshape(-1, 2)
        self.bounds = (b[:, 0], b[:, 1])
        self.workers = max(1, int(workers))
        self.deadline = deadline
        self.on_eval = on_eval
        self.history: list[Evaluation] = []
        self.sim_runs = 0
        self.sim_time_s = 0.0
        self.t_start = time.perf_counter()
        self.best: tuple[float, np.ndarray, dict[str, np.ndarray] | None] | None = None
        self._cache: dict[bytes, np.ndarray | None] = {}
        self.joint = joint
        self._jacobians: dict[bytes, np.ndarray] = {}
        self._pool: ProcessPoolExecutor | None = None
        self.last_failure = ""

    # ------------------------------------------------------------------------------ coordinates
    def values(self, u: np.ndarray) -> dict[str, float]:
        """Parameter values at ``u``."""
        return {s.name: s.to_value(float(ui)) for s, ui in zip(self.specs, np.asarray(u, dtype=float))}

    def u_of(self, values: Mapping[str, float]) -> np.ndarray:
        """Coordinates of parameter ``values``."""
        return np.array([s.to_u(float(values[s.name])) for s in self.specs])

    # ------------------------------------------------------------------------------ evaluation
    def _check_time(self, phase: str) -> None:
        if self.deadline is not None and phase != "final" and time.perf_counter() > self.deadline:
            raise _OutOfTime(phase)

    def reserve(self, count: int, phase: str) -> None:
        """Check that ``count`` more replays fit in :attr:`max_replays` before starting them.

        Raises:
            _OutOfReplays: they do not (never for the ``initial`` and ``final`` phases).
        """
        if self.max_replays is not None and phase not in ("initial", "final") and \
                self.sim_runs + int(count) > self.max_replays:
            raise _OutOfReplays(phase)

    def _record(self, u: np.ndarray, r: np.ndarray | None, phase: str, wall: float,
                prediction: dict[str, np.ndarray] | None = None) -> None:
        self.sim_runs += 1
        self.sim_time_s += wall
        cost = math.inf if r is None else 0.5 * float(r @ r)
        ev = Evaluation(np.array(u, dtype=float), cost, phase, time.perf_counter() - self.t_start)
        self.history.append(ev)
        self._cache[np.asarray(u, dtype=float).tobytes()] = r
        if r is not None and (self.best is None or cost < self.best[0]):
            self.best = (cost, np.array(u, dtype=float), prediction)
            if self.warm_start and self.last_positions is not None:
                self.model.warm_start = self.last_positions
        self.last_positions = None
        if self.on_eval is not None:
            self.on_eval(ev)

    def best_prediction(self) -> dict[str, np.ndarray]:
        """Aligned predictions at the best point (replayed again when it was evaluated in a worker).

        Raises:
            CalibrationError: nothing was evaluated successfully.
        """
        if self.best is None:
            raise CalibrationError("no replay succeeded")
        cost, u, prediction = self.best
        if prediction is None:
            prediction = self.model.predict(self.model.simulate(self.values(u)))
            self.best = (cost, u, prediction)
        return prediction

    def residual(self, u: np.ndarray, phase: str = "local") -> np.ndarray | None:
        """Whitened residual at ``u`` (None when the replay diverged); cached per u."""
        u = np.asarray(u, dtype=float)
        key = u.tobytes()
        if key in self._cache:
            return self._cache[key]
        self._check_time(phase)
        self.reserve(1, phase)
        t = time.perf_counter()
        joint = None
        if self.joint is not None and phase in self.JOINT_PHASES:
            try:
                joint = self.joint(self, u)
            except SimulationDivergedError as err:
                self.last_failure = str(err)
                self._record(u, None, phase, time.perf_counter() - t)
                return None
            except ConfigError:  # the replay is not differentiable (e.g. dt halved): plain replay below
                joint = None
        if joint is not None:
            r, J, prediction = joint
            self._record(u, r, phase, time.perf_counter() - t, prediction)
            if J is not None:
                self.keep_jacobian(u, J)
            return r
        try:
            # the budget is checked at every replay step too: a hard trial point (many Newton
            # iterations per step) cannot hold the fit past its deadline
            on_step = None if self.deadline is None or phase == "final" else (lambda k, K: self._check_time(phase))
            trace = self.model.simulate(self.values(u), keep_positions=self.warm_start, on_step=on_step)
            prediction = self.model.predict(trace)
            r = self.model.residuals(prediction)
            self.last_positions = trace.positions
        except SimulationDivergedError as err:
            prediction, r = None, None
            self.last_failure = str(err)
        self._record(u, r, phase, time.perf_counter() - t, prediction)
        return r

    def keep_jacobian(self, u: np.ndarray, J: np.ndarray) -> None:
        """Keep the Jacobian ``J`` ``(m, p)`` at ``u`` for :meth:`cached_jacobian` (a column of NaN:
        not computed yet)."""
        key = np.asarray(u, dtype=float).tobytes()
        self._jacobians.pop(key, None)
        self._jacobians[key] = J
        best = self.best[1].tobytes() if self.best is not None else None
        recent = list(self._jacobians)[-self.JACOBIANS_KEPT:]
        for k in list(self._jacobians):
            if k not in recent and k != best:
                del self._jacobians[k]
        for k in list(self._extra):
            if k not in self._jacobians:
                del self._extra[k]

    def keep_extra_jacobian(self, u: np.ndarray, J: np.ndarray) -> None:
        """Keep the columns ``J`` ``(m, len(extra))`` of the :attr:`extra_specs` at ``u``, as long as the Jacobian
        at ``u`` is kept (:meth:`keep_jacobian`, which a joint replay's caller calls next)."""
        self._extra[np.asarray(u, dtype=float).tobytes()] = J

    def extra_jacobian(self, u: np.ndarray) -> np.ndarray | None:
        """The :attr:`extra_specs`' columns a joint replay computed at ``u`` (kept with its Jacobian), or None."""
        return self._extra.get(np.asarray(u, dtype=float).tobytes())

    def cached_jacobian(self, u: np.ndarray) -> np.ndarray | None:
        """The Jacobian a joint replay computed at ``u`` (one of the last few, or the best point's), or None."""
        return self._jacobians.get(np.asarray(u, dtype=float).tobytes())

    def evaluate_many(self, points: Sequence[np.ndarray], phase: str) -> list[np.ndarray | None]:
        """Residuals at several points (as one batch with :attr:`batched`, in parallel when ``workers > 1``)."""
        todo = [np.asarray(p, dtype=float) for p in points if np.asarray(p, dtype=float).tobytes() not in self._cache]
        if self.batched and len(todo) > 1:
            todo = list({u.tobytes(): u for u in todo}.values())
            self._check_time(phase)
            self.reserve(len(todo), phase)
            traces, _ = simulate_batch(self.model, [self.values(u) for u in todo], self.batch_size)
            for u, trace in zip(todo, traces):
                prediction = None if trace is None else self.model.predict(trace)
                r = None if prediction is None else self.model.residuals(prediction)
                self._record(u, r, phase, 0.0 if trace is None else trace.wall_time_s, prediction)
        elif self.workers > 1 and len(todo) > 1:
            self._check_time(phase)
            self.reserve(len(todo), phase)
            if self._pool is None:
                # the forked workers inherit compiled kernels; one a child compiles itself hangs it
                # (Taichi's compile thread pool does not survive fork): ObservationModel.compile_kernels
                warm = getattr(self.model, "compile_kernels", None)
                if callable(warm):
                    warm()
                self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("fork"),
                                                 initializer=_worker_init, initargs=(self,))
            for u, (r, wall) in zip(todo, self._pool.map(_worker_residual, todo)):
                self._record(u, r, phase, wall)
        return [self.residual(p, phase) for p in points]

    def close(self) -> None:
        """Shut the worker pool down."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.update(_pool=None, on_eval=None, _cache={}, _jacobians={}, history=[], best=None, joint=None, made=None,
                     last_positions=None)
        return state


# ====================================================================================== result
@dataclass
class FitResult:
    """Outcome of :func:`fit` (see :mod:`sysid.results` for its JSON form).

    Attributes:
        names: fitted parameter names, shape ``(p,)`` order of every matrix.
        specs: their search coordinates.
        initial, values: parameter values before / after.
        sigma: 1-sigma (Gauss-Newton) per parameter in its units, or None when J^T J is singular or
            was not computed; ``sigma_log``: 1-sigma of ln(theta) (log parameters).
        sigma_scaled: ``sigma * sqrt(reduced_chi2)``.
        covariance_u: ``(p, p)`` covariance of the coordinates u, or None.
        correlation: ``(p, p)``, or None.
        cost_initial, cost_final: ``0.5 |r|^2``.
        reduced_chi2: ``|r|^2 / (m - p)`` at the optimum.
        rms_initial, rms_final: per-channel RMS (:meth:`ObservationModel.channel_rms`).
        prediction_initial, prediction_final: channel -> predicted array at the stamps.
        history: every replay (:class:`Evaluation`).
        iterations: accepted iterates of the local phase; nfev, njev: its function / Jacobian calls.
        sim_runs, sim_time_s: replays and their total wall time; wall_time_s: whole fit.
        status, message: ``converged`` | ``max_nfev`` | ``replay_budget`` | ``time_budget`` | ``failed``
            and detail.
        jacobian: provider name; global_phase: summary of the global phase or None.
        channels, residual_count, step_count, dt: problem size.
        warnings: messages raised during the fit.
        model: the observation model (not serialised).
        sigma_scale: channel -> the factor on its noise level in the fit's residual
            (``reweight_channels``), or None.
        sigma_robust: 1-sigma per parameter in its units from :attr:`robust` (None when not computed).
        not_identified: the parameters the recording does not identify (:mod:`sysid.identifiability`: their
            interval reaches a bound of their prior range); each has a line in ``warnings``.
        intervals: name -> :class:`sysid.identifiability.Interval`: the interval the data give and the verdict.
        profile_runs: replays of the parameters' profiles (``profile_replays``; also in ``sim_runs``).
        robust: the robust covariance of the coordinates (:class:`sysid.covariance.RobustCovariance`:
            method, ``(p, p)`` matrix, lag window), or None (``robust=None``, or no Jacobian).
        held: the parameters :func:`fit` ``hold_unidentified`` held (no step taken along them) at the last
            accepted point (each has a line in ``warnings``).
    """

    names: tuple[str, ...]
    specs: tuple[ParameterSpec, ...]
    initial: dict[str, float]
    values: dict[str, float]
    sigma: dict[str, float] | None
    sigma_log: dict[str, float] | None
    sigma_scaled: dict[str, float] | None
    covariance_u: np.ndarray | None
    correlation: np.ndarray | None
    cost_initial: float
    cost_final: float
    reduced_chi2: float
    rms_initial: dict[str, dict[str, Any]]
    rms_final: dict[str, dict[str, Any]]
    prediction_initial: dict[str, np.ndarray]
    prediction_final: dict[str, np.ndarray]
    history: list[Evaluation]
    iterations: int
    nfev: int
    njev: int
    sim_runs: int
    sim_time_s: float
    wall_time_s: float
    status: str
    message: str
    jacobian: str
    global_phase: dict[str, Any] | None
    channels: tuple[str, ...]
    residual_count: int
    step_count: int
    dt: float
    warnings: list[str] = field(default_factory=list)
    model: ObservationModel | None = None
    sigma_scale: dict[str, float] | None = None
    sigma_robust: dict[str, float] | None = None
    not_identified: tuple[str, ...] = ()
    robust: RobustCovariance | None = None
    held: tuple[str, ...] = ()
    intervals: dict[str, Interval] = field(default_factory=dict)
    profile_runs: int = 0


def gauss_newton_covariance(J: np.ndarray, rcond: float = 1e-12) -> tuple[np.ndarray | None, str]:
    """``(J^T J)^-1`` of a whitened Jacobian ``(m, p)`` (Gauss-Newton approximation of the inverse Hessian).

    Returns:
        ``(cov (p, p), note)``; cov is None (with the reason in note) when J^T J is singular to
        ``rcond`` relative to its largest eigenvalue.
    """
    H = J.T @ J
    w, V = np.linalg.eigh(H)
    if w.size == 0 or w[-1] <= 0.0 or w[0] <= rcond * w[-1]:
        return None, f"J^T W J is singular (eigenvalues {w.tolist()}): some parameters are not identifiable"
    return (V / w) @ V.T, "ok"


def gauss_newton_step(J: np.ndarray, r: np.ndarray, rcond: float = 1e-12) -> tuple[np.ndarray, np.ndarray | None]:
    """Gauss-Newton step ``delta = -(J^T J)^-1 J^T r`` of a whitened residual ``r (m,)`` with Jacobian
    ``J (m, p)``, and the 1-sigma ``sqrt(diag (J^T J)^-1)`` of the coordinates (None when ``J^T J``
    is singular to ``rcond``; the step is then the least-squares one)."""
    cov, _ = gauss_newton_covariance(J, rcond)
    if cov is None:
        return np.linalg.lstsq(J, -r, rcond=None)[0], None
    return -cov @ (J.T @ r), np.sqrt(np.diag(cov))


def _covariance_summary(specs: Sequence[ParameterSpec], values: Mapping[str, float], cov: np.ndarray | None,
                        chi2_red: float) -> tuple[dict | None, dict | None, dict | None, np.ndarray | None]:
    if cov is None:
        return None, None, None, None
    su = np.sqrt(np.diag(cov))
    corr = cov / np.outer(su, su)
    sigma = sigma_of(specs, values, cov)
    sigma_log, scaled = {}, {}
    for s, sd in zip(specs, su):
        if s.log:
            sigma_log[s.name] = float(sd)
        scaled[s.name] = float(sigma[s.name] * math.sqrt(max(chi2_red, 0.0)))
    return sigma, sigma_log, scaled, corr


# ====================================================================================== global phase
def _global_phase(problem: FitProblem, u0: np.ndarray, method: str, seed: int, max_evals: int | None,
                  sigma0: float) -> dict[str, Any]:
    lb, ub = problem.bounds
    p = u0.shape[0]
    start_best = problem.best[0] if problem.best is not None else math.inf
    evals_before = problem.sim_runs
    if method == "cma":
        import cma  # optional dependency: cma, for the CMA-ES optimiser only

        popsize = 4 + int(3 * math.log(p))
        budget = max_evals if max_evals is not None else 6 * popsize
        es = cma.CMAEvolutionStrategy(list(u0), sigma0, {
            "bounds": [list(np.maximum(lb, -LOG_SPAN)), list(np.minimum(ub, LOG_SPAN))], "seed": int(seed) + 1,
            "popsize": popsize, "maxfevals": budget, "verbose": -9})
        generations = 0
        try:
            while not es.stop() and problem.sim_runs - evals_before + popsize <= budget:
                X = [np.asarray(x, dtype=float) for x in es.ask()]
                res = problem.evaluate_many(X, phase="global")
                costs = [0.5 * float(r @ r) if r is not None else 1e300 for r in res]
                es.tell([list(x) for x in X], costs)
                generations += 1
        except _OutOfTime:
            pass
        info = {"method": "cma", "popsize": popsize, "generations": generations, "sigma0": sigma0}
    elif method == "multistart":
        n = max_evals if max_evals is not None else 4 * (p + 1)
        lo, hi = np.maximum(lb, u0 - 2.0 * sigma0), np.minimum(ub, u0 + 2.0 * sigma0)
        starts = qmc.scale(qmc.LatinHypercube(d=p, seed=seed).random(n), lo, hi) if p else np.zeros((0, 0))
        try:
            problem.evaluate_many(list(starts), phase="global")
        except _OutOfTime:
            pass
        info = {"method": "multistart", "points": int(n), "box_half_width": 2.0 * sigma0}
    else:
        raise ConfigError(f"unknown global method {method!r} (choose from {', '.join(GLOBAL_METHODS)})")
    info.update(evaluations=problem.sim_runs - evals_before, best_cost_before=start_best,
                best_cost_after=problem.best[0] if problem.best else math.inf,
                best_values=problem.values(problem.best[1]) if problem.best else None)
    return info


# ====================================================================================== fit
def _held_where(value: float, start: float) -> str:
    """Where a held parameter stayed, in the words of its warning: its start, or the point an earlier step took it to
    while the data still identified it there."""
    if value == start:
        return f"its start value {value:.4g}"
    return f"{value:.4g}, where an earlier step took it from its start {start:.4g} while the data still identified it"


def fit(model: ObservationModel, params: Sequence[str] = DEFAULT_PARAMETERS, *,
        initial: Mapping[str, float] | None = None, jacobian: str | JacobianProvider = "auto",
        global_method: str | None = None, global_evals: int | None = None, global_sigma: float = 1.0,
        max_time: float | None = None, max_nfev: int = 30, ftol: float = 1e-6, xtol: float = 1e-5,
        gtol: float = 1e-10, fd_step: float = 0.01, workers: int = 1, seed: int = 0,
        on_eval: Callable[[Evaluation], None] | None = None, stop_sigma: float | None = STOP_SIGMA,
        stop_trial_sigma: float | None = STOP_TRIAL_SIGMA, stop_rms: float | None = STOP_RMS,
        warm_start: bool = True, bounds: Mapping[str, tuple[float, float]] | None = None,
        max_replays: int | None = None, reweight_channels: bool | float = False, batched: bool = False,
        batch_size: int | str | None = None, robust: str | None = DEFAULT_ROBUST_METHOD,
        stop_robust_sigma: float | None = None, stop_trial_robust: bool = False,
        nuisance: Mapping[str, float] | None = None, hold_unidentified: bool = False,
        first_step: float | None = None, made: Any = None,
        prior: Mapping[str, tuple[float, float]] | None = None, profile_replays: int = 0,
        split: bool = True) -> FitResult:
    """Fit parameters ``params`` of ``model``'s scene to its recording.

    Args:
        model: the observation model (recording + scene + replay settings).
        params: global parameter names (``Model.parameter_names``), default :data:`DEFAULT_PARAMETERS`.
        initial: start values (default: the scene's nominal values).
        jacobian: ``"auto"``, ``"fd"``, ``"sensitivity"`` or a provider object.
        global_method: None, ``"cma"`` or ``"multistart"`` (global phase before the local one).
        global_evals: replay budget of the global phase (default 6 CMA generations / 4(p+1) points).
        global_sigma: initial CMA step / multi-start half-width / 2, in u units (1 = factor e).
        max_time: wall-time budget in s; when spent, the best point so far is returned with
            ``status="time_budget"``. The global phase gets at most half of it. The result then
            depends on the machine's speed and load; ``max_replays`` does not.
        reweight_channels: after the start replay, weigh each channel by the model's gap there:
            its noise level is multiplied by ``max(1, whitened RMS of the channel at the start)``
            for the rest of the fit (``ObservationModel.sigma_scale``; restored afterwards), so that
            every channel's residual enters at about unit variance. A variance component estimated
            from the start's residual per channel (feasible weighted least squares, e.g. Carroll &
            Ruppert 1988, "Transformation and Weighting in Regression", ch. 3): a channel the model
            cannot follow (its whitened RMS far above the others', e.g. a card the gel lifts with a
            tack the model lacks) then cannot drive the fit, while channels at their noise level
            keep their weight. A number ``T`` instead of True: only the channels whose whitened RMS at the start
            exceeds ``T`` are weighed so (the channels the model does not follow, ``thinshell sysid`` without the
            tack layer: :data:`sysid.calibration.FOLLOWED_RMS`), and only where another channel is at or below
            ``T`` there (one channel, or all far off at a start far from the fit, has nothing to be rebalanced
            against); the others keep their noise level. The cost,
            covariance and ``reduced_chi2`` are in these units;
            ``rms_initial`` / ``rms_final`` stay in noise units. The factors are in ``sigma_scale``.
        max_replays: replay budget of the whole fit (every replay counts: plain, with tangents, or a
            finite-difference column; the start is always replayed). A replay that would exceed it
            is not started, and the best point so far is returned with ``status="replay_budget"``:
            the same replays, and so the same result, on any machine. None: no budget.
        max_nfev: function evaluations of the local phase.
        ftol, xtol, gtol: ``least_squares`` tolerances.
        fd_step: finite-difference step in u.
        workers: processes for batched replays.
        seed: seed of the global phase.
        on_eval: progress callback, called with each :class:`Evaluation`.
        stop_sigma: also stop the local phase at an accepted point whose Gauss-Newton step
            (:func:`gauss_newton_step`) is below ``stop_sigma`` times the Gauss-Newton 1-sigma in
            every coordinate: the optimum is then known to that fraction of its statistical
            uncertainty, and further iterations (each a replay) cannot change the result beyond
            it. None or 0: only the ``least_squares`` tolerances.
        stop_trial_sigma: also stop when a trial step from the last accepted point, shorter than
            ``stop_trial_sigma`` times the scaled 1-sigma in every coordinate, does not lower the
            cost: the cost is then flat to within the replay's numerical noise (Newton tolerance,
            contact set changes, the warm start) on the scale of the uncertainty the fit reports,
            where the trust region would only keep shrinking until ``xtol`` (one replay per
            quartering). The scaled 1-sigma is the Gauss-Newton one times ``sqrt(chi2_red)`` (at
            least 1x; ``sigma_scaled`` of the result). The accepted point is returned; a continued
            search could only have moved within that step, i.e. within the reported uncertainty.
            On the bundled bag the default 1.0 ends the 3-parameter fit two replays earlier than
            0.25 of the unscaled sigma did (its last trials were 0.3 and 0.08 sigma, rejected by
            +0.34 % cost: the warm start's offset). None or 0: off.
        stop_rms: also stop at an accepted point whose whitened RMS is lower than the previous
            accepted point's by less than this fraction (``1 - sqrt(S_k / S_k-1) < stop_rms`` with
            ``S = r.r / 2``): a relative-decrease criterion measured on the replays, at the scale of
            their numerical resolution where a robust step rule decides (:data:`SYSID_STOP_RMS`, how it is
            measured), a coarse precision stop where none does (:data:`STOP_RMS`). None or 0: off.
        warm_start: start the Newton solves of the local phase's replays from the best replay so
            far (:class:`FitProblem` ``warm_start``); each step still converges to the solver's
            tolerance. The global phase's replays start cold.
        batched, batch_size: replay each finite-difference Jacobian's columns and each global population as
            one batch of scene copies stepped together (:class:`FitProblem`); they start cold, so with
            ``warm_start=False`` the fit is the serial one to the Newton tolerance.
        robust: covariance that holds under model error, reported beside the Gauss-Newton one
            (:data:`sysid.covariance.ROBUST_METHODS`: ``"hac"``, the Newey-West sandwich with the
            residuals' time correlation, default; ``"block_bootstrap"``; None: none). Computed from
            the Jacobian and residual at the optimum: no extra replay.
        stop_robust_sigma: also stop the local phase at an accepted point whose Gauss-Newton step is
            below ``stop_robust_sigma`` times the robust 1-sigma (method ``robust``, computed from the
            same Jacobian and residual) in every coordinate. Where the model does not follow the
            recording exactly the robust sigma is many times the Gauss-Newton one and ``stop_sigma``
            asks for a precision far below what the fit can claim; each further iteration is a
            replay. None or 0 (or ``robust=None``): off. ``thinshell sysid``:
            :data:`STOP_ROBUST_SIGMA`.
        nuisance: parameters the fit holds fixed whose values are uncertain, name -> prior 1-sigma
            (relative for a positive scale parameter, in the parameter's units for a Poisson ratio or
            a zero-start one; :func:`nuisance_prior_u`): their propagated covariance
            (:func:`sysid.covariance.nuisance_covariance`; their columns from the tangents of every joint replay of
            a cold fit, else one more replay with tangents at the optimum) is added to the robust one (method
            ``<robust>+nuisance``). None or empty: off.
        stop_trial_robust: measure the ``stop_trial_sigma`` rule's trial step in the larger of the
            scaled and the robust 1-sigma (``robust``): a rejected trial step within the uncertainty
            the fit reports ends the fit. On nominal_s101 (``thinshell sysid`` defaults, 2026-11-27)
            the last five of nine replays were trial steps from the final point, each rejected, of
            1.15, 0.32, 0.11, 0.04 and 0.01 robust sigma (15.5, 8.5, 4.8, 1.8 and 0.5 scaled sigma;
            the HAC sigma 14-59 times the Gauss-Newton one): this rule ends that fit after the second
            of them with the same result. False:
            the scaled sigma only (``thinshell sysid``: True).
        hold_unidentified: hold a parameter that the data do not identify at its start value: at every
            accepted point (the start first) the parameters whose robust 2-sigma interval there reaches zero
            (:func:`sysid.covariance.not_identified`, judged with the robust covariance of method ``robust``
            from that point's Jacobian and the residual its Gauss-Newton step would leave, ``r + J delta``, no
            replay: at a start far off the residual itself is mostly the parameters' own error and would inflate
            the sandwich; at an optimum the two agree), and those whose column is zero where ``J^T J``
            is singular (:func:`unseen_columns`), get a column orthogonal to the residual and the other
            columns in the Jacobian the trust region sees (:func:`sysid.fit_region.held_jacobian`; a zero
            column made that Jacobian rank deficient and sent every step to the region's boundary), so
            ``least_squares`` takes no step along them, and the stops measure the step of the others.
            A trust-region step along a direction the residual barely sees is set by the region's size, not
            the data: with the default ``+-ln(1000)`` bounds the reflective method's Coleman-Li scaling
            ``sqrt(distance to the bound)`` makes the first region ``sqrt(ln 1000) = 2.63`` wide in log units,
            and on nominal_s101 the bending stiffness went x13.8 in the first step, from 0.0074 to 0.103
            (session 51), where the fit then stopped. A held parameter is re-judged at every accepted point
            and released once the data identify it; those held at the last one are :attr:`FitResult.held`,
            each with a warning, and are reported where they were held (their start, unless an earlier step
            moved them) with their interval. False: every parameter is stepped (``thinshell sysid``: True).
        first_step: width of the local phase's first trust region in every search coordinate (log units for a
            positive parameter; :func:`first_region_scale` sets ``least_squares``' ``x_scale`` for it). None: the
            method's own (``x_scale = 1``: 2.63 log units, a factor 13.8, within the default bounds).
            ``thinshell sysid``: :data:`FIRST_STEP`.
        made: a cold replay with tangents made before the fit (:class:`sysid.jacobians.TangentReplay`; ``thinshell
            sysid``: the calibration's secant step, at the fit's start): the start's joint evaluation takes it where
            it is the same replay (its parameters bitwise, its drive, the tangent columns
            :func:`joint_tangent_names` gives), instead of replaying. None: none.
        prior: name -> the range ``(lower, upper)`` (parameter units) the user's data sheet leaves open for a fitted
            parameter (:func:`sysid.identifiability.prior_ranges`); a parameter without one is judged on its search
            bounds. Whether the recording identifies each parameter and the interval reported are judged against it
            (:mod:`sysid.identifiability`, :attr:`FitResult.intervals`); the search is not bounded by it.
        profile_replays: replays allowed on each side of each parameter's profile (:func:`sysid.identifiability.
            profile_intervals`: the robust interval's ends replayed, widened where the cost is flatter than its
            tangent said); 0: the linearised rule alone (no replay).
        split: also judge each parameter by the split-sample test over the recording's motion phases
            (:mod:`sysid.split_sample`, no replay): a parameter whose value moves between the phases by more than the
            null allows is reported not identified (:func:`sysid.identifiability.split_verdict`). False: not tested.

    Returns:
        the :class:`FitResult`.

    Raises:
        ConfigError: unknown parameter name / provider / global method.
        CalibrationError: empty or duplicate parameter list, a non-finite start, a start outside
            ``bounds`` or bounds that leave no range, the replay at the start diverged, or the time
            budget ran out before the start was evaluated.
    """
    t0 = time.perf_counter()
    names = tuple(params)
    if not names:
        raise CalibrationError("no parameters to fit")
    if len(set(names)) != len(names):
        raise CalibrationError(f"parameter list has duplicates: {', '.join(names)}")
    start = {n: float(initial[n]) if initial and n in initial else model.parameter_value(n) for n in names}
    specs = [bounded_spec(parameter_spec(n, start[n]), (bounds or {}).get(n)) for n in names]
    provider = make_jacobian(jacobian, fd_step) if isinstance(jacobian, str) else jacobian
    deadline = t0 + max_time if max_time is not None else None
    joint = getattr(provider, "joint", None)
    if max_replays is not None and not max_replays >= 1:
        raise ConfigError(f"max_replays must be >= 1, got {max_replays!r}")
    nuisance = {n: float(v) for n, v in (nuisance or {}).items() if n not in names}
    for n, v in nuisance.items():
        nuisance_prior_u(n, model.parameter_value(n), v)  # unknown names and bad priors fail before any replay
    if robust is not None and robust not in ROBUST_METHODS:
        raise ConfigError(f"unknown robust covariance method {robust!r} (choose from {', '.join(ROBUST_METHODS)})")
    if max_replays is not None and max_replays < 2:
        joint = None  # no replay left for a step or a difference column: the start's tangents would go unused
    # the nuisance columns from every cold joint replay's tangents (no replay of the optimum again for them)
    extra = [parameter_spec(n, model.parameter_value(n))
             for n in joint_nuisance(names, nuisance, robust=robust, warm_start=warm_start)] if joint is not None else []
    problem = FitProblem(model, specs, workers=workers, deadline=None, on_eval=on_eval, joint=joint,
                         warm_start=warm_start, max_replays=max_replays, batched=batched, batch_size=batch_size,
                         extra=extra, made=made)
    saved_warm_start, model.warm_start = getattr(model, "warm_start", None), None
    saved_scale = getattr(model, "sigma_scale", None)
    if reweight_channels:
        model.sigma_scale = None
    channel_scale: dict[str, float] | None = None
    notes: list[str] = [f"fitting without {ch}: {why}" for ch, why in model.dropped.items()]
    with _warnings.catch_warnings(record=True) as caught:
        _warnings.simplefilter("always")
        try:
            u0 = np.zeros(len(names))
            r0 = problem.residual(u0, phase="initial")
            if r0 is None:
                raise CalibrationError(f"the replay diverged at the start values {start}: {problem.last_failure} "
                                       "(try a smaller --dt)")
            if reweight_channels:
                floor = 0.0 if reweight_channels is True else float(reweight_channels)
                channel_scale, r0 = _reweight_start(problem, u0, r0, floor)
            cost0, prediction0 = problem.best[0], problem.best_prediction()
            global_info = None
            if global_method is not None:
                problem.deadline = t0 + 0.5 * max_time if max_time is not None else None
                model.warm_start = None  # forked workers replay far-apart points: cold
                global_info = _global_phase(problem, u0, global_method, seed, global_evals, global_sigma)
            problem.deadline = deadline
            u_start = problem.best[1].copy()
            lb, ub = problem.bounds
            fail_level = 10.0 * max(1.0, float(np.sqrt(np.mean(r0 ** 2))))
            jac_at: dict[str, Any] = {}

            def fun(u: np.ndarray) -> np.ndarray:
                r = problem.residual(u, phase="local")
                sigma_trial = jac_at.get("sigma_trial")
                if stop_trial_sigma and jac_at.get("in_local") and r is not None and sigma_trial is not None:
                    ratio = float(np.max(np.abs(u - jac_at["u"]) / sigma_trial))
                    if 0.5 * float(r @ r) >= jac_at["cost"] and ratio < stop_trial_sigma:
                        jac_at["trial_in_sigma"] = ratio
                        raise _WithinNoise()
                return np.full_like(r0, fail_level) if r is None else r

            def jac(u: np.ndarray) -> np.ndarray:
                if jac_at.get("in_local"):
                    problem._check_time("local")  # a Jacobian costs a replay per parameter: not past the budget
                J = provider(problem, u)
                jac_at.update(u=np.array(u, dtype=float), J=J, count=jac_at.get("count", 0) + 1)
                r = problem.residual(u, phase="local") if jac_at.get("in_local") else None
                held = np.zeros(u.size, dtype=bool)
                if (stop_sigma or stop_trial_sigma or stop_rms or stop_robust_sigma or stop_trial_robust
                        or hold_unidentified) and r is not None:
                    _, sigma_u = gauss_newton_step(J, r)
                    seen = np.ones(u.size, dtype=bool)
                    if hold_unidentified and sigma_u is None:  # J^T J singular: the columns the replay does not see
                        seen = ~unseen_columns(J)
                        _, sigma_seen = gauss_newton_step(J[:, seen], r) if seen.any() else (None, None)
                        if sigma_seen is not None:  # an unseen coordinate's sigma is infinite
                            sigma_u = np.full(u.size, np.inf)
                            sigma_u[seen] = sigma_seen
                    sigma_rob = None
                    if (stop_robust_sigma or stop_trial_robust) and robust is not None and sigma_u is not None:
                        sigma_rob = robust_sigma(model, J, r, seen, robust, seed)
                    if hold_unidentified:
                        # judged on the residual the linearised fit would leave (r itself at an optimum): at a start
                        # far off, r is mostly the parameters' own error, which would inflate the sandwich
                        sigma_gate = None
                        if robust is not None and sigma_u is not None:
                            r_lin = r + J[:, seen] @ gauss_newton_step(J[:, seen], r)[0]
                            sigma_gate = robust_sigma(model, J, r_lin, seen, robust, seed)
                        held = ~seen if sigma_gate is None else ~seen | unidentified_coordinates(specs, u, sigma_gate)
                        jac_at["held"] = tuple(n for n, h in zip(names, held) if h)
                        if held.all():
                            raise _AllHeld()
                    # the step of the parameters the data identify, the held ones staying where they are; the
                    # stops measure it in the marginal sigma of the whole problem (the uncertainty reported)
                    step = np.zeros(u.size)
                    step[~held] = gauss_newton_step(J[:, ~held], r)[0]
                    cost = 0.5 * float(r @ r)
                    # the trial-step stop measures steps in the reported (residual-scaled) 1-sigma
                    chi2_red = 2.0 * cost / max(r.size - u.size, 1)
                    jac_at.update(sigma_u=sigma_u, cost=cost,
                                  sigma_trial=None if sigma_u is None else sigma_u * math.sqrt(max(chi2_red, 1.0)))
                    inside = bool(np.all(u + step >= lb) and np.all(u + step <= ub))
                    if stop_sigma and sigma_u is not None and np.all(np.abs(step) <= stop_sigma * sigma_u):
                        if inside:
                            jac_at["step_in_sigma"] = float(np.max(np.abs(step) / sigma_u))
                            raise _WithinNoise()
                    if stop_trial_robust and sigma_rob is not None:
                        # the trial-step stop measures steps in the robust 1-sigma where it is the larger
                        jac_at["sigma_trial"] = np.maximum(jac_at["sigma_trial"], sigma_rob)
                    if stop_robust_sigma and sigma_rob is not None and inside:
                        if np.all(np.abs(step) <= stop_robust_sigma * sigma_rob):
                            jac_at["step_in_robust_sigma"] = float(np.max(np.abs(step) / sigma_rob))
                            raise _WithinNoise()
                    previous = jac_at.get("accepted_cost")
                    jac_at["accepted_cost"] = cost
                    if stop_rms and previous is not None and previous > 0.0 and cost <= previous:
                        gain = 1.0 - math.sqrt(cost / previous)
                        if gain < stop_rms:
                            jac_at["rms_gain"] = gain
                            raise _WithinNoise()
                if held.any():  # a column orthogonal to r and the rest: least_squares takes no step along it
                    J = held_jacobian(J, r, held)
                return J

            status, message, nfev = "failed", "", 0
            jac_at["in_local"] = True
            try:
                res = least_squares(fun, u_start, jac=jac, bounds=(lb, ub), method="trf",
                                    x_scale=first_region_scale(u_start, lb, ub, first_step),
                                    ftol=ftol, xtol=xtol, gtol=gtol, max_nfev=max_nfev)
                status = "max_nfev" if res.status == 0 else "converged" if res.status > 0 else "failed"
                message, nfev = str(res.message), int(res.nfev)
            except _OutOfReplays:
                status, message = "replay_budget", (f"stopped at the replay budget ({max_replays} replays, "
                                                    f"{problem.sim_runs} made); best point so far returned")
            except _OutOfTime:
                status, message = "time_budget", f"stopped after {max_time} s; best point so far returned"
            except _AllHeld:
                status = "converged"
                message = ("no parameter is identified at the start (every robust 2-sigma interval reaches zero): "
                           "all held at their start values")
                nfev = sum(e.phase == "local" for e in problem.history)
            except _WithinNoise:
                status = "converged"
                if "rms_gain" in jac_at:
                    message = (f"the last accepted step lowered the RMS by {100 * jac_at['rms_gain']:.2g} %, below "
                               f"the stop fraction {100 * stop_rms:g} % (the replays' numerical noise)")
                elif "step_in_robust_sigma" in jac_at:
                    message = (f"the Gauss-Newton step is {jac_at['step_in_robust_sigma']:.2g} robust sigma ({robust}) "
                               f"at most, below the stop fraction {stop_robust_sigma:g}")
                elif "trial_in_sigma" in jac_at:
                    unit = "sigma (the larger of scaled and robust)" if stop_trial_robust else "scaled sigma"
                    message = (f"a trial step of {jac_at['trial_in_sigma']:.2g} {unit} at most (below {stop_trial_sigma:g}) "
                               "did not lower the cost: flat to within the replay's numerical noise")
                else:
                    message = (f"the Gauss-Newton step is {jac_at['step_in_sigma']:.2g} sigma at most, below the stop "
                               f"fraction {stop_sigma:g} of the 1-sigma uncertainty")
                nfev = sum(e.phase == "local" for e in problem.history)
            jac_at["in_local"] = False
            prediction_best = problem.best_prediction()
            cost_best, u_best = problem.best[0], problem.best[1]
            njev = int(jac_at.get("count", 0))
            J, spent = None, "time" if status == "time_budget" else "replay"
            if "u" in jac_at and np.array_equal(jac_at["u"], u_best):
                J, jac_note = jac_at["J"], "ok"
            elif status != "time_budget":
                problem.deadline = None
                try:  # within the replay budget (a finite-difference column costs a replay)
                    J, jac_note = jac(u_best), "ok"
                except _OutOfReplays:
                    J = None
            if J is None and "J" in jac_at:
                J, jac_note = jac_at["J"], f"Jacobian of the last accepted iterate ({spent} budget spent)"
            elif J is None:
                J, jac_note = None, f"no Jacobian computed before the {spent} budget ran out"
            J_nuisance, nuisance_runs = None, 0
            if nuisance and robust is not None and J is not None:
                J_nuisance, nuisance_runs = _nuisance_jacobian(problem, u_best, nuisance, fd_step, notes)
        finally:
            problem.close()
            model.warm_start = saved_warm_start
            model.sigma_scale = saved_scale
    notes += [str(w.message) for w in caught]
    m, p = model.residual_count, len(names)
    chi2_red = 2.0 * cost_best / max(m - p, 1)
    cov, cov_note = gauss_newton_covariance(J) if J is not None else (None, jac_note)
    if cov_note != "ok":
        notes.append(f"covariance: {cov_note}")
    elif jac_note != "ok":
        notes.append(f"covariance: {jac_note}")
    values = problem.values(u_best)
    sigma, sigma_log, scaled, corr = _covariance_summary(specs, values, cov, chi2_red)
    robust_cov, sigma_robust = None, None
    r_best = problem._cache.get(np.asarray(u_best, dtype=float).tobytes())
    if robust is not None and cov is not None and r_best is not None:
        try:
            # no better than the sensor's own noise allows (the sandwich's small-sample bias; the stops keep it raw)
            robust_cov = model_robust_covariance(model, J, r_best, robust, seed).floored(J)
        except CalibrationError as err:
            notes.append(f"robust covariance: {err}")
        else:
            if J_nuisance is not None:
                nuisance_sd = np.array([nuisance_prior_u(n, problem.model.parameter_value(n), s) for n, s in nuisance.items()])
                ncov, A = nuisance_covariance(J, J_nuisance, nuisance_sd)
                robust_cov = robust_cov.with_nuisance(ncov, {n: float(s) for n, s in nuisance.items()},
                                                      {n: A[:, k] for k, n in enumerate(nuisance)})
            sigma_robust = sigma_of(specs, values, robust_cov.covariance_u)
    held = tuple(jac_at.get("held", ()))
    notes.extend(f"{n} was held at {_held_where(values[n], start[n])} by the fit: at the last accepted point its robust "
                 "2-sigma interval reached zero, so no step was taken along it (a step there is set by the trust "
                 "region's size, not by the data)" for n in held)
    intervals = judge(specs, values, sigma_robust, prior)
    profile_runs = 0
    if profile_replays and robust_cov is not None and r_best is not None:
        saved = model.warm_start, model.sigma_scale
        model.warm_start, model.sigma_scale = None, channel_scale  # cold replays in the fit's units
        problem.deadline, problem.max_replays = None, None  # the verdict is not cut short by the search's budgets
        runs_before = problem.sim_runs
        try:
            times, bin_s = model_residual_times(model)
            intervals = profile_intervals(lambda u: problem.residual(u, phase="profile"), specs, u_best, J, r_best,
                                          robust_cov, intervals, times, bin_s, profile_replays,
                                          many=lambda pts: problem.evaluate_many(pts, phase="profile"))
        except CalibrationError as err:
            notes.append(f"profile of the fitted parameters not computed ({err}); the linearised rule stands")
        finally:
            problem.close()
            model.warm_start, model.sigma_scale = saved
            profile_runs = problem.sim_runs - runs_before
    if split and J is not None and r_best is not None and robust_cov is not None:
        try:
            times, bin_s = model_residual_times(model)
            tests = split_test(names, J, r_best, times, bin_s, robust_cov.lag_bins, model_phases(model, bin_s))
        except CalibrationError as err:
            notes.append(f"split-sample test not computed ({err})")
        else:
            intervals = split_verdict(specs, u_best, intervals, tests)
    unidentified = tuple(n for n in names if not intervals[n].identified)
    notes.extend(not_identified_note(intervals[n]) for n in unidentified)
    notes.extend(w for w in (lower_cost_note(intervals[n]) for n in names) if w)
    return FitResult(
        names=names, specs=tuple(specs), initial=start, values=values, sigma=sigma, sigma_log=sigma_log,
        sigma_scaled=scaled, covariance_u=cov, correlation=corr, cost_initial=cost0, cost_final=cost_best,
        reduced_chi2=chi2_red, rms_initial=model.channel_rms(prediction0), rms_final=model.channel_rms(prediction_best),
        prediction_initial=prediction0, prediction_final=prediction_best, history=problem.history,
        iterations=max(njev - 1, 0), nfev=nfev, njev=njev, sim_runs=problem.sim_runs + nuisance_runs,
        sim_time_s=problem.sim_time_s, wall_time_s=time.perf_counter() - t0, status=status, message=message,
        jacobian=provider.name, global_phase=global_info, channels=model.channels,
        residual_count=m, step_count=model.step_count, dt=model.dt, warnings=notes, model=model,
        sigma_scale=channel_scale, sigma_robust=sigma_robust, robust=robust_cov, not_identified=unidentified,
        held=held, intervals=intervals, profile_runs=profile_runs,
    )


def joint_tangent_names(params: Sequence[str], nuisance: Mapping[str, float], *, robust: str | None,
                        warm_start: bool) -> tuple[str, ...]:
    """The tangent columns of :func:`fit`'s joint replays with the sensitivity provider, in order
    (:func:`sysid.jacobians.tangent_columns` of the fitted parameters and of the nuisance parameters
    :func:`joint_nuisance` hands the joint replays). What a replay made before the fit must carry to be taken as its
    start's joint replay (``made``)."""
    own, kept = tangent_columns(params, joint_nuisance(params, nuisance, robust=robust, warm_start=warm_start))
    return own + kept


def joint_nuisance(params: Sequence[str], nuisance: Iterable[str], *, robust: str | None,
                   warm_start: bool) -> list[str]:
    """The nuisance parameters (names; those of ``params`` left out) whose columns :func:`fit` asks of every joint
    replay (:attr:`FitProblem.extra_specs`): all of them where the covariance is robust and the replays are cold
    (the optimum's own replay then gives them, :func:`_nuisance_jacobian`), else none."""
    return [n for n in nuisance if n not in params] if robust is not None and not warm_start else []


def nuisance_prior_u(name: str, value: float, prior: float) -> float:
    """Prior 1-sigma of nuisance parameter ``name`` (nominal ``value``) in its search coordinate: ``prior``
    is relative for a positive scale parameter (log coordinate), in the parameter's units otherwise.

    Raises:
        CalibrationError: a prior that is not a positive number.
    """
    if not (math.isfinite(prior) and prior > 0.0):
        raise CalibrationError(f"nuisance prior of {name} must be a positive number, got {prior!r}")
    spec = parameter_spec(name, value)
    return float(prior) if spec.log else float(prior) / spec.scale


def _nuisance_jacobian(problem: FitProblem, u_best: np.ndarray, nuisance: Mapping[str, float], fd_step: float,
                       notes: list[str]) -> tuple[np.ndarray | None, int]:
    """Whitened Jacobian ``(m, q)`` of the nuisance parameters at the fitted point, and the replays it took: the
    columns the point's own cold joint replay computed (:attr:`FitProblem.extra_specs`; no replay), else one replay
    with tangents where the sensitivity provider is available, else finite differences."""
    model = problem.model
    kept = problem.extra_jacobian(u_best)
    if kept is not None and not problem.warm_start and [s.name for s in problem.extra_specs] == list(nuisance):
        return kept, 0  # the optimum's own cold replay computed them: a replay of it again would give the same
    ext = FitProblem(model, list(problem.specs) + [parameter_spec(n, model.parameter_value(n)) for n in nuisance])
    try:
        J = make_jacobian("auto", fd_step)(ext, np.concatenate([np.asarray(u_best, dtype=float),
                                                                np.zeros(len(nuisance))]))
    except (CalibrationError, ConfigError, SimulationDivergedError) as err:
        notes.append(f"robust covariance: nuisance Jacobian not computed ({err}); the time-correlation part only")
        return None, ext.sim_runs
    finally:
        ext.close()
    return J[:, len(problem.specs):], ext.sim_runs


def _reweight_start(problem: FitProblem, u0: np.ndarray, r0: np.ndarray,
                    floor: float = 0.0) -> tuple[dict[str, float], np.ndarray]:
    """``fit(reweight_channels=...)``: set the model's per-channel ``sigma_scale`` from the start's
    whitened residual ``r0`` (the channels above ``floor`` only) and express what the problem
    holds at the start (residual, cost, Jacobian) in the reweighted units. Returns ``(channel -> factor,
    reweighted r0)``."""
    model = problem.model
    slices = model.channel_slices()
    rms = {ch: float(np.sqrt(np.mean(r0[sl] ** 2))) if sl.stop > sl.start else 1.0 for ch, sl in slices.items()}
    followed = floor <= 0.0 or any(v <= floor for v in rms.values())
    # above a floor, only beside a channel the model follows: one channel, or every channel off by a start far from
    # the fit, has no channel to rebalance against (its weight would only widen the stops' sigmas)
    scale = {ch: max(1.0, v) if v > floor and followed else 1.0 for ch, v in rms.items()}
    model.sigma_scale = dict(scale)
    vec = np.ones_like(r0)
    for ch, sl in slices.items():
        vec[sl] = scale[ch]
    key = np.asarray(u0, dtype=float).tobytes()
    r = r0 / vec
    problem._cache[key] = r
    J = problem.cached_jacobian(u0)
    if J is not None:
        problem.keep_jacobian(u0, J / vec[:, None])
    cost, u_best, prediction = problem.best
    problem.best = (0.5 * float(r @ r), u_best, prediction)
    for ev in problem.history:
        if ev.u.tobytes() == key:
            ev.cost = problem.best[0]
    return scale, r
