"""The Dirichlet data of a lockstep step for every copy at once: the rate-limited effector poses and their
driven vertex positions, vectorised over the ``B`` copies of each scene effector.

:meth:`sim_core.solver.NewtonSolver.boundary` walks the stacked model's effectors one by one (``B`` per scene
effector, ``<name>#<copy>``): 130 ms a step at 1024 Forming copies on the H200 host (docs/benchmarks_log.md,
session 40, 28lock). :class:`StackedBoundary` gives the same Dirichlet data with one NumPy expression per
quantity over the copies: the pose limit of :func:`sim_core.effector.limit_pose_step` (translation clipped to
``max_translation_per_step``; the rotation ``q_t q_c^-1`` as a rotation vector clipped to
``max_rotation_per_step``) and the driven positions of :func:`sim_core.effector.driven_positions`
(``x_i = R (p_i + s_i (opening - opening_0) / 2 a) + t``), equal to theirs to round-off.
"""

from __future__ import annotations

import numpy as np

from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.state import State
from sim_core.transforms import quat_to_matrix

_ROTVEC_SMALL = 1e-12
"""Below this rotation angle (rad) or quaternion vector norm the rotation vector maps to the quaternion by its
first-order series (the threshold of :func:`sim_core.transforms.quat_from_rotvec` / ``quat_to_rotvec``)."""


def quat_multiply_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a_i * b_i`` of quaternions (x y z w), shapes ``(B, 4)`` -> ``(B, 4)``
    (:func:`sim_core.transforms.quat_multiply` row by row)."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=1)


