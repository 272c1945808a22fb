"""All candidate potentials of one step, built from scratch (for tests and one-off probes)."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from sim_core.candidates.hook import CandidateHook
from sim_core.contact_set import ContactSet
from sim_core.elastic import ElasticTerms


def candidate_terms(model, state, x_prev: np.ndarray, dt: float, params: Mapping[str, float]) -> list:
    """All candidate potentials of one step, built from scratch (no caches).

    Rebuilds the model's elastic terms and contact set (the lagged friction at ``x_prev`` with the
    state's side memory); a solver uses :class:`~sim_core.candidates.hook.CandidateHook` with its own.

    Args:
        model: the :class:`~sim_core.model.Model`.
        state: the state at the start of the step.
        x_prev: ``x^n`` in m, shape ``(n, 3)``.
        dt: step in s.
        params: candidate parameters ``{name: beta, setting: value}``.

    Returns:
        list of potentials (``Potential`` contract), contact-like first.

    Raises:
        ConfigError: invalid candidate parameters.
    """
    contact = ContactSet(model)
    memory = contact.begin_step(x_prev, state.contact_memory)
    friction = contact.friction(x_prev, dt, memory)
    contact_like, body_like = CandidateHook(params).terms(model, state, x_prev, dt, ElasticTerms(model), friction)
    return contact_like + body_like
