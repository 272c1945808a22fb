"""Slot tables of translated chunks: the tables of a stacked scene's copies from those of its first copy.

A stacked scene's copies of one body (:mod:`sim_core.batch.stacked`) have the same elements with every vertex index
moved, and the static pattern's rows of a moved copy are the first copy's moved (:meth:`StaticPattern.slot_runs
<sim_core.static_pattern.StaticPattern.slot_runs>`): each slot of a copy's elements is the first copy's plus one
offset a copy. :func:`translated` writes the tables of every copy of a run from the first copy's; the slot maps of
:mod:`sim_core.static_pattern` and the packed upper tables of the fused kernels
(:class:`~sim_core.ti_kernels.block_projection.SlotTables`) are made through it.
"""

from __future__ import annotations

import numpy as np


def translated(table: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """A slot table of ``P`` chunks from its first chunk's.

    Args:
        table: int32 ``(k0, ...)``, the first chunk's table: a slot map
            (:meth:`~sim_core.static_pattern.StaticPattern.slot_map`: ``>= 0`` a slot, ``-1`` none) or a table packed
            from one (:func:`~sim_core.ti_kernels.block_projection.upper_slot_table`: also ``<= -2``, the slot
            ``-2 - entry``).
        offsets: int32 ``(P,)``, the slot shift of each chunk
            (:meth:`~sim_core.static_pattern.StaticPattern.slot_runs`).

    Returns:
        int32 ``(P k0, ...)``: chunk ``j`` the table with every slot moved by ``offsets[j]`` (``-1`` kept), written
        into one output array (a product and a sum), no temporaries of its size.
    """
    table = np.asarray(table, dtype=np.int32)
    step = np.sign(table + 1, dtype=np.int32)  # +1 where a slot, -1 where a packed slot (<= -2), 0 at -1
    out = np.empty((offsets.size,) + table.shape, dtype=np.int32)
    np.multiply(np.asarray(offsets, dtype=np.int32).reshape((-1,) + (1,) * table.ndim), step[None], out=out)
    out += table[None]
    return out.reshape((-1,) + table.shape[1:])


def joined(runs: list[tuple[np.ndarray, np.ndarray | None]]) -> np.ndarray:
    """The table of consecutive runs ``(table, offsets)`` (:meth:`~sim_core.static_pattern.StaticPattern.slot_runs`:
    ``offsets`` None where ``table`` is the run's own), one after another: int32 ``(k, ...)``; at least one run."""
    parts = [table if offsets is None else translated(table, offsets) for table, offsets in runs]
    return parts[0] if len(parts) == 1 else np.concatenate(parts)
