"""Rollouts of a task: a scene, a sequence of per-step actions, the reward of the final state.

An episode starts at the scene's initial state, applies one action row before each step
(:func:`sim_core.tasks.spec.apply_action`: commanded poses and openings accumulate the increments)
and stops early when the state becomes infeasible, as ThinShellLab's ``check_early_stop``
(``code/task_scene/Scene_folding.py``, ``Scene_pick.py``): a solver failure or non-finite positions,
a contact force component above ``max_force_N`` on an effector, or (after ``contact_after_step``
steps) an effector whose net contact force is below ``min_contact_force_N``.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from sim_core.batch.simulation import BatchedSimulation, BatchStep
from sim_core.control import Control
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.model import Model
from sim_core.scenes.task_scene import build_task_scene, task_initial_state
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from sim_core.state import State
from sim_core.step_info import StepInfo
from sim_core.tasks.spec import TaskSpec, apply_action


@dataclass
class RolloutResult:
    """What one rollout did.

    Attributes:
        reward: the task's reward of the last state reached (also when infeasible), in the task's units.
        steps_done: steps completed (``<= horizon``).
        infeasible: why the rollout stopped early, or None when it ran all its actions feasibly.
        states: the states ``0 .. steps_done`` when asked for (``keep_states``), else None.
        effector_poses: effector -> poses ``[x y z qx qy qz qw]``, shape ``(steps_done + 1, 7)``.
        gripper: effector -> finger opening in m, shape ``(steps_done + 1,)`` (effectors with fingers).
        step_infos: the solver's :class:`StepInfo` of each completed step.
        wrench: effector -> net contact wrench on its body ``[fx fy fz tx ty tz]`` (N, N m; world axes,
            torque about the effector frame's origin), shape ``(steps_done + 1, 6)``.
        sim_time_s: wall-clock seconds spent stepping.
    """

    reward: float
    steps_done: int
    infeasible: str | None
    states: list[State] | None
    effector_poses: dict[str, np.ndarray]
    gripper: dict[str, np.ndarray]
    step_infos: list[StepInfo] = field(default_factory=list)
    wrench: dict[str, np.ndarray] = field(default_factory=dict)
    sim_time_s: float = 0.0


def build_task_simulation(task: TaskSpec, params: dict[str, float] | None = None, backend: str = "numpy",
                          solver_config: SolverConfig | None = None, scene_model: Model | None = None) -> Simulation:
    """A Simulation of the task's scene at its initial state, with parameters overridden.

    Args:
        task: the task.
        params: global parameter name -> value (``Model.parameter_names``), applied after building.
        backend: solver backend (:mod:`sim_core.backend`) when ``solver_config`` is None.
        solver_config: full solver settings (its backend wins).
        scene_model: the task's scene as :func:`build_task_scene` builds it from ``task.scene`` (no parameter
            set), deep-copied instead of building the scene again (a population builds it once: 23 ms a
            copy for Folding-U on the 2-core CPU, against 0.5 ms for the copy); None builds it.

    Returns:
        the Simulation (``dt`` = the task's).

    Raises:
        ConfigError: an unknown parameter or an out-of-range value.
    """
    model = build_task_scene(copy.deepcopy(task.scene)) if scene_model is None else copy.deepcopy(scene_model)
    for name, value in (params or {}).items():
        model.set_parameter(name, value)
    sim = Simulation(model, dt=task.dt, solver_config=solver_config or SolverConfig(backend=backend))
    sim.state = task_initial_state(model)
    return sim


def effector_wrench(sim: Simulation, state: State, effector: str) -> np.ndarray:
    """Net contact wrench on an effector's body: ``[sum f, sum (x - p) x f]``.

    Args:
        sim: the simulation.
        state: a state with ``contact_force``.
        effector: effector name (its body is ``model.meta["effector_bodies"][effector]``, else the body
            of that name, else the gel of the tactile sensor it carries).

    Returns:
        ``[fx fy fz tx ty tz]`` in N and N m, world axes, torque about the effector frame's origin ``p``.

    Raises:
        ConfigError: the effector has no body.
    """
    model = sim.model
    name = model.meta.get("effector_bodies", {}).get(effector, effector)
    if name not in model.bodies:
        gels = [s.gel_body for s in model.sensors.values() if s.effector == effector]
        if not gels:
            raise ConfigError(f"effector {effector!r} has no body (no body of that name, no tactile gel)")
        name = gels[0]
    body = model.bodies[name]
    f = np.zeros((0, 3)) if state.contact_force is None else state.contact_force[body.vertex_start:body.vertex_stop]
    r = state.x[body.vertex_start:body.vertex_stop] - state.effector_pose[effector][:3]
    return np.concatenate([f.sum(axis=0), np.cross(r, f).sum(axis=0)])


class TaskEpisode:
    """One episode of a task, stepped action row by action row (used by :func:`rollout` and the
    Gymnasium environments).

    Args:
        task: the task.
        params: parameter overrides (see :func:`build_task_simulation`).
        backend: solver backend.
        solver_config: full solver settings, or None.
        scene_model: the task's scene model to copy (see :func:`build_task_simulation`), or None.

    Attributes:
        sim: the Simulation.
        pose_targets: effector -> commanded pose.
        gripper_targets: effector -> commanded opening (m), effectors with fingers.
        infeasible: why the episode stopped, or None.
    """

    def __init__(self, task: TaskSpec, params: dict[str, float] | None = None, backend: str = "numpy",
                 solver_config: SolverConfig | None = None, scene_model: Model | None = None) -> None:
        self.task = task
        self.sim = build_task_simulation(task, params, backend, solver_config, scene_model)
        self._initial = self.sim.state.copy()
        self._start()  # the solver, built at its first use, has no caches yet: nothing for reset() to clear

    def reset(self) -> None:
        """Back to the initial state (solver caches cleared)."""
        self.sim.solver.reset_caches()
        self._start()

    def _start(self) -> None:
        """The initial state and commanded targets, no step taken."""
        self.sim.state = self._initial.copy()
        self.pose_targets = {k: np.array(v) for k, v in self.sim.state.effector_pose.items()}
        self.gripper_targets = {k: float(v) for k, v in self.sim.state.gripper_opening.items()
                                if self.sim.model.effectors[k].finger_sign is not None}
        self.infeasible: str | None = None
        self.steps_done = 0
        self._wrenches: tuple[State, dict[str, np.ndarray]] | None = None  # (state, its wrenches): wrenches()

    def wrenches(self, state: State | None = None) -> dict[str, np.ndarray]:
        """Effector -> net contact wrench (:func:`effector_wrench`) of ``state`` (default: current). The last
        state object's wrenches are kept (a step's early-stop check and its log read the same state; a step
        replaces the state object, never edits it), so each new state is summed once."""
        state = state or self.sim.state
        kept = self._wrenches
        if kept is None or kept[0] is not state:
            kept = self._wrenches = (state, {name: effector_wrench(self.sim, state, name)
                                             for name in self.sim.model.effectors})
        return dict(kept[1])

    def step(self, row: np.ndarray) -> StepInfo | None:
        """Apply one action row and advance one step.

        Returns:
            the solver's StepInfo, or None when the step failed (``infeasible`` then says why; the state
            is the last good one).

        Raises:
            ConfigError: the episode already ended, or a bad action row.
        """
        control = self.command(row)
        try:
            info = self.sim.step(control)
        except SimulationDivergedError as err:
            return self.record_step(None, str(err))
        return self.record_step(info)

    def command(self, row: np.ndarray) -> Control:
        """The control of the next step: apply one action row to the commanded targets (the first half
        of :meth:`step`; a batch steps the simulation itself, then calls :meth:`record_step`).

        Raises:
            ConfigError: the episode already ended, or a bad action row.
        """
        if self.infeasible is not None or self.steps_done >= self.task.horizon:
            raise ConfigError(f"task {self.task.name}: episode is over ({self.infeasible or 'horizon reached'})")
        row = self.task.check_actions(np.asarray(row, dtype=float)[None, :])[0]
        self.pose_targets, self.gripper_targets = apply_action(self.task, row, self.pose_targets, self.gripper_targets)
        return Control(effector_pose_target={k: v.copy() for k, v in self.pose_targets.items()},
                       gripper_target=dict(self.gripper_targets))

    def record_step(self, info: StepInfo | None, failure: str | None = None) -> StepInfo | None:
        """Account for the step just taken on :attr:`sim` with the control of :meth:`command` (the
        second half of :meth:`step`): ``info`` its StepInfo, or ``failure`` the solver's message when
        it failed. Sets :attr:`infeasible` by the task's early-stop rules.

        Returns:
            ``info``, or None when the step failed.
        """
        step = self.steps_done + 1
        if failure is not None or info is None:
            self.infeasible = f"solver failure at step {step}: {failure}"
            return None
        self.steps_done = step
        if not np.all(np.isfinite(self.sim.state.x)):
            self.infeasible = f"non-finite positions at step {step}"
            return info
        self.infeasible = self._check(step)
        return info

    def _check(self, step: int) -> str | None:
        rules = self.task.infeasible
        wrench = self.wrenches()
        for name, w in wrench.items():
            if rules.max_force_N is not None and np.max(np.abs(w[:3])) > rules.max_force_N:
                return (f"excessive force at step {step}: effector {name} |f| components {np.abs(w[:3]).round(3).tolist()} N "
                        f"> {rules.max_force_N} N")
        if rules.min_contact_force_N is not None and step > rules.contact_after_step:
            names = rules.contact_effectors or tuple(e for e, k in self.task.action_layout if k == "pose")
            for name in names:
                if float(np.linalg.norm(wrench[name][:3])) < rules.min_contact_force_N:
                    return (f"no contact at step {step}: effector {name} net contact force "
                            f"{np.linalg.norm(wrench[name][:3]):.3g} N < {rules.min_contact_force_N} N")
        return None

    def reward(self) -> float:
        """The task's reward of the current state."""
        return float(self.task.reward(self.sim.model, self.sim.state))


