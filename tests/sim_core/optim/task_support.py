"""TaskSpec-like tasks for the optimiser tests, built from ``config/scenes/forming.yaml`` and
``folding.yaml`` with the rewards of :mod:`sim_core.tasks.rewards` (the task contract's fields the
optimisers read)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from sim_core.scenes.task_scene import build_task_scene, task_initial_state
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from sim_core.tasks import folding_reward, forming_benchmark_offsets, forming_reward, pose_targets
from sim_core.control import Control

SCENES = Path(__file__).resolve().parents[3] / "config" / "scenes"
MAX_STEP = 1.0e-3  # m per step (ThinShellLab --max_dist 0.001 of the Forming / Folding scripts)
MAX_TURN = 0.02  # rad per step (the effector's rotation limit)


@dataclass
class FormingReward:
    """-|sheet - target|^2 (m^2)."""

    target: np.ndarray
    sheet: slice

    def __call__(self, model, state) -> float:
        return forming_reward(state.x[self.sheet], self.target)


@dataclass
class FoldingReward:
    """Rest angles on the creases of columns 7 and 8 (rad)."""

    hinges_local: np.ndarray
    nx: int
    weights: dict = field(default_factory=lambda: {7: 1.0, 8: -1.0})

    def __call__(self, model, state) -> float:
        return folding_reward(state.hinge_theta_bar["sheet"], self.hinges_local, self.nx, self.weights)


@dataclass
class Task:
    name: str
    kind: str
    scene: dict
    horizon: int
    dt: float
    action_layout: tuple
    action_low: np.ndarray
    action_high: np.ndarray
    control_points: int
    cma_sigma: float
    cma_population: int
    cma_generations: int
    reward: object
    identify: tuple = ()
    reference_actions: np.ndarray | None = None
    success_score: float | None = None
    human_score: float | None = None
    source: str = "tests"

    @property
    def action_dim(self) -> int:
        return len(self.action_low)


def _bounds():
    high = np.array([MAX_STEP] * 3 + [MAX_TURN] * 3)
    return -high, high


def scene(name: str) -> dict:
    return yaml.safe_load((SCENES / f"{name}.yaml").read_text())


def forming_task(horizon: int = 4, control_points: int = 2) -> Task:
    """Forming at a short horizon; the target is the sheet after ``horizon`` steps of the benchmark
    trajectory (ThinShellLab's target is the sheet after its human-designed trajectory)."""
    sc = scene("forming")
    model = build_task_scene(sc)
    sim = Simulation(model, solver_config=SolverConfig())
    sim.state = task_initial_state(model)
    targets = pose_targets(sim.state.effector_pose["dome"], forming_benchmark_offsets(horizon))
    for p in targets:
        sim.step(Control({"dome": p}))
    b = model.bodies["sheet"]
    sl = slice(b.vertex_start, b.vertex_stop)
    low, high = _bounds()
    return Task("Forming", "manipulation", sc, horizon, 0.005, (("dome", "pose"),), low, high, control_points,
                2.5, 6, 2, FormingReward(sim.state.x[sl].copy(), sl))


def folding_task(horizon: int = 4, control_points: int = 2) -> Task:
    """Folding-L (columns 7 / 8 weighted +1 / -1) at a short horizon."""
    sc = scene("folding")
    model = build_task_scene(sc)
    b = model.bodies["sheet"]
    low, high = _bounds()
    reference = np.zeros((horizon, 6))
    reference[:, 2] = -5e-4  # press the fold (ThinShellLab's folding trajectories start by pressing down)
    return Task("Folding-L", "manipulation", sc, horizon, 0.005, (("dome", "pose"),), low, high, control_points,
                2.5, 6, 2, FoldingReward(np.asarray(b.hinges) - b.vertex_start, sc["sheets"]["sheet"]["resolution"][0]),
                reference_actions=reference)