def rotvec_rows(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (axis * angle, angle in [0, pi], rad) of unit quaternions ``q`` ``(B, 4)`` -> ``(B, 3)``
    (:func:`sim_core.transforms.quat_to_rotvec` row by row)."""
    q = np.where(q[:, 3:4] < 0, -q, q)
    s = np.sqrt(np.einsum("ij,ij->i", q[:, :3], q[:, :3]))
    small = s < _ROTVEC_SMALL
    angle = 2.0 * np.arctan2(s, q[:, 3])
    scale = np.where(small, 2.0, angle / np.where(small, 1.0, s))
    return q[:, :3] * scale[:, None]


def quat_from_rotvec_rows(r: np.ndarray) -> np.ndarray:
    """Quaternions (x y z w) of rotation vectors ``r`` ``(B, 3)`` (rad) -> ``(B, 4)``
    (:func:`sim_core.transforms.quat_from_rotvec` row by row)."""
    angle = np.sqrt(np.einsum("ij,ij->i", r, r))
    small = angle < _ROTVEC_SMALL
    safe = np.where(small, 1.0, angle)
    series = np.concatenate([0.5 * r, np.ones((len(r), 1))], axis=1) / np.sqrt(1 + 0.25 * angle ** 2)[:, None]
    exact = np.concatenate([r / safe[:, None] * np.sin(0.5 * angle)[:, None], np.cos(0.5 * angle)[:, None]], axis=1)
    return np.where(small[:, None], series, exact)


def limit_pose_steps(current: np.ndarray, target: np.ndarray, max_translation: float,
                     max_rotation: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sim_core.effector.limit_pose_step` of ``B`` poses at once: each pose ``current[i]`` moved toward
    ``target[i]`` (both ``[x y z qx qy qz qw]``, shape ``(B, 7)``) by at most ``max_translation`` (m) and
    ``max_rotation`` (rad).

    Returns:
        ``(poses (B, 7), limited (B,) bool)``.

    Raises:
        ConfigError: a non-finite target or one whose quaternion is not of unit norm (within 1e-3), naming the
            first such row.
    """
    target = np.asarray(target, dtype=float)
    norm_t = np.sqrt(np.einsum("ij,ij->i", target[:, 3:], target[:, 3:]))
    bad = ~np.all(np.isfinite(target), axis=1) | ~(np.abs(norm_t - 1.0) <= 1e-3)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ConfigError(f"effector target pose {i} must be 7 finite numbers with a unit quaternion, got "
                          f"{target[i].tolist()}")
    q_t = target[:, 3:] / norm_t[:, None]
    p_c, q_c = current[:, :3], current[:, 3:]
    dp = target[:, :3] - p_c
    dist = np.sqrt(np.einsum("ij,ij->i", dp, dp))
    moved = dist > max_translation
    dp = dp * np.where(moved, max_translation / np.where(moved, dist, 1.0), 1.0)[:, None]
    r = rotvec_rows(quat_multiply_rows(q_t, q_c * np.array([-1.0, -1.0, -1.0, 1.0])))
    ang = np.sqrt(np.einsum("ij,ij->i", r, r))
    turned = ang > max_rotation
    r = r * np.where(turned, max_rotation / np.where(turned, ang, 1.0), 1.0)[:, None]
    q_new = np.where(turned[:, None], quat_multiply_rows(quat_from_rotvec_rows(r), q_c), q_t)
    q_new /= np.sqrt(np.einsum("ij,ij->i", q_new, q_new))[:, None]
    return np.concatenate([p_c + dp, q_new], axis=1), moved | turned


class StackedBoundary:
    """:meth:`sim_core.solver.NewtonSolver.boundary` of a stacked model whose effectors are the scene's ``names`` per
    copy (``<name>#<copy>``, :mod:`sim_core.batch.stacked`), vectorised over the ``copies`` (module docstring), with
    what does not change between steps made once: each scene effector's stacked names and vertices, and the fixed
    mask (the static one and every effector's vertices: the same read-only array at every call while the model's
    ``vertex_fixed`` is unchanged). A copy without a pose target keeps its pose.

    Args:
        model: the stacked model.
        copies: the number of copies ``B``.
        names: the scene's effector names.
    """

    def __init__(self, model, copies: int, names: list[str]) -> None:
        self.model, self.copies = model, copies
        # per scene effector: (stacked names, copy 0's effector, their vertices (B k,), and those vertices' DoFs
        # (3 B k,): the driven positions are written through the flat array, one element an index; NumPy 2.4's row
        # indexing of an (N, 3) array by an index array is ~10x slower than that (18 against 0.7 ms for Forming's
        # 123,904 driven vertices at B = 1024 on the CI's VM; NumPy 2.5 on the H200 host: 1.45 against 0.85 ms)
        self._effectors = []
        for name in names:
            keys = [f"{name}#{i}" for i in range(copies)]
            vertices = np.stack([model.effectors[k].vertices for k in keys]).ravel()
            dofs = (3 * vertices[:, None] + np.arange(3)).ravel()
            self._effectors.append((keys, model.effectors[keys[0]], vertices, dofs))
        self._static: np.ndarray | None = None  # the model's vertex_fixed the mask was made of
        self._fixed: np.ndarray | None = None

    def fixed(self) -> np.ndarray:
        """The fixed-vertex mask ``(N,)`` bool (read-only): the model's ``vertex_fixed`` and every effector's
        vertices; the same array object while ``vertex_fixed`` holds the same values."""
        static = self.model.vertex_fixed
        if self._fixed is None or not np.array_equal(static, self._static):
            fixed = static.copy()
            for _, _, vertices, _ in self._effectors:
                fixed[vertices] = True
            fixed.flags.writeable = False
            self._static, self._fixed = static.copy(), fixed
        return self._fixed

    def __call__(self, state: State, control: Control) -> tuple[np.ndarray, np.ndarray, dict, dict, list[str]]:
        """The Dirichlet data at ``state`` under ``control``.

        Returns:
            ``(fixed (N,) bool (read-only, :meth:`fixed`), x_target (N, 3) m, poses, openings,
            limited_effector_names)`` as :meth:`~sim_core.solver.NewtonSolver.boundary` returns them.

        Raises:
            ConfigError: a copy's target pose is not finite or its quaternion not of unit norm.
        """
        x_target = state.x.copy()
        poses, openings, limited = {}, {}, []
        for keys, ref, _, dofs in self._effectors:
            pose = np.array([state.effector_pose[k] for k in keys], dtype=float)
            aimed = np.array([k in control.effector_pose_target for k in keys])
            if aimed.any():
                targets = np.array([control.effector_pose_target[k] for k in np.asarray(keys)[aimed]], dtype=float)
                pose[aimed], was_limited = limit_pose_steps(pose[aimed], targets.reshape(-1, 7),
                                                            ref.max_translation_per_step, ref.max_rotation_per_step)
                limited += [k for k, hit in zip(np.asarray(keys)[aimed], was_limited) if hit]
            opening = np.array([float(control.gripper_target.get(k, state.gripper_opening.get(k, ref.initial_opening)))
                                for k in keys])
            points = np.asarray(ref.local_points, dtype=float)
            local = np.broadcast_to(points, (self.copies,) + points.shape)
            if ref.finger_sign is not None:
                local = local + (0.5 * (opening - ref.initial_opening))[:, None, None] * np.outer(
                    ref.finger_sign, ref.finger_axis)[None]
            driven = np.matmul(local, np.swapaxes(quat_to_matrix(pose[:, 3:7]), 1, 2)) + pose[:, None, :3]
            x_target.reshape(-1)[dofs] = driven.reshape(-1)  # (x_target: a new C-contiguous array, the view its)
            poses.update(zip(keys, pose))
            openings.update(zip(keys, opening.tolist()))
        return self.fixed(), x_target, poses, openings, limited