def rollout(task: TaskSpec, actions: np.ndarray, params: dict[str, float] | None = None, *, backend: str = "numpy",
            keep_states: bool = False, solver_config: SolverConfig | None = None, clip: bool = False) -> RolloutResult:
    """Run an action sequence from the task's initial state and score the final state.

    Args:
        task: the task.
        actions: per-step action rows, shape ``(k, action_dim)`` with ``k <= horizon`` (see
            :mod:`sim_core.tasks.spec` for their meaning); must lie within the task's bounds.
        params: global parameter overrides (inverse tasks: the candidate values).
        backend: solver backend (``"numpy"``, ``"taichi-cpu"``, ...).
        keep_states: keep every state in the result.
        solver_config: full solver settings, or None.
        clip: clip finite actions to the task's bounds (as ThinShellLab's ``fix_action`` limits each
            step) instead of refusing them.

    Returns:
        the :class:`RolloutResult` (an infeasible rollout stops at the failing step and says why).

    Raises:
        ConfigError: bad actions (shape, non-finite, or outside the bounds without ``clip``) or parameters.
    """
    a = _checked_actions(task, actions, clip)
    ep = TaskEpisode(task, params, backend, solver_config)
    log = _EpisodeLog(ep, keep_states)
    t0 = time.perf_counter()
    for row in a:
        info = ep.step(row)
        if info is None:
            break
        log.add(info)
        if ep.infeasible is not None:
            break
    return log.result(time.perf_counter() - t0)


