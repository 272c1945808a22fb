"""A step that changed nothing, kept so that the next identical step can repeat it
(``SolverConfig.repeat_fixed_points``): the record and the bitwise comparisons of states."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_core.collision.memory import CollisionMemory
from sim_core.state import State
from sim_core.step_info import StepInfo


@dataclass
class FixedPoint:
    """A step that left its state unchanged, and what it depended on (:meth:`sim_core.solver.NewtonSolver._repeat_fixed_point`).

    Attributes:
        inputs: the model revision, ``dt``, gravity, damping, friction table and solver settings of the step.
        state: the step's output (= its input but for ``t``, ``step_index``), a copy.
        fixed, x_target, poses, openings, limited: the step's Dirichlet data (:meth:`NewtonSolver.boundary`).
        info: how the step ended.
    """

    inputs: tuple
    state: State
    fixed: np.ndarray
    x_target: np.ndarray
    poses: dict
    openings: dict
    limited: list
    info: StepInfo


def same_resting_state(a: State, b: State, *, with_velocity: bool) -> bool:
    """Whether ``a`` and ``b`` are bitwise the same state: positions, effector poses, gripper
    openings, rest angles and contact memory (both present), and velocities when ``with_velocity``."""
    return (a.contact_memory is not None and b.contact_memory is not None
            and same_array(a.x, b.x) and (not with_velocity or same_array(a.v, b.v))
            and same_arrays(a.effector_pose, b.effector_pose) and a.gripper_opening == b.gripper_opening
            and same_arrays(a.hinge_theta_bar, b.hinge_theta_bar)
            and same_memory(a.contact_memory, b.contact_memory))


def same_array(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether ``a`` and ``b`` have the same shape, dtype and bytes (bitwise equal)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def same_arrays(a: dict, b: dict) -> bool:
    """Whether two dicts of arrays have the same keys and bitwise equal arrays (:func:`same_array`)."""
    return a.keys() == b.keys() and all(same_array(a[k], b[k]) for k in a)


def same_memory(a: CollisionMemory, b: CollisionMemory) -> bool:
    """Whether two contact side memories hold the same pairs and sides."""
    return a.vertex_triangle == b.vertex_triangle and a.edge_edge == b.edge_edge


def copy_state_into(src: State, dst: State) -> None:
    """Set every attribute of ``dst`` to ``src``'s (a solver writes only its ``state_out``)."""
    for k, v in vars(src).items():
        setattr(dst, k, v)
