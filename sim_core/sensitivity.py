"""Forward-mode (tangent) sensitivities of a rollout w.r.t. a few material parameters, and their
map to observations (for system identification: few parameters, many residuals; SYSID.md).

The tangents ``dX/dp`` are propagated step by step with the linearisation of
:class:`sim_core.adjoint.StepLinearization` (same exact Hessian, same factorisation, ``P`` right-hand
sides per step):

    dx_f^{n+1} = -H_ff^{-1} (dg/dx^n dx^n + dg/dv^n dv^n + dg/dtheta_bar dtheta_bar^n + dg/dp + H_fd dx_d),
    dv^{n+1} = (dx^{n+1} - dx^n) / dt,  dtheta_bar^{n+1} from the plastic update,

with the controls held fixed (driven vertices have zero tangent; clamped vertices keep the tangent
of ``x^n``). What is differentiated and what is held fixed is listed in :mod:`sim_core.adjoint`.

An effector on a series spring along an axis ``n`` (:mod:`sim_core.series_drive`: the step's compression
``b`` solves ``h(b) = F(x^{n+1}(b)) - K b + (c / dt) (a - q^n) . n = 0``, ``F`` the contact load on the
tool along ``-n``, ``K = k_s + c / dt``, ``q^n`` the tool's position at the step's start) is not a
fixed control: its driven vertices move by ``-db n``. The step's tangent is then the fixed-control tangent
``dx^0`` plus ``db`` times the response ``u`` to a unit compression (one more right-hand side with the
same factorisation, ``H_ff u_f = -H_fd e``, ``e = -n`` on the driven vertices), and the implicit function
theorem on ``h = 0`` gives

    db = (dF^0 - (c / dt) n . dq^n) / (K - dF/db),   dF/db = -n . sum_load (df of u)  (<= 0),

``dF^0`` the load's tangent with the compression held (:class:`DriveStep`, :meth:`TangentPropagation.advance`).
A step whose compression was an unknown of its Newton solve (:mod:`sim_core.drive_compression`) balances the
base's reaction, ``F + N`` with ``N = n . sum_load [m / dt^2 (x - x^n - dt v^n) + gamma m / dt (x - x^n)]`` the
load body's inertia and damping (``DriveStep.inertial``): ``dN`` joins ``dF^0`` and ``dN/db`` joins ``dF/db``.
The tool's position tangent ``dq = -db n`` moves the sensor frame of the observations
(:func:`observation_sensitivities` ``effector_position``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from sim_core.adjoint import StepLinearization, SupportTerms, Trajectory, _check_trajectory, check_parameters, rollout_step
from sim_core.contact_set import ContactSet
from sim_core.control import Control
from sim_core.elastic import ElasticTerms
from sim_core.errors import ConfigError
from sim_core.linsolve import LinearSolver
from sim_core.model import Model
from sim_core.state import State
from sim_core.sensors.markers import marker_vertex_weights
from sim_core.transforms import compose_poses, quat_to_matrix


@dataclass(frozen=True)
class DriveStep:
    """One step of an effector on a series spring along an axis (module docstring), as its tangent needs it.

    Attributes:
        vertices: global indices of the effector's driven vertices, shape ``(m,)``.
        load_vertices: global indices of the vertices whose contact forces load the tool, shape ``(l,)``.
        axis: unit axis ``n`` (3,), world, pointing into the contact.
        stiffness: ``K = k_s + c / dt``, N/m (the spring and the damper's spring to the tool's last position).
        damping_rate: ``c / dt``, N/m (0 without a damper).
        inertial: the load counts the load vertices' inertia and damping beside the contact forces (the joint
            solve's balance, :mod:`sim_core.drive_compression`).
    """

    vertices: np.ndarray
    load_vertices: np.ndarray
    axis: np.ndarray
    stiffness: float
    damping_rate: float = 0.0
    inertial: bool = False


class TangentPropagation:
    """Step-by-step forward tangents ``dX/dp`` (and optionally the contact-force tangents).

    Holds the tangents of the current state (``dx``, ``dv``, ``dtheta_bar``) and advances them by
    one converged step per :meth:`advance` call (module docstring for the equations).

    Args:
        model: the model (parameters as during the rollout).
        params: checked global parameter names, ``P`` of them.
        contact_force: also compute the tangent of each new state's ``contact_force``.
        backend: the rollout solver's concrete backend (``NewtonSolver.backend``), for the contact set
            that rebuilds friction rows (:class:`~sim_core.contact_set.ContactSet`).

    Attributes:
        dx: tangent of the current positions, ``(n, 3, P)`` m per parameter unit.
        dv: tangent of the current velocities, ``(n, 3, P)``.
        dtb: sheet -> tangent of the rest angles, ``(h, P)``.
        dq: tangent of the position of the effector on a series spring in the current state, ``(3, P)``
            (zero after a step without one, :class:`DriveStep`).
        db: tangent of the spring's compression in the last step, ``(P,)`` (zero without one).
        support_terms: the rollout's :class:`~sim_core.adjoint.SupportTerms`: the static terms whose Hessian blocks
            touch no driven vertex are not evaluated for a drive step's support product.
    """

    def __init__(self, model: Model, params: Sequence[str], contact_force: bool = False, backend: str = "numpy") -> None:
        self.model, self.params, self.contact_force = model, list(params), contact_force
        n, P = model.vertex_count, len(self.params)
        self.elastic, self.contact = ElasticTerms(model), ContactSet(model, backend=backend)
        self.mass = model.vertex_mass()
        self.dx = np.zeros((n, 3, P))
        self.dv = np.zeros((n, 3, P))
        self.dtb = {name: np.zeros((len(model.bodies[name].hinges), P)) for name in self.elastic.hinges}
        self.dq = np.zeros((3, P))
        self.db = np.zeros(P)
        self.support_terms = SupportTerms()
        self.dyield = {}
        for name in self.elastic.hinges:
            key = f"{name}.yield_angle"
            if key in self.params:
                self.dyield[name] = np.eye(P)[self.params.index(key)]

    def linearization(self, record, state: State, linear_solver: LinearSolver | str = "pardiso",
                      factorization: LinearSolver | None = None) -> StepLinearization:
        """The :class:`StepLinearization` of one step (``state``: the state it started from)."""
        return StepLinearization(self.model, record, state, self.elastic, self.contact, self.mass, linear_solver,
                                 factorization=factorization)

    def _inertial_load(self, drive: DriveStep, dt: float, dx: np.ndarray, dxn: np.ndarray | None) -> np.ndarray:
        """Tangent ``(r,)`` of ``N = n . sum_load [m / dt^2 (x - x^n - dt v^n) + gamma m / dt (x - x^n)]`` (module
        docstring) for the new positions' tangents ``dx`` ``(n, 3, r)`` and the start's (``self.dx``, ``self.dv``;
        ``dxn`` None: held, the response to a unit compression)."""
        loads, axis, gamma = drive.load_vertices, np.asarray(drive.axis, dtype=float), float(self.model.damping)
        m = self.mass[loads][:, None, None]
        total = (m / dt ** 2 + gamma * m / dt) * dx[loads]
        if dxn is not None:
            total = total - m / dt ** 2 * (dxn[loads] + dt * self.dv[loads]) - gamma * m / dt * dxn[loads]
        return np.einsum("d,ldr->r", axis, total)

    def advance(self, lin: StepLinearization, drive: DriveStep | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Propagate the tangents through the step of ``lin``.

        Args:
            lin: the step's linearisation.
            drive: the step's series drive (module docstring), or None: every effector held at its control.

        Returns:
            ``(dx^{n+1} (n, 3, P), df^{n+1} (n, 3, P) or None)``; the held tangents advance too.
        """
        n, P = self.dx.shape[0], self.dx.shape[2]
        dxn = self.dx
        rhs = lin.state_rhs(dxn, self.dv, self.dtb)
        for j, p in enumerate(self.params):
            rhs[:, :, j] += lin.parameter_rhs(p)
        dx_d = np.zeros_like(dxn)
        dx_d[lin.static] = dxn[lin.static]
        if np.any(dx_d):  # static clamps keep x^n: their tangent stays 0 from a zero start
            rhs += lin.hessian_product(dx_d)
        unit = None
        if drive is not None:  # the response to a unit compression: the driven vertices moved by -n
            unit = np.zeros((n, 3, 1))
            unit[drive.vertices, :, 0] = -np.asarray(drive.axis, dtype=float)
            rhs = np.concatenate([rhs, lin.support_product(unit, self.support_terms)], axis=2)
        solved = -lin.solve(rhs.reshape(3 * n, rhs.shape[2])).reshape(n, 3, rhs.shape[2])
        dx_new = solved[:, :, :P]
        dx_new[lin.fixed] = dx_d[lin.fixed]
        df = None
        if self.contact_force or drive is not None:
            dpar = np.stack([lin.contact_parameter_rhs(p) for p in self.params], axis=2) if P else np.zeros((n, 3, 0))
            df = lin.contact_force_tangent(dx_new, dxn, dpar)
        if drive is not None:
            response = solved[:, :, P:]
            response[lin.fixed] = unit[lin.fixed]
            df_unit = -lin.contact_hessian_product(response)
            axis = np.asarray(drive.axis, dtype=float)

            def load(f: np.ndarray) -> np.ndarray:  # tangent of F = -n . sum_load f, (r,)
                return -np.einsum("d,dr->r", axis, f[drive.load_vertices].sum(axis=0))

            slope = float(load(df_unit)[0])  # dF/db <= 0: the load falls as the tool backs off
            pull = -drive.damping_rate * (axis @ self.dq)  # d[(c/dt) (a - q^n) . n]
            held = load(df)
            if drive.inertial:  # the base's reaction: the load body's inertia and damping too
                held = held + self._inertial_load(drive, lin.dt, dx_new, dxn)
                slope += float(self._inertial_load(drive, lin.dt, response, None)[0])
            self.db = (held + pull) / (drive.stiffness - slope)
            dx_new = dx_new + response * self.db[None, None, :]
            df = df + df_unit * self.db[None, None, :]
            self.dq = -np.outer(axis, self.db)
        else:
            self.db = np.zeros(P)
            self.dq = np.zeros((3, P))
        self.dv = (dx_new - dxn) / lin.dt
        self.dtb = lin.plastic_tangent(dx_new, self.dtb, self.dyield)
        self.dx = dx_new
        return dx_new, df if self.contact_force else None


