"""Sleeping bodies (``SolverConfig.sleeping``): a body at rest that nothing moving can reach is held
out of the Newton system until something could change it.

This is the "sleeping islands" idea of rigid-body engines (e.g. Box2D's ``b2Island`` sleep test,
Bullet's deactivation; Erleben, "Stable, robust, and versatile multibody dynamics animation", 2004,
Sec. 3.6) applied to one implicit-Euler step: a body falls asleep after a step that left it at a
strict rest (its velocity and its own part of the last Newton update both below
``sleep_velocity``), with no contact candidate pair shared with a moving vertex, and no moving
vertex within reach of its bounding box. While asleep its DoFs are Dirichlet at the held positions,
its elastic terms are not evaluated (their energy is a constant, kept for ``StepInfo.energy``) and
its contacts with static geometry stay as they were. It is woken before a step when its state is
not the held one, when the step's inputs (model revision, gravity, damping, friction table, dt,
solver settings) differ from those it fell asleep under, or when a moving vertex could reach it
within the step; and during a step (the step is then solved again with it awake) as soon as a
contact candidate pair joins it to a moving vertex.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_core.model import Model
from sim_core.state import State

SLEEPING_KINDS = ("sheet", "solid")
"""Body kinds that may sleep (frozen bodies and spheres never move; effector-driven bodies never sleep)."""


def sleeping_eligible(model: Model) -> list[str]:
    """The names of the bodies of ``model`` that may sleep: kind in :data:`SLEEPING_KINDS`, with
    vertices, none of them driven by an effector; in the model's body order."""
    driven = np.zeros(model.vertex_count, dtype=bool)
    for eff in model.effectors.values():
        driven[eff.vertices] = True
    return [b.name for b in model.bodies.values()
            if b.kind in SLEEPING_KINDS and b.vertex_stop > b.vertex_start and not np.any(driven[b.vertices])]


class Woken(Exception):
    """Raised inside a step when a contact candidate pair joins sleeping bodies to a moving vertex; the
    solver wakes them and solves the step again (never leaves the solver).

    Attributes:
        bodies: the reached bodies' names, sorted.
    """

    def __init__(self, bodies: list[str]) -> None:
        super().__init__(f"sleeping bodies reached: {', '.join(bodies)}")
        self.bodies = list(bodies)


@dataclass
class SleepingBody:
    """A body held out of the Newton system.

    Attributes:
        name: the body's name.
        vertices: its vertex indices, int64 shape ``(k,)``.
        x: its held positions, m, shape ``(k, 3)`` (a copy).
        lo, hi: the corners of its bounding box at ``x``, m, ``(3,)`` each.
        theta_bar: its rest dihedral angles when it fell asleep (rad, ``(h,)``), or None (no hinges).
        energy: its elastic energy at ``x`` (J), added to ``StepInfo.energy`` while it sleeps.
    """

    name: str
    vertices: np.ndarray
    x: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    theta_bar: np.ndarray | None
    energy: float


