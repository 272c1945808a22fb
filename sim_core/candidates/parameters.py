"""The names, settings and valid ranges of the missing-physics candidates' parameters (the
``candidate.<name>`` parameters of :meth:`sim_core.model.Model.set_parameter`)."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from sim_core.errors import ConfigError

CANDIDATE_NAMES = ("stiction", "gel_viscoelasticity", "adhesion", "anisotropic_bending", "damping", "gel_damping")
"""Physics-level candidates (SYSID.md effect vocabulary)."""

CANDIDATE_SETTINGS = {"stiction.slip_scale": 2.0, "gel_viscoelasticity.tau": 0.3, "adhesion.delta": 2.5e-4,
                      "adhesion.reach": None, "adhesion.release": None, "adhesion.release_time": None,
                      "adhesion.shear": None, "adhesion.shear_stiffness": None,
                      "adhesion.normal_ratio": None}
"""Secondary settings and their defaults (``adhesion.reach`` None = ``ADHESION_REACH_FRACTION``
``adhesion.delta``, ``adhesion.release`` None = ``ADHESION_RELEASE_FRACTION`` ``adhesion.delta``;
``adhesion.shear`` None = no shear: the tangential length ``delta_t`` (m) of the anchored bonds' coupled
law (:mod:`sim_core.candidates.adhesion`, shear), the bonds hold the sheet's point in every direction; by
default a bond pulls along the normal only; ``adhesion.shear_stiffness`` None = no compliant layer: the tangential
stiffness ``k_t`` (N/m per bonded pair) of anchored bonds that hold in shear with a linear spring beside the normal
law (:mod:`sim_core.candidates.adhesion`, shear compliance; exclusive with ``adhesion.shear``);
``adhesion.normal_ratio`` None = the layer's bonds pull along the normal with the cohesive law: else the compliant
layer's bonds are linear springs along the normal too, of stiffness ``normal_ratio * k_t`` per pair (1: isotropic
springs; the bonds' terms need ``adhesion.shear_stiffness`` with it; :mod:`sim_core.candidates.adhesion`, normal compliance);
``adhesion.release_time`` None = never: from that simulated time (s) on, every bond is broken and
none forms, the peel of a gel whose tack is lost;
:meth:`sim_core.candidates.hook.CandidateHook.setting`)."""


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
        if name in ("stiction", "gel_viscoelasticity", "adhesion", "damping", "gel_damping") and v < 0:
            raise ConfigError(f"candidate parameter {name!r} must be >= 0 (0 = off), got {v}")
        if name in CANDIDATE_SETTINGS and v <= 0:
            raise ConfigError(f"candidate setting {name!r} must be > 0, got {v}")
        out[name] = v
    if out.get("adhesion.shear") is not None and out.get("adhesion.shear_stiffness") is not None:
        raise ConfigError("candidate settings 'adhesion.shear' (the coupled law's delta_t) and "
                          "'adhesion.shear_stiffness' (the compliant layer's k_t) exclude each other; give one")
    return out
