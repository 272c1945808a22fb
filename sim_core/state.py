"""State: everything that changes from step to step (Newton-style ``model.state()``)."""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_core.collision.memory import CollisionMemory


@dataclass
class State:
    """Per-step simulation state.

    Attributes:
        t: simulated time in s.
        x: vertex positions in m, shape ``(vertex_count, 3)``.
        v: vertex velocities in m/s, shape ``(vertex_count, 3)``.
        hinge_theta_bar: sheet name -> rest dihedral angles in rad, shape ``(hinge_count,)``
            (changed by bending plasticity).
        effector_pose: effector name -> pose ``[x y z qx qy qz qw]`` in ``world``.
        gripper_opening: effector name -> finger opening in m.
        contact_memory: collision side memory (see ``sim_core.collision``), or None before the
            first step.
        contact_force: contact + friction force ON each vertex at the end of the step, N,
            shape ``(vertex_count, 3)``.
        step_index: number of steps taken since the initial state.
        candidate_state: internal variables of optional missing-physics candidates
            (``sim_core.candidates``; e.g. the gel's relaxed deformation), empty when none.
    """

    t: float
    x: np.ndarray
    v: np.ndarray
    hinge_theta_bar: dict[str, np.ndarray] = field(default_factory=dict)
    effector_pose: dict[str, np.ndarray] = field(default_factory=dict)
    gripper_opening: dict[str, float] = field(default_factory=dict)
    contact_memory: Any = None
    contact_force: np.ndarray | None = None
    step_index: int = 0
    candidate_state: dict = field(default_factory=dict)

    def copy(self) -> "State":
        """Deep copy: an independent state (arrays, dicts of arrays and the contact memory duplicated).

        The fields are duplicated one by one (:func:`_duplicate`) rather than by ``copy.deepcopy``,
        which walks every object through its memo (50-70 us a state, against about 8 us; the Newton
        solver copies states per step). Aliasing between fields is not preserved.
        """
        out = object.__new__(type(self))  # same class, no __init__
        out.__dict__.update({name: _duplicate(value) for name, value in self.__dict__.items()})
        return out


def _duplicate(value: Any) -> Any:
    """An independent copy of a state field: arrays copied, dicts duplicated value by value, the contact
    memory through :meth:`~sim_core.collision.memory.CollisionMemory.copy`, anything else through
    ``copy.deepcopy``."""
    if isinstance(value, np.ndarray):
        return value.copy(order="K")
    if type(value) is dict:
        return {k: _duplicate(v) for k, v in value.items()}
    if value is None or isinstance(value, (float, int, str, bool)):
        return value
    if isinstance(value, CollisionMemory):
        return value.copy()
    return copy.deepcopy(value)
