"""Jacobians of the whitened fit residual ``r(u)`` (:mod:`sysid.fit`): central finite differences
in the search coordinates, or forward sensitivities through the simulator
(``sim_core.sensitivity``: implicit differentiation of each Newton step with its converged
factorisation; through the effector's series drive where the replay takes one,
:func:`sysid.replay_drive.drive_sensitivities`), alone or joint with the residual replay.
"""

from __future__ import annotations

import importlib
import math
import time
import warnings as _warnings
from dataclasses import dataclass
from typing import Any, Mapping, Protocol, Sequence

import numpy as np

from sim_core.errors import CalibrationError, ConfigError, SimulationDivergedError
from sysid.observation import SENSOR_PARAMETERS, ObservationModel, SimTrace
from sysid.replay_drive import drive_sensitivities

JACOBIAN_KINDS = ("auto", "sensitivity", "fd")

LAYER_NORMAL_RATIO_SETTING = "candidate.adhesion.normal_ratio"
"""The tack layer's normal-to-shear stiffness ratio (:data:`sysid.diagnose.shear_layer.NORMAL_RATIO_SETTING`; named
here, below the diagnosis): a nuisance of a lift's fit with no tangent of its own."""
DIFFERENCE_PARAMETERS = (*SENSOR_PARAMETERS, LAYER_NORMAL_RATIO_SETTING)
"""Parameters whose Jacobian columns the sensitivity provider takes by forward differences: the
replay's sensor offset (not a simulator parameter). The friction mollifier width ``contact.eps_v`` has its
tangent (:meth:`sim_core.energies.friction.reference.LaggedFriction.eps_v_gradient`), the tack's shear layer
(:data:`sysid.diagnose.tack.SHEAR_STIFFNESS_SETTING`) its own
(:meth:`sim_core.candidates.adhesion.LaggedAdhesion.parameter_gradient`, with the bonds' lagged normals in the state
tangents)."""

DIFFERENCE_STEPS = {"sensor.normal_offset": 0.1, LAYER_NORMAL_RATIO_SETTING: 0.1}
"""Forward-difference step (search coordinates) of each difference parameter, when larger than the
provider's ``fd_step``: 5 um of sensor offset, 10 % of the tack layer's normal ratio. A replay's cost is rough at
the 0.3 % level under small changes of such parameters (the contact set and the lagged friction's
stick/slip state switch pair by pair), so a 1 % step measures that roughness rather than the slope."""


