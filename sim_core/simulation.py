"""Simulation: the facade that the ROS node, the CLI and system identification drive.

It owns a Model, a NewtonSolver (built at its first use) and the current State, and turns the state into
observations (effector poses, tactile readings, sheet points) following INTERFACES.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from sim_core.control import Control
from sim_core.model import Model
from sim_core.backend import resolve_backend
from sim_core.scenes import load_scene
from sim_core.sensors.tactile import read_tactile
from sim_core.solver import NewtonSolver, SolverConfig, StepInfo, StepTotals
from sim_core.state import State
from sim_core.transforms import compose_poses


class Observation(NamedTuple):
    """What the simulator publishes at one instant.

    Attributes:
        t: time in s.
        effector_pose: effector name -> ``[x y z qx qy qz qw]`` in ``world``.
        tactile: sensor name -> ``sim_core.sensors.tactile.TactileReading``.
        sheet_points: tracked sheet vertices in ``world``, m, shape ``(p, 3)`` (grid order).
        sheet_triangles: triangles over ``sheet_points``, shape ``(t, 3)``.
    """

    t: float
    effector_pose: dict[str, np.ndarray]
    tactile: dict[str, Any]
    sheet_points: np.ndarray
    sheet_triangles: np.ndarray


class Simulation:
    """Model + solver + state.

    The :class:`NewtonSolver` is built at the first read of :attr:`solver` (a step, a warm-up, a caller's read):
    a copy of a lockstep batch (:class:`~sim_core.batch.BatchedSimulation`), which a stacked solver steps, never
    builds one. The backend is resolved at construction all the same (Taichi initialised, a backend that cannot
    start refused); an unknown linear solver name is refused when the solver is built.

    Args:
        model: the scene model.
        dt: time step in s (default: the scene's ``dt`` in ``model.meta``, else 5 ms).
        solver_config: Newton settings (default ``SolverConfig()``).

    Raises:
        ConfigError: ``solver_config.backend`` cannot start here (:func:`sim_core.backend.resolve_backend`).

    Attributes:
        last_info: the :class:`StepInfo` of the last step (None before one).
        step_totals: how the steps since construction or the last :meth:`reset` ended
            (:class:`StepTotals`: substep retries, relaxed acceptances).
    """

    def __init__(self, model: Model, dt: float | None = None, solver_config: SolverConfig | None = None) -> None:
        self.model = model
        self.dt = float(dt if dt is not None else model.meta.get("dt", 0.005))
        self._solver_config = solver_config or SolverConfig()
        self._backend = resolve_backend(self._solver_config.backend)
        self._solver: NewtonSolver | None = None  # built at the first read of .solver
        self.state: State = model.state()
        self.last_info: StepInfo | None = None
        self.step_totals = StepTotals()
        self._observed: tuple[tuple, Observation] | None = None  # (_observation_key, observation) of the last observe

    @classmethod
    def from_scene(cls, scene: str | Path | dict, dt: float | None = None,
                   solver_config: SolverConfig | None = None) -> "Simulation":
        """Load a scene file (or dict) and build the simulation.

        Raises:
            ConfigError: invalid scene (the message names the file and key).
        """
        return cls(load_scene(scene), dt=dt, solver_config=solver_config)

    # ------------------------------------------------------------------ solver
    @property
    def solver(self) -> NewtonSolver:
        """The :class:`NewtonSolver` of :attr:`model` with :attr:`solver_config`, built at the first read."""
        if self._solver is None:
            self._solver = NewtonSolver(self.model, self._solver_config)
        return self._solver

    @property
    def solver_config(self) -> SolverConfig:
        """The Newton settings (the solver's ``config`` once built), read without building the solver."""
        return self._solver_config if self._solver is None else self._solver.config

    @property
    def backend(self) -> str:
        """The concrete backend of :attr:`solver_config` (``numpy``, ``taichi-cpu`` or ``taichi-cuda``), read
        without building the solver."""
        return self._backend if self._solver is None else self._solver.backend

    # ------------------------------------------------------------------ stepping
    @property
    def t(self) -> float:
        """Current simulated time in s."""
        return self.state.t

    def step(self, control: Control | None = None) -> StepInfo:
        """Advance one step of ``dt`` (the state is replaced only if the step succeeds)."""
        out = self.state.copy()
        info = self.solver.step(self.state, out, control, self.dt)
        self.step_totals.add(info, self.state.step_index)
        self.state = out
        self.last_info = info
        return info

    def warm_up(self) -> None:
        """Build the solver's per-model structures for the current state before the first step
        (:meth:`NewtonSolver.warm_up`), so that the first step takes about as long as the others."""
        self.solver.warm_up(self.state)

    def reset(self) -> None:
        """Return to the initial state, with the solver's step-to-step caches cleared
        (:meth:`NewtonSolver.reset_caches`): the same controls then give the same steps bit for bit.
        :attr:`step_totals` start again from zero."""
        self.state = self.model.state()
        if self._solver is not None:  # a solver not built yet has no caches
            self._solver.reset_caches()
        self.step_totals = StepTotals()

    # ------------------------------------------------------------------ parameters
    @property
    def parameter_names(self) -> list[str]:
        """Editable parameter names (see ``Model.parameter_names``)."""
        return self.model.parameter_names

    def get_parameter(self, name: str) -> float:
        """Current value of a parameter."""
        return self.model.get_parameter(name)

    def set_parameter(self, name: str, value: float) -> None:
        """Set a parameter; the solver rebuilds what depends on it before the next step."""
        self.model.set_parameter(name, value)
        if self._solver is not None:  # a solver not built yet reads the model when it is
            self._solver.notify_model_changed()

    @property
    def effector_names(self) -> list[str]:
        """Names of the effectors."""
        return list(self.model.effectors)

    @property
    def sensor_names(self) -> list[str]:
        """Names of the tactile sensors."""
        return list(self.model.sensors)

    # ------------------------------------------------------------------ observation
    def sensor_pose(self, name: str, state: State | None = None) -> np.ndarray:
        """Pose of sensor ``name``'s frame in ``world``: effector pose * mount."""
        state = state or self.state
        s = self.model.sensors[name]
        return compose_poses(state.effector_pose[s.effector], s.mount)

    def observe(self, render_image: bool = False, state: State | None = None) -> Observation:
        """Observation of ``state`` (default: the current state).

        The last observation is kept: a state whose positions, contact forces and effector poses are
        bitwise those it was read from (at the same model revision and ``render_image``) reads the same
        values, which are then copied from it with the state's time (a scene at rest, whose steps
        repeat: ``SolverConfig.repeat_fixed_points``).
        """
        state = state or self.state
        key = _observation_key(state, render_image, self.model.revision)
        kept = self._observed
        if kept is not None and kept[0] == key:
            return _copy_observation(kept[1], state.t)
        obs = self._read(state, render_image)
        self._observed = (key, _copy_observation(obs, obs.t))
        return obs

    def _read(self, state: State, render_image: bool) -> Observation:
        """:meth:`observe` of ``state``, read from it."""
        tactile = {}
        for name, s in self.model.sensors.items():
            gel = self.model.bodies[s.gel_body]
            tactile[name] = read_tactile(
                s.spec, s.camera, s.embedding, state.x, s.contact_triangles, self.sensor_pose(name, state),
                state.contact_force, gel.vertices, render_image=render_image,
            )
        sheets = self.model.tracked_sheets()
        if sheets:
            pts = state.x[self.model.tracked_sheet_vertices()].copy()
            offsets = np.cumsum([0] + [b.vertex_stop - b.vertex_start for b in sheets[:-1]])
            tris = np.concatenate([b.triangles - b.vertex_start + o for b, o in zip(sheets, offsets)])
        else:
            pts, tris = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        return Observation(
            t=state.t, effector_pose={k: np.array(v) for k, v in state.effector_pose.items()},
            tactile=tactile, sheet_points=pts, sheet_triangles=tris,
        )


def _observation_key(state: State, render_image: bool, revision: int) -> tuple:
    """What :meth:`Simulation.observe` reads from ``state`` besides its time, as bytes: positions,
    contact forces, effector poses; with the model revision and ``render_image``."""
    force = state.contact_force
    return (bool(render_image), revision, state.x.shape, np.asarray(state.x, dtype=float).tobytes(),
            None if force is None else np.asarray(force, dtype=float).tobytes(),
            tuple((k, np.asarray(v, dtype=float).tobytes()) for k, v in state.effector_pose.items()))


def _copy_observation(obs: Observation, t: float) -> Observation:
    """``obs`` at time ``t`` with every array copied (the kept observation stays the caller's to change)."""
    tactile = {name: type(r)(*(None if a is None else np.array(a) for a in r)) for name, r in obs.tactile.items()}
    return Observation(t=t, effector_pose={k: np.array(v) for k, v in obs.effector_pose.items()}, tactile=tactile,
                       sheet_points=obs.sheet_points.copy(), sheet_triangles=obs.sheet_triangles.copy())
