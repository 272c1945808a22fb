"""Damping of the gel: a Kelvin-Voigt (stiffness-proportional Rayleigh) dashpot beside its elasticity.

Candidate ``gel_damping`` of SYSID.md's ``damping`` effect (the elastomer's internal friction; alpha
in s, 0 = off). A Kelvin-Voigt solid carries the stress ``sigma = C : (eps + alpha d eps/dt)``, the
stiffness-proportional (Rayleigh) damping that elastomers and other engines' soft bodies have
(MuJoCo's flex ``damping``; Rayleigh 1877, *Theory of Sound*, sec. 97; Bathe 2014, *Finite Element
Procedures*, sec. 9.3.3). Its force runs ahead of the elastic response by ``alpha``: ``F = k (x +
alpha dx/dt)``, i.e. ``k x(t + alpha)`` to first order, the lead that the damping signature reads
(:mod:`sysid.diagnose.signatures.damping`). The mass-proportional sheet drag
(:mod:`.sheet_damping`) has no such lead on the contact force.

Implicit Euler with the dashpot is the minimisation of the gel's own energy density evaluated on the
increment of the step, scaled by ``alpha / dt``:

    E = alpha / dt sum_t V_t psi_SNH(F_t F_t^{n,-1}; E, nu),

whose gradient is, to first order in the increment, ``alpha / dt C : (F F^{n,-1} - I) = alpha C :
(dF/dt) F^{n,-1}``: the Kelvin-Voigt stress of the strain rate over the step, with the gel's stiffness
at rest carried by ``F^n`` (it differs from the tangent at ``F^n`` by the order of the strain: 5 % at
3 % strain). It is the Maxwell branch
of :mod:`.gel_viscoelasticity` with the branch stiffness ``alpha / dt`` and the relaxed state at the
start of the step (``F_r = F^n``: a branch that relaxes completely within every step is a dashpot),
so it shares its energy, gradient, PSD-projected Hessian and fused evaluation and needs no state.
"""

from __future__ import annotations

import numpy as np

from sim_core.candidates.gel_viscoelasticity import MaxwellBranch
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.errors import ConfigError


def kelvin_voigt_branch(solid: StableNeoHookean, x_prev: np.ndarray, alpha: float, dt: float) -> MaxwellBranch:
    """The gel's Kelvin-Voigt dashpot over one step (module docstring).

    Args:
        solid: the gel's :class:`StableNeoHookean` (tets, rest shape, E, nu).
        x_prev: positions at the start of the step ``x^n``, m, shape ``(n, 3)``.
        alpha: damping time constant, s (>= 0; 0 = off).
        dt: step, s (> 0).

    Returns:
        a :class:`MaxwellBranch` with stiffness ratio ``alpha / dt`` and relaxed state ``F(x^n)``.

    Raises:
        ConfigError: negative / non-finite ``alpha``, non-positive ``dt``, an inverted tet at ``x^n``
            (names its index).
    """
    alpha = float(alpha)
    if not (np.isfinite(alpha) and alpha >= 0.0):
        raise ConfigError(f"gel_damping: time constant alpha must be finite and >= 0 s, got {alpha}")
    if not (np.isfinite(dt) and dt > 0.0):
        raise ConfigError(f"gel_damping: time step dt must be finite and > 0 s, got {dt}")
    return MaxwellBranch(solid, solid.deformation_gradient(x_prev), alpha / float(dt))