def tangent_columns(names: Sequence[str], extra: Sequence[str] = ()) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The parameters a joint replay (:meth:`SensitivityJacobian.joint`) solves tangents for, in column order:
    ``(own, kept)``, ``own`` the parameters ``names`` without the :data:`DIFFERENCE_PARAMETERS` (their columns are
    forward differences), ``kept`` the ``extra`` ones (a fit's nuisance parameters, held at their nominal) where
    none of them is a difference parameter, else none (their columns then come from the fit's own nuisance
    Jacobian). The one home of the rule: a replay made before a fit (:class:`TangentReplay`) carries these."""
    own = tuple(n for n in names if n not in DIFFERENCE_PARAMETERS)
    kept = () if any(n in DIFFERENCE_PARAMETERS for n in extra) else tuple(extra)
    return own, kept


# ====================================================================================== Jacobians
class ReplayProblem(Protocol):
    """What a Jacobian provider needs of a fit problem (:class:`sysid.fit.FitProblem` is one): the
    whitened residual ``r(u)``, shape ``(m,)``, of search coordinates ``u``, shape ``(p,)``, and its
    replay bookkeeping."""

    model: ObservationModel
    specs: Sequence[Any]
    names: Sequence[str]
    bounds: tuple[np.ndarray, np.ndarray]
    sim_runs: int
    sim_time_s: float
    warm_start: bool
    last_positions: np.ndarray | None

    def values(self, u: np.ndarray) -> dict[str, float]: ...

    def residual(self, u: np.ndarray, phase: str = "local") -> np.ndarray | None: ...

    def evaluate_many(self, points: Sequence[np.ndarray], phase: str) -> list[np.ndarray | None]: ...

    def reserve(self, count: int, phase: str) -> None: ...

    def keep_jacobian(self, u: np.ndarray, J: np.ndarray) -> None: ...

    def cached_jacobian(self, u: np.ndarray) -> np.ndarray | None: ...


class JacobianProvider(Protocol):
    """Computes ``J = d r / d u``, shape ``(m, p)``, of the whitened residual at coordinates ``u``."""

    name: str

    def __call__(self, problem: ReplayProblem, u: np.ndarray) -> np.ndarray: ...


class FiniteDifferenceJacobian:
    """Central differences ``(r(u + h e_i) - r(u - h e_i)) / 2h`` in the search coordinates.

    2p replays per Jacobian, batched through :meth:`ReplayProblem.evaluate_many`; one-sided at a bound
    or where one side diverged.

    Args:
        step: h, > 0 (log units for positive parameters: 0.01 = 1 %).

    Raises:
        ConfigError: non-positive step.
    """

    name = "fd"

    def __init__(self, step: float = 0.01) -> None:
        if not step > 0.0:
            raise ConfigError(f"finite-difference step must be > 0, got {step!r}")
        self.step = float(step)

    def __call__(self, problem: ReplayProblem, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        lb, ub = problem.bounds
        points, steps = [], []
        for i in range(u.shape[0]):
            hp, hm = min(self.step, ub[i] - u[i]), min(self.step, u[i] - lb[i])
            up, um = u.copy(), u.copy()
            up[i] += hp
            um[i] -= hm
            points += [up, um]
            steps.append((hp, hm))
        res = problem.evaluate_many(points, phase="jacobian")
        cols = []
        for i, (hp, hm) in enumerate(steps):
            rp, rm = res[2 * i], res[2 * i + 1]
            if rp is not None and rm is not None and hp + hm > 0.0:
                cols.append((rp - rm) / (hp + hm))
                continue
            r0 = problem.residual(u, phase="jacobian")
            if r0 is not None and rp is not None and hp > 0.0:
                cols.append((rp - r0) / hp)
            elif r0 is not None and rm is not None and hm > 0.0:
                cols.append((r0 - rm) / hm)
            else:
                raise CalibrationError(f"finite-difference Jacobian: the simulation diverged on both sides of "
                                       f"{problem.names[i]} = {problem.values(u)[problem.names[i]]:.6g}")
        return np.stack(cols, axis=1)


class SensitivityJacobian:
    """Forward parameter sensitivities of the simulator mapped to the whitened residual.

    ``sim_core.sensitivity.parameter_sensitivities`` propagates ``dX/dtheta`` (and the contact-force
    tangents) through one recorded replay, ``observation_sensitivities`` maps them to
    d(observation)/d(theta) per step, :meth:`ObservationModel.align` interpolates those to the stamps
    (linear), and the chain rule to u multiplies by ``d theta / d u`` (theta for log coordinates, the
    scale otherwise). One replay plus p right-hand sides per step instead of 2p replays. In
    :func:`fit` the local phase's replays are joint ones (:meth:`joint`): each computes the residual
    and the Jacobian together, with the tangents solved by the Newton factorisation of every step,
    so the Jacobian that ``least_squares`` then asks for at an accepted point costs no further
    replay. A replay that the sensitivity code refuses (a step retried with a smaller dt is not
    differentiable) falls back to finite differences for that Jacobian, with a warning.

    Raises:
        CalibrationError: the sensitivity module is missing.
    """

    name = "sensitivity"

    def __init__(self, fd_step: float = 0.01) -> None:
        self.module = load_sensitivity()
        self.fallback = FiniteDifferenceJacobian(fd_step)

    def __call__(self, problem: ReplayProblem, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        names, other = self._split(problem)
        J = problem.cached_jacobian(u)
        if J is not None:
            if other and np.isnan(J[:, other]).any():  # a joint replay's: its difference columns now
                mine = [i for i in range(len(problem.names)) if i not in other]
                J = self._with_difference_columns(problem, u, J[:, mine], other, None)
                problem.keep_jacobian(u, J)
            return J
        model = problem.model
        values = problem.values(u)
        if not names:  # only difference columns: no tangents to propagate
            return self._with_difference_columns(problem, u, np.zeros((model.residual_count, 0)), other, None)
        problem.reserve(1 + len(other), "jacobian")
        t = time.perf_counter()
        try:
            sim = model.prepare(values)
            traj, dX, dF, dQ = rollout_with_tangents(model, sim, names)
        except ConfigError as err:
            _warnings.warn(f"sensitivity Jacobian unavailable for this replay ({err}); finite differences used",
                           stacklevel=2)
            return self.fallback(problem, u)
        except SimulationDivergedError as err:
            raise CalibrationError(f"sensitivity Jacobian: the replay diverged at {values} ({err})") from err
        problem.sim_runs += 1
        problem.sim_time_s += time.perf_counter() - t
        trace = None
        if model.gain_profile is not None:  # the gains refitted to this replay first (sysid.gain_profile)
            trace = model.trace_of(sim, traj.states)
            model.predict(trace)
        J = self._whitened(problem, values, sim, traj, dX, dF, dQ)
        if trace is not None:  # ... and their columns projected out
            J = model.gain_profile.project(model.predict_raw(trace), J)
        return self._with_difference_columns(problem, u, J, other, None)

    def _split(self, problem: ReplayProblem) -> tuple[list[str], list[int]]:
        """Names with simulator sensitivities, and the indices of the parameters without them,
        whose columns are forward differences (:data:`DIFFERENCE_PARAMETERS`)."""
        other = [i for i, n in enumerate(problem.names) if n in DIFFERENCE_PARAMETERS]
        return list(tangent_columns(problem.names)[0]), other

    def _with_difference_columns(self, problem: ReplayProblem, u: np.ndarray, J: np.ndarray, other: list[int],
                                 r0: np.ndarray | None) -> np.ndarray:
        """``J`` ``(m, p - len(other))`` completed with forward-difference columns at ``other``."""
        if not other:
            return J
        lb, ub = problem.bounds
        points, steps = [], []
        for i in other:
            step = max(self.fallback.step, DIFFERENCE_STEPS.get(problem.names[i], 0.0))
            h = step if u[i] + step <= ub[i] else -step
            du = u.copy()
            du[i] += h
            points.append(du)
            steps.append(h)
        r0 = problem.residual(u, phase="jacobian") if r0 is None else r0
        problem.reserve(len(points), "jacobian")
        res = problem.evaluate_many(points, phase="jacobian")
        full = np.zeros((J.shape[0], len(problem.names)))
        mine = [i for i in range(len(problem.names)) if i not in other]
        full[:, mine] = J
        for i, h, r in zip(other, steps, res):
            if r is None and r0 is not None:  # the other side
                h = -h
                du = u.copy()
                du[i] += h
                r = problem.residual(du, phase="jacobian")
            if r is None or r0 is None:
                raise CalibrationError(f"finite-difference Jacobian: the replay diverged on both sides of "
                                       f"{problem.names[i]} = {problem.values(u)[problem.names[i]]:.6g}")
            full[:, i] = (r - r0) / h
        return full

    def joint(self, problem: ReplayProblem, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Residual, Jacobian and prediction at ``u`` from one replay (``FitProblem(joint=...)``).

        The tangents are solved step by step with the Newton factorisation of each step
        (``sim_core.sensitivity.rollout_sensitivities``), so the Jacobian costs about a quarter of
        a replay on top of it instead of a second replay. The columns of the difference parameters
        (:data:`DIFFERENCE_PARAMETERS`, a replay each) are left NaN: :meth:`__call__` computes them
        when the Jacobian at ``u`` is asked for, i.e. at an accepted point of the fit, so that a
        rejected trial point costs one replay.

        Raises:
            SimulationDivergedError: the replay diverged.
            ConfigError: the replay is not differentiable, or no parameter has simulator
                sensitivities (the caller replays without tangents).
        """
        model = problem.model
        values = problem.values(u)
        names, other = self._split(problem)
        if not names:
            raise ConfigError("no parameter with simulator sensitivities: a plain replay gives the residual")
        # the columns of the problem's extra parameters (a fit's nuisance parameters at their nominal) in the same
        # replay, where every one has tangents: the fit then needs no replay of its own for them at its optimum
        extra = tuple(getattr(problem, "extra_specs", ()))
        kept = tangent_columns(names, [s.name for s in extra])[1]
        extra = extra if kept else ()
        tangent_names = [*names, *kept]
        made = getattr(problem, "made", None)
        sim = model.prepare(values)
        t = time.perf_counter()
        if made is not None and made.matches(model, values, tangent_names):  # made before the fit: taken once
            problem.made = None
            traj, dX, dF, dQ = made.rollout
        else:
            traj, dX, dF, dQ = rollout_with_tangents(model, sim, tangent_names)
        if problem.warm_start:  # the start of the next replays
            problem.last_positions = np.stack([s.x for s in traj.states])
        trace = model.trace_of(sim, traj.states, time.perf_counter() - t)
        prediction = model.predict(trace)
        r = model.residuals(prediction)
        J = np.full((r.shape[0], len(problem.names)), np.nan)
        mine = self._whitened(problem, {**values, **{s.name: s.to_value(0.0) for s in extra}}, sim, traj, dX, dF, dQ,
                              extra)
        if model.gain_profile is not None:  # the gains refitted at every replay: their columns projected out
            mine = model.gain_profile.project(model.predict_raw(trace), mine)
        J[:, [i for i in range(len(problem.names)) if i not in other]] = mine[:, :len(names)]
        if extra:
            problem.keep_extra_jacobian(u, mine[:, len(names):])
        return r, J, prediction

    def _whitened(self, problem: ReplayProblem, values: Mapping[str, float], sim, traj, dX: np.ndarray,
                  dF: np.ndarray, dQ: np.ndarray | None = None, extra: Sequence[Any] = ()) -> np.ndarray:
        """Whitened residual Jacobian ``(m, p)`` in the search coordinates from the state tangents (``dQ``: those
        of the sensor's effector position on a series drive, :func:`rollout_with_tangents`); with ``extra`` parameter specs
        (their tangents after the problem's, their values in ``values``) ``(m, p + len(extra))``."""
        model = problem.model
        obs = self.module.observation_sensitivities(sim.model, traj, dX, dF, sensor=model.sensor, effector_position=dQ)
        specs = [*(s for s in problem.specs if s.name not in DIFFERENCE_PARAMETERS), *extra]
        dtheta_du = np.array([abs(values[s.name]) if s.log else s.scale for s in specs])
        cal = getattr(model, "sensor_calibration", None)
        blocks = []
        for ch in model.channels:
            d = model.align(ch, obs[ch]) * dtheta_du
            if cal is not None:
                d = cal.derivative(ch, d)
            blocks.append(model.whiten_derivative(ch, d))
        return np.concatenate(blocks, axis=0)


def rollout_with_tangents(model: ObservationModel, sim, names: Sequence[str]):
    """One replay of ``model`` from the :meth:`~ObservationModel.prepare`'d ``sim`` with its tangents:
    ``(trajectory, dX, dF, dQ)``, ``dQ`` the tangents of the position of an effector on a series drive
    (:func:`sysid.replay_drive.drive_sensitivities`; None for a kinematic replay).

    Raises:
        CalibrationError: the sensitivity module is missing.
        ConfigError: a step the replay cannot differentiate (dt halved), an unknown parameter.
        SimulationDivergedError: from the solver.
    """
    if math.isfinite(model.drive_stiffness):
        return drive_sensitivities(model, sim, names)
    traj, dX, dF = load_sensitivity().rollout_sensitivities(sim, model.controls_list(), names, contact_force=True)
    return traj, dX, dF, None


@dataclass
class TangentReplay:
    """A cold replay with its tangents, made before a fit and handed to the fit's first joint evaluation
    (:meth:`SensitivityJacobian.joint`), which takes it instead of replaying where it is the same replay.

    ``thinshell sysid`` makes the calibration's secant step (:func:`sysid.calibration_secant.secant_calibration`
    ``last``) this way: the fit starts at the stick speed that step replayed, at the start's materials, so its first
    joint replay would be that replay again, for its tangents (10-14 % of a default fit of nominal_s101; docs/benchmarks_log.md,
    session 54, s54-49time). A replay is a function of its parameters, its drive and the model's recording only when
    it is cold (``model.warm_start`` None, the default), as both are.

    Attributes:
        values: every parameter the replay set or read, SI: the values it was given, and the model's nominal then of
            every tangent name it was not given.
        names: its tangent columns, in order (those the fit's joint replay asks for).
        drive: the model's ``(drive_stiffness, drive_damping)`` during the replay.
        rollout: ``(trajectory, dX, dF, dQ)`` of :func:`rollout_with_tangents`.
    """

    values: dict[str, float]
    names: tuple[str, ...]
    drive: tuple[float, float]
    rollout: tuple

    @classmethod
    def make(cls, model: ObservationModel, values: Mapping[str, float], names: Sequence[str]
             ) -> tuple["TangentReplay", SimTrace]:
        """Replay ``model`` at ``values`` (SI; others at their nominal) cold, with the tangents of ``names``.

        Returns:
            the replay and its :class:`~sysid.observation.SimTrace` (without states), as a plain replay's.

        Raises:
            as :func:`rollout_with_tangents`; CalibrationError: a warm start is set (such a replay is not a
            function of its parameters).
        """
        if getattr(model, "warm_start", None) is not None:
            raise CalibrationError("TangentReplay.make: the model has a warm start; only a cold replay can be handed on")
        sim = model.prepare(values)
        t = time.perf_counter()
        rollout = rollout_with_tangents(model, sim, list(names))
        trace = model.trace_of(sim, rollout[0].states, time.perf_counter() - t)
        return cls(cls._resolved(model, values, names), tuple(names),
                   (float(model.drive_stiffness), float(model.drive_damping)), rollout), trace

    @staticmethod
    def _resolved(model: ObservationModel, values: Mapping[str, float], names: Sequence[str]) -> dict[str, float]:
        return {n: float(values[n]) if n in values else float(model.parameter_value(n)) for n in (*values, *names)}

    def matches(self, model: ObservationModel, values: Mapping[str, float], names: Sequence[str]) -> bool:
        """Whether a cold replay of ``model`` at ``values`` with the tangents of ``names`` is this one: the same
        tangent names in the same order, the same drive, every parameter bitwise the same (given or nominal)."""
        if tuple(names) != self.names or getattr(model, "warm_start", None) is not None:
            return False
        if (float(model.drive_stiffness), float(model.drive_damping)) != self.drive:
            return False
        return self._resolved(model, values, (*self.values, *names)) == self.values


def load_sensitivity() -> Any:
    """``sim_core.sensitivity`` when it provides ``parameter_sensitivities``, ``rollout_sensitivities``
    and ``observation_sensitivities``.

    Raises:
        CalibrationError: the module or a function is missing.
    """
    try:
        mod = importlib.import_module("sim_core.sensitivity")
    except ImportError as err:
        raise CalibrationError(f"jacobian 'sensitivity' needs sim_core.sensitivity, which is not available ({err}); "
                               "use --jacobian fd") from err
    for fn in ("parameter_sensitivities", "rollout_sensitivities", "observation_sensitivities"):
        if not hasattr(mod, fn):
            raise CalibrationError(f"jacobian 'sensitivity': sim_core.sensitivity has no {fn}(); use --jacobian fd")
    return mod


def make_jacobian(kind: str = "auto", fd_step: float = 0.01) -> JacobianProvider:
    """A provider by name: ``"sensitivity"``, ``"fd"``, or ``"auto"`` (sensitivity when
    ``sim_core.sensitivity`` is importable, else finite differences).

    Raises:
        ConfigError: unknown kind.
        CalibrationError: ``"sensitivity"`` requested but unavailable.
    """
    if kind not in JACOBIAN_KINDS:
        raise ConfigError(f"unknown jacobian provider {kind!r} (choose from {', '.join(JACOBIAN_KINDS)})")
    if kind == "sensitivity":
        return SensitivityJacobian(fd_step)
    if kind == "auto" and _sensitivity_available():
        return SensitivityJacobian(fd_step)
    return FiniteDifferenceJacobian(fd_step)


def _sensitivity_available() -> bool:
    try:
        load_sensitivity()
    except CalibrationError:
        return False
    return True