class SleepSet:
    """Which bodies of a model sleep, and the tests that put them to sleep and wake them.

    Args:
        model: the scene model (bodies, effectors, Dirichlet vertices, contact settings).
        sleep_velocity: the rest threshold, m/s (``SolverConfig.sleep_velocity``).

    Attributes:
        sleep_velocity: the rest threshold, m/s.
        static: the vertices that never move (statically fixed, not driven by an effector), bool ``(n,)``.
        bodies: the sleeping bodies by name.
        inputs: the step inputs (``NewtonSolver._step_inputs``) they fell asleep under, None when none sleeps.
        eligible: the names of the bodies that may sleep: kind in :data:`SLEEPING_KINDS`, with
            vertices, none driven by an effector.
        radius: the contact search distance ``eps + candidate_margin``, m.
        sphere_radius: the radius (m) of each sphere body, whose one vertex is its centre.
    """

    def __init__(self, model: Model, sleep_velocity: float) -> None:
        self.model = model
        self.sleep_velocity = float(sleep_velocity)
        n = model.vertex_count
        driven = np.zeros(n, dtype=bool)
        for eff in model.effectors.values():
            driven[eff.vertices] = True
        # vertices that never move: statically fixed and not driven
        self.static = np.asarray(model.vertex_fixed, dtype=bool) & ~driven
        self.eligible = sleeping_eligible(model)
        self.radius = float(model.contact.eps + model.contact.candidate_margin)
        # a sphere body is its centre vertex: its surface lies this far (m) beyond the vertex
        self.sphere_radius = {b.name: float(b.material["radius"]) for b in model.bodies.values() if b.kind == "sphere"}
        self.bodies: dict[str, SleepingBody] = {}
        self.inputs: tuple | None = None
        self._mask: np.ndarray | None = None
        self._code: np.ndarray | None = None  # _vertex_code, for the current mask
        self._pairs_seen: dict[int, tuple] = {}  # id(pair vertices) -> (the array, its joining vertices or None)

    # ------------------------------------------------------------------ queries
    @property
    def names(self) -> tuple[str, ...]:
        """The sleeping bodies' names, sorted."""
        return tuple(sorted(self.bodies))

    @property
    def mask(self) -> np.ndarray:
        """The sleeping vertices, bool shape ``(n,)``."""
        if self._mask is None:
            mask = np.zeros(self.model.vertex_count, dtype=bool)
            for body in self.bodies.values():
                mask[body.vertices] = True
            self._mask = mask
        return self._mask

    def mask_of(self, names) -> np.ndarray:
        """The vertices of the bodies ``names`` (asleep or not), bool shape ``(n,)``."""
        mask = np.zeros(self.model.vertex_count, dtype=bool)
        for name in names:
            mask[self.model.bodies[name].vertices] = True
        return mask

    @property
    def energy(self) -> float:
        """The sleeping bodies' elastic energy, J."""
        return float(sum(b.energy for b in self.bodies.values()))

    def reached_by_pairs(self, contact_terms: list, x: np.ndarray) -> list[str]:
        """The sleeping bodies that a contact candidate pair of ``contact_terms`` (as
        :meth:`~sim_core.contact_set.ContactSet.potentials` returns them: vertex-triangle and
        edge-edge pairs with ``vertices`` ``(p, 4)``) joins to a moving vertex (neither asleep nor
        static), or that a moving sphere obstacle (a term with a ``center`` vertex and a ``radius``)
        at positions ``x`` ``(n, 3)`` m comes within the contact search distance of, sorted. A pair
        array seen before (the contact set keeps its candidate lists while they cover the iterates)
        is answered from the last look."""
        if not self.bodies:
            return []
        hit = None
        for pot in contact_terms:
            center = getattr(pot, "center", None)
            if center is not None and self._vertex_code()[center] == 2:
                near = np.flatnonzero(self.mask)
                dist = np.linalg.norm(x[near] - x[center], axis=1) - float(pot.radius)
                close = near[dist < self.radius]
                if len(close):
                    hit = close if hit is None else np.concatenate([hit, close])
                continue
            v = getattr(pot, "vertices", None)
            if v is None or v.ndim != 2 or not len(v):
                continue
            kept = self._pairs_seen.get(id(v))
            if kept is None or kept[0] is not v:
                code = self._vertex_code()
                c = code[v]
                rows = ((c & 1).any(axis=1)) & ((c & 2).any(axis=1))
                if len(self._pairs_seen) >= 16:  # the lists of earlier searches: not asked again
                    self._pairs_seen.clear()
                kept = self._pairs_seen[id(v)] = (v, v[rows].reshape(-1) if np.any(rows) else None)
            if kept[1] is not None:
                hit = kept[1] if hit is None else np.concatenate([hit, kept[1]])
        if hit is None:
            return []
        asleep_hit = np.zeros(self.model.vertex_count, dtype=bool)
        asleep_hit[hit] = True
        asleep_hit &= self.mask
        return sorted(name for name, b in self.bodies.items() if np.any(asleep_hit[b.vertices]))

    def _vertex_code(self) -> np.ndarray:
        """Per vertex: 1 asleep, 2 moving (neither asleep nor static), 0 static; int8 ``(n,)``."""
        if self._code is None:
            self._code = np.where(self.mask, 1, np.where(self.static, 0, 2)).astype(np.int8)
        return self._code

    def _within_reach(self, lo: np.ndarray, hi: np.ndarray, x: np.ndarray, x_end: np.ndarray,
                      moving: np.ndarray) -> bool:
        """Whether a ``moving`` vertex (bool ``(n,)``) at ``x`` or ``x_end`` ``(n, 3)`` may come within the
        contact search distance of the box ``[lo, hi]`` (m, ``(3,)`` each) in one step: a box gap below
        ``radius`` plus twice the largest move ``|x_end - x|`` of a moving vertex, per body."""
        if not np.any(moving):
            return False
        reach = 2.0 * float(np.sqrt(np.max(np.sum((x_end[moving] - x[moving]) ** 2, axis=1))))
        for other in self.model.bodies.values():
            sl = slice(other.vertex_start, other.vertex_stop)
            m = moving[sl]
            if not np.any(m):
                continue
            a, b = x[sl][m], x_end[sl][m]
            gap = np.maximum(0.0, np.maximum(np.minimum(a.min(axis=0), b.min(axis=0)) - hi,
                                             lo - np.maximum(a.max(axis=0), b.max(axis=0))))
            if float(np.linalg.norm(gap)) - self.sphere_radius.get(other.name, 0.0) < self.radius + reach:
                return True
        return False

    # ------------------------------------------------------------------ transitions
    def _forget_mask(self) -> None:
        """The sleeping set changed: forget the vertex mask, codes and pair answers built on it."""
        self._mask = None
        self._code = None
        self._pairs_seen = {}

    def wake(self, names) -> None:
        """Wake the bodies ``names`` (those not asleep are ignored)."""
        for name in names:
            if self.bodies.pop(name, None) is not None:
                self._forget_mask()
        if not self.bodies:
            self.inputs = None

    def wake_all(self) -> list[str]:
        """Wake every body; their names, sorted."""
        names = self.names
        self.wake(names)
        return list(names)

    def wake_before_step(self, state_in: State, inputs: tuple, x_target: np.ndarray, fixed: np.ndarray,
                         dt: float) -> list[str]:
        """Wake, before a step from ``state_in``, the sleeping bodies it could change: every one when the
        step's ``inputs`` differ from those they fell asleep under; one whose positions in ``state_in``
        are not bitwise the held ones, whose velocity exceeds ``sleep_velocity``, or whose rest angles
        changed; one that a moving vertex may reach within the step (:meth:`_within_reach`, with the
        driven vertices at their targets ``x_target`` ``(n, 3)`` where ``fixed`` ``(n,)`` and the free
        ones at ``x + dt v``). Returns the woken names, sorted."""
        if not self.bodies:
            return []
        if inputs != self.inputs:
            return self.wake_all()
        woken = []
        for name, body in self.bodies.items():
            sl = slice(int(body.vertices[0]), int(body.vertices[-1]) + 1)  # a body's vertices are contiguous
            v = state_in.v[sl]
            tb = state_in.hinge_theta_bar.get(name)
            if (not np.array_equal(state_in.x[sl], body.x)
                    or (v.size and float(np.max(np.abs(v))) > self.sleep_velocity)
                    or (tb is None) != (body.theta_bar is None)
                    or (tb is not None and not np.array_equal(tb, body.theta_bar))):
                woken.append(name)
        self.wake(woken)
        if not self.bodies:
            return sorted(woken)
        x_end = np.where(fixed[:, None], x_target, state_in.x + dt * state_in.v)
        moving = ~(self.mask | self.static)
        reached = [name for name, b in self.bodies.items() if self._within_reach(b.lo, b.hi, state_in.x, x_end, moving)]
        self.wake(reached)
        return sorted(woken + reached)

    def fall_asleep(self, state_in: State, state_out: State, update: np.ndarray | None, dt: float,
                    contact_terms: list, inputs: tuple, energy_of) -> list[str]:
        """Put to sleep the awake eligible bodies that a strictly converged step from ``state_in`` to
        ``state_out`` left at rest: velocities in and out and their part of the step's last Newton update
        ``update`` ``(3 n,)`` (m; the one the stopping test measured) all below ``sleep_velocity``
        (m/s; the update divided by ``dt``), no contact candidate pair of ``contact_terms`` (the
        result's) shared with a moving vertex, no moving vertex within reach (:meth:`_within_reach`,
        at ``state_out`` with its velocities). ``energy_of(name, x)``: the body's elastic energy (J).
        Returns the names that fell asleep, sorted."""
        if update is None:
            return []
        if self.bodies and inputs != self.inputs:
            return []
        d = np.linalg.norm(np.asarray(update).reshape(-1, 3), axis=1) / dt
        speed_in = np.linalg.norm(state_in.v, axis=1)
        speed_out = np.linalg.norm(state_out.v, axis=1)
        x = state_out.x
        candidates = []
        for name in self.eligible:
            if name in self.bodies:
                continue
            b = self.model.bodies[name]
            sl = slice(b.vertex_start, b.vertex_stop)
            if max(float(d[sl].max()), float(speed_in[sl].max()), float(speed_out[sl].max())) <= self.sleep_velocity:
                candidates.append(name)
        if not candidates:
            return []
        # pairs and reach as if the candidates slept (each alone would give the same answer for the
        # pairs; the reach test treats the others as moving, the conservative side)
        asleep = []
        x_end = x + dt * state_out.v
        for name in candidates:
            b = self.model.bodies[name]
            trial = self.mask.copy()
            trial[b.vertex_start:b.vertex_stop] = True
            moving = ~(trial | self.static)
            inside = np.zeros(self.model.vertex_count, dtype=bool)
            inside[b.vertex_start:b.vertex_stop] = True
            joined = any(np.any(inside[v].any(axis=1) & moving[v].any(axis=1))
                         for v in (getattr(p, "vertices", None) for p in contact_terms)
                         if v is not None and v.ndim == 2 and len(v))
            xb = x[b.vertex_start:b.vertex_stop]
            if joined or self._within_reach(xb.min(axis=0), xb.max(axis=0), x, x_end, moving):
                continue
            asleep.append(name)
        for name in asleep:
            b = self.model.bodies[name]
            tb = state_out.hinge_theta_bar.get(name)
            xb = x[b.vertex_start:b.vertex_stop].copy()
            self.bodies[name] = SleepingBody(name=name, vertices=b.vertices, x=xb, lo=xb.min(axis=0),
                                             hi=xb.max(axis=0), theta_bar=None if tb is None else np.array(tb),
                                             energy=float(energy_of(name, x)))
            self._forget_mask()
        if asleep:
            self.inputs = inputs
        return sorted(asleep)
