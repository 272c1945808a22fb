"""Stacked scene: ``B`` copies of one scene as one model of disconnected copies (lockstep stepping).

:func:`stack_models` concatenates the copies' meshes into one :class:`~sim_core.model.Model`, so that
every existing per-element kernel (elastic, contact, friction) evaluates all copies in one launch and
the Newton system of all copies is one sparse matrix, block diagonal by copy
(:mod:`sim_core.batch.lockstep` steps it).

Layout. The stacked vertices are body-major: for each body of the scene, then each *material group*,
then each copy of that group, the copy's vertices of that body. A material group is the set of copies
with equal body materials and friction coefficients; each group has its own stacked bodies (named
``<body>#<group>``, or ``<body>`` when all copies form one group), so copies that differ in material
parameters keep their own values, and copies that do not share one body per scene body (one kernel
launch per energy). :attr:`StackedScene.index` maps copy ``i``'s vertex ``v`` to its stacked vertex.
Effectors are per copy (``<effector>#<copy>``).

Separation. Copy ``i`` is translated by :attr:`StackedScene.offset` ``[i]``, on a lattice in the
directions orthogonal to every plane normal of the scene (the planes stay shared and valid for every
copy), spaced by :attr:`StackedScene.spacing` (the scene's extent plus a margin far beyond any
contact radius), so that the contact broad phase never pairs two copies. The incremental potential
is invariant under translation (gravity is uniform, elastic and contact energies depend on position
differences, the inertia on ``x - x_hat``), so each copy's solution is its separate solution
translated, up to rounding.

Not stacked: sensors (they read each copy's unstacked state), missing-physics candidates (a
:class:`~sim_core.errors.ConfigError`), per-copy contact settings, damping or gravity (the copies must
share them; a :class:`~sim_core.errors.ConfigError` names the difference).
"""

from __future__ import annotations

import copy as _copy
from dataclasses import dataclass
from functools import cached_property
from typing import Sequence

import numpy as np

from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.model import Body, Effector, Model
from sim_core.state import State

DEFAULT_MARGIN = 0.5
"""Distance added to the scene's extent between neighbouring copies, m (:func:`stack_models`)."""