def _checked_actions(task: TaskSpec, actions: np.ndarray, clip: bool) -> np.ndarray:
    """``actions`` validated (:meth:`TaskSpec.check_actions`), clipped first when ``clip``."""
    a = np.asarray(actions, dtype=float)
    if clip and a.ndim == 2 and np.all(np.isfinite(a)):
        a = np.clip(a, task.action_low, task.action_high)
    return task.check_actions(a)


class _EpisodeLog:
    """What :class:`RolloutResult` reports of an episode, gathered step by step."""

    def __init__(self, ep: TaskEpisode, keep_states: bool) -> None:
        sim = ep.sim
        self.ep = ep
        self.states = [sim.state.copy()] if keep_states else None
        self.poses = {k: [np.array(v)] for k, v in sim.state.effector_pose.items()}
        self.grip = {k: [float(sim.state.gripper_opening[k])] for k in ep.gripper_targets}
        self.wrench = {k: [v] for k, v in ep.wrenches().items()}
        self.infos: list[StepInfo] = []

    def add(self, info: StepInfo) -> None:
        """Record the step just completed (``info``) and the state it reached."""
        state = self.ep.sim.state
        self.infos.append(info)
        if self.states is not None:
            self.states.append(state.copy())
        for k in self.poses:
            self.poses[k].append(np.array(state.effector_pose[k]))
        for k in self.grip:
            self.grip[k].append(float(state.gripper_opening[k]))
        for k, v in self.ep.wrenches().items():
            self.wrench[k].append(v)

    def result(self, sim_time_s: float) -> RolloutResult:
        """The :class:`RolloutResult` (reward of the current state)."""
        ep = self.ep
        return RolloutResult(
            reward=ep.reward(), steps_done=ep.steps_done, infeasible=ep.infeasible, states=self.states,
            effector_poses={k: np.array(v) for k, v in self.poses.items()},
            gripper={k: np.array(v) for k, v in self.grip.items()}, step_infos=self.infos,
            wrench={k: np.array(v) for k, v in self.wrench.items()}, sim_time_s=sim_time_s,
        )


