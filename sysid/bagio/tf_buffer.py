"""A TF buffer read from a recording's ``/tf_static`` and ``/tf`` (tf2_msgs/TFMessage), without ROS.

Every edge ``parent -> child`` keeps its own samples: a static edge one transform valid at all times,
a dynamic edge a series of stamped transforms (header stamps, int64 ns). A lookup at time t
interpolates each dynamic edge of the chain on its own (position linear, rotation spherical-linear:
lerp + slerp, as tf2 does) and composes the chain. Frames form a tree (one parent per child, as tf2
requires); a child given two parents is an error.

Poses are ``[x y z qx qy qz qw]`` (m, unit quaternion), arrays ``(N, 7)``; a pose of frame ``c`` in
frame ``p`` maps points of ``c`` into ``p``: ``x_p = R x_c + t`` (REP 103, tf2's ``lookupTransform(p, c)``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim_core.errors import BagReadError


# ------------------------------------------------------------------------------ pose algebra
def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions (x y z w), shapes ``(..., 4)`` broadcast."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors ``v (..., 3)`` rotated by unit quaternions ``q (..., 4)``: ``v + 2 w (u x v) + 2 u x (u x v)``."""
    q = np.asarray(q, dtype=np.float64)
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion), ``(..., 4)``."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def pose_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a * b`` of poses ``(..., 7)``: frame b given in frame a, a given in its parent -> b in a's parent."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return np.concatenate([a[..., :3] + quat_rotate(a[..., 3:], b[..., :3]), quat_mul(a[..., 3:], b[..., 3:])],
                          axis=-1)


def pose_inverse(a: np.ndarray) -> np.ndarray:
    """Inverse pose ``(..., 7)``: ``[-R^T t, q*]``."""
    a = np.asarray(a, dtype=np.float64)
    qi = quat_conj(a[..., 3:])
    return np.concatenate([-quat_rotate(qi, a[..., :3]), qi], axis=-1)


def quat_slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Spherical-linear interpolation ``(N, 4)`` at weights ``w (N,)`` in [0, 1], shortest arc.

    Exactly ``q0`` at ``w = 0`` and ``+-q1`` at ``w = 1``; normalised lerp where the two are within
    1e-6 rad (sin of the half angle vanishes).
    """
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)[:, None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    small = sin < 1e-6
    safe = np.where(small, 1.0, sin)
    a = np.where(small, 1.0 - w, np.sin((1.0 - w) * theta) / safe)
    b = np.where(small, w, np.sin(w * theta) / safe)
    out = a * q0 + b * q1
    out = np.where(w == 0.0, q0, np.where(w == 1.0, q1, out))
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def wrench_transform(pose_ab: np.ndarray, wrench_b: np.ndarray) -> np.ndarray:
    """A wrench given in frame b about b's origin, expressed in frame a about a's origin.

    ``F_a = R F_b``, ``tau_a = R tau_b + t x F_a`` with ``pose_ab = [t, q]`` the pose of b in a (the
    moment moved with the lever arm ``t``, the position of b's origin in a).

    Args:
        pose_ab: ``(..., 7)``.
        wrench_b: ``(..., 6)`` [Fx Fy Fz Tx Ty Tz] (N, N m).

    Returns:
        ``(..., 6)``.
    """
    pose_ab, wrench_b = np.asarray(pose_ab, dtype=np.float64), np.asarray(wrench_b, dtype=np.float64)
    f = quat_rotate(pose_ab[..., 3:], wrench_b[..., :3])
    tau = quat_rotate(pose_ab[..., 3:], wrench_b[..., 3:]) + np.cross(pose_ab[..., :3], f)
    return np.concatenate([f, tau], axis=-1)


def hemisphere_continuous(pose: np.ndarray) -> np.ndarray:
    """Poses ``(N, 7)`` with each quaternion's sign chosen to agree with the previous one (q and -q are one rotation)."""
    pose = np.array(pose, dtype=np.float64)
    q = pose[:, 3:]
    flip = np.concatenate([[1.0], np.sign(np.einsum("ij,ij->i", q[1:], q[:-1]))])
    flip[flip == 0] = 1.0
    pose[:, 3:] = q * np.cumprod(flip)[:, None]
    return pose


# ----------------------------------------------------------------------------------- buffer
@dataclass
class _Edge:
    parent: str
    static: bool
    t_ns: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)