@dataclass
class StackedScene:
    """``B`` copies of one scene as one stacked model (see the module docstring).

    Attributes:
        model: the stacked model (``B * n`` vertices, no sensors).
        copies: number of copies ``B``.
        index: stacked vertex of copy ``i``'s vertex ``v``, shape ``(B, n)`` int64.
        offset: translation of each copy in the stacked model, m, shape ``(B, 3)``.
        spacing: lattice spacing between copies, m.
        group_of_copy: material group of each copy, shape ``(B,)`` int.
        slot_in_group: position of each copy within its group, shape ``(B,)`` int.
        group_names: per group, scene body name -> stacked body name.
        hinge_counts: scene sheet name -> hinges per copy.
        effector_names: the scene's effector names (stacked as ``<name>#<copy>``).
    """

    model: Model
    copies: int
    index: np.ndarray
    offset: np.ndarray
    spacing: float
    group_of_copy: np.ndarray
    slot_in_group: np.ndarray
    group_names: list[dict[str, str]]
    hinge_counts: dict[str, int]
    effector_names: list[str]

    @property
    def vertex_count(self) -> int:
        """Vertices of one copy ``n``."""
        return int(self.index.shape[1])

    @property
    def dof_index(self) -> np.ndarray:
        """Stacked DoF of copy ``i``'s DoF ``k``, shape ``(B, 3 n)`` int64."""
        return (3 * self.index[:, :, None] + np.arange(3)).reshape(self.copies, -1)

    # ------------------------------------------------------------------ states
    def stack_states(self, states: Sequence[State]) -> State:
        """One stacked state of the copies' states (positions, velocities and effector poses translated by
        :attr:`offset`). The copies' contact side memories are not carried: the stacked state starts with
        a fresh one (``contact_memory`` None), as a copy's first step does.

        Raises:
            ConfigError: not one state per copy, or a state of another vertex count (naming the copy).
        """
        if len(states) != self.copies:
            raise ConfigError(f"stacked scene: {len(states)} states for {self.copies} copies")
        N = self.model.vertex_count
        x, v, f = np.zeros((N, 3)), np.zeros((N, 3)), np.zeros((N, 3))
        poses, openings = {}, {}
        for i, s in enumerate(states):
            if s.x.shape != (self.vertex_count, 3):
                raise ConfigError(f"batch copy {i}: state positions of shape {s.x.shape}, expected ({self.vertex_count}, 3)")
            x[self.index[i]] = s.x + self.offset[i]
            v[self.index[i]] = s.v
            if s.contact_force is not None:
                f[self.index[i]] = s.contact_force
            for name in self.effector_names:
                poses[f"{name}#{i}"] = _moved_pose(s.effector_pose[name], self.offset[i])
                if name in s.gripper_opening:
                    openings[f"{name}#{i}"] = float(s.gripper_opening[name])
        theta = {}
        for g, names in enumerate(self.group_names):
            members = np.flatnonzero(self.group_of_copy == g)
            members = members[np.argsort(self.slot_in_group[members])]
            for sheet, h in self.hinge_counts.items():
                theta[names[sheet]] = np.concatenate(
                    [np.asarray(states[i].hinge_theta_bar.get(sheet, np.zeros(h)), dtype=float) for i in members])
        return State(t=float(states[0].t), x=x, v=v, hinge_theta_bar=theta, effector_pose=poses,
                     gripper_opening=openings, contact_force=f, step_index=int(states[0].step_index))

    def copy_state(self, stacked: State, i: int, t: float, step_index: int) -> State:
        """Copy ``i``'s state read from the stacked state (positions and poses translated back), with its
        own time ``t`` (s) and step index; no contact memory (the stacked state holds it)."""
        return self.copy_states(stacked, np.array([i]), np.array([t]), np.array([step_index]))[0]

    def copy_states(self, stacked: State, copies: np.ndarray, t: np.ndarray, step_index: np.ndarray,
                    rows: dict | None = None) -> list[State]:
        """:meth:`copy_state` of each copy in ``copies`` (int ``(k,)``) with its own time ``t[j]`` (s) and step
        index ``step_index[j]``: positions (less the copies' offsets), velocities and contact forces gathered from the
        stacked arrays at once (each state's arrays are views of one ``(k, n, 3)`` array a
        quantity), or taken from ``rows`` where given: ``{"x", "v", "force"}``, those ``(k, n, 3)`` arrays gathered
        where the stacked state is kept (the lockstep solver's device,
        :meth:`~sim_core.batch.lockstep.LockstepSolver.resident_rows`; the same values)."""
        copies = np.asarray(copies, dtype=np.int64)
        offsets = self.offset[copies]
        if rows is not None:
            x, v, force = rows["x"], rows["v"], rows["force"]
        else:
            gather = self._copy_rows(copies)
            x = gather(stacked.x, offsets, translated=True)
            v = gather(stacked.v)
            force = None if stacked.contact_force is None else gather(stacked.contact_force)
        # the effectors' poses translated back, one (k, 7) array an effector (its rows the copies' poses)
        poses = {n: np.array([stacked.effector_pose[f"{n}#{i}"] for i in copies], dtype=float).reshape(len(copies), 7)
                 for n in self.effector_names}
        for pose in poses.values():
            pose[:, :3] -= offsets
        theta = self._copy_rest_angles(stacked.hinge_theta_bar, copies)
        t, step_index = np.asarray(t, dtype=float).tolist(), np.asarray(step_index).astype(np.int64).tolist()
        names, openings = self.effector_names, stacked.gripper_opening
        # the rows as lists of views, made once (an array's iteration), not indexed copy by copy
        xs, vs, forces = list(x), list(v), [None] * len(copies) if force is None else list(force)
        theta_rows = [(sheet, list(rows)) for sheet, rows in theta.items()]
        pose_rows = [(n, list(poses[n])) for n in names]
        return [State(t=t[j], x=xs[j], v=vs[j], hinge_theta_bar={sheet: rows[j] for sheet, rows in theta_rows},
                      effector_pose={n: rows[j] for n, rows in pose_rows},
                      gripper_opening={n: openings[f"{n}#{i}"] for n in names if f"{n}#{i}" in openings},
                      contact_force=forces[j], step_index=step_index[j])
                for j, i in enumerate(copies.tolist())]

    @cached_property
    def _blocks(self) -> list[tuple[int, int, int]] | None:
        """The layout of :attr:`index` as blocks: ``(a, b, start)`` a segment of a copy's vertices ``a .. b - 1``
        (a body, or the whole copy) such that copy ``i``'s are the stacked rows ``start + i (b - a) + (0 .. b - a -
        1)``, the segments covering ``0 .. n``; None where the index has no such layout."""
        index = self.index
        B, n = index.shape
        if n == 0 or B == 0:
            return None
        edges = [0, *(np.flatnonzero(np.any(np.diff(index, axis=1) != 1, axis=0)) + 1).tolist(), n]
        blocks = []
        for a, b in zip(edges[:-1], edges[1:]):
            start = int(index[0, a])
            if not np.array_equal(index[:, a], start + (b - a) * np.arange(B)):
                return None
            blocks.append((a, b, start))
        return blocks

    def _copy_rows(self, copies: np.ndarray):
        """A function ``gather(a, minus=None, translated=False)`` taking the rows of ``copies`` (int ``(k,)``) from a
        stacked ``(N, 3)`` array as a new ``(k, n, 3)`` array, less ``minus[j]`` (``(k, 3)``) in copy ``j``'s rows where
        given (``translated``: ``minus`` is :attr:`offset` of ``copies``): by whole blocks of rows (:attr:`_blocks`: each
        body's copies stacked one after another; no gather where ``copies`` are all of them in order) where the index
        has that layout, else by a gather of :attr:`index`'s rows; ``minus`` subtracted a coordinate at a time (inner
        loops over the vertices, not over three numbers), or, for every copy in order translated back, in the copy of
        each block in one pass over its contiguous rows (:attr:`_offset_rows`: on the VM ~3.3 against 7.7 ms for
        Forming's positions at B = 1024, best of 41); the same values (the same subtraction)."""
        shape = (len(copies), self.vertex_count, 3)
        blocks = self._blocks
        idx = self.index[copies].reshape(-1) if blocks is None else None
        every = len(copies) == self.copies and bool(np.all(copies == np.arange(self.copies)))

        def gather(a: np.ndarray, minus: np.ndarray | None = None, translated: bool = False) -> np.ndarray:
            if blocks is None:
                out = np.take(a, idx, axis=0).reshape(shape)
            else:
                out = np.empty(shape, dtype=a.dtype)
                tiled = self._offset_rows if minus is not None and translated and every else None
                for lo, hi, start in blocks:
                    rows = a[start:start + self.copies * (hi - lo)].reshape(self.copies, hi - lo, 3)
                    if tiled is None:
                        out[:, lo:hi] = rows if every else rows[copies]
                    else:  # (a copy's rows of the block are contiguous in both: (B, 3 (hi - lo)) views)
                        width = 3 * (hi - lo)
                        np.subtract(rows.reshape(self.copies, width), tiled[:, :width],
                                    out=out[:, lo:hi].reshape(self.copies, width))
                if tiled is not None:
                    return out
            if minus is not None:
                for c in range(3):
                    out[:, :, c] -= minus[:, c, None]
            return out
        return gather

    @cached_property
    def _offset_rows(self) -> np.ndarray:
        """Each copy's :attr:`offset` repeated over the rows of the widest block of :attr:`_blocks`, ``(B, 3 w)``
        (``[ox, oy, oz] * w``), made at the first use and kept: the translation back of :meth:`copy_states`'
        positions in one contiguous pass a block."""
        width = max(hi - lo for lo, hi, _ in self._blocks)
        return np.tile(np.asarray(self.offset, dtype=float), width)

    def _copy_rest_angles(self, theta_bar: dict, copies: np.ndarray) -> dict[str, np.ndarray]:
        """Per scene sheet, the rest angles of ``copies`` (int ``(k,)``) as one new ``(k, h)`` array (row ``j``:
        copy ``copies[j]``'s), read from the stacked ``theta_bar`` (stacked sheet name -> its groups' copies' angles
        in slot order)."""
        out = {}
        for sheet, h in self.hinge_counts.items():
            rows = np.empty((len(copies), h))
            for g, names in enumerate(self.group_names):
                mine = np.flatnonzero(self.group_of_copy[copies] == g)
                if len(mine):
                    angles = np.asarray(theta_bar[names[sheet]]).reshape(-1, h)
                    rows[mine] = angles[self.slot_in_group[copies[mine]]]
            out[sheet] = rows
        return out

    def stack_controls(self, controls: Sequence[Control | None]) -> Control:
        """One stacked control of the copies' controls (pose targets translated by :attr:`offset`).

        Raises:
            ConfigError: a control with a ``position_guess`` (the lockstep step starts every copy at
                its step's initial positions), or not one control per copy.
        """
        if len(controls) != self.copies:
            raise ConfigError(f"stacked scene: {len(controls)} controls for {self.copies} copies")
        out = Control()
        keys, targets, copies = [], [], []
        for i, c in enumerate(controls):
            if c is None:
                continue
            if c.position_guess is not None:
                raise ConfigError(f"batch copy {i}: a lockstep batch takes no Control.position_guess")
            for name, target in c.effector_pose_target.items():
                keys.append(f"{name}#{i}")
                targets.append(target)
                copies.append(i)
            for name, opening in c.gripper_target.items():
                out.gripper_target[f"{name}#{i}"] = float(opening)
        out.effector_pose_target.update(zip(keys, _moved_poses(targets, self.offset[copies])))
        return out

    def copy_of_effector(self, stacked_name: str) -> tuple[int, str]:
        """``(copy, scene effector name)`` of a stacked effector name ``<name>#<copy>``."""
        name, _, i = stacked_name.rpartition("#")
        return int(i), name


