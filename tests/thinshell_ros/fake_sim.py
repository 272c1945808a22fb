"""A kinematic stand-in with the Simulation facade API, for node plumbing tests without the solver.

Physics of the stand-in (simple enough to assert on): the effector pose equals the step's target;
the gel (sensor frame = effector frame, z along the effector's z axis) touches a rigid plane at
``z = top``; the penetration ``d = max(0, top - z_gel)`` along world -z gives a normal force
``F_z = -k d`` ON the gel in the sensor frame (the frame's z points down, into the object) and pushes
the markers to ``z = -d`` in the sensor frame.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from sim_core.control import Control
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.sensors.tactile import TactileReading
from sim_core.simulation import Observation

HOME = np.array([0.06, 0.0, 0.004, 1.0, 0.0, 0.0, 0.0])


class FakeSimulation:
    """Facade-compatible kinematic press (see module docstring); ``fail_below`` z triggers divergence."""

    def __init__(self, top: float = 0.0003, k: float = 1000.0, fail_below: float = -0.01) -> None:
        self.dt = 0.005
        self.top, self.fail_below = top, fail_below
        self.effector_names, self.sensor_names = ["ee"], ["tactile"]
        self._params = {"sheet.youngs_modulus": 3.0e9, "contact.stiffness": k}
        self.model = SimpleNamespace(control=Control, effectors={})
        self.reset()

    @property
    def parameter_names(self) -> list[str]:
        return list(self._params)

    def get_parameter(self, name: str) -> float:
        if name not in self._params:
            raise ConfigError(f"unknown parameter {name!r}")
        return self._params[name]

    def set_parameter(self, name: str, value: float) -> None:
        if name not in self._params:
            raise ConfigError(f"unknown parameter {name!r}")
        if not np.isfinite(value) or value <= 0:
            raise ConfigError(f"parameter {name!r} must be > 0, got {value}")
        self._params[name] = float(value)

    @property
    def t(self) -> float:
        return self.state.t

    def reset(self) -> None:
        self.state = SimpleNamespace(t=0.0, effector_pose={"ee": HOME.copy()})

    def step(self, control: Control | None = None) -> None:
        target = (control.effector_pose_target if control else {}).get("ee", self.state.effector_pose["ee"])
        if target[2] < self.fail_below:
            raise SimulationDivergedError(f"step at t = {self.t:.3f} s: fake divergence below z = {self.fail_below}")
        self.state = SimpleNamespace(t=self.state.t + self.dt, effector_pose={"ee": np.array(target, dtype=float)})

    def observe(self, render_image: bool = False) -> Observation:
        pose = self.state.effector_pose["ee"]
        depth = max(0.0, self.top - pose[2])
        gx, gy = np.meshgrid(np.linspace(-0.008, 0.008, 9), np.linspace(-0.006, 0.006, 7))
        xyz = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -depth)], axis=1)
        uv = np.stack([300 * xyz[:, 0] / (xyz[:, 2] + 0.025) + 160, 300 * xyz[:, 1] / (xyz[:, 2] + 0.025) + 120], axis=1)
        wrench = np.array([0.0, 0.0, -self._params["contact.stiffness"] * depth, 0.0, 0.0, 0.0])
        image = np.full((24, 32), int(min(255, depth * 1e5)), np.uint8) if render_image else None
        sx, sy = np.meshgrid(np.linspace(0, 0.1, 5), np.linspace(-0.03, 0.03, 3))
        sheet = np.stack([sx.ravel(), sy.ravel(), np.full(sx.size, self.top)], axis=1)
        tris = np.array([[0, 1, 5], [1, 6, 5]])
        return Observation(self.t, {"ee": pose.copy()}, {"tactile": TactileReading(xyz, uv, wrench, image)}, sheet, tris)
