"""Sparse assembly of Hessian blocks into the upper triangle of the constrained Newton matrix.

The Newton matrix is ``D H D + (I - D)`` with ``D = diag(free)``: Dirichlet DoFs are eliminated by
dropping their rows and columns and putting 1 on their diagonal. It is symmetric, so only its upper
triangle (``row <= col``, full diagonal) is assembled, the input of the Cholesky solver
(:class:`sim_core.linsolve.PardisoCholesky`).

Patterns are cached as maps from block entries to CSR slots, so an assembly is a few
``np.bincount`` calls (no COO -> CSR conversion, no index sort):

* static blocks (elastic terms, the same elements every call, recognised by the identity of their
  ``vertices`` arrays) + the diagonal: one map per set of arrays and free mask, the last
  :data:`STATIC_PATTERNS_KEPT` of them kept (a sleeping body's steps and its awake steps each have
  their own, :mod:`sim_core.sleeping`);
* dynamic blocks (contact, friction: the active pairs change): their entries are mapped into a
  union pattern "static + recently used dynamic entries", which is rebuilt only when an entry
  that is not in it appears; dynamic entries stay in it (as structural zeros) until they have been
  unused for :data:`STICKY_ASSEMBLIES` assemblies. So the pattern, and with it the linear solver's
  symbolic analysis, changes far less often than the active contact set (contacts that come and go
  between Newton iterations). :mod:`sim_core.dynamic_slots` keeps the slots of the dynamic elements
  seen so far, so a merge maps only new elements and a rebuild translates the old pattern.

Fused kernels (:mod:`sim_core.fused_elastic`) skip the per-element blocks: they get the static
pattern (:meth:`HessianAssembler.static_pattern`) and its per-element slot maps
(:meth:`StaticPattern.slot_map`), add their Hessian entries straight into the static value array,
and :meth:`HessianAssembler.assemble_upper_values` merges that array with the dynamic blocks.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.sparse as sp

from sim_core.dynamic_slots import STICKY_ASSEMBLIES, DynamicMerge  # noqa: F401 (documented here)
from sim_core.energies.base import HessianBlocks
from sim_core.static_pattern import StaticPattern

STATIC_PATTERNS_KEPT = 4
"""Static patterns an assembler keeps (the most recently used): one per sleeping set and free mask a
solver switches between (:meth:`HessianAssembler.static_pattern`). A cache bound only: a pattern is a
function of its arrays and mask, so a kept one and a rebuilt one are the same."""


class HessianAssembler:
    """Assemble ``static`` blocks + ``dynamic`` blocks + a diagonal into the constrained upper triangle.

    Args:
        dof_count: ``3 * vertex_count``.
    """

    def __init__(self, dof_count: int) -> None:
        self.dof_count = dof_count
        self._static: StaticPattern | None = None
        # key -> (pattern, its vertex arrays: referenced, so that their ids stay unique), most recent last
        self._patterns: dict[tuple, tuple[StaticPattern, list[np.ndarray]]] = {}
        self._dynamic = DynamicMerge(dof_count)

    def static_pattern(self, vertex_arrays: Sequence[np.ndarray], free: np.ndarray) -> StaticPattern:
        """The pattern of the static element-vertex arrays and ``free``, made the current one: the same
        object as the last call's for the same arrays and mask, else a kept one of an earlier call
        (:data:`STATIC_PATTERNS_KEPT`), else a new one.

        Args:
            vertex_arrays: the ``vertices`` arrays of the static blocks, the same objects every call.
            free: free-DoF mask, shape ``(dof_count,)`` bool.
        """
        key = (tuple((id(v), v.shape) for v in vertex_arrays), np.packbits(free).tobytes())
        kept = self._patterns.pop(key, None)
        if kept is None:
            kept = (StaticPattern(list(vertex_arrays), free, self.dof_count), list(vertex_arrays))
            while len(self._patterns) >= STATIC_PATTERNS_KEPT:
                del self._patterns[next(iter(self._patterns))]
        self._patterns[key] = kept  # the most recent last
        self._static = kept[0]
        return self._static

    def use_pattern(self, pattern: StaticPattern) -> None:
        """Make ``pattern``, a static pattern of another assembler of the same ``dof_count`` (e.g. the one a
        fused evaluator is bound to, :mod:`sim_core.fused_elastic`), this one's current static pattern, for
        :meth:`assemble_upper_values` with this assembler's own union of dynamic entries.

        Raises:
            ValueError: the pattern is of another DoF count.
        """
        if pattern.dof_count != self.dof_count:
            raise ValueError(f"use_pattern: pattern of {pattern.dof_count} DoFs, assembler of {self.dof_count}")
        self._static = pattern

    def assemble_upper(
        self,
        static: Sequence[HessianBlocks],
        dynamic: Sequence[HessianBlocks],
        diagonal: np.ndarray,
        free: np.ndarray,
    ) -> sp.csr_matrix:
        """Upper triangle (with the diagonal) of ``D H D + (I - D)``, ``D = diag(free)``.

        Args:
            static: blocks whose ``vertices`` arrays are the same objects every call (elastic terms).
            dynamic: blocks that change (contact, friction).
            diagonal: extra diagonal, shape ``(dof_count,)`` (inertia, damping).
            free: free-DoF mask, shape ``(dof_count,)`` bool.

        Returns:
            CSR matrix ``(dof_count, dof_count)`` with sorted indices, entries ``row <= col`` only.
        """
        pat = self.static_pattern([b.vertices for b in static], free)
        diagonal = np.asarray(diagonal, dtype=float)
        vals = np.concatenate([b.blocks.reshape(-1) for b in static] + [diagonal])
        static_data = np.bincount(pat.slot, weights=vals[pat.entry_index], minlength=pat.keys.size)
        static_data[pat.fixed_diag_slots] = 1.0
        return self._dynamic.merge(pat, static_data, dynamic, free)

    def assemble_upper_values(
        self,
        pattern: StaticPattern,
        static_values: np.ndarray,
        dynamic: Sequence[HessianBlocks],
        diagonal: np.ndarray,
        free: np.ndarray,
    ) -> sp.csr_matrix:
        """:meth:`assemble_upper` with the static part given as values in ``pattern``'s slots.

        Args:
            pattern: :meth:`static_pattern` of this call's static arrays and ``free``.
            static_values: summed static Hessian entries per slot, shape ``(pattern.keys.size,)``
                (e.g. written by fused kernels through :meth:`StaticPattern.slot_map`); not modified.
            dynamic, diagonal, free: as :meth:`assemble_upper`.
        """
        if pattern is not self._static:
            raise ValueError("assemble_upper_values: pattern is not this assembler's current static pattern")
        return self._dynamic.merge_values(pattern, static_values, diagonal, dynamic, free)
