"""Plugging the candidates into the Newton step: extra terms before it, state update after it.

:class:`CandidateHook` is what the solver calls (``docs/patches/solver_candidate_hook.diff``):

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
from typing import Any, Mapping

import numpy as np

from sim_core.errors import ConfigError
from sim_core.candidates.adhesion import LaggedAdhesion, bonded_after, bonded_pairs
from sim_core.candidates.anisotropic_bending import AnisotropicBendingCorrection
from sim_core.candidates.gel_viscoelasticity import MaxwellBranch, relax_state
from sim_core.candidates.sheet_damping import SheetDamping, sheet_vertices
from sim_core.candidates.stiction import StictionFriction
from sim_core.potentials.base import HessianBlocks, Projection
from sim_core.potentials.bending import DiscreteShellBending
from sim_core.solver import NewtonSolver, SolverConfig

CANDIDATE_NAMES = ("stiction", "gel_viscoelasticity", "adhesion", "anisotropic_bending", "damping")
"""Physics-level candidates (SYSID.md effect vocabulary)."""

CANDIDATE_SETTINGS = {"stiction.slip_scale": 2.0, "gel_viscoelasticity.tau": 0.3, "adhesion.delta": 2.5e-4,
                      "adhesion.reach": None, "adhesion.release": None}
"""Secondary settings and their defaults (``adhesion.reach`` None = ``ADHESION_REACH_FRACTION``
``adhesion.delta``, ``adhesion.release`` None = ``ADHESION_RELEASE_FRACTION`` ``adhesion.delta``)."""

ADHESION_RELEASE_FRACTION = 5.0
"""Default release opening of a bonded pair, in units of ``adhesion.delta``: at ``r = 5`` the
exponential law's traction ``r exp(1 - r)`` is 9 % of its peak and 96 % of the work of separation is
spent (:mod:`sim_core.candidates.adhesion`, bond memory)."""

ADHESION_REACH_FRACTION = 0.01
"""Default reach of an adhesion pair, in units of ``adhesion.delta``: a bond forms only where the gel
touches the sheet (opening at the start of the step at most 2.5 um beyond the contact offset with the
default delta, i.e. in contact up to the solver's gap tolerance). A tacky interface adheres where it
touches; with pairs formed up to 5 delta (1.25 mm) away, the candidate pulled a card that had buckled
away from the gel and changed the buckling, a signature no adhesion has (benchmarks.md,
2026-11-22)."""

_STATE_KEY = "gel_viscoelasticity"
_ADHESION_KEY = "adhesion"


def validate_candidate_parameters(params: Mapping[str, float] | None) -> dict[str, float]:
    """Check names and ranges; returns a plain dict.

    Raises:
        ConfigError: unknown name (lists the known ones), non-finite value, negative beta of a
            one-sided candidate, ``|anisotropic_bending| >= 1``, non-positive setting.
    """
    out: dict[str, float] = {}
    for name, value in (params or {}).items():
        if name not in CANDIDATE_NAMES and name not in CANDIDATE_SETTINGS:
            raise ConfigError(f"unknown candidate parameter {name!r}; known: {list(CANDIDATE_NAMES) + list(CANDIDATE_SETTINGS)}")
        if value is None and name in CANDIDATE_SETTINGS:
            continue
        v = float(value)
        if not np.isfinite(v):
            raise ConfigError(f"candidate parameter {name!r} must be finite, got {value}")
        if name == "anisotropic_bending" and not abs(v) < 1.0:
            raise ConfigError(f"candidate parameter 'anisotropic_bending' must satisfy |beta| < 1, got {v}")
        if name in ("stiction", "gel_viscoelasticity", "adhesion", "damping") and v < 0:
            raise ConfigError(f"candidate parameter {name!r} must be >= 0 (0 = off), got {v}")
        if name in CANDIDATE_SETTINGS and v <= 0:
            raise ConfigError(f"candidate setting {name!r} must be > 0, got {v}")
        out[name] = v
    return out


class FrictionWithStiction:
    """Sum of a lagged friction and its stiction bump, used where the solver expects one friction."""

    def __init__(self, friction: Any, stiction: StictionFriction) -> None:
        self.friction, self.stiction = friction, stiction
        self.parameter_names = tuple(friction.parameter_names) + tuple(stiction.parameter_names)

    def energy(self, x: np.ndarray) -> float:
        """Friction + stiction energy in J."""
        return self.friction.energy(x) + self.stiction.energy(x)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``."""
        return self.friction.gradient(x) + self.stiction.gradient(x)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Both block sets stacked (each PSD-projected on its own)."""
        a, b = self.friction.hessian(x, projection), self.stiction.hessian(x, projection)
        return HessianBlocks(np.concatenate([a.vertices, b.vertices]), np.concatenate([a.blocks, b.blocks]))

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """``mu`` of the friction or ``beta`` of the stiction."""
        return self.stiction.parameter_gradient(x, name) if name == "beta" else self.friction.parameter_gradient(x, name)


def _gel_contact_vertices(model) -> np.ndarray:
    parts = [np.unique(s.contact_triangles) for s in model.sensors.values() if hasattr(s, "contact_triangles")]
    if not parts:
        parts = [np.unique(b.triangles) for b in model.bodies.values() if b.kind == "solid"]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


def _sheet_triangles(model) -> np.ndarray:
    parts = [b.triangles for b in model.bodies.values() if b.kind == "sheet"]
    return np.concatenate(parts).astype(np.int64) if parts else np.zeros((0, 3), np.int64)


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
        if name == "adhesion.release" and v is None:
            return max(ADHESION_RELEASE_FRACTION * self.setting("adhesion.delta"), self.setting("adhesion.reach"))
        return float(v)

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
        stored = (getattr(state, "candidate_state", None) or {}).get(_STATE_KEY, {})
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
                self.body_terms(model, state, elastic) + self.damping_terms(model, x_prev, dt))

    def damping_terms(self, model, x_prev: np.ndarray, dt: float) -> list:
        """The sheets' viscous drag (:class:`SheetDamping`) when ``damping`` is set."""
        if "damping" not in self.params:
            return []
        return [SheetDamping(sheet_vertices(model), model.vertex_mass(), x_prev, self.params["damping"], dt)]

    def contact_terms(self, model, x_prev: np.ndarray, friction, state=None) -> list:
        """Stiction (on the step's friction pairs) and adhesion (pairs found at ``x_prev``: gel vertices
        in contact, and the bonded ones of ``state.candidate_state["adhesion"]`` up to the release
        opening; :mod:`sim_core.candidates.adhesion`). ``state`` None: no bonded vertices."""
        p = self.params
        out: list = []
        if "stiction" in p and friction is not None:
            out.append(StictionFriction(friction, p["stiction"], self.setting("stiction.slip_scale")))
        if "adhesion" in p:
            v, w, n = bonded_pairs(x_prev, _gel_contact_vertices(model), _sheet_triangles(model), model.contact.eps,
                                   self.setting("adhesion.reach"), self.setting("adhesion.release"),
                                   self.bonded(state))
            out.append(LaggedAdhesion(v, w, n, model.contact.eps, p["adhesion"], self.setting("adhesion.delta")))
        return out

    @staticmethod
    def bonded(state) -> np.ndarray:
        """Bonded gel vertices of ``state`` (``candidate_state["adhesion"]``; none when absent), ``(b,)``."""
        return np.asarray((getattr(state, "candidate_state", None) or {}).get(_ADHESION_KEY, ()), dtype=np.int64)

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
        out = dict(getattr(state_in, "candidate_state", None) or {})
        if "adhesion" in self.params:
            out[_ADHESION_KEY] = bonded_after(x, _gel_contact_vertices(model), _sheet_triangles(model), model.contact.eps,
                                              self.setting("adhesion.reach"), self.setting("adhesion.release"),
                                              self.bonded(state_in))
        if "gel_viscoelasticity" in self.params:
            Fr = self.relaxed_states(model, state_in, elastic)
            tau = self.setting("gel_viscoelasticity.tau")
            out[_STATE_KEY] = {name: relax_state(Fr[name], solid.deformation_gradient(x), dt, tau)
                               for name, solid in elastic.solids.items()}
        return out


def candidate_terms(model, state, x_prev: np.ndarray, dt: float, params: Mapping[str, float]) -> list:
    """All candidate potentials of one step, built from scratch (no caches).

    Rebuilds the model's elastic terms and contact set (the lagged friction at ``x_prev`` with the
    state's side memory); a solver should use :class:`CandidateHook` with its own instead.

    Returns:
        list of potentials (``Potential`` contract), contact-like first.
    """
    from sim_core.contact_set import ContactSet
    from sim_core.elastic import ElasticTerms

    contact = ContactSet(model)
    memory = contact.begin_step(x_prev, state.contact_memory)
    friction = contact.friction(x_prev, dt, memory)
    contact_like, body_like = CandidateHook(params).terms(model, state, x_prev, dt, ElasticTerms(model), friction)
    return contact_like + body_like


class _ElasticWithCandidates:
    """ElasticTerms proxy whose ``potentials`` also returns the body-like candidate terms."""

    def __init__(self, base, solver: "CandidateNewtonSolver") -> None:
        self._base, self._solver = base, solver

    def __getattr__(self, name: str) -> Any:
        return getattr(self._base, name)

    def potentials(self, hinge_theta_bar):
        s = self._solver
        if s._state_in is None:
            return self._base.potentials(hinge_theta_bar)
        extra = s.hook.body_terms(s.model, s._state_in, self._base)
        damping = getattr(s.hook, "damping_terms", None)  # other hooks (benchmark effects) may lack it
        if damping is not None:
            extra = extra + damping(s.model, s._state_in.x, s._dt)
        return self._base.potentials(hinge_theta_bar) + extra


class _ContactWithCandidates:
    """ContactSet proxy: friction gets the stiction bump, contact potentials get adhesion."""

    def __init__(self, base, solver: "CandidateNewtonSolver") -> None:
        self._base, self._solver = base, solver
        self._extra: list = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._base, name)

    def begin_step(self, x_n, memory):
        self._extra = []
        return self._base.begin_step(x_n, memory)

    def friction(self, x_n, dt, memory):
        friction = self._base.friction(x_n, dt, memory)
        s = self._solver
        self._extra = s.hook.contact_terms(s.model, x_n, friction, s._state_in) if s._state_in is not None else []
        stiction = [t for t in self._extra if isinstance(t, StictionFriction)]
        return FrictionWithStiction(friction, stiction[0]) if stiction else friction

    def potentials(self, x, x_n, memory):
        # every contact-like term but stiction (which acts through friction): the library's adhesion
        # and any other hook's terms (benchmark effects)
        return self._base.potentials(x, x_n, memory) + [t for t in self._extra if not isinstance(t, StictionFriction)]


