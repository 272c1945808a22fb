"""Small task scenes (``kind: task`` dicts) of a tactile pad pressing sheets onto a table, and the
press-and-drag driver shared by the no-tunnelling tests.

The pad is the box gel of ``config/scenes/press_slide.yaml`` (18.6 x 14.3 x 4 mm, E = 0.3 MPa,
nu = 0.45) on a coarse 5 x 4 x 2 grid; sheets are paper (E = 3 GPa, t = 0.3 mm, D = 7.4e-3 N m).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from sim_core.control import Control
from sim_core.simulation import Simulation

PAPER = {"thickness": 3e-4, "density": 700.0, "membrane": {"model": "stvk", "youngs_modulus": 3e9, "poisson_ratio": 0.3},
         "bending": {"bending_stiffness": 7.4e-3}, "yield_angle": 1e9, "clamped_edge": "none"}
GEL = {"youngs_modulus": 3e5, "poisson_ratio": 0.45, "density": 1100.0}
EPS = 4e-4  # contact offset, m


def paper_sheet(size, resolution, origin) -> dict:
    """A paper sheet block: ``size`` (m, 2), ``resolution`` (vertices, 2), ``origin`` (m, 3)."""
    return {**PAPER, "size": list(size), "resolution": list(resolution), "origin": list(origin)}


def pad_scene(sheets: dict, pad_bottom_z: float, friction: list, table: str = "plane", pad_x: float = 0.0) -> dict:
    """A task scene: ``sheets`` under a pad whose contact face is at ``pad_bottom_z`` (m) and
    centred at ``(pad_x, 0)``, on a table z = 0: the plane ``table`` or a frozen 9 x 9 x 2 tet box
    ``table`` (70 x 70 x 8.75 mm, top face z = 0), gravity -z, dt 5 ms."""
    scene = {
        "kind": "task", "version": 1, "name": "pad_press", "dt": 0.005, "gravity": [0.0, 0.0, -9.81],
        "contact": {"stiffness": 2e4, "eps": EPS, "self_contact": False},
        "sheets": sheets,
        "effectors": {"pad": {"shape": "pad", "size": [0.0186, 0.0143, 0.004], "resolution": [5, 4, 2], "material": GEL,
                              "initial_pose": [pad_x, 0.0, pad_bottom_z, 1.0, 0.0, 0.0, 0.0]}},
        "friction": friction,
    }
    if table == "plane":
        scene["planes"] = {"table": {"normal": [0.0, 0.0, 1.0], "offset": 0.0}}
    else:
        scene["boxes"] = {"table": {"size": [0.07, 0.07, 0.00875], "resolution": [9, 9, 2],
                                    "origin": [-0.035, -0.035, -0.00875], "frozen": True}}
    return scene


def press_and_drag(sim: Simulation, effector: str, depth: float, drag: float, n_press: int, n_drag: int,
                   on_step: Callable[[np.ndarray, Simulation], None]) -> None:
    """Lower ``effector`` by ``depth`` (m) in ``n_press`` equal steps, then move it ``drag`` (m)
    along +x in ``n_drag`` steps; ``on_step(x_n, sim)`` is called after every step with the
    positions at its start."""
    pose0 = sim.state.effector_pose[effector].copy()
    control = Control()
    for i in range(n_press + n_drag):
        target = pose0.copy()
        target[2] -= depth * min(1.0, (i + 1) / n_press)
        target[0] += drag * max(0, i + 1 - n_press) / n_drag
        control.effector_pose_target[effector] = target
        x_n = sim.state.x.copy()
        sim.step(control)
        on_step(x_n, sim)