def parameter_sensitivities(sim, controls: Sequence[Control | None] | None, params: Sequence[str],
                            trajectory: Trajectory | None = None, contact_force: bool = False):
    """Tangent propagation of ``dX/dp`` through a rollout.

    Without ``trajectory`` the rollout and the tangents are computed in one pass
    (:func:`rollout_sensitivities`: each step's tangents are solved with the Newton factorisation of
    that step). With a recorded ``trajectory`` each step is linearised again from its record (the
    record's exact Newton matrix is factorised as it is when it has one).

    Args:
        sim: the Simulation; when ``trajectory`` is None it is rolled out from its current state
            through ``controls``.
        controls: one control per step (ignored when ``trajectory`` is given).
        params: global parameter names (``Model.parameter_names``), ``P`` of them.
        trajectory: an already recorded rollout of ``sim`` (optional).
        contact_force: also return the tangents of every state's ``contact_force``.

    Returns:
        ``(trajectory, dX)`` with ``dX`` of shape ``(T + 1, n, 3, P)`` in m per parameter unit
        (``dX[0] = 0``); with ``contact_force=True`` ``(trajectory, dX, dF)``, ``dF`` of the same shape
        in N per parameter unit.

    Raises:
        ConfigError: unknown parameter, trajectory without records or with stale parameters.
    """
    if trajectory is None:
        return rollout_sensitivities(sim, list(controls or []), params, contact_force=contact_force)
    model: Model = sim.model
    params = check_parameters(model, params)
    _check_trajectory(model, trajectory)
    T, n, P = trajectory.step_count, model.vertex_count, len(params)
    tangents = TangentPropagation(model, params, contact_force, backend=sim.solver.backend)
    linear_solver = sim.solver.general_solver()
    dX = np.zeros((T + 1, n, 3, P))
    dF = np.zeros((T + 1, n, 3, P)) if contact_force else None
    for i in range(T):
        lin = tangents.linearization(trajectory.records[i], trajectory.states[i], linear_solver)
        dX[i + 1], df = tangents.advance(lin)
        if contact_force:
            dF[i + 1] = df
    if contact_force:
        return trajectory, dX, dF
    return trajectory, dX


