"""Physics-level missing-physics candidates (SYSID.md "Candidate library").

Each candidate adds one parameter ``beta`` whose value 0 switches it off, as an extra term of the
incremental potential (and, for the viscoelastic gel and the adhesion bonds, a state update after each step):

| name | module | beta | extra settings (defaults) |
|---|---|---|---|
| ``stiction`` | :mod:`.stiction` | ``mu_s / mu_k - 1`` | ``stiction.slip_scale`` (2: eps_s / eps_u) |
| ``gel_viscoelasticity`` | :mod:`.gel_viscoelasticity` | Maxwell / equilibrium stiffness | ``gel_viscoelasticity.tau`` (0.3 s) |
| ``adhesion`` | :mod:`.adhesion` | bond strength per pair, N | ``adhesion.delta`` (0.25 mm), ``adhesion.reach`` (0.01 delta: bonds form in contact), ``adhesion.release`` (5 delta: a bonded vertex keeps its pair up to it), ``adhesion.release_time`` (s; default never: from it on every bond is broken, the peel), ``adhesion.shear_stiffness`` (N/m a pair: the compliant layer's k_t), ``adhesion.normal_ratio`` (the layer's normal spring over k_t, in place of the cohesive law; release at ``beta / k_n``) |
| ``anisotropic_bending`` | :mod:`.anisotropic_bending` | grain anisotropy, abs < 1 | |
| ``damping`` | :mod:`.sheet_damping` | drag on the sheets' vertices, 1/s | |
| ``gel_damping`` | :mod:`.gel_damping` | the gels' Kelvin-Voigt (stiffness-proportional) time constant, s | |

:class:`~sim_core.candidates.hook.CandidateHook` builds the terms of each step and owns the
post-step state update; it is a :class:`~sim_core.candidates.hook.StepHook`, the one way terms are
added to :class:`~sim_core.solver.NewtonSolver`'s step (the solver builds it from the model's
``candidate.<name>`` parameters, or takes another hook: ``NewtonSolver(..., hook=...)``).
"""

from __future__ import annotations

from sim_core.candidates.adhesion import LaggedAdhesion, adhesion_pairs
from sim_core.candidates.anisotropic_bending import AnisotropicBendingCorrection, hinge_grain_cosine
from sim_core.candidates.gel_damping import kelvin_voigt_branch
from sim_core.candidates.gel_viscoelasticity import MaxwellBranch, relax_state
from sim_core.candidates.hook import CandidateHook, StepHook
from sim_core.candidates.parameters import CANDIDATE_NAMES, CANDIDATE_SETTINGS, validate_candidate_parameters
from sim_core.candidates.sheet_damping import SheetDamping, sheet_vertices
from sim_core.candidates.stiction import StictionFriction

DIAGNOSIS_CANDIDATES = {
    "stiction": {"parameter": "candidate.stiction", "probe": 0.5, "one_sided": True},
    "gel_viscoelasticity": {"parameter": "candidate.gel_viscoelasticity", "probe": 0.5, "one_sided": True},
    "adhesion": {"parameter": "candidate.adhesion", "probe": 0.05, "one_sided": True},
    "anisotropic_bending": {"parameter": "candidate.anisotropic_bending", "probe": 0.3, "one_sided": False},
    "damping": {"parameter": "candidate.damping", "probe": 100.0, "one_sided": True},
}
"""What ``sysid.diagnose.candidates.default_candidates`` reads: effect -> global parameter name (once
``Model.set_parameter`` routes ``candidate.<name>`` to the solver's :class:`CandidateHook`), probe
value for the secant signature (damping and adhesion: raised / set from the scene by
``default_candidates``), and whether beta is one-sided (>= 0)."""

__all__ = [
    "AnisotropicBendingCorrection", "CANDIDATE_NAMES", "DIAGNOSIS_CANDIDATES", "CANDIDATE_SETTINGS", "CandidateHook",
    "LaggedAdhesion", "MaxwellBranch", "SheetDamping", "StepHook", "StictionFriction", "adhesion_pairs",
    "hinge_grain_cosine", "kelvin_voigt_branch", "relax_state", "sheet_vertices", "validate_candidate_parameters",
]
