"""Plugging extra terms into the Newton step: the :class:`StepHook` contract and the candidates' hook.

A :class:`StepHook` is the one way to add terms to the solver's step
(:class:`sim_core.solver.NewtonSolver`: ``NewtonSolver(model, config, hook=...)`` or
:meth:`~sim_core.solver.NewtonSolver.set_hook`; the model's ``candidate.<name>`` parameters select a
:class:`CandidateHook` when no hook is given):

- ``hook.terms(model, state_in, x_prev, dt, elastic, friction)`` -> ``(contact_like, body_like)``:
  potentials added to the incremental potential of the step. ``contact_like`` (stiction,
  adhesion) act between gel and sheet and count in ``State.contact_force`` (hence the wrench);
  ``body_like`` (the gel's Maxwell branch, the anisotropic bending part) do not.
- ``hook.update_state(model, state_in, x, dt, elastic)`` -> the new ``State.candidate_state``
  (viscoelastic relaxed states per gel, the bonded gel vertices of adhesion), a dict of arrays.

Candidate parameters are a dict ``{name: beta, setting: value}`` (see the package docstring); a
candidate absent from the dict adds nothing, one present with ``beta = 0`` adds a term of zero
energy whose ``parameter_gradient`` is the signature ``d(grad E)/d beta`` at ``beta = 0``.
"""

from __future__ import annotations

import copy
import math
from typing import Any, Mapping, Protocol, runtime_checkable

import numpy as np

from sim_core.candidates.adhesion import (Anchors, LaggedAdhesion, anchored_after, anchored_pairs, bonded_after,
                                          bonded_pairs, no_anchors)
from sim_core.candidates.anisotropic_bending import AnisotropicBendingCorrection
from sim_core.candidates.gel_damping import kelvin_voigt_branch
from sim_core.candidates.gel_viscoelasticity import MaxwellBranch, relax_state
from sim_core.candidates.parameters import CANDIDATE_NAMES, CANDIDATE_SETTINGS, validate_candidate_parameters
from sim_core.candidates.sheet_damping import SheetDamping, sheet_vertices
from sim_core.candidates.stiction import StictionFriction
from sim_core.energies.hinge_bending.reference import DiscreteShellBending
from sim_core.errors import ConfigError

__all__ = ["ADHESION_REACH_FRACTION", "ADHESION_RELEASE_FRACTION", "CANDIDATE_NAMES", "CANDIDATE_SETTINGS",
           "CandidateHook", "GelContactFace", "StepHook", "checked_hook", "validate_candidate_parameters"]

ADHESION_RELEASE_FRACTION = 5.0
"""Default release opening of a bonded pair, in units of ``adhesion.delta``: at ``r = 5`` the
exponential law's traction ``r exp(1 - r)`` is 9 % of its peak and 96 % of the work of separation is
spent (:mod:`sim_core.candidates.adhesion`, bond memory)."""

ADHESION_REACH_FRACTION = 0.01
"""Default reach of an adhesion pair, in units of ``adhesion.delta``: a bond forms only where the gel
touches the sheet (opening at the start of the step at most 2.5 um beyond the contact offset with the
default delta, i.e. in contact up to the solver's gap tolerance). A tacky interface adheres where it
touches; with pairs formed up to 5 delta (1.25 mm) away, the candidate pulled a card that had buckled
away from the gel and changed the buckling, a signature no adhesion has (benchmarks_log.md,
2026-11-22)."""

_STATE_KEY = "gel_viscoelasticity"
RELEASE_TIME_TOLERANCE = 1e-9
"""Tolerance (s) of the comparison of the simulated time with ``adhesion.release_time``."""

_ADHESION_KEY = "adhesion"
_ANCHOR_TRIANGLE_KEY = "adhesion_anchor_triangle"
_ANCHOR_WEIGHTS_KEY = "adhesion_anchor_weights"


@runtime_checkable
class GelContactFace(Protocol):
    """A sensor with a gel contact face (a tactile sensor,
    :class:`sim_core.scenes.tactile_scene.TactileSensorInstance`)."""

    contact_triangles: np.ndarray
    """Global triangles of the gel's contact face, shape ``(t, 3)``."""