def rollout_population(task: TaskSpec, actions: Sequence[np.ndarray],
                       params: Sequence[Mapping[str, float] | None] | Mapping[str, float] | None = None, *,
                       backend: str = "numpy", keep_states: bool = False, solver_config: SolverConfig | None = None,
                       clip: bool = False) -> list[RolloutResult]:
    """:func:`rollout` of a population of action sequences, stepped together as one batch
    (:class:`sim_core.batch.BatchedSimulation`: one copy of the task's scene per member).

    Each member's result is the one :func:`rollout` gives for its actions and parameters alone (same
    steps, early stops and reward); members stop independently (early stop, solver failure, end of
    their actions) and the others go on.

    Args:
        task: the task.
        actions: per member, action rows of shape ``(k_i, action_dim)``, ``k_i <= horizon``.
        params: parameter overrides: one mapping for every member, or one per member (None entries:
            none), or None.
        backend: solver backend of every copy when ``solver_config`` is None.
        keep_states: keep every state in each result.
        solver_config: full solver settings of every copy, or None.
        clip: clip finite actions to the task's bounds (as :func:`rollout`).

    Returns:
        one :class:`RolloutResult` per member, in order; ``sim_time_s`` is the member's own stepping
        time (the sum of its steps' ``StepInfo.time_total``).

    Raises:
        ConfigError: bad actions (naming the member), parameters, or a ``params`` list of another length.
    """
    return PopulationRollout(task, actions, params, backend=backend, keep_states=keep_states,
                             solver_config=solver_config, clip=clip).run()