class CandidateNewtonSolver(NewtonSolver):
    """:class:`NewtonSolver` with candidate physics (what the solver patch does, without editing it).

    The elastic terms and the contact set are wrapped so that the base ``_single_step`` picks up
    the body-like terms with the elastic potentials and the contact-like ones with friction and
    contact (so stiction and adhesion forces count in ``contact_force``); the viscoelastic state
    update runs after each step into ``state_out.candidate_state``.

    Args:
        model: the scene model.
        config: Newton settings.
        candidates: candidate parameters ``{name: beta, setting: value}`` (see the package docstring).

    Raises:
        ConfigError: invalid candidate parameters.
    """

    def __init__(self, model, config: SolverConfig | None = None, candidates: Mapping[str, float] | None = None):
        self.hook = CandidateHook(candidates)
        self._state_in, self._dt = None, None
        super().__init__(model, config)

    def set_candidates(self, candidates: Mapping[str, float] | None) -> None:
        """Replace the candidate parameters (takes effect at the next step)."""
        self.hook = CandidateHook(candidates)

    def notify_model_changed(self) -> None:
        """Rebuild as the base solver does, then re-wrap elastic terms and contact set."""
        super().notify_model_changed()
        self.elastic = _ElasticWithCandidates(self.elastic, self)
        self.contact = _ContactWithCandidates(self.contact, self)

    def _single_step(self, state_in, state_out, control, dt, guess=None):
        self._state_in, self._dt = state_in, dt
        try:
            info = super()._single_step(state_in, state_out, control, dt, guess=guess)
        finally:
            self._state_in = None
        state_out.candidate_state = self.hook.update_state(self.model, state_in, state_out.x, dt, self.elastic._base)
        return info
