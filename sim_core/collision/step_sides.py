"""The sides of a step's contact pairs, fixed for all its Newton iterates (the contact set's side memory at ``x^n``).

A pair above the face (vertex-triangle) or with both closest points interior (edge-edge) at ``x^n`` keeps its
remembered side, so a vertex that slips through the face during the step is pushed back to where it came from. Any
other pair is unsigned (0): at ``x^n`` it is beside its triangle or beyond an end of its edges, where the side of the
triangle's plane (of the line-line normal) does not tell which way it is approaching, and a sheet may wrap round a
free edge. Sides re-derived at every Newton iterate from its region made the energy change from iterate to iterate,
and a pair that entered the interior on the geometrically other side of the lines than at ``x^n`` jumped to
``d = -2 eps``, which made Newton cycle (a sysid replay failed at t = 1.87 s). :class:`sim_core.contact_set.ContactSet`
takes the sides of its candidate lists from :func:`step_sides`.
"""

from __future__ import annotations

import numpy as np

from sim_core.collision.memory import ContactMemory


def step_sides(above: np.ndarray, pairs: np.ndarray, geometric: np.ndarray, memory: ContactMemory,
               keys: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Sides of the step (module docstring), shape ``(p,)``: the remembered side of a pair ``above``, else its
    ``geometric`` side there; 0 for every other pair.

    Args:
        above: pairs in the face / interior region at ``x^n``, shape ``(p,)`` bool.
        pairs: the pairs, shape ``(p, 2)`` (sorted, as the candidate lists: the memory's fast lookup).
        geometric: their side at ``x^n``, shape ``(p,)``, taken where ``memory`` has none.
        memory: the side memory of the pairs' kind (only the pairs ``above`` are looked up).
        keys: ``pairs``' packed keys, sorted and unique
            (:meth:`~sim_core.energies.contact.pair_lists.CandidateVertices.keys`), or None: the remembered pairs are
            then placed among them (:meth:`ContactMemory.found_in`) instead of every pair ``above`` being looked up;
            the same sides.
        out: a float64 array ``(p,)`` to write the sides into (returned), or None: a new one.
    """
    sides = np.zeros(len(above)) if out is None else out
    if out is not None:
        sides[...] = 0.0
    if keys is not None:
        np.copyto(sides, geometric, where=above)
        rows, remembered = memory.found_in(keys)
        mask = above[rows]
        sides[rows[mask]] = remembered[mask]
        return sides
    rows = np.flatnonzero(above)
    sides[rows] = memory.resolve(np.take(pairs, rows, axis=0), geometric[rows])  # (np.take: rows of a 2-D array)
    return sides