class PopulationRollout:
    """The batch of one :func:`rollout_population` call, built and then run (:meth:`run`); kept as an
    object so that a benchmark can read the batch's memory after the run, and so that an optimiser can
    run the next population's actions on the same batch (:meth:`restart`: no copy, stacked model or
    lockstep solver built again, its kernels and device arrays kept).

    Args: as :func:`rollout_population`.

    Attributes:
        episodes: one :class:`TaskEpisode` per member.
        batch: the :class:`sim_core.batch.BatchedSimulation` of the episodes' simulations (None for an
            empty population).

    Raises:
        ConfigError: as :func:`rollout_population`.
    """

    def __init__(self, task: TaskSpec, actions: Sequence[np.ndarray],
                 params: Sequence[Mapping[str, float] | None] | Mapping[str, float] | None = None, *,
                 backend: str = "numpy", keep_states: bool = False, solver_config: SolverConfig | None = None,
                 clip: bool = False) -> None:
        self.task, self.clip = task, clip
        arrays = self._checked(actions)
        B = len(arrays)
        if params is None or isinstance(params, Mapping):
            plist = [params] * B
        else:
            plist = list(params)
            if len(plist) != B:
                raise ConfigError(f"rollout_population: {len(plist)} parameter sets for {B} action sequences")
        self.actions = arrays
        self.keep_states = keep_states
        scene_model = build_task_scene(copy.deepcopy(task.scene)) if B > 1 else None  # built once, copied per member
        self.episodes = [TaskEpisode(task, p, backend, solver_config, scene_model) for p in plist]
        self.batch = BatchedSimulation([ep.sim for ep in self.episodes], finite_check=False) if B else None

    def _checked(self, actions: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Each member's actions validated (:func:`_checked_actions`), the error naming the member."""
        arrays = []
        for i, a in enumerate(actions):
            try:
                arrays.append(_checked_actions(self.task, a, self.clip))
            except ConfigError as err:
                raise ConfigError(f"population member {i}: {err}") from err
        return arrays

    def restart(self, actions: Sequence[np.ndarray]) -> None:
        """Every member back to the task's initial state with new actions, for the next :meth:`run` on the
        same batch: one batched reset (:meth:`BatchedSimulation.reset`: failures cleared; in lockstep the
        stacked state dropped and the stacked solver's step-to-step caches cleared at the next step, as a
        copy's :meth:`Simulation.reset` clears its solver's), then each episode's initial state and
        commanded targets. The members' results are then those of a new :class:`PopulationRollout` of
        ``actions`` with the same parameters (bit for bit: the same steps from the same states and caches).

        Args:
            actions: per member, action rows of shape ``(k_i, action_dim)``, ``k_i <= horizon``; as many
                members as the batch has.

        Raises:
            ConfigError: bad actions (naming the member), or another number of members than the batch's.
        """
        arrays = self._checked(actions)
        if len(arrays) != len(self.episodes):
            raise ConfigError(f"population restart: {len(arrays)} action sequences for a batch of "
                              f"{len(self.episodes)} members")
        self.actions = arrays
        if self.batch is not None:
            self.batch.reset()
        for ep in self.episodes:
            ep._start()  # the initial state of the task (not the model's rest state that Simulation.reset set)

    def run(self, step: Callable[..., BatchStep] | None = None) -> list[RolloutResult]:
        """Step every member through its actions (once); one :class:`RolloutResult` per member.

        Args:
            step: what advances the batch, ``step(controls, mask) -> BatchStep``: default
                :meth:`BatchedSimulation.step`; :meth:`sim_core.batch.adjoint.TrajectoryRecorder.step` records
                the steps for the batched adjoint.
        """
        arrays, episodes, batch = self.actions, self.episodes, self.batch
        B = len(arrays)
        if B == 0:
            return []
        logs = [_EpisodeLog(ep, self.keep_states) for ep in episodes]
        running = np.array([len(a) > 0 for a in arrays])
        for k in range(max(len(a) for a in arrays)):
            mask = running & np.array([k < len(a) for a in arrays])
            if not mask.any():
                break
            controls = [episodes[i].command(arrays[i][k]) if mask[i] else None for i in range(B)]
            res = (step or batch.step)(controls, mask)
            for i in np.flatnonzero(mask):
                info = episodes[i].record_step(res.infos[i], batch.failures[i] if i in res.failed_now else None)
                if info is None:
                    running[i] = False
                    continue
                logs[i].add(info)
                if episodes[i].infeasible is not None:
                    running[i] = False
        return [log.result(float(sum(info.time_total for info in log.infos))) for log in logs]