def _gel_contact_vertices(model) -> np.ndarray:
    parts = [np.unique(s.contact_triangles) for s in model.sensors.values() if isinstance(s, GelContactFace)]
    if not parts:
        parts = [np.unique(b.triangles) for b in model.bodies.values() if b.kind == "solid"]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


def _sheet_triangles(model) -> np.ndarray:
    parts = [b.triangles for b in model.bodies.values() if b.kind == "sheet"]
    return np.concatenate(parts).astype(np.int64) if parts else np.zeros((0, 3), np.int64)


@runtime_checkable
class StepHook(Protocol):
    """Extra terms of each Newton step and the state update after it (module docstring)."""

    def terms(self, model, state, x_prev: np.ndarray, dt: float, elastic, friction) -> tuple[list, list]:
        """``(contact_like, body_like)`` potentials of the step that starts at ``state``: lists of
        :class:`~sim_core.energies.base.Potential`; ``x_prev`` ``(n, 3)`` m, ``dt`` s, ``elastic``
        the solver's :class:`~sim_core.elastic.ElasticTerms`, ``friction`` the step's lagged friction
        or None."""
        ...

    def update_state(self, model, state_in, x: np.ndarray, dt: float, elastic) -> dict[str, Any]:
        """The new ``State.candidate_state`` after a step from ``state_in`` that ended at ``x`` ``(n, 3)`` m."""
        ...


