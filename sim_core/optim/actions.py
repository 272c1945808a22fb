"""Actions of a task episode: per-step effector increments, their decoding from CMA-ES control
points, and the chain rule from commanded-target gradients to action gradients.

Action layout (the task contract, ``TaskSpec.action_layout``): per step, 6 values for each
``(effector, "pose")`` entry - a world-frame translation increment ``dx dy dz`` (m) and a
world-frame rotation-vector increment ``rx ry rz`` (rad) - and 1 value for each
``(effector, "gripper")`` entry - a finger-opening increment (m). The commanded target of step
``i`` (0-based) accumulates the increments from the effector's initial pose::

    p_i = p_{i-1} + d_i,    q_i = exp(r_i) * q_{i-1},    opening_i = opening_{i-1} + g_i,

with ``(p_{-1}, q_{-1})`` the initial pose and ``exp`` the rotation-vector quaternion
(:func:`~sim_core.transforms.quat_from_rotvec`), as :func:`sim_core.tasks.spec.apply_action` applies
them (it renormalises q, which changes q only along itself: the adjoint's derivative of a commanded
quaternion is tangent to the unit sphere, so :func:`action_gradient` needs no normalisation term).
The rate limiter of :mod:`sim_core.effector` then moves the effector toward that target.

Control points (ThinShellLab ``code/training/run_cmaes_all.py``, ``abs_step``): the horizon is cut
into ``K`` equal segments; control point ``k`` holds the per-step increment of every step of
segment ``k`` (a piecewise-constant velocity). The search coordinates are in the original's units:
one unit is ``0.0003 / 5 = 6e-5`` m per step of translation and ``0.01 / 5 = 2e-3`` rad per step of
rotation (the original decodes ``(x - 5) / sub_steps / scaling`` with
``scaling = 5 / (sub_steps 0.0003)``, i.e. ``(x - 5) 0.0003 / 5`` m per step, and 0.01 rad for the
angles); a gripper increment uses the translation unit. Here the coordinates are centred (``z = x - 5``,
start ``z = 0``, the zero trajectory). Decoded actions are clipped to the task's per-step bounds
``[action_low, action_high]`` (the original rescales each step's move to ``max_dist``,
``agent_trajopt.fix_action``; a box clip keeps every coordinate independent and the CMA-ES bounds
exact).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from sim_core.adjoint import Gradient
from sim_core.errors import ConfigError
from sim_core.transforms import quat_from_rotvec, quat_multiply

CMA_TRANSLATION_UNIT = 0.0003 / 5.0
"""m per step per control-point unit (ThinShellLab ``run_cmaes_all.py``)."""
CMA_ROTATION_UNIT = 0.01 / 5.0
"""rad per step per control-point unit (ThinShellLab ``run_cmaes_all.py``)."""
ROTVEC_FD_STEP = 1e-6
"""Central-difference step (rad) of the 3 -> 4 Jacobian of the rotation-vector quaternion (error
O(h^2) ~ 1e-12 relative)."""

LAYOUT_KINDS = ("pose", "gripper")


def layout_slices(layout: Sequence[tuple[str, str]]) -> list[tuple[str, str, slice]]:
    """Columns of each layout entry in an action row.

    Args:
        layout: ``((effector, "pose" | "gripper"), ...)``.

    Returns:
        ``[(effector, kind, slice), ...]``; a pose takes 6 columns, a gripper 1.

    Raises:
        ConfigError: an unknown kind or an entry repeated.
    """
    out, start, seen = [], 0, set()
    for entry in layout:
        if len(entry) != 2 or entry[1] not in LAYOUT_KINDS:
            raise ConfigError(f"action layout entry {entry!r}: expected (effector, 'pose' | 'gripper')")
        if tuple(entry) in seen:
            raise ConfigError(f"action layout entry {entry!r} appears twice")
        seen.add(tuple(entry))
        width = 6 if entry[1] == "pose" else 1
        out.append((str(entry[0]), entry[1], slice(start, start + width)))
        start += width
    return out


def action_units(layout: Sequence[tuple[str, str]]) -> np.ndarray:
    """Physical size of one control-point unit per action column, shape ``(action_dim,)`` (m or rad)."""
    units = []
    for _, kind, _ in layout_slices(layout):
        units += [CMA_TRANSLATION_UNIT] * 3 + [CMA_ROTATION_UNIT] * 3 if kind == "pose" else [CMA_TRANSLATION_UNIT]
    return np.array(units, dtype=float)


@dataclass(frozen=True)
class ControlPointDecoder:
    """Piecewise-constant per-step actions from ``control_points`` control points (module docstring).

    Attributes:
        horizon: steps per episode T.
        control_points: K, 1 <= K <= T.
        units: physical size of one unit per action column, shape ``(action_dim,)``.
        low, high: per-step action bounds, shape ``(action_dim,)`` (m, rad).
    """

    horizon: int
    control_points: int
    units: np.ndarray
    low: np.ndarray
    high: np.ndarray

    def __post_init__(self) -> None:
        if not 1 <= int(self.control_points) <= int(self.horizon):
            raise ConfigError(f"control_points must be in 1..horizon={self.horizon}, got {self.control_points}")
        if not (self.units.shape == self.low.shape == self.high.shape) or np.any(self.low > self.high):
            raise ConfigError(f"action bounds: low {self.low.tolist()} / high {self.high.tolist()} do not match the units")

    @classmethod
    def for_task(cls, task, horizon: int | None = None, control_points: int | None = None) -> "ControlPointDecoder":
        """The decoder of a task (``action_layout``, bounds, ``control_points``; optional overrides)."""
        T = int(horizon if horizon is not None else task.horizon)
        K = int(control_points if control_points is not None else task.control_points)
        return cls(T, min(K, T), action_units(task.action_layout), np.asarray(task.action_low, dtype=float),
                   np.asarray(task.action_high, dtype=float))

    @property
    def action_dim(self) -> int:
        """Action columns per step."""
        return int(self.units.shape[0])

    @property
    def dim(self) -> int:
        """Search dimension ``K * action_dim``."""
        return self.control_points * self.action_dim

    def segment_of_step(self) -> np.ndarray:
        """Control point of each step, shape ``(T,)`` (equal segments, the last ones one step longer
        when K does not divide T)."""
        return (np.arange(self.horizon) * self.control_points) // self.horizon

    def decode(self, z: np.ndarray, base: np.ndarray | None = None) -> np.ndarray:
        """Per-step actions of search coordinates ``z``.

        Args:
            z: shape ``(K * action_dim,)``, control point-major.
            base: per-step actions the control points are added to, shape ``(T, action_dim)``
                (a warm start: ``z = 0`` decodes to ``base``); None: zero.

        Returns:
            actions ``base + piecewise-constant(z)``, shape ``(T, action_dim)``, clipped to the bounds.

        Raises:
            ConfigError: wrong size or non-finite coordinates, or a base of the wrong shape.
        """
        z = np.asarray(z, dtype=float)
        if z.shape != (self.dim,) or not np.all(np.isfinite(z)):
            raise ConfigError(f"control points: expected {self.dim} finite values, got shape {z.shape}")
        actions = (z.reshape(self.control_points, self.action_dim) * self.units)[self.segment_of_step()]
        if base is not None:
            base = np.asarray(base, dtype=float)
            if base.shape != actions.shape:
                raise ConfigError(f"control points: base actions have shape {base.shape}, expected {actions.shape}")
            actions = actions + base
        return np.clip(actions, self.low, self.high)

    def bounds(self, warm: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Box bounds of the search coordinates, each shape ``(K * action_dim,)``.

        Args:
            warm: the coordinates are added to base actions within the action bounds
                (:meth:`decode`'s ``base``): the box is the span ``+-(high - low)`` that can move any
                base action to any bounded action; otherwise the box that keeps every decoded action
                within the action bounds.
        """
        if warm:
            span = (self.high - self.low) / self.units
            return np.tile(-span, self.control_points), np.tile(span, self.control_points)
        return np.tile(self.low / self.units, self.control_points), np.tile(self.high / self.units, self.control_points)