def _moved_pose(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``pose`` ``[x y z qx qy qz qw]`` translated by ``offset`` (m)."""
    out = np.array(pose, dtype=float)
    out[:3] += offset
    return out


def _moved_poses(poses: list, offsets: np.ndarray) -> list[np.ndarray]:
    """:func:`_moved_pose` of each pose ``poses[j]`` by ``offsets[j]`` (``(k, 3)``, m): as the rows of one new
    ``(k, 7)`` array where every pose has 7 numbers, else pose by pose."""
    try:
        rows = np.array(poses, dtype=float)
    except ValueError:  # poses of different shapes
        rows = None
    if rows is None or rows.shape != (len(poses), 7):
        return [_moved_pose(np.asarray(p, dtype=float), o) for p, o in zip(poses, offsets)]
    rows[:, :3] += offsets
    return list(rows)


def _material_key(model: Model) -> tuple:
    """What makes two copies' materials equal: every body's material and the friction table."""
    bodies = tuple((b.name, tuple(sorted((k, float(v)) for k, v in b.material.items()))) for b in model.bodies.values())
    friction = tuple(sorted((tuple(sorted(k)), float(v)) for k, v in model.friction.items()))
    return bodies, friction


def _shared_settings(ref: Model, other: Model, i: int) -> None:
    """Raise :class:`ConfigError` naming copy ``i`` when it differs from copy 0 in what the stacked model
    shares (contact settings, damping, gravity, gravity scale, planes, candidates, meta forms)."""
    if other.candidates or ref.candidates:
        raise ConfigError("a lockstep batch does not stack missing-physics candidates (model.candidates); "
                          "step such copies one after another")
    checks = [
        ("contact settings", ref.contact == other.contact),
        ("damping", ref.damping == other.damping),
        ("gravity", np.array_equal(ref.gravity, other.gravity)),
        ("vertex gravity scale", (ref.vertex_gravity_scale is None) == (other.vertex_gravity_scale is None) and (
            ref.vertex_gravity_scale is None or np.array_equal(ref.vertex_gravity_scale, other.vertex_gravity_scale))),
        ("planes", list(ref.planes) == list(other.planes) and all(
            np.array_equal(p.normal, other.planes[n].normal) and p.offset == other.planes[n].offset
            for n, p in ref.planes.items())),
        ("membrane / bending model / solid element", ref.meta.get("membrane") == other.meta.get("membrane")
         and ref.meta.get("bending_model") == other.meta.get("bending_model")
         and ref.meta.get("solid_element") == other.meta.get("solid_element")),
        ("vertex_fixed", np.array_equal(ref.vertex_fixed, other.vertex_fixed)),
    ]
    for what, same in checks:
        if not same:
            raise ConfigError(f"batch copy {i}: its {what} differ from copy 0's; a lockstep batch shares them")


def separation_axes(model: Model) -> np.ndarray:
    """Orthonormal directions orthogonal to every plane normal of ``model``, shape ``(k, 3)``, ``k`` in
    1..3 (the coordinate axes when there are no planes).

    Raises:
        ConfigError: the plane normals span all three directions (no translation keeps every plane).
    """
    normals = np.array([np.asarray(p.normal, dtype=float) for p in model.planes.values()]).reshape(-1, 3)
    if normals.size == 0:
        return np.eye(3)
    _, s, vt = np.linalg.svd(normals)
    rank = int(np.sum(s > 1e-9 * max(s.max(), 1.0)))
    if rank >= 3:
        raise ConfigError(f"a lockstep batch separates copies along directions parallel to every plane; the planes "
                          f"{list(model.planes)} leave none")
    return vt[rank:]


def stack_models(models: Sequence[Model], margin: float = DEFAULT_MARGIN) -> StackedScene:
    """The stacked scene of ``B`` copies of one scene (module docstring).

    Args:
        models: the copies' models (same topology: :func:`sim_core.batch.simulation.same_topology`,
            which the caller checks; own materials and friction coefficients).
        margin: distance added to the scene's extent between neighbouring copies, m (beyond any
            effector travel of a rollout; the default 0.5 m is about 5 scene sizes of the task scenes).

    Returns:
        the :class:`StackedScene`.

    Raises:
        ConfigError: no copies; copies that differ in a shared setting (:func:`_shared_settings`);
            candidates; rigid sphere bodies; planes that leave no separation direction.
    """
    models = list(models)
    if not models:
        raise ConfigError("a stacked scene needs at least one copy")
    ref = models[0]
    for i, m in enumerate(models):
        _shared_settings(ref, m, i)
    spheres = [b.name for b in ref.bodies.values() if b.kind == "sphere"]
    if spheres:
        raise ConfigError(f"a lockstep batch does not stack rigid spheres ({', '.join(spheres)}: one kinematic "
                          f"vertex per body); step such copies one after another")
    B, n = len(models), ref.vertex_count
    # material groups, in order of first appearance
    keys, group_of_copy, slot = [], np.zeros(B, dtype=np.int64), np.zeros(B, dtype=np.int64)
    sizes: list[int] = []
    for i, m in enumerate(models):
        key = _material_key(m)
        if key not in keys:
            keys.append(key)
            sizes.append(0)
        g = keys.index(key)
        group_of_copy[i], slot[i] = g, sizes[g]
        sizes[g] += 1
    G = len(keys)
    members = [np.flatnonzero(group_of_copy == g) for g in range(G)]
    group_names = [{name: (name if G == 1 else f"{name}#{g}") for name in ref.bodies} for g in range(G)]
    # separation lattice
    axes = separation_axes(ref)
    pts = np.concatenate([ref.x_rest] + ([ref.initial_x] if ref.initial_x is not None else []))
    extent = float(np.max(pts.max(axis=0) - pts.min(axis=0))) if len(pts) else 0.0
    spacing = extent + float(margin) + 4.0 * (ref.contact.eps + ref.contact.candidate_margin)
    side = int(np.ceil(B ** (1.0 / len(axes)) - 1e-9))
    lattice = np.stack(np.unravel_index(np.arange(B), (side,) * len(axes)), axis=1).astype(float)
    offset = spacing * lattice @ axes
    # vertex layout: body-major, then group, then copy
    index = np.zeros((B, n), dtype=np.int64)
    bodies: dict[str, Body] = {}
    start = 0
    for name, body in ref.bodies.items():
        m_b = body.vertex_stop - body.vertex_start
        for g in range(G):
            g_start = start
            for i in members[g]:
                index[i, body.vertex_start:body.vertex_stop] = np.arange(start, start + m_b)
                start += m_b
            bodies[group_names[g][name]] = Body(
                name=group_names[g][name], kind=body.kind, vertex_start=g_start, vertex_stop=start,
                triangles=np.zeros((0, 3), dtype=np.int64), edges=np.zeros((0, 2), dtype=np.int64),
                material=dict(models[members[g][0]].bodies[name].material))
    N = start
    for name, body in ref.bodies.items():
        for g in range(G):
            sb = bodies[group_names[g][name]]
            sb.triangles = _stacked(body.triangles, index, members[g])
            sb.edges = _stacked(body.edges, index, members[g])
            sb.tets = None if body.tets is None else _stacked(body.tets, index, members[g])
            sb.hinges = None if body.hinges is None else _stacked(body.hinges, index, members[g])
    x_rest = np.zeros((N, 3))
    fixed = np.zeros(N, dtype=bool)
    gravity_scale = None if ref.vertex_gravity_scale is None else np.zeros(N)
    for i, m in enumerate(models):
        x_rest[index[i]] = m.x_rest + offset[i]
        fixed[index[i]] = m.vertex_fixed
        if gravity_scale is not None:
            gravity_scale[index[i]] = m.vertex_gravity_scale
    effectors = {}
    for i in range(B):
        for name, e in ref.effectors.items():
            effectors[f"{name}#{i}"] = Effector(
                name=f"{name}#{i}", vertices=index[i, e.vertices], local_points=np.array(e.local_points),
                initial_pose=_moved_pose(e.initial_pose, offset[i]), max_translation_per_step=e.max_translation_per_step,
                max_rotation_per_step=e.max_rotation_per_step,
                finger_sign=None if e.finger_sign is None else np.array(e.finger_sign),
                finger_axis=np.array(e.finger_axis), initial_opening=e.initial_opening)
    friction = {}
    for g in range(G):
        for pair, mu in models[members[g][0]].friction.items():
            friction[frozenset(group_names[g].get(p, p) for p in pair)] = float(mu)
    meta = {"dt": ref.meta.get("dt"), "stacked_copies": B}
    for key in ("membrane", "bending_model", "solid_element"):
        form = ref.meta.get(key)
        if isinstance(form, dict):
            meta[key] = {names[body]: value for names in group_names for body, value in form.items() if body in names}
        elif form is not None:
            meta[key] = form
    model = Model(x_rest=x_rest, vertex_fixed=fixed, bodies=bodies, effectors=effectors,
                  planes=_copy.deepcopy(ref.planes), gravity=np.array(ref.gravity, dtype=float),
                  contact=_copy.deepcopy(ref.contact), friction=friction, damping=ref.damping, meta=meta,
                  vertex_gravity_scale=gravity_scale)
    hinge_counts = {name: int(b.hinges.shape[0]) for name, b in ref.bodies.items() if b.hinges is not None}
    return StackedScene(model=model, copies=B, index=index, offset=offset, spacing=spacing,
                        group_of_copy=group_of_copy, slot_in_group=slot, group_names=group_names,
                        hinge_counts=hinge_counts, effector_names=list(ref.effectors))


def _stacked(elements: np.ndarray, index: np.ndarray, copies: np.ndarray) -> np.ndarray:
    """Element array (copy-local vertex indices, shape ``(e, k)``) of every copy in ``copies`` in stacked
    vertex indices, concatenated in copy order, shape ``(len(copies) e, k)``."""
    elements = np.asarray(elements, dtype=np.int64)
    if len(copies) == 0:
        return elements[:0]
    return index[copies][:, elements].reshape(-1, elements.shape[1])