class CandidateHook:
    """Extra terms and state update of a set of candidates (module docstring).

    Args:
        params: candidate parameters ``{name: beta, setting: value}``.

    Raises:
        ConfigError: see :func:`validate_candidate_parameters`.
    """

    def __init__(self, params: Mapping[str, float] | None = None) -> None:
        self.params = validate_candidate_parameters(params)
        self._bending: dict[str, DiscreteShellBending] = {}

    def setting(self, name: str) -> float:
        """Value of a secondary setting (default from :data:`CANDIDATE_SETTINGS`)."""
        v = self.params.get(name, CANDIDATE_SETTINGS[name])
        if name == "adhesion.reach" and v is None:
            return ADHESION_REACH_FRACTION * self.setting("adhesion.delta")
        if name == "adhesion.shear" and v is None:
            return math.inf
        if name == "adhesion.release" and v is None and self._normal_stiffness():
            return max(float(self.params.get("adhesion", 0.0)) / self._normal_stiffness(), self.setting("adhesion.reach"))
        if name == "adhesion.release" and v is None:
            return max(ADHESION_RELEASE_FRACTION * self.setting("adhesion.delta"), self.setting("adhesion.reach"))
        if name == "adhesion.release_time" and v is None:
            return math.inf
        return float(v)

    def _shear_stiffness(self) -> float | None:
        """``adhesion.shear_stiffness`` in N/m per pair, None when the bonds have no compliant layer."""
        v = self.params.get("adhesion.shear_stiffness")
        return None if v is None else float(v)

    def _normal_stiffness(self) -> float | None:
        """The compliant layer's normal spring ``adhesion.normal_ratio * adhesion.shear_stiffness`` in N/m per pair,
        None with the cohesive normal law (its bonds then release where that spring's force reaches the bond
        strength: ``adhesion.release`` None = ``beta / k_n``)."""
        ratio, k_t = self.params.get("adhesion.normal_ratio"), self._shear_stiffness()
        return None if ratio is None or k_t is None else float(ratio) * k_t

    def peeled(self, state) -> bool:
        """Whether the adhesion bonds are gone at ``state`` (its time ``t`` s at or past
        ``adhesion.release_time``, to :data:`RELEASE_TIME_TOLERANCE`: the step clock is a sum of
        steps, so ``12 * 0.01`` may read 0.11999999999999998; ``state`` None: not peeled)."""
        return state is not None and float(state.t) >= self.setting("adhesion.release_time") - RELEASE_TIME_TOLERANCE

    def _hinge_bending(self, model, name: str, hinges: np.ndarray, theta_bar) -> DiscreteShellBending:
        """Discrete-shell bending of sheet ``name`` (built once per stiffness, rest angles replaced)."""
        D = float(model.bodies[name].material["bending_stiffness"])
        cached = self._bending.get(name)
        if cached is None or cached.bending_stiffness != D:
            cached = DiscreteShellBending(hinges, model.x_rest, D)
            self._bending[name] = cached
        clone = copy.copy(cached)
        if theta_bar is not None:
            clone.hinge_theta_bar = np.asarray(theta_bar, dtype=float)
        return clone

    def relaxed_states(self, model, state, elastic) -> dict[str, np.ndarray]:
        """``F_r`` per gel solid from ``state.candidate_state`` (identity when absent)."""
        stored = (state.candidate_state or {}).get(_STATE_KEY, {})
        out = {}
        for name, solid in elastic.solids.items():
            Fr = stored.get(name)
            out[name] = np.array(Fr) if Fr is not None else np.tile(np.eye(3), (solid.tets.shape[0], 1, 1))
        return out

    def terms(self, model, state, x_prev: np.ndarray, dt: float, elastic, friction) -> tuple[list, list]:
        """``(contact_like, body_like)`` potentials of one step (module docstring).

        Args:
            model: the :class:`~sim_core.model.Model`.
            state: the state at the start of the step (``hinge_theta_bar``, ``candidate_state``).
            x_prev: ``x^n`` in m, shape ``(n, 3)``.
            dt: step in s.
            elastic: the solver's :class:`~sim_core.elastic.ElasticTerms`.
            friction: the step's lagged friction, or None.
        """
        return (self.contact_terms(model, x_prev, friction, state),
                self.body_terms(model, state, elastic) + self.damping_terms(model, x_prev, dt, elastic))

    def damping_terms(self, model, x_prev: np.ndarray, dt: float, elastic=None) -> list:
        """The sheets' viscous drag (:class:`SheetDamping`) when ``damping`` is set; the gels'
        Kelvin-Voigt dashpots (:func:`~sim_core.candidates.gel_damping.kelvin_voigt_branch`) when
        ``gel_damping`` is set (``elastic``: the solver's elastic terms, whose solids are the gels)."""
        out: list = []
        if "damping" in self.params:
            out.append(SheetDamping(sheet_vertices(model), model.vertex_mass(), x_prev, self.params["damping"], dt))
        if "gel_damping" in self.params and elastic is not None:
            out += [kelvin_voigt_branch(solid, x_prev, self.params["gel_damping"], dt) for solid in elastic.solids.values()]
        return out

    def contact_terms(self, model, x_prev: np.ndarray, friction, state=None) -> list:
        """Stiction (on the step's friction pairs) and adhesion (pairs found at ``x_prev``: gel vertices
        in contact, and the bonded ones of ``state.candidate_state["adhesion"]`` up to the release
        opening; :mod:`sim_core.candidates.adhesion`), none from ``adhesion.release_time`` on.
        ``state`` None: no bonded vertices."""
        p = self.params
        out: list = []
        if "stiction" in p and friction is not None:
            out.append(StictionFriction(friction, p["stiction"], self.setting("stiction.slip_scale")))
        if "adhesion" in p and not self.peeled(state):
            shear, k_shear = self.setting("adhesion.shear"), self._shear_stiffness()
            if math.isinf(shear) and k_shear is None:
                v, w, n = bonded_pairs(x_prev, _gel_contact_vertices(model), _sheet_triangles(model), model.contact.eps,
                                       self.setting("adhesion.reach"), self.setting("adhesion.release"),
                                       self.bonded(state))
            else:
                v, w, n = anchored_pairs(x_prev, _gel_contact_vertices(model), _sheet_triangles(model),
                                         model.contact.eps, self.setting("adhesion.reach"), self.anchors(state))
            out.append(LaggedAdhesion(v, w, n, model.contact.eps, p["adhesion"], self.setting("adhesion.delta"),
                                      None if math.isinf(shear) else shear, k_shear,
                                      self.params.get("adhesion.normal_ratio")))
        return out

    @staticmethod
    def bonded(state) -> np.ndarray:
        """Bonded gel vertices of ``state`` (``candidate_state["adhesion"]``; none when absent), ``(b,)``."""
        stored = {} if state is None else (state.candidate_state or {})
        return np.asarray(stored.get(_ADHESION_KEY, ()), dtype=np.int64)

    @staticmethod
    def anchors(state) -> Anchors:
        """The anchored bonds of ``state`` (:data:`sim_core.candidates.adhesion.Anchors`; none when absent)."""
        stored = {} if state is None else (state.candidate_state or {})
        if _ANCHOR_TRIANGLE_KEY not in stored:
            return no_anchors()
        return (np.asarray(stored[_ADHESION_KEY], dtype=np.int64),
                np.asarray(stored[_ANCHOR_TRIANGLE_KEY], dtype=np.int64),
                np.asarray(stored[_ANCHOR_WEIGHTS_KEY], dtype=float).reshape(-1, 3))

    def body_terms(self, model, state, elastic) -> list:
        """The gels' Maxwell branches and the sheets' anisotropic bending parts."""
        p = self.params
        out: list = []
        if "gel_viscoelasticity" in p:
            Fr = self.relaxed_states(model, state, elastic)
            out += [MaxwellBranch(solid, Fr[name], p["gel_viscoelasticity"]) for name, solid in elastic.solids.items()]
        if "anisotropic_bending" in p:
            for name, hinges in elastic.hinges.items():
                bending = self._hinge_bending(model, name, hinges, state.hinge_theta_bar.get(name))
                out.append(AnisotropicBendingCorrection(bending, model.x_rest, p["anisotropic_bending"]))
        return out

    def update_state(self, model, state_in, x: np.ndarray, dt: float, elastic) -> dict[str, Any]:
        """New ``candidate_state`` after a step that ended at ``x`` (viscoelastic relaxation, adhesion bonds)."""
        out = dict(state_in.candidate_state or {})
        shear = self.setting("adhesion.shear")
        if "adhesion" in self.params and math.isinf(shear) and self._shear_stiffness() is None:
            out[_ADHESION_KEY] = (np.zeros(0, np.int64) if self.peeled(state_in) else
                                  bonded_after(x, _gel_contact_vertices(model), _sheet_triangles(model),
                                               model.contact.eps, self.setting("adhesion.reach"),
                                               self.setting("adhesion.release"), self.bonded(state_in)))
        elif "adhesion" in self.params:
            release = self.setting("adhesion.release")
            anchors = (no_anchors() if self.peeled(state_in) else
                       anchored_after(x, _gel_contact_vertices(model), _sheet_triangles(model), model.contact.eps,
                                      self.setting("adhesion.reach"), release,
                                      release * shear / self.setting("adhesion.delta"),  # inf: the layer's spring
                                      self.anchors(state_in)))
            out[_ADHESION_KEY], out[_ANCHOR_TRIANGLE_KEY], out[_ANCHOR_WEIGHTS_KEY] = anchors
        if "gel_viscoelasticity" in self.params:
            Fr = self.relaxed_states(model, state_in, elastic)
            tau = self.setting("gel_viscoelasticity.tau")
            out[_STATE_KEY] = {name: relax_state(Fr[name], solid.deformation_gradient(x), dt, tau)
                               for name, solid in elastic.solids.items()}
        return out


def checked_hook(hook: StepHook | None) -> StepHook | None:
    """``hook`` if it is None or a :class:`StepHook`.

    Raises:
        ConfigError: it is neither (names its type and the missing methods).
    """
    if hook is None or isinstance(hook, StepHook):
        return hook
    missing = [m for m in ("terms", "update_state") if not callable(getattr(hook, m, None))]
    raise ConfigError(f"NewtonSolver: hook {type(hook).__name__} is not a StepHook (missing {', '.join(missing)})")
