"""Forward-mode (tangent) sensitivities of a rollout w.r.t. a few material parameters, and their
map to observations (for system identification: few parameters, many residuals; SYSID.md).

The tangents ``dX/dp`` are propagated step by step with the linearisation of
:class:`sim_core.adjoint.StepLinearization` (same exact Hessian, same factorisation, ``P`` right-hand
sides per step):

    dx_f^{n+1} = -H_ff^{-1} (dg/dx^n dx^n + dg/dv^n dv^n + dg/dtheta_bar dtheta_bar^n + dg/dp + H_fd dx_d),
    dv^{n+1} = (dx^{n+1} - dx^n) / dt,  dtheta_bar^{n+1} from the plastic update,

with the controls held fixed (driven vertices have zero tangent; clamped vertices keep the tangent
of ``x^n``). What is differentiated and what is held fixed is listed in :mod:`sim_core.adjoint`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from sim_core.adjoint import StepLinearization, Trajectory, _check_trajectory, check_parameters, rollout
from sim_core.contact_set import ContactSet
from sim_core.control import Control
from sim_core.elastic import ElasticTerms
from sim_core.errors import ConfigError
from sim_core.linsolve import make_linear_solver
from sim_core.model import Model
from sim_core.sensors.markers import marker_vertex_weights
from sim_core.transforms import compose_poses, quat_to_matrix


def parameter_sensitivities(sim, controls: Sequence[Control | None] | None, params: Sequence[str],
                            trajectory: Trajectory | None = None, contact_force: bool = False):
    """Tangent propagation of ``dX/dp`` through a rollout.

    Args:
        sim: the Simulation; when ``trajectory`` is None it is rolled out from its current state
            through ``controls`` (see :func:`sim_core.adjoint.rollout`).
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
    model: Model = sim.model
    params = check_parameters(model, params)
    if trajectory is None:
        trajectory = rollout(sim, list(controls or []))
    _check_trajectory(model, trajectory)
    T, n, P = trajectory.step_count, model.vertex_count, len(params)
    elastic, contact, mass = ElasticTerms(model), ContactSet(model), model.vertex_mass()
    linear_solver = make_linear_solver(sim.solver.config.linear_solver)
    dX = np.zeros((T + 1, n, 3, P))
    dF = np.zeros((T + 1, n, 3, P)) if contact_force else None
    dv = np.zeros((n, 3, P))
    dtb = {name: np.zeros((len(model.bodies[name].hinges), P)) for name in elastic.hinges}
    dyield = {}
    for name in elastic.hinges:
        key = f"{name}.yield_angle"
        if key in params:
            dyield[name] = np.eye(P)[params.index(key)]
    for i in range(T):
        lin = StepLinearization(model, trajectory.records[i], trajectory.states[i], elastic, contact, mass,
                                linear_solver)
        dxn = dX[i]
        rhs = lin.state_rhs(dxn, dv, dtb)
        for j, p in enumerate(params):
            rhs[:, :, j] += lin.parameter_rhs(p)
        dx_d = np.zeros_like(dxn)
        dx_d[lin.static] = dxn[lin.static]
        rhs += lin.hessian_product(dx_d)
        dx_new = -lin.solve(rhs.reshape(3 * n, P)).reshape(n, 3, P)
        dx_new[lin.fixed] = dx_d[lin.fixed]
        dX[i + 1] = dx_new
        dv = (dx_new - dxn) / lin.dt
        dtb = lin.plastic_tangent(dx_new, dtb, dyield)
        if contact_force:
            dpar = np.stack([lin.contact_parameter_rhs(p) for p in params], axis=2) if P else np.zeros((n, 3, 0))
            dF[i + 1] = lin.contact_force_tangent(dx_new, dxn, dpar)
    if contact_force:
        return trajectory, dX, dF
    return trajectory, dX


def observation_sensitivities(model: Model, trajectory: Trajectory, dX: np.ndarray, dF: np.ndarray | None = None,
                              sensor: str | None = None) -> dict[str, np.ndarray]:
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
    sheet = model.bodies.get("sheet")
    if sheet is not None:
        out["sheet_points"] = dX[:, sheet.vertex_start:sheet.vertex_stop]
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
        xyz_t[i] = np.einsum("ed,kdr->ker", R, dp)
        p_world = np.einsum("kj,kjd->kd", weights, state.x[verts])
        xyz = (p_world - pose[:3]) @ R
        uv_t[i] = np.einsum("ked,kdr->ker", s.camera.project_jacobian(xyz), xyz_t[i])
        if dF is not None and state.contact_force is not None:
            f = state.contact_force[gel]
            arm = state.x[gel] - pose[:3]
            df, dx = dF[i][gel], dX[i][gel]
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
