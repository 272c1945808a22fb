"""The effector's drive along the sensor normal in a replay: a series spring anchored at the command.

An impedance-controlled arm's measured pose lags its command by the load over its stiffness. A
replay that imposes the measured pose (the kinematic drive) loads the gel through the contact's own
stiffness instead, so a sink of the measured pose by 0.1 mm while the pad slides becomes a few newtons
more load (docs/benchmarks_log.md, session 37, 23drag). :class:`ReplayDrive` replays such an arm:
along the sensor normal ``n`` the pad hangs on a spring of stiffness ``k_s`` anchored at the recorded
command's position along ``n`` (the recorded pose's where no command was recorded), with the arm's
damper on the pad's velocity along ``n`` beside it, across ``n`` and in rotation it follows the recorded
pose, and each step is solved for the spring's compression
(:class:`sim_core.series_drive.SeriesSpringDrive`). The recorded wrench is not an input.

:func:`drive_sensitivities` replays through the drive and propagates the parameter tangents with it
(:class:`sim_core.sensitivity.DriveStep`: the compression's tangent by the implicit function theorem on the
spring's balance), so that a fit through the drive has analytic Jacobians: one replay, not ``2 p`` replays
of finite differences whose columns carry the drive's force tolerance divided by the difference step.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from sim_core.adjoint import Trajectory, check_parameters
from sim_core.carried_start import clear_of_contact
from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.sensitivity import DriveStep, TangentPropagation
from sim_core.series_drive import SeriesSpringDrive


DRIVE_FORCE_TOLERANCE = 0.005
"""Force tolerance of a series drive's step, in noise levels of the recorded normal force (-).