def rollout_sensitivities(sim, controls: Sequence[Control | None], params: Sequence[str],
                          contact_force: bool = False, record: bool = False,
                          on_step: Callable[[int, int], None] | None = None):
    """Roll out ``sim`` through ``controls`` and propagate ``dX/dp`` in the same pass.

    After each step the tangents are solved with the factorisation of the constrained exact Hessian at the
    converged positions (``NewtonSolver.exact_factorization``: the matrix of the final Newton iteration the
    solver already holds; where the step ended on the simplified Newton test or a projected matrix, the
    exact one assembled by the solver's fused kernels and Cholesky-factorised once); only where that
    Hessian is not positive definite is it assembled again and LU-factorised. The states and the
    tangents are those of :func:`sim_core.adjoint.rollout` followed by :func:`parameter_sensitivities`
    on the recorded trajectory, up to round-off.

    Args:
        sim: the Simulation, rolled out from its current state.
        controls: one control per step (None = hold every effector).
        params: global parameter names, ``P`` of them.
        contact_force: also return the contact-force tangents.
        record: keep the step records in the returned trajectory (memory: every step's potentials).
        on_step: called as ``on_step(k, T)`` after step k.

    Returns:
        ``(trajectory, dX)`` or ``(trajectory, dX, dF)`` as :func:`parameter_sensitivities`; the
        trajectory has ``records=None`` unless ``record``.

    Raises:
        ConfigError: unknown parameter; a step retried with a smaller dt (not differentiable).
        SimulationDivergedError: from the solver.
    """
    model: Model = sim.model
    params = check_parameters(model, params)
    T, n, P = len(controls), model.vertex_count, len(params)
    tangents = TangentPropagation(model, params, contact_force, backend=sim.solver.backend)
    fallback = None
    dX = np.zeros((T + 1, n, 3, P))
    dF = np.zeros((T + 1, n, 3, P)) if contact_force else None
    states = [sim.state.copy()]
    records = [] if record else None
    applied = []
    for i, c in enumerate(controls):
        c = rollout_step(sim, c, i)
        rec = sim.solver.last_record
        factorization = sim.solver.exact_factorization()
        if factorization is None:
            fallback = fallback or sim.solver.general_solver()
        lin = tangents.linearization(rec, states[-1], fallback, factorization=factorization)
        dX[i + 1], df = tangents.advance(lin)
        if contact_force:
            dF[i + 1] = df
        if record:
            records.append(rec)
        states.append(sim.state.copy())
        applied.append(c)
        if on_step is not None:
            on_step(i + 1, T)
    trajectory = Trajectory(states=states, records=records, controls=applied, model_revision=model.revision)
    if contact_force:
        return trajectory, dX, dF
    return trajectory, dX


