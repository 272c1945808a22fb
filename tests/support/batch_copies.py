"""Three copies of a small pad-press scene with their own parameters and motions, and one copy run
alone: the batch tests' reference (``tests/sim_core/batch``, ``tests/sim_core/ti_kernels``)."""

from __future__ import annotations

import copy

import numpy as np

from sim_core.control import Control
from sim_core.scenes.task_scene import build_task_scene, task_initial_state
from sim_core.simulation import Simulation
from tests.support.press_scenes import pad_scene, paper_sheet

STEPS = 4
PARAMS = [{}, {"pad.youngs_modulus": 6e5, "friction.pad_sheet": 0.2},
          {"sheet.bending_stiffness": 2e-2, "friction.pad_sheet": 0.9}]
# per copy: press depth per step (m) and drag per step along x (m)
MOTIONS = [(3e-4, 0.0), (2e-4, 2e-4), (4e-4, -1e-4)]


def pad_model():
    """A 7 x 7 paper sheet on a table plane under the coarse gel pad, 0.6 mm above it (89 vertices)."""
    scene = pad_scene({"sheet": paper_sheet((0.03, 0.03), (7, 7), (-0.015, -0.015, 0.0))}, 6e-4,
                      [{"pair": ["pad", "sheet"], "mu": 0.5}, {"pair": ["sheet", "table"], "mu": 0.3}])
    return build_task_scene(scene)


def control(pose0: np.ndarray, motion: tuple[float, float], k: int) -> Control:
    """The pad's target at step ``k`` (0-based): ``motion = (press m/step, drag m/step along x)`` from ``pose0``."""
    target = pose0.copy()
    target[2] -= motion[0] * (k + 1)
    target[0] += motion[1] * k
    return Control(effector_pose_target={"pad": target})


def separate_run(model, params, motion, config=None):
    """One copy run alone (a Simulation of its own, ``STEPS`` steps): the state after each step."""
    m = copy.deepcopy(model)
    for name, value in params.items():
        m.set_parameter(name, value)
    sim = Simulation(m, solver_config=config)
    sim.state = task_initial_state(m)
    pose0 = sim.state.effector_pose["pad"].copy()
    states = []
    for k in range(STEPS):
        sim.step(control(pose0, motion, k))
        states.append(sim.state.copy())
    return states
