"""The predicted contact summary of an optimised episode: effector wrenches and tactile readings.

``thinshell optimise`` writes it into ``trajectory.yaml``'s ``prediction`` (docs/trajectory_format.md),
so that a robot run of the trajectory can be compared with what the simulator expects. Flat keys
(the ``prediction`` mapping holds numbers or lists of numbers):

| key | value | unit |
|---|---|---|
| ``wrench_peak_N.<effector>`` | largest net contact force on the effector over the episode | N |
| ``torque_peak_Nm.<effector>`` | largest net contact torque about the effector frame's origin | N*m |
| ``wrench_final.<effector>`` | net contact wrench ``[Fx Fy Fz Tx Ty Tz]`` in ``world`` at the last step | N, N*m |
| ``tactile_normal_peak_N.<sensor>`` | largest ``|Fz|`` of the gel's wrench in the sensor frame (z: the gel's normal) | N |
| ``tactile_shear_peak_N.<sensor>`` | largest ``hypot(Fx, Fy)`` of the gel's wrench in the sensor frame | N |
| ``tactile_marker_shift_peak_m.<sensor>`` | largest displacement of a marker from its position in the first state, sensor frame | m |

Effector wrenches are :func:`sim_core.tasks.rollout.effector_wrench` (contact and friction forces on
the effector's vertices); tactile readings are :meth:`sim_core.simulation.Simulation.observe`
(``sim_core.sensors.tactile``, INTERFACES.md), so the summary is that of the recorded topics a
robot run produces.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from sim_core.errors import ConfigError
from sim_core.simulation import Simulation
from sim_core.state import State
from sim_core.tasks.rollout import effector_wrench


def contact_summary(sim: Simulation, states: Sequence[State]) -> dict[str, float | list[float]]:
    """Effector-wrench and tactile summary of an episode (keys in the module docstring).

    Args:
        sim: the simulation the states belong to (its model gives the effectors and sensors).
        states: the episode's states, initial state first (at least one), each with its
            ``contact_force`` (None counts as no contact).

    Returns:
        ``{key: number or list of numbers}``; no keys for a scene without effectors or sensors.

    Raises:
        ConfigError: no states.
    """
    if not states:
        raise ConfigError("contact summary: the episode has no states")
    out: dict[str, float | list[float]] = {}
    for name in sim.model.effectors:
        w = np.array([effector_wrench(sim, s, name) for s in states])
        out[f"wrench_peak_N.{name}"] = float(np.linalg.norm(w[:, :3], axis=1).max())
        out[f"torque_peak_Nm.{name}"] = float(np.linalg.norm(w[:, 3:], axis=1).max())
        out[f"wrench_final.{name}"] = [float(v) for v in w[-1]]
    sensors = list(sim.model.sensors)
    if not sensors:
        return out
    readings = [sim.observe(state=s).tactile for s in states]
    for name in sensors:
        f = np.array([r[name].wrench[:3] for r in readings])
        m = np.array([r[name].markers_xyz for r in readings])
        out[f"tactile_normal_peak_N.{name}"] = float(np.abs(f[:, 2]).max())
        out[f"tactile_shear_peak_N.{name}"] = float(np.hypot(f[:, 0], f[:, 1]).max())
        out[f"tactile_marker_shift_peak_m.{name}"] = float(np.linalg.norm(m - m[0], axis=2).max()) if m.size else 0.0
    return out