def observation_sensitivities(model: Model, trajectory: Trajectory, dX: np.ndarray, dF: np.ndarray | None = None,
                              sensor: str | None = None, effector_position: np.ndarray | None = None
                              ) -> dict[str, np.ndarray]:
    """Map state tangents to tangents of the observations (``Simulation.observe``), controls fixed.

    Markers: ``p = sum_j b_j x_j`` on the gel's contact surface, in the sensor frame
    ``xyz = R^T (p - t)`` (sensor pose = effector pose * mount, independent of the parameters), so
    ``dxyz = R^T dp``; pixels ``duv = (d project / d xyz) dxyz`` (``PinholeCamera.project_jacobian``).
    Wrench ``[F, tau] = R^T [sum f_i, sum (x_i - t) x f_i]`` over the gel vertices:
    ``dF = R^T sum df_i``, ``dtau = R^T sum (dx_i x f_i + (x_i - t) x df_i)``.

    Args:
        model: the model of the rollout.
        trajectory: the rollout.
        dX: ``(T + 1, n, 3, P)`` from :func:`parameter_sensitivities`.
        dF: contact-force tangents ``(T + 1, n, 3, P)`` (``contact_force=True``); the wrench is only
            returned when given.
        sensor: tactile sensor name (default: the first one; none when the model has no sensor).
        effector_position: tangent ``(T + 1, 3, P)`` of the position of the sensor's effector
            (:attr:`TangentPropagation.dq`, an effector on a series spring); None: held (zero). The sensor
            frame moves with it: ``dxyz = R^T (dp - dq)``, the torque's arms by ``dx_i - dq``.

    Returns:
        ``sheet_points`` ``(T + 1, p, 3, P)`` (body ``sheet``, when present), ``markers_xyz``
        ``(T + 1, k, 3, P)``, ``markers_uv`` ``(T + 1, k, 2, P)``, ``wrench`` ``(T + 1, 6, P)``.

    Raises:
        ConfigError: unknown sensor, shape mismatch.
    """
    T = trajectory.step_count
    if dX.ndim != 4 or dX.shape[:3] != (T + 1, model.vertex_count, 3):
        raise ConfigError(f"observation_sensitivities: dX has shape {dX.shape}, expected (T+1, n, 3, P) with T = {T}")
    out: dict[str, np.ndarray] = {}
    tracked = model.tracked_sheet_vertices()
    if tracked.size:
        out["sheet_points"] = dX[:, tracked]
    if not model.sensors:
        return out
    name = sensor if sensor is not None else next(iter(model.sensors))
    if name not in model.sensors:
        raise ConfigError(f"observation_sensitivities: unknown sensor {name!r}; known: {list(model.sensors)}")
    s = model.sensors[name]
    verts, weights = marker_vertex_weights(s.embedding, s.contact_triangles)
    gel = model.bodies[s.gel_body].vertices
    P = dX.shape[3]
    xyz_t = np.zeros((T + 1, verts.shape[0], 3, P))
    uv_t = np.zeros((T + 1, verts.shape[0], 2, P))
    wrench_t = np.zeros((T + 1, 6, P))
    for i, state in enumerate(trajectory.states):
        pose = compose_poses(state.effector_pose[s.effector], s.mount)
        R = quat_to_matrix(pose[3:7])
        dp = np.einsum("kj,kjdr->kdr", weights, dX[i][verts])
        dq = None if effector_position is None else effector_position[i]
        if dq is not None:
            dp = dp - dq[None]
        xyz_t[i] = np.einsum("ed,kdr->ker", R, dp)
        p_world = np.einsum("kj,kjd->kd", weights, state.x[verts])
        xyz = (p_world - pose[:3]) @ R
        uv_t[i] = np.einsum("ked,kdr->ker", s.camera.project_jacobian(xyz), xyz_t[i])
        if dF is not None and state.contact_force is not None:
            f = state.contact_force[gel]
            arm = state.x[gel] - pose[:3]
            df, dx = dF[i][gel], dX[i][gel] if dq is None else dX[i][gel] - dq[None]
            force = df.sum(axis=0)
            torque = (np.cross(dx, f[:, :, None], axisa=1, axisb=1, axisc=1)
                      + np.cross(arm[:, :, None], df, axisa=1, axisb=1, axisc=1)).sum(axis=0)
            wrench_t[i, :3] = R.T @ force
            wrench_t[i, 3:] = R.T @ torque
    out["markers_xyz"] = xyz_t
    out["markers_uv"] = uv_t
    if dF is not None:
        out["wrench"] = wrench_t
    return out