class TFBuffer:
    """Transforms of a recording, per edge, with interpolation and chain composition.

    Built with :meth:`add` (one call per ``geometry_msgs/TransformStamped``), then :meth:`lookup`.
    ``source`` (the bag path) names the recording in every error.
    """

    def __init__(self, source: str) -> None:
        self.source = source
        self._edges: dict[str, _Edge] = {}
        self._arrays: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def add(self, parent: str, child: str, t_ns: int, pose7: np.ndarray, static: bool) -> None:
        """One transform: the pose of ``child`` in ``parent`` at ``t_ns`` (static: valid at all times).

        Raises:
            BagReadError: ``child`` already has another parent, or a non-finite / zero quaternion.
        """
        parent, child = parent.lstrip("/"), child.lstrip("/")
        pose7 = np.asarray(pose7, dtype=np.float64)
        norm = float(np.linalg.norm(pose7[3:]))
        if not np.all(np.isfinite(pose7)) or norm < 1e-9:
            raise BagReadError(f"{self.source}: transform {parent} -> {child} at {t_ns} ns is not finite or has a "
                               "zero quaternion")
        pose7 = np.concatenate([pose7[:3], pose7[3:] / norm])
        edge = self._edges.get(child)
        if edge is None:
            edge = self._edges[child] = _Edge(parent, static)
        elif edge.parent != parent:
            raise BagReadError(f"{self.source}: frame {child} has two parents in the TF tree ({edge.parent} and "
                               f"{parent})")
        if static:  # a re-published static transform replaces the previous one
            edge.static, edge.t_ns, edge.poses = True, [0], [pose7]
        elif not edge.static:
            edge.t_ns.append(int(t_ns))
            edge.poses.append(pose7)
        self._arrays.pop(child, None)

    @property
    def frames(self) -> tuple[str, ...]:
        """Every frame named in the buffer (children and parents), sorted."""
        return tuple(sorted(set(self._edges) | {e.parent for e in self._edges.values()}))

    def _path_to_root(self, frame: str) -> list[str]:
        path = [frame]
        while path[-1] in self._edges:
            path.append(self._edges[path[-1]].parent)
            if len(path) > len(self._edges) + 1:
                raise BagReadError(f"{self.source}: the TF tree has a cycle through {frame}")
        return path

    def chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """Frames from ``source`` up to the common ancestor, and from ``target`` up to it.

        Raises:
            BagReadError: a frame is unknown or the two are not connected (names both and the frames known).
        """
        target, source = target.lstrip("/"), source.lstrip("/")
        for f in (target, source):
            if f not in self.frames:
                raise BagReadError(f"{self.source}: frame {f} is not in /tf or /tf_static (frames: "
                                   f"{', '.join(self.frames) or 'none'})")
        up_s, up_t = self._path_to_root(source), self._path_to_root(target)
        common = next((f for f in up_s if f in up_t), None)
        if common is None:
            raise BagReadError(f"{self.source}: frames {target} and {source} are not connected in the TF tree")
        return up_s[: up_s.index(common) + 1], up_t[: up_t.index(common) + 1]

    def _edge_arrays(self, child: str) -> tuple[np.ndarray, np.ndarray]:
        cached = self._arrays.get(child)
        if cached is None:
            edge = self._edges[child]
            t = np.asarray(edge.t_ns, dtype=np.int64)
            poses = np.stack(edge.poses)
            order = np.argsort(t, kind="stable")
            t, poses = t[order], hemisphere_continuous(poses[order])
            keep = np.concatenate([[True], np.diff(t) > 0])  # a repeated stamp: the first transform
            cached = self._arrays[child] = (t[keep], poses[keep])
        return cached

    def edge_stamps(self, child: str) -> np.ndarray | None:
        """Stamps ``(N,)`` of the dynamic edge into ``child``; None for a static edge."""
        edge = self._edges[child.lstrip("/")]
        return None if edge.static else self._edge_arrays(child.lstrip("/"))[0]

    def _edge_at(self, child: str, t_ns: np.ndarray) -> np.ndarray:
        """Pose of ``child`` in its parent at ``t_ns (N,)`` (lerp + slerp between the bracketing samples)."""
        t, poses = self._edge_arrays(child)
        if self._edges[child].static or t.shape[0] == 1:
            if not self._edges[child].static and np.any(t_ns != t[0]):
                raise BagReadError(f"{self.source}: dynamic transform {self._edges[child].parent} -> {child} has one "
                                   f"sample (at {t[0]} ns); it cannot be looked up at other times")
            return np.repeat(poses[:1], t_ns.shape[0], axis=0)
        outside = (t_ns < t[0]) | (t_ns > t[-1])
        if outside.any():
            bad = int(t_ns[outside][0])
            raise BagReadError(f"{self.source}: transform {self._edges[child].parent} -> {child} is needed at {bad} ns, "
                               f"outside its samples [{t[0]}, {t[-1]}] ns (extrapolation)")
        i = np.clip(np.searchsorted(t, t_ns, side="right") - 1, 0, t.shape[0] - 2)
        w = (t_ns - t[i]).astype(np.float64) / (t[i + 1] - t[i]).astype(np.float64)
        pos = (1.0 - w)[:, None] * poses[i, :3] + w[:, None] * poses[i + 1, :3]
        pos = np.where((w == 0.0)[:, None], poses[i, :3], np.where((w == 1.0)[:, None], poses[i + 1, :3], pos))
        return np.concatenate([pos, quat_slerp(poses[i, 3:], poses[i + 1, 3:], w)], axis=1)

    def lookup(self, target: str, source: str, t_ns: np.ndarray) -> np.ndarray:
        """Pose of frame ``source`` in frame ``target`` at stamps ``t_ns (N,)`` -> ``(N, 7)``.

        Raises:
            BagReadError: unknown or unconnected frames, or a time outside a dynamic edge's samples.
        """
        t_ns = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        up_s, up_t = self.chain(target, source)
        identity = np.tile(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]), (t_ns.shape[0], 1))
        common_T_source = identity
        for child in reversed(up_s[:-1]):  # from the common ancestor down to source
            common_T_source = pose_compose(common_T_source, self._edge_at(child, t_ns))
        common_T_target = identity
        for child in reversed(up_t[:-1]):
            common_T_target = pose_compose(common_T_target, self._edge_at(child, t_ns))
        return pose_compose(pose_inverse(common_T_target), common_T_source)

    def dynamic_stamps(self, target: str, source: str) -> np.ndarray:
        """The stamps at which the chain ``target`` <-> ``source`` has a sample: the union of its dynamic
        edges' stamps inside the span all of them cover (empty when the chain is static)."""
        up_s, up_t = self.chain(target, source)
        stamps = [self.edge_stamps(c) for c in up_s[:-1] + up_t[:-1]]
        stamps = [s for s in stamps if s is not None]
        if not stamps:
            return np.zeros(0, dtype=np.int64)
        lo, hi = max(int(s[0]) for s in stamps), min(int(s[-1]) for s in stamps)
        union = np.unique(np.concatenate(stamps))
        return union[(union >= lo) & (union <= hi)]
