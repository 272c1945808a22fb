"""Batched gradients: the reverse (adjoint) passes of ``B`` lockstep rollouts run together.

A lockstep :class:`~sim_core.batch.BatchedSimulation` steps its copies as one stacked model of disconnected
copies (:mod:`sim_core.batch.stacked`); each step's :class:`~sim_core.step_info.StepRecord` is the stacked
step's. :class:`TrajectoryRecorder` keeps those records with the stacked states and controls, and
:func:`batched_rollout_gradient` runs :func:`sim_core.adjoint.reverse_pass` once on the stacked model: per
step, the exact Hessian of all copies is one block-diagonal matrix (block ``i`` is copy ``i``'s exact
Hessian at its converged step, translated: the incremental potential is invariant under translation),
one solve gives every copy's adjoint vector, and the pullbacks (previous state, rest angles, Dirichlet
vertices, effector commands) are evaluated over the stacked arrays. The solve: one LU of the stacked
matrix, or each copy's block by its own LU (:class:`~sim_core.batch.adjoint_solvers.CopyBlockLU`, faster on the
CPU), or the batched CG on a Taichi device (:class:`~sim_core.batch.adjoint_solvers.StackedAdjointCG`); a block
that is not positive definite is solved by LU, as the single path solves it. The copies'
blocks never couple, so copy ``i``'s gradient is its separate :func:`sim_core.adjoint.rollout_gradient`
(to the Newton tolerance of the lockstep forward pass). Parameter derivatives are per copy
(:class:`CopyParameterAdjoint`: each copy's own material parameters, the shared ones split by copy).

A copy that failed in the forward pass (reported by the batch) or was not stepped in every recorded step
(an early stop) gets no gradient (None, with the reason); its block of the adjoint is zero (its loss is
not asked for), so the others' gradients are unchanged by it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from sim_core.adjoint import Gradient, Trajectory, check_parameters, rest_angle_adjoint, reverse_pass
from sim_core.batch.simulation import BatchedSimulation, BatchStep
from sim_core.batch.stacked import StackedScene
from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.backend import uses_taichi
from sim_core.linsolve import LinearSolver, make_linear_solver
from sim_core.model import Model


@dataclass
class BatchedTrajectory:
    """A recorded lockstep rollout of ``B`` copies.

    Attributes:
        scene: the stacked scene of the recording.
        trajectory: the stacked :class:`~sim_core.adjoint.Trajectory` (``T + 1`` stacked states, the ``T``
            stacked step records and stacked controls).
        complete: copies stepped (and not failed) in every recorded step, shape ``(B,)`` bool.
        failures: per copy, why it has no gradient (the batch's failure message, or the step it stopped
            at), None for a complete copy.
        models: the copies' models.
        revisions: the copies' ``Model.revision`` during the recording.
    """

    scene: StackedScene
    trajectory: Trajectory
    complete: np.ndarray
    failures: list[str | None]
    models: list[Model]
    revisions: list[int]

    @property
    def copies(self) -> int:
        """Number of copies ``B``."""
        return self.scene.copies

    @property
    def step_count(self) -> int:
        """Recorded steps ``T``."""
        return self.trajectory.step_count


class TrajectoryRecorder:
    """Steps a lockstep batch and keeps what the batched adjoint needs (module docstring).

    Args:
        batch: a :class:`~sim_core.batch.BatchedSimulation` whose copies run in lockstep
            (``SolverConfig.lockstep``); during the recording it must be stepped only through
            :meth:`step`, neither reset nor its copies' states or parameters replaced.

    Raises:
        ConfigError: a batch that is not lockstep.
    """

    def __init__(self, batch: BatchedSimulation) -> None:
        if batch.lockstep is None:
            raise ConfigError("batched gradients need a lockstep batch (SolverConfig(lockstep=True))")
        self.batch = batch
        self.states: list = []
        self.records: list = []
        self.controls: list[Control] = []
        self.stepped: list[np.ndarray] = []
        self.revisions = [s.model.revision for s in batch.sims]

    def step(self, controls: Sequence[Control | None] | Control | None = None,
             mask: Sequence[bool] | np.ndarray | None = None) -> BatchStep:
        """:meth:`BatchedSimulation.step`, recording the stacked step (none when no copy advanced).

        Raises:
            ConfigError: as :meth:`BatchedSimulation.step`; the batch was reset or a copy's state replaced
                since the last recorded step; a step with sleeping bodies (``SolverConfig.sleeping``).
        """
        batch, engine = self.batch, self.batch.lockstep
        B = batch.batch_size
        if controls is None or isinstance(controls, Control):
            controls = [controls] * B
        controls = list(controls)
        before = [s.state for s in batch.sims]
        state_in = engine.state if self.records else None
        res = batch.step(controls, mask)
        advanced = np.array([info is not None for info in res.infos], dtype=bool)
        if not advanced.any():
            return res
        scene = engine.scene
        if state_in is None:
            state_in = scene.stack_states(before)
        rec = engine.solver.last_record
        if not np.array_equal(state_in.x, rec.x_prev):
            raise ConfigError("batched gradient: the batch was reset or a copy's state replaced during the recording")
        if rec.asleep:
            raise ConfigError(f"batched gradient: bodies {list(rec.asleep)} slept through a step "
                              "(SolverConfig.sleeping): use SolverConfig(sleeping=False) for gradients")
        if not self.states:
            self.states.append(state_in)
        self.states.append(engine.state)
        self.records.append(rec)
        self.controls.append(scene.stack_controls([c if res.stepped[i] else None for i, c in enumerate(controls)]))
        self.stepped.append(advanced)
        return res

    def trajectory(self) -> BatchedTrajectory:
        """The recording so far.

        Raises:
            ConfigError: nothing recorded.
        """
        if not self.records:
            raise ConfigError("batched gradient: no step was recorded")
        engine = self.batch.lockstep
        stepped = np.array(self.stepped)
        complete = stepped.all(axis=0)
        failures = []
        for i in range(self.batch.batch_size):
            why = self.batch.failures[i]
            if why is None and not complete[i]:
                why = f"not stepped in every recorded step ({int(stepped[:, i].sum())} of {len(self.records)})"
            failures.append(None if complete[i] and why is None else why)
        complete &= np.array([f is None for f in failures])
        traj = Trajectory(states=self.states, records=self.records, controls=self.controls,
                          model_revision=engine.scene.model.revision)
        return BatchedTrajectory(engine.scene, traj, complete, failures, [s.model for s in self.batch.sims],
                                 list(self.revisions))


class CopyParameterAdjoint:
    """:class:`~sim_core.adjoint.ParameterAdjoint` of a stacked model, per copy.

    A scene parameter (``body.key``, ``friction.a_b``, ``contact.stiffness``, ``damping``) of copy ``i`` is
    the stacked parameter of its material group (``<body>#<group>.key``, the friction pair of the group's
    bodies; the shared ones as they are); copy ``i``'s derivative is the sum of ``w * dg/dp`` over its own
    vertices.

    Args:
        scene: the stacked scene.
        models: the copies' models (copy 0's friction pairs name the scene's).
        params: checked scene parameter names.

    Attributes:
        values: per copy, parameter -> dL/dp.
    """

    def __init__(self, scene: StackedScene, models: Sequence[Model], params: Sequence[str]) -> None:
        self.scene = scene
        self.params = list(params)
        self.values = [{p: 0.0 for p in self.params} for _ in range(scene.copies)]
        pairs = {}
        for pair in models[0].friction:
            a, b = sorted(pair)
            pairs[f"friction.{a}_{b}"] = pairs[f"friction.{b}_{a}"] = pair
        self._members = [np.flatnonzero(scene.group_of_copy == g) for g in range(len(scene.group_names))]
        self._sheets = {stacked: (g, body) for g, names in enumerate(scene.group_names)
                        for body, stacked in names.items()}
        targets: dict[str, dict[str, list[np.ndarray]]] = {}
        for g, names in enumerate(scene.group_names):
            for p in self.params:
                head, _, key = p.partition(".")
                if p in pairs:
                    a, b = sorted(names.get(x, x) for x in pairs[p])
                    stacked = f"friction.{a}_{b}"
                elif head in names:
                    stacked = f"{names[head]}.{key}"
                else:
                    stacked = p
                targets.setdefault(stacked, {}).setdefault(p, []).append(self._members[g])
        self._targets = {s: {p: np.concatenate(m) for p, m in by.items()} for s, by in targets.items()}

    def add_step(self, lin, w: np.ndarray) -> None:
        """As :meth:`sim_core.adjoint.ParameterAdjoint.add_step`."""
        index = self.scene.index
        for stacked, by_param in self._targets.items():
            prod = w * lin.parameter_rhs(stacked)
            for p, copies in by_param.items():
                sums = prod[index[copies]].sum(axis=(1, 2))
                for i, s in zip(copies.tolist(), sums.tolist()):
                    self.values[i][p] += s

    def add_yield(self, sheet: str, yielding: np.ndarray, sign: np.ndarray, a: np.ndarray) -> None:
        """As :meth:`sim_core.adjoint.ParameterAdjoint.add_yield` (``sheet`` a stacked sheet)."""
        g, body = self._sheets[sheet]
        name = f"{body}.yield_angle"
        if name not in self.values[0]:
            return
        h = self.scene.hinge_counts[body]
        for i in self._members[g].tolist():
            sl = slice(int(self.scene.slot_in_group[i]) * h, (int(self.scene.slot_in_group[i]) + 1) * h)
            y = yielding[sl]
            self.values[i][name] -= float(np.dot(sign[sl][y], a[sl][y]))


@dataclass
class BatchedGradient:
    """Per-copy results of :func:`batched_rollout_gradient`.

    Attributes:
        gradients: per copy its :class:`~sim_core.adjoint.Gradient` (as :func:`~sim_core.adjoint.rollout_gradient`
            gives for its separate rollout), None for a copy without one.
        failures: per copy why it has none (None for a copy with a gradient).
        solver: the solver of the stacked exact Hessians (its statistics, e.g.
            :attr:`~sim_core.batch.adjoint_solvers.StackedAdjointCG.lu_copies`).
    """

    gradients: list[Gradient | None]
    failures: list[str | None]
    solver: LinearSolver | None = None


class _StackedRows:
    """dL/dx of every copy stacked step by step (the stacked ``(T + 1, N, 3)`` array is never formed):
    ``rows[k]`` has shape ``(N, 3)``."""

    def __init__(self, scene: StackedScene, rows: Sequence[np.ndarray | None]) -> None:
        self.scene, self.rows = scene, rows

    def __getitem__(self, k: int) -> np.ndarray:
        out = np.zeros((self.scene.model.vertex_count, 3))
        for i, r in enumerate(self.rows):
            if r is not None:
                out[self.scene.index[i]] = r[k]
        return out


def batched_rollout_gradient(recording: BatchedTrajectory, dL_dx: Sequence[np.ndarray | None],
                             params: Sequence[str] = (),
                             dL_dtheta_bar: Sequence[dict[str, np.ndarray] | None] | None = None,
                             linear_solver: str = "pardiso", backend: str = "numpy") -> BatchedGradient:
    """Each complete copy's reverse-mode derivative, all copies' reverse passes run together (module docstring).

    Args:
        recording: from :meth:`TrajectoryRecorder.trajectory`.
        dL_dx: per copy dL/dx of every state of its rollout, shape ``(T + 1, n, 3)``, or None (no gradient
            asked for that copy).
        params: scene parameter names (``Model.parameter_names``) to differentiate, per copy.
        dL_dtheta_bar: per copy (or None) sheet -> dL/d(rest angles of the final state), shape ``(h,)``.
        linear_solver: the solver of the stacked exact Hessians: ``"pardiso"`` or ``"scipy"`` (one LU of the
            stacked matrix a step, :func:`sim_core.linsolve.make_linear_solver`), ``"pardiso-blocks"`` or
            ``"scipy-blocks"`` (each copy's block by its own LU,
            :class:`~sim_core.batch.adjoint_solvers.CopyBlockLU`), or ``"pcg"`` (the batched CG
            on the Taichi device, a copy whose block is not positive definite by LU:
            :class:`~sim_core.batch.adjoint_solvers.StackedAdjointCG`; a Taichi ``backend`` only).
        backend: the concrete backend of the batch (the contact set that rebuilds the friction frames, the CG).

    Returns:
        the :class:`BatchedGradient`: a gradient for every complete copy whose ``dL_dx`` is given.

    Raises:
        ConfigError: lists of the wrong length, a copy's parameters changed since the recording, unknown
            parameters, a bad shape (naming the copy), or ``"pcg"`` on a backend without Taichi.
    """
    B, T, scene = recording.copies, recording.step_count, recording.scene
    n = scene.vertex_count
    dtb = list(dL_dtheta_bar) if dL_dtheta_bar is not None else [None] * B
    if len(dL_dx) != B or len(dtb) != B:
        raise ConfigError(f"batched gradient: {len(dL_dx)} dL_dx and {len(dtb)} dL_dtheta_bar for {B} copies")
    changed = [i for i, (m, r) in enumerate(zip(recording.models, recording.revisions)) if m.revision != r]
    if changed:
        raise ConfigError(f"batched gradient: parameters of copies {changed} changed since the rollout; roll out again")
    params = check_parameters(recording.models[0], params)
    failures = list(recording.failures)
    rows: list[np.ndarray | None] = [None] * B
    atb = rest_angle_adjoint(scene.model, None)
    for i in range(B):
        if dL_dx[i] is None or not recording.complete[i]:
            failures[i] = failures[i] or "no loss given"
            continue
        rows[i] = np.asarray(dL_dx[i], dtype=float)
        if rows[i].shape != (T + 1, n, 3):
            raise ConfigError(f"batched gradient: copy {i}'s dL_dx has shape {rows[i].shape}, expected {(T + 1, n, 3)}")
        try:
            own = rest_angle_adjoint(recording.models[i], dtb[i])
        except ConfigError as err:
            raise ConfigError(f"batched gradient: copy {i}: {err}") from err
        g, k = int(scene.group_of_copy[i]), int(scene.slot_in_group[i])
        for sheet, value in own.items():
            h = scene.hinge_counts[sheet]
            atb[scene.group_names[g][sheet]][k * h:(k + 1) * h] = value
    parameters = CopyParameterAdjoint(scene, recording.models, params)
    solver = _adjoint_solver(scene, linear_solver, backend)
    stacked = reverse_pass(scene.model, recording.trajectory, _StackedRows(scene, rows), atb, parameters, solver,
                           backend, fixed_rows=True)
    gradients = [None if rows[i] is None else _copy_gradient(scene, stacked, i, parameters.values[i])
                 for i in range(B)]
    return BatchedGradient(gradients, [None if gr is not None else why for gr, why in zip(gradients, failures)], solver)


def _adjoint_solver(scene: StackedScene, linear_solver: str, backend: str) -> LinearSolver:
    """The stacked exact Hessians' solver named ``linear_solver`` (:func:`batched_rollout_gradient`).

    Raises:
        ConfigError: ``"pcg"`` on a backend without Taichi, or an unknown name.
    """
    if linear_solver.endswith("-blocks"):
        from sim_core.batch.adjoint_solvers import CopyBlockLU

        return CopyBlockLU(scene, linear_solver.removesuffix("-blocks"))
    if linear_solver != "pcg":
        return make_linear_solver(linear_solver)
    if not uses_taichi(backend):
        raise ConfigError(f"batched gradient: linear_solver 'pcg' runs in Taichi: it needs a Taichi backend, "
                          f"not {backend!r}")
    from sim_core.batch.adjoint_solvers import StackedAdjointCG  # Taichi kernels: loaded on a Taichi backend only

    return StackedAdjointCG(scene)


def _copy_gradient(scene: StackedScene, stacked: Gradient, i: int, params: dict[str, float]) -> Gradient:
    """Copy ``i``'s :class:`Gradient` read from the stacked one."""
    g, k = int(scene.group_of_copy[i]), int(scene.slot_in_group[i])
    names = scene.effector_names
    idx = scene.index[i]
    return Gradient(
        controls=[{e: step[f"{e}#{i}"] for e in names} for step in stacked.controls],
        gripper=[{e: step[f"{e}#{i}"] for e in names} for step in stacked.gripper],
        params=dict(params), x0=stacked.x0[idx], v0=stacked.v0[idx],
        initial_pose={e: stacked.initial_pose[f"{e}#{i}"] for e in names},
        theta_bar0={sheet: stacked.theta_bar0[scene.group_names[g][sheet]][k * h:(k + 1) * h]
                    for sheet, h in scene.hinge_counts.items()})
