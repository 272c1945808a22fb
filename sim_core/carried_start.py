"""The first Newton iterate of a step with the effectors' solid bodies carried along
(``SolverConfig.carried_start``).

An effector drives some vertices of a body (a tactile pad's back face, a finger's mount) along a
rigid frame; the body's other vertices start the step's Newton iterations at their last positions
``x^n`` by default, so the first iterations only bring the body along with the frame. For a solid
(a gel pad) in free space the motion over one step is close to the frame's own: the carried start
moves its free vertices by the frame's rigid motion over the step,

    x_0 = R_1 (R_0^T (x^n - t_0) + s (o_1 - o_0) / 2 a) + t_1,

with ``(t_0, R_0)`` and ``(t_1, R_1)`` the effector pose at the start and end of the step
(:meth:`sim_core.solver.NewtonSolver.boundary`), and for a gripper finger ``s`` its side (+1/-1),
``o`` the opening and ``a`` the finger axis (:func:`sim_core.effector.driven_positions`, whose driven
vertices follow the same map). Newton then starts from a body that is where the frame puts it, with
only its inertial lag left to solve: on the bundled press_slide scene a 0.2 mm move of the pad in
the air takes 1 Newton iteration instead of 3 (docs/benchmarks_log.md, session 37, 24tail). The
step's minimiser is the same; the accepted iterate differs from the one reached from ``x^n`` by less
than the Newton tolerance (``tol_velocity * dt``).

Only a body clear of everything is carried (:func:`clear_of_contact`): carried into a contact, a
pad's surface would start the step pressed into (or, for a thin sheet, through) what it touches,
a different start for the penalty contact than the one the recorded and replayed steps take. Sheets
are not carried (a sheet held at an edge bends rather than follows the frame), nor a solid driven by
two effectors, nor one holding both fingers of a gripper while the opening changes (with the opening
held, both fingers follow the frame).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from sim_core.model import Model
from sim_core.transforms import quat_to_matrix

CARRIED_KINDS = ("solid",)
"""Body kinds :func:`carry_driven_bodies` moves with their effector."""


def clear_of_contact(model: Model, body: str, x_n: np.ndarray, v_n: np.ndarray, dt: float, move: float,
                     x_target: np.ndarray, fixed: np.ndarray) -> bool:
    """Whether ``body`` stays out of contact reach during a step in which it moves by at most ``move``.

    The body's bounding box at ``x^n``, grown by ``move`` plus the contact search radius
    (``contact.eps + contact.candidate_margin``), must keep off every plane and must not meet the
    bounding box of any other body grown by that body's own possible move in the step (its largest
    ``dt |v^n|`` plus its largest Dirichlet jump ``|x_target - x^n|``; a sphere's radius).

    Args:
        model: the model.
        body: the carried body's name.
        x_n, v_n: positions (m) and velocities (m/s) at the start of the step, shape ``(n, 3)``.
        dt: the step, s.
        move: the largest move of the body's vertices by the carry, m.
        x_target, fixed: the step's Dirichlet targets ``(n, 3)`` m and mask ``(n,)``.

    Returns:
        True when no contact pair or plane contact can involve the body in the step.
    """
    b = model.bodies[body]
    reach = float(model.contact.eps + model.contact.candidate_margin) + move
    xb = x_n[b.vertex_start:b.vertex_stop]
    low, high = xb.min(axis=0) - reach, xb.max(axis=0) + reach
    for plane in model.planes.values():
        normal = np.asarray(plane.normal, dtype=float)
        if float((xb @ normal).min()) - plane.offset <= reach:
            return False
    for other in model.bodies.values():
        if other.name == body:
            continue
        s = slice(other.vertex_start, other.vertex_stop)
        xo = x_n[s]
        grow = dt * float(np.sqrt(np.max(np.sum(v_n[s] ** 2, axis=1))))
        jumps = x_target[s][fixed[s]] - xo[fixed[s]]
        if len(jumps):
            grow += float(np.sqrt(np.max(np.sum(jumps ** 2, axis=1))))
        if other.kind == "sphere":
            grow += float(other.material["radius"])
        if np.all(xo.max(axis=0) + grow >= low) and np.all(xo.min(axis=0) - grow <= high):
            return False
    return True


def carry_driven_bodies(model: Model, x_n: np.ndarray, v_n: np.ndarray, dt: float,
                        poses_n: Mapping[str, np.ndarray], openings_n: Mapping[str, float],
                        poses: Mapping[str, np.ndarray], openings: Mapping[str, float],
                        fixed: np.ndarray, x_target: np.ndarray, x: np.ndarray) -> list[str]:
    """Move the free vertices of every effector-driven solid clear of contact (:func:`clear_of_contact`)
    in ``x`` by its effector's rigid motion over the step (module docstring); the other vertices of
    ``x`` are left as they are.

    Args:
        model: the model (bodies, effectors, planes, contact settings).
        x_n, v_n: positions (m) and velocities (m/s) at the start of the step, shape ``(n, 3)``.
        dt: the step, s.
        poses_n, openings_n: effector poses ``[x y z qx qy qz qw]`` and gripper openings (m) at the
            start of the step (``State.effector_pose``, ``State.gripper_opening``; an opening
            absent there is the effector's ``initial_opening``).
        poses, openings: the same at the end of the step (the step's Dirichlet data).
        fixed: the step's Dirichlet mask, shape ``(n,)`` bool: these vertices are not moved.
        x_target: the step's Dirichlet targets, shape ``(n, 3)``, m.
        x: the first iterate, shape ``(n, 3)``, written in place.

    Returns:
        the names of the bodies moved (none for an effector whose pose and opening did not change).
    """
    bodies = [b for b in model.bodies.values() if b.kind in CARRIED_KINDS]
    owners: dict[str, list[str]] = {b.name: [] for b in bodies}
    for name, eff in model.effectors.items():
        for b in bodies:
            if np.any((eff.vertices >= b.vertex_start) & (eff.vertices < b.vertex_stop)):
                owners[b.name].append(name)
    moved = []
    for b in bodies:
        if len(owners[b.name]) != 1:
            continue
        name = owners[b.name][0]
        eff = model.effectors[name]
        o0 = float(openings_n.get(name, eff.initial_opening))
        o1 = float(openings.get(name, o0))
        pose0, pose1 = np.asarray(poses_n[name], dtype=float), np.asarray(poses[name], dtype=float)
        if o1 == o0 and np.array_equal(pose0, pose1):
            continue
        shift = np.zeros(3)
        if eff.finger_sign is not None and o1 != o0:
            inside = (eff.vertices >= b.vertex_start) & (eff.vertices < b.vertex_stop)
            signs = np.unique(np.asarray(eff.finger_sign)[inside])
            if signs.size != 1:  # both fingers in one body, opening or closing: not one rigid motion
                continue
            shift = float(signs[0]) * 0.5 * (o1 - o0) * np.asarray(eff.finger_axis, dtype=float)
        v = np.arange(b.vertex_start, b.vertex_stop)
        v = v[~fixed[v]]
        if v.size == 0:
            continue
        R0, R1 = quat_to_matrix(pose0[3:7]), quat_to_matrix(pose1[3:7])
        carried = ((x_n[v] - pose0[:3]) @ R0 + shift) @ R1.T + pose1[:3]
        move = float(np.sqrt(np.max(np.sum((carried - x_n[v]) ** 2, axis=1))))
        if not clear_of_contact(model, b.name, x_n, v_n, dt, move, x_target, fixed):
            continue
        x[v] = carried
        moved.append(b.name)
    return moved
