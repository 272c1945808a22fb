"""BatchedSimulation: ``B`` independent copies of one scene advanced together, one call per step.

Every copy has its own :class:`~sim_core.model.Model` (same topology, own material parameters), its
own :class:`~sim_core.solver.NewtonSolver` (own Newton convergence, line search, contact set and
union sparsity pattern) and its own :class:`~sim_core.state.State`, and takes its own
:class:`~sim_core.control.Control` each step. The copies run on one backend
(``SolverConfig.backend``, :mod:`sim_core.backend`: ``numpy``, ``taichi-cpu`` or ``taichi-cuda``),
which they share in this process (one Taichi runtime, kernels compiled once for all copies).

Two executions, chosen by the copies' ``SolverConfig.lockstep``:

* sequential (``lockstep=False``, default): :meth:`BatchedSimulation.step` advances every active copy
  by one ``dt`` with that copy's solver, in copy order.
* lockstep (``lockstep=True``): the copies' models are stacked into one model of disconnected copies
  and every step is one Newton solve of all copies together (:mod:`sim_core.batch.lockstep`: one
  evaluation per energy term and one linear solve per iteration for all copies; per-copy convergence,
  line search and failure). Each copy's ``Simulation.state`` is written after every step; each copy's
  states are those of its separate run to the Newton tolerance. The copies' own solvers are not used (nor built:
  :attr:`Simulation.solver <sim_core.simulation.Simulation.solver>` is built at its first read).

Sequential execution in detail: Each copy's step is exactly what a
separate :class:`~sim_core.simulation.Simulation` of the same model, state and control computes (same
code, same per-copy caches), so a batch gives per copy the states of separate runs. A copy whose step
fails (:class:`~sim_core.errors.SimulationDivergedError`, or non-finite positions) keeps its last good
state, is marked failed with the reason (:attr:`BatchedSimulation.failures`) and is skipped by later
steps; the other copies go on.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from sim_core.control import Control
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.model import Model
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from sim_core.state import State
from sim_core.step_info import StepInfo


@dataclass
class BatchStep:
    """What one :meth:`BatchedSimulation.step` did.

    Attributes:
        infos: per copy, the solver's :class:`StepInfo`, or None for a copy that did not step
            (inactive, already failed) or failed in this step.
        failed_now: indices of the copies that failed in this step.
        stepped: per copy, whether it was stepped (attempted) in this call, shape ``(B,)`` bool.
        wall_s: wall-clock seconds of the whole call.
    """

    infos: list[StepInfo | None]
    failed_now: list[int] = field(default_factory=list)
    stepped: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    wall_s: float = 0.0


def same_topology(a: Model, b: Model) -> str | None:
    """Why two models are not copies of one scene (None when they are).

    Two models are copies when they have the same vertex count, the same bodies (name, kind, vertex
    range, triangles, tetrahedra, hinges) and the same effectors. Material parameters may differ.
    """
    if a.vertex_count != b.vertex_count:
        return f"vertex count {a.vertex_count} != {b.vertex_count}"
    if list(a.bodies) != list(b.bodies):
        return f"bodies {list(a.bodies)} != {list(b.bodies)}"
    for name, ba in a.bodies.items():
        bb = b.bodies[name]
        if (ba.kind, ba.vertex_start, ba.vertex_stop) != (bb.kind, bb.vertex_start, bb.vertex_stop):
            return f"body {name!r}: kind or vertex range differ"
        for attr in ("triangles", "tets", "hinges"):
            ea, eb = getattr(ba, attr), getattr(bb, attr)
            if (ea is None) != (eb is None) or (ea is not None and not np.array_equal(ea, eb)):
                return f"body {name!r}: {attr} differ"
    if list(a.effectors) != list(b.effectors):
        return f"effectors {list(a.effectors)} != {list(b.effectors)}"
    return None


class BatchedSimulation:
    """``B`` copies of one scene stepped together (see the module docstring).

    Args:
        simulations: the copies, each a :class:`Simulation` with its own model and solver (built with
            :meth:`from_model` or by the caller, e.g. one per task episode). Their models must be
            copies of one scene (:func:`same_topology`), their solver settings on one backend, and no two
            copies may share a model or state object (each builds its own solver).
        finite_check: treat a step that ends with non-finite positions as a failure (the copy keeps
            its last good state). False leaves such a state in place for the caller to judge (the
            task episodes do, as :func:`sim_core.tasks.rollout.rollout` does).

    Raises:
        ConfigError: no copies, models of different topology, shared objects, or solvers on different
            backends (the message names the copy).

    Attributes:
        sims: the copies.
        failures: per copy, why it stopped (the solver's message, naming the step), or None while it runs.
        lockstep: the :class:`~sim_core.batch.lockstep.LockstepEngine` when the copies' solver settings
            ask for lockstep stepping (``SolverConfig.lockstep``), else None.
    """

    def __init__(self, simulations: Sequence[Simulation], finite_check: bool = True) -> None:
        sims = list(simulations)
        if not sims:
            raise ConfigError("a batch needs at least one copy")
        ref = sims[0]
        for i, sim in enumerate(sims[1:], start=1):
            why = same_topology(ref.model, sim.model)
            if why is not None:
                raise ConfigError(f"batch copy {i} is not a copy of copy 0's scene: {why}")
            if sim.backend != ref.backend:
                raise ConfigError(f"batch copy {i} runs on backend {sim.backend!r}, copy 0 on "
                                  f"{ref.backend!r}: a batch runs on one backend")
        for what in ("model", "state"):
            ids = [id(getattr(s, what)) for s in sims]
            if len(set(ids)) != len(ids):
                raise ConfigError(f"batch copies share a {what} object: every copy needs its own")
        self.sims = sims
        self.failures: list[str | None] = [None] * len(sims)
        self.finite_check = bool(finite_check)
        self.lockstep = None
        if ref.solver_config.lockstep:
            from sim_core.batch.lockstep import LockstepEngine

            self.lockstep = LockstepEngine(sims)

    @classmethod
    def from_model(cls, model: Model, batch_size: int, *, dt: float | None = None,
                   solver_config: SolverConfig | Sequence[SolverConfig] | None = None,
                   params: Sequence[Mapping[str, float]] | None = None,
                   state: State | None = None) -> "BatchedSimulation":
        """``batch_size`` copies of ``model`` (each a deep copy, so that parameters are per copy).

        Args:
            model: the scene (not modified).
            batch_size: number of copies ``B >= 1``.
            dt: time step in s (default: the model's, as :class:`Simulation`).
            solver_config: one setting for every copy, or one per copy (same backend).
            params: per copy, parameter name -> value (``Model.parameter_names``), length ``B``.
            state: the initial state of every copy (copied), default ``model.state()``.

        Raises:
            ConfigError: ``batch_size < 1``, lists of the wrong length, unknown parameters or values
                out of range (naming the copy), different backends.
        """
        if int(batch_size) < 1:
            raise ConfigError(f"batch_size must be >= 1, got {batch_size}")
        B = int(batch_size)
        configs = _per_copy(solver_config, B, "solver_config")
        if params is not None and len(params) != B:
            raise ConfigError(f"params: {len(params)} entries for a batch of {B}")
        sims = []
        for i in range(B):
            m = copy.deepcopy(model)
            for name, value in (params[i] if params is not None else {}).items():
                try:
                    m.set_parameter(name, value)
                except ConfigError as err:
                    raise ConfigError(f"batch copy {i}: {err}") from err
            sim = Simulation(m, dt=dt, solver_config=copy.deepcopy(configs[i]) if configs[i] is not None else None)
            if state is not None:
                sim.state = state.copy()
            sims.append(sim)
        return cls(sims)

    # ------------------------------------------------------------------ views
    @property
    def batch_size(self) -> int:
        """Number of copies ``B``."""
        return len(self.sims)

    @property
    def backend(self) -> str:
        """The concrete backend of every copy (:attr:`Simulation.backend <sim_core.simulation.Simulation.backend>`)."""
        return self.sims[0].backend

    @property
    def states(self) -> list[State]:
        """Current state of each copy (the copies' own objects)."""
        return [s.state for s in self.sims]

    @property
    def active(self) -> np.ndarray:
        """Copies that have not failed, shape ``(B,)`` bool."""
        return np.array([f is None for f in self.failures], dtype=bool)

    def positions(self) -> np.ndarray:
        """Positions of every copy, m, shape ``(B, vertex_count, 3)`` (a new array)."""
        return np.stack([s.state.x for s in self.sims])

    # ------------------------------------------------------------------ stepping
    def warm_up(self) -> None:
        """:meth:`Simulation.warm_up` of every copy (per-copy solver structures before the first step)."""
        if self.lockstep is not None:
            self.lockstep.warm_up()
            return
        for sim in self.sims:
            sim.warm_up()

    def step(self, controls: Sequence[Control | None] | Control | None = None,
             mask: Sequence[bool] | np.ndarray | None = None) -> BatchStep:
        """Advance every active copy by one step.

        Args:
            controls: one control per copy (length ``B``; None entries = no command), or one control
                for all, or None.
            mask: copies to step, shape ``(B,)`` bool (default: all); failed copies are never stepped.

        Returns:
            the :class:`BatchStep`; a copy that fails here is in ``failed_now`` and in
            :attr:`failures`, its state the last good one.

        Raises:
            ConfigError: controls or mask of the wrong length, or a control with an unknown effector
                or a non-finite pose target (raised before any copy is stepped, naming the copy); any
                other invalid control the solver refuses (naming the copy).
        """
        t0 = time.perf_counter()
        B = self.batch_size
        if controls is None or isinstance(controls, Control):
            controls = [controls] * B
        controls = list(controls)
        if len(controls) != B:
            raise ConfigError(f"batch step: {len(controls)} controls for a batch of {B}")
        run = self.active if mask is None else np.asarray(mask, dtype=bool) & self.active
        if run.shape != (B,):
            raise ConfigError(f"batch step: mask of shape {run.shape} for a batch of {B}")
        _check_controls(self.sims, controls, run)  # the caller's errors before any copy moves
        if self.lockstep is not None:
            infos, failures = self.lockstep.step(controls, run)
            for i, why in failures.items():
                self.failures[i] = why
            return BatchStep(infos=infos, failed_now=sorted(failures), stepped=run, wall_s=time.perf_counter() - t0)
        infos: list[StepInfo | None] = [None] * B
        failed_now = []
        for i in np.flatnonzero(run):
            sim = self.sims[i]
            before = sim.state
            try:
                info = sim.step(controls[i])
            except SimulationDivergedError as err:
                self.failures[i] = str(err)
                failed_now.append(int(i))
                continue
            except ConfigError as err:
                raise ConfigError(f"batch copy {i}: {err}") from err
            if self.finite_check and not np.all(np.isfinite(sim.state.x)):
                sim.state = before
                self.failures[i] = f"step {before.step_index} (t = {before.t:.6g} s): non-finite positions"
                failed_now.append(int(i))
                continue
            infos[i] = info
        return BatchStep(infos=infos, failed_now=failed_now, stepped=run, wall_s=time.perf_counter() - t0)

    def reset(self) -> None:
        """Every copy back to its model's initial state (:meth:`Simulation.reset`), failures cleared."""
        for sim in self.sims:
            sim.reset()
        if self.lockstep is not None:
            self.lockstep.reset()
        self.failures = [None] * self.batch_size

    def set_parameter(self, copy_index: int, name: str, value: float) -> None:
        """Set a material parameter of one copy (:meth:`Simulation.set_parameter`).

        Raises:
            ConfigError: unknown parameter or value out of range (naming the copy); IndexError: no such copy.
        """
        try:
            self.sims[copy_index].set_parameter(name, value)
        except ConfigError as err:
            raise ConfigError(f"batch copy {copy_index}: {err}") from err


def _check_controls(sims: list, controls: list, run: np.ndarray) -> None:
    """:func:`_check_control` of each copy in ``run`` (bool ``(B,)``) with its model: the pose targets' finiteness
    tested in one array; where a name is unknown or a target not finite (or the targets are not one array), each
    copy's own test in copy order, which raises for the first such copy as before."""
    targets, known = [], True
    for i in np.flatnonzero(run).tolist():
        control = controls[i]
        if control is None:
            continue
        effectors = sims[i].model.effectors
        for name, target in control.effector_pose_target.items():
            known &= name in effectors
            targets.append(target)
    try:
        finite = bool(np.isfinite(np.asarray(targets, dtype=float)).all())
    except (TypeError, ValueError):
        finite = False
    if not (known and finite):
        for i in np.flatnonzero(run):
            _check_control(sims[i].model, controls[i], int(i))


def _check_control(model: Model, control: Control | None, index: int) -> None:
    """Raise :class:`ConfigError` naming copy ``index`` for a control with an effector ``model`` does
    not have or a non-finite pose target."""
    if control is None:
        return
    for name, target in control.effector_pose_target.items():
        if name not in model.effectors:
            raise ConfigError(f"batch copy {index}: unknown effector {name!r} in control; known: {list(model.effectors)}")
        if not np.all(np.isfinite(np.asarray(target, dtype=float))):
            raise ConfigError(f"batch copy {index}: effector {name!r} pose target is not finite: {np.asarray(target).tolist()}")


def _per_copy(value, B: int, what: str) -> list:
    """``value`` repeated ``B`` times, or the list itself when it has ``B`` entries."""
    if value is None or isinstance(value, SolverConfig):
        return [value] * B
    values = list(value)
    if len(values) != B:
        raise ConfigError(f"{what}: {len(values)} entries for a batch of {B}")
    backends = {v.backend for v in values if v is not None}
    if len(backends) > 1:
        raise ConfigError(f"{what}: copies on different backends {sorted(backends)}: a batch runs on one backend")
    return values