A step's secant on the spring's compression stops within this mismatch of spring and contact force, so the replayed
force carries up to that error each step and its stopping point jumps with the parameters. Convergence study on
nominal_s101 through its fitted drive (2,979 N/m; normal-force noise 0.21 N), every step to 1e-7 m/s
(:data:`sysid.observation.REPLAY_TOL_VELOCITY`), cost at the scene's values (sensor uncalibrated): 1,586,906 /
1,598,345 / 1,597,588 / 1,597,606 at 0.5 / 0.05 / 0.005 / 0.0005; at 0.5 the replay at the scene's values stood 0.001
whitened RMS (markers) off the line its neighbours 1e-5 apart in the gel modulus lie on, at 0.05 and below they are on
it. 0.005 (1 mN there, :class:`~sim_core.series_drive.SeriesSpringDrive`'s own default) is converged to 1e-5 of the
cost; 0.5 (until session 55) moved it 0.7 % (docs/benchmarks_log.md, session 55, s55-49rest)."""


DRIVE_STARTS = "line"
"""The replay's drive evaluations start Newton from a function of their own compression
(:class:`sim_core.series_drive.CompressionLoad`), so a step's load ``F(b)`` does not depend on the order of the
secant's evaluations; the replay's 1e-7 m/s (:data:`sysid.observation.REPLAY_TOL_VELOCITY`) resolves the drive's
force tolerance from such starts. Against the chained starts (docs/benchmarks_log.md, session 57, s57-49release):
the calibration's whitened RMS the same to 4 digits on latency_s103 and nominal_s101, one replay of nominal_s101
550 evaluations and 16.3 CPU s with either; latency_s103's stick-speed probe still keeps the card on the lifting
pad (the line continues the held branch of the lift-off's fold)."""


DRIVE_SOLVE = "joint"
"""How the replay's drive steps solve for the spring's compression (:data:`sim_core.series_drive.SERIES_SOLVES`):
``"joint"``, the compression an unknown of the step's own Newton solve (:mod:`sim_core.drive_compression`: one Newton
solve a step, the lift-off's fold decided by the step's energy), or ``"secant"``, the safeguarded secant over whole
step solves. Measured (VM, 2 cores shared, docs/benchmarks_log.md, session 58, s58-49drive): one replay of
nominal_s101 at the scene's values 1,585 Newton iterations and 1,314 factorisations against the secant's 2,046 and
1,612 (550 evaluations), the same loads within the force tolerance; ``thinshell sysid`` nominal_s101 163 CPU s
against 185, every fitted value within 2e-5 of the secant's; the calibration of latency_s103 7.79 / 11.07 / 5.77
(markers / pixels / wrench) against 8.51 / 12.14 / 5.85 (the released card lies down after the lift), of
nominal_s101 the same to 3 digits."""


def first_compression(load: float, slope: float, reach: float, stiffness: float, rate: float) -> float:
    """The first compression a drive step tries (m): the root of the step's spring balance with the load linear
    in the tool's advance.

    :class:`sim_core.series_drive.SeriesSpringDrive` balances ``h(b) = F(b) - K b + c d / dt`` (``K = k_s + c /
    dt``, ``d`` the anchor's reach past the tool's position at the step's start along the normal). With the load
    the last step's ``F_0`` plus the contact's slope ``s`` times the tool's advance ``d - b`` over the step,
    ``F(b) = F_0 + s (d - b)``, the root is ``b = (F_0 + (s + c / dt) d) / (K + s)``: exact in free motion (``F =
    0``, ``s = 0``: the damper's lag in one evaluation), and off by the load's change at a fixed tool (a slide's) in
    contact. One replay of nominal_s101 through its drive makes 550 step evaluations and 2,076 Newton iterations
    from it, 661 and 2,441 from the last compression plus the anchor's advance times ``s / (s + K)`` (the damper's
    lag left out: two evaluations a step on the approach and the retreat), the two within the drive's force
    tolerance of each other at every step (docs/benchmarks_log.md, session 56, s56-49pre).

    Args:
        load: the last step's load ``F_0`` on the driven body, N (0 before contact).
        slope: the contact's slope ``s = -dF/db``, N/m (>= 0; the last secant's estimate, 0 when none).
        reach: ``d``, m (into the contact positive).
        stiffness: the spring's ``k_s``, N/m.
        rate: the damper's ``c / dt``, N/m.
    """
    return (load + (slope + rate) * reach) / (stiffness + rate + slope)


def inertial_start(sim, effector: str, reach: np.ndarray) -> np.ndarray | None:
    """A drive step's first Newton iterate: the vertices of every body clear of contact over the step carried on
    at their velocity (``x^n + dt v^n``, the inertia's own prediction), every other vertex at ``x^n``; None where
    no body is clear (the solver's own start).

    A body near a contact keeps ``x^n``: its penalty contacts take their sides at ``x^n``
    (:mod:`sim_core.contact_set`), and a first iterate carried past them starts Newton in another minimum of
    the step's energy, the converged answer of a different path (as :mod:`sim_core.carried_start` carries only
    a body clear of contact). Every vertex carried on, latency_s103's replay at the scene's values (VM, session
    57) kept the released card on the lifting pad (sheet points whitened RMS 61 after the lift, against 1.0
    from ``x^n`` and in the recording; the whole replay 24.9 against 12.9): each step within the Newton
    tolerance, a different answer. Clear of contact is
    :func:`sim_core.carried_start.clear_of_contact` with the body's own move ``dt max|v^n|`` and the driven
    vertices' move bounded by the anchor's reach past the tool.

    Args:
        sim: the :class:`~sim_core.simulation.Simulation` at the step's start.
        effector: the driven effector's name.
        reach: ``(3,)`` the step's target position of the effector minus its position at the step's start, m.

    Returns:
        ``(n, 3)`` positions, m, or None.
    """
    model, state, dt = sim.model, sim.state, sim.dt
    x_n, v_n = np.asarray(state.x, dtype=float), np.asarray(state.v, dtype=float)
    fixed = np.zeros(len(x_n), dtype=bool)
    driven = np.asarray(model.effectors[effector].vertices, dtype=np.int64)
    fixed[driven] = True
    x_target = x_n.copy()
    x_target[driven] += np.asarray(reach, dtype=float)
    guess, carried = x_n.copy(), False
    for body in model.bodies.values():
        s = slice(body.vertex_start, body.vertex_stop)
        move = dt * float(np.sqrt(np.max(np.sum(v_n[s] ** 2, axis=1)))) if body.vertex_stop > body.vertex_start else 0.0
        if move > 0.0 and clear_of_contact(model, body.name, x_n, v_n, dt, move, x_target, fixed):
            guess[s] += dt * v_n[s]
            carried = True
    return guess if carried else None


class ReplayDrive:
    """Series drive of one replay.

    Args:
        spring: the :class:`~sim_core.series_drive.SeriesSpringDrive` (its effector, stiffness, damping, gel
            vertices).
        controls: ``(K + 1, 7)`` the replay's recorded poses at the step times.
        commands: ``(K + 1, 7)`` the recorded commanded poses at the step times, or None (the spring is
            then anchored at the recorded pose).
        normal: pose ``(7,)`` -> unit sensor normal ``(3,)`` into the contact, world.

    Attributes:
        evaluations: step evaluations since :meth:`start` (each one implicit step).
        unconverged: steps since :meth:`start` that ended on the evaluation limit.
        last_axis: the sensor normal ``(3,)`` of the last :meth:`step` (None before one).
    """

    def __init__(self, spring: SeriesSpringDrive, controls: np.ndarray, commands: np.ndarray | None,
                 normal: Callable[[np.ndarray], np.ndarray]) -> None:
        self.spring = spring
        self.controls = controls
        self.commands = commands
        self.normal = normal
        self.start()

    @classmethod
    def of_model(cls, model) -> "ReplayDrive | None":
        """The drive of an :class:`~sysid.observation.ObservationModel`'s next replay: its ``drive_stiffness``
        and ``drive_damping`` on the sensor's gel, each step solved to :data:`DRIVE_FORCE_TOLERANCE` of the
        recorded normal force's noise; None for a kinematic drive (``inf``)."""
        if math.isinf(model.drive_stiffness):
            return None
        sim = model.simulation()
        gel = sim.model.bodies[sim.model.sensors[model.sensor].gel_body].vertices
        tolerance = DRIVE_FORCE_TOLERANCE * float(model.sigma["wrench"][2]) if "wrench" in model.sigma else 1.0e-3
        spring = SeriesSpringDrive(model.effector, model.drive_stiffness, gel, force_tolerance=tolerance,
                                   damping=model.drive_damping, starts=DRIVE_STARTS, solve=DRIVE_SOLVE)
        return cls(spring, model.controls, model.commands, model.sensor_normal)

    def start(self) -> None:
        """Begin a replay: no load and no contact slope carried, counts at zero."""
        self._carried = (0.0, 0.0)
        self.last_axis: np.ndarray | None = None
        self.evaluations = 0
        self.unconverged = 0
        self.last_joint = False
        self.secant_retries = 0

    def step(self, sim, control: Control, k: int) -> None:
        """Advance ``sim`` by step ``k`` (1-based) of ``control``: the effector's target is moved along the
        sensor normal to the command's position there, and hangs on the spring from it.

        Raises:
            SimulationDivergedError: a step evaluation failed.
        """
        name = self.spring.effector
        pose = np.array(control.effector_pose_target[name], dtype=float)
        axis = self.normal(pose)
        if self.commands is not None:
            pose[:3] += float(np.dot(self.commands[k, :3] - self.controls[k, :3], axis)) * axis
        tool = np.asarray(sim.state.effector_pose[name], dtype=float)[:3]
        guess = control.position_guess
        if guess is None:
            guess = inertial_start(sim, self.spring.effector, pose[:3] - tool)
        anchored = Control({**control.effector_pose_target, name: pose}, dict(control.gripper_target), guess)
        load, slope = self._carried
        start = first_compression(load, slope, float(np.dot(pose[:3] - tool, axis)), self.spring.stiffness,
                                  self.spring.damping / sim.dt)
        result = self.spring.step(sim, anchored, axis, start=start, contact_slope=slope)
        self.last_axis, self.last_joint = axis, result.joint
        self._carried = (result.load, result.contact_slope)
        self.evaluations += result.evaluations
        self.unconverged += int(not result.converged)
        self.secant_retries += int(self.spring.solve == "joint" and not result.joint)

    def summary(self) -> dict[str, float]:
        """JSON-ready: stiffness (N/m), damping (N s/m), whether anchored at the command, evaluations,
        unconverged steps, joint steps taken again by the secant (:attr:`SeriesDriveStep.joint`)."""
        return {"stiffness": self.spring.stiffness, "damping": self.spring.damping,
                "anchored_at_command": self.commands is not None,
                "evaluations": int(self.evaluations), "unconverged": int(self.unconverged),
                "secant_retries": int(self.secant_retries)}


def drive_sensitivities(model, sim, params: Sequence[str]
                        ) -> tuple[Trajectory, np.ndarray, np.ndarray, np.ndarray]:
    """Replay ``model``'s recording through its series drive and propagate ``dX/dp`` in the same pass.

    Each step is solved by :meth:`ReplayDrive.step` (its Newton solves start from ``model.warm_start`` when
    set); its tangents are solved with the factorisation of the step's accepted evaluation
    (``NewtonSolver.exact_factorization``) and carried through the spring's compression
    (:meth:`sim_core.sensitivity.TangentPropagation.advance` with a :class:`~sim_core.sensitivity.DriveStep`).

    Args:
        model: the :class:`~sysid.observation.ObservationModel`, with a finite ``drive_stiffness``.
        sim: its simulation, :meth:`~sysid.observation.ObservationModel.prepare`'d at the parameter values.
        params: global parameter names, ``P`` of them.

    Returns:
        ``(trajectory, dX, dF, dQ)``: the rollout (states only), the position tangents ``(K + 1, n, 3, P)`` m
        per parameter unit, the contact-force tangents of the same shape (N per unit) and the tangents of the
        driven effector's position ``(K + 1, 3, P)`` (:func:`sim_core.sensitivity.observation_sensitivities`
        ``effector_position``).

    Raises:
        ConfigError: no drive is set; unknown parameter; a step the solver retried with a smaller dt (not
            differentiable).
        SimulationDivergedError: from the solver.
    """
    drive = model.replay_drive()
    if drive is None:
        raise ConfigError("drive_sensitivities: the replay has no series drive (kinematic)")
    params = check_parameters(sim.model, params)
    K, n, P = model.step_count, sim.model.vertex_count, len(params)
    tangents = TangentPropagation(sim.model, params, contact_force=True, backend=sim.solver.backend)
    vertices = np.asarray(sim.model.effectors[drive.spring.effector].vertices, dtype=np.int64)
    rate = drive.spring.damping / sim.dt
    dX, dF, dQ = np.zeros((K + 1, n, 3, P)), np.zeros((K + 1, n, 3, P)), np.zeros((K + 1, 3, P))
    guess = model.warm_start
    states, controls, fallback = [sim.state.copy()], [], None
    for k in range(1, K + 1):
        control = model.control(k, guess)
        drive.step(sim, control, k)
        record = sim.solver.last_record
        if abs(float(record.dt) - float(sim.dt)) > 1e-12 * float(sim.dt):
            raise ConfigError(f"drive replay step {k}: the solver halved dt (dt {record.dt:g} s of {sim.dt:g} s); "
                              "such a step is not differentiable")
        factorization = sim.solver.exact_factorization()
        if factorization is None:
            fallback = fallback or sim.solver.general_solver()
        lin = tangents.linearization(record, states[-1], fallback, factorization=factorization)
        step = DriveStep(vertices, drive.spring.load_vertices, drive.last_axis, drive.spring.stiffness + rate, rate,
                         inertial=drive.last_joint)
        dX[k], dF[k] = tangents.advance(lin, step)
        dQ[k] = tangents.dq
        states.append(sim.state.copy())
        controls.append(control)
    return Trajectory(states=states, records=None, controls=controls, model_revision=sim.model.revision), dX, dF, dQ
