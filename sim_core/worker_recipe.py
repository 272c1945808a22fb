"""What an elastic worker evaluates: recipes of fused parts, compared by identity.

A :class:`Recipe` names the fused kernels (``"module:function"``) and their arguments; the fused parts
(``sim_core/energies/<energy>/fused_*kernel.py``) build theirs with :func:`part_recipe`, :class:`~sim_core.fused_elastic.FusedElastic`
combines them, and :class:`~sim_core.elastic_worker.ElasticWorker` runs them in its process. This module
holds the records only, so that the fused terms do not depend on the process machinery.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Recipe(NamedTuple):
    """What a worker evaluates: ``parts`` ``((target, args), ...)``, each ``target`` a
    ``"module:function"`` called as ``function(args, x, grad, values) -> energy`` (adding into
    ``grad`` and ``values``), in order, the energies summed in order from 0.0; part ``apart``
    (an index, or None) is evaluated into zeroed buffers that are added after the others.
    Arrays in ``args`` are compared by identity when a worker checks whether a recipe is the one it
    has (a recipe's arrays must not be changed in place)."""

    parts: tuple
    apart: int | None = None


def _same_part(a: tuple, b: tuple) -> bool:
    """Whether two parts ``(target, args)`` are the same: the same object, or the same target and
    arguments (arrays the same objects, other values equal)."""
    if a is b:
        return True
    (ta, xa), (tb, xb) = a, b
    return ta == tb and len(xa) == len(xb) and all(
        u is v or (not isinstance(u, np.ndarray) and not isinstance(v, np.ndarray) and u == v) for u, v in zip(xa, xb))


def same_recipe(a: Recipe | None, b: Recipe) -> bool:
    """Whether ``a`` and ``b`` evaluate the same: the same object, or the same targets, ``apart`` and
    arguments (arrays the same objects, other values equal)."""
    if a is b:
        return True
    return (a is not None and a.apart == b.apart and len(a.parts) == len(b.parts)
            and all(_same_part(pa, pb) for pa, pb in zip(a.parts, b.parts)))


def part_recipe(kept: tuple | None, target: str, args: tuple) -> tuple:
    """A part's ``(target, args)``: ``kept`` (the part's last one) when it has the same target and
    arguments (arrays the same objects, other values equal), else a new tuple. Keeping the object
    makes the worker's check for a configured recipe one identity test."""
    part = (target, args)
    return kept if kept is not None and _same_part(kept, part) else part