def check_actions(actions: np.ndarray, horizon: int, action_dim: int, where: str = "actions") -> np.ndarray:
    """``actions`` as a float array of shape ``(horizon, action_dim)``.

    Raises:
        ConfigError: wrong shape or non-finite values (naming the first bad step).
    """
    a = np.asarray(actions, dtype=float)
    if a.shape != (horizon, action_dim):
        raise ConfigError(f"{where}: expected shape {(horizon, action_dim)}, got {a.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
    if bad.size:
        raise ConfigError(f"{where}: step {int(bad[0])} is not finite: {a[bad[0]].tolist()}")
    return a


def _left_multiplication(e: np.ndarray) -> np.ndarray:
    """Matrix of ``q -> e * q`` (exact: the product is linear in q), shape ``(4, 4)``."""
    return np.stack([quat_multiply(e, col) for col in np.eye(4)], axis=1)


def _rotvec_product_jacobian(r: np.ndarray, q: np.ndarray) -> np.ndarray:
    """d(exp(r) * q)/dr, shape ``(4, 3)``: right multiplication by q (exact) times the central
    difference of ``exp`` (step :data:`ROTVEC_FD_STEP`)."""
    right = np.stack([quat_multiply(col, q) for col in np.eye(4)], axis=1)
    d_exp = np.empty((4, 3))
    for j in range(3):
        h = np.zeros(3)
        h[j] = ROTVEC_FD_STEP
        d_exp[:, j] = (quat_from_rotvec(r + h) - quat_from_rotvec(r - h)) / (2.0 * ROTVEC_FD_STEP)
    return right @ d_exp


def action_gradient(actions: np.ndarray, layout: Sequence[tuple[str, str]], initial_pose: dict[str, np.ndarray],
                    gradient: Gradient) -> np.ndarray:
    """dL/d(actions) from the adjoint's derivatives w.r.t. the commanded targets (reverse chain rule).

    Args:
        actions: the actions of the rollout, shape ``(T, action_dim)``.
        layout: the action layout.
        initial_pose: effector -> initial pose ``[x y z qx qy qz qw]``.
        gradient: :func:`sim_core.adjoint.rollout_gradient` of that rollout (``controls`` and
            ``gripper`` per step).

    Returns:
        shape ``(T, action_dim)``.

    Raises:
        ConfigError: the gradient covers a different number of steps.
    """
    actions = np.asarray(actions, dtype=float)
    T = actions.shape[0]
    if len(gradient.controls) != T:
        raise ConfigError(f"action_gradient: {len(gradient.controls)} steps of gradient for {T} actions")
    out = np.zeros_like(actions)
    for eff, kind, cols in layout_slices(layout):
        if kind == "gripper":
            g = np.array([gradient.gripper[i].get(eff, 0.0) for i in range(T)])
            out[:, cols.start] = np.cumsum(g[::-1])[::-1]
            continue
        a = actions[:, cols]
        # forward pass again for the quaternion before each step
        q_prev = np.empty((T, 4))
        q = np.array(initial_pose[eff][3:7], dtype=float)
        for i in range(T):
            q_prev[i] = q
            q = quat_multiply(quat_from_rotvec(a[i, 3:6]), q)
        carry_p, carry_q = np.zeros(3), np.zeros(4)
        for i in range(T - 1, -1, -1):
            g = gradient.controls[i].get(eff, np.zeros(7))
            gp, gq = g[:3] + carry_p, g[3:] + carry_q
            out[i, cols.start:cols.start + 3] = gp
            out[i, cols.start + 3:cols.stop] = _rotvec_product_jacobian(a[i, 3:6], q_prev[i]).T @ gq
            carry_p = gp
            carry_q = _left_multiplication(quat_from_rotvec(a[i, 3:6])).T @ gq
    return out
