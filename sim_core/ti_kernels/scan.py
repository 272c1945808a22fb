"""Running sums of integer counts inside a Taichi kernel, by chunks: the prefix sum of counting sorts and compactions.

:func:`running_sums` is called at a kernel's top level (its loops then run as the kernel's own loops: in parallel on
CUDA, serially on the CPU): each chunk of :data:`SCAN_CHUNK` counts is summed (in parallel over the chunks), the chunks'
totals are turned into their offsets (one thread), and each chunk's running sums are written from its offset (in
parallel). Integer additions: the same sums in any order of the threads. Used by the spatial hash's bucket table and its
pairs' counting sort (:mod:`sim_core.ti_kernels.hash_grid`) and by the compaction of indices
(:mod:`sim_core.ti_kernels.compaction`).
"""

# No ``from __future__ import annotations`` here: Taichi reads ti.func annotations as objects.

from sim_core.ti_backend import serial_loops, ti

SCAN_CHUNK = 512
"""Counts a thread of :func:`running_sums`' chunk loops reads."""


@ti.func
def running_sums(values: ti.template(), n: ti.i32, chunk_total: ti.template(), total: ti.template(), slot: ti.i32):
    """``values[1 .. n]`` (int32 ndarray, the count of item ``h`` at ``h + 1``; ``values[0]`` is left as it is, 0 for
    offsets) replaced by their running sums, so that ``values[h]`` is the sum of the counts before item ``h``
    (``values[0] = 0``); the sum of all ``n`` counts written to ``total[slot]``. Scratch ``chunk_total`` (at least
    ``ceil(n / SCAN_CHUNK)`` entries). Call it at a kernel's top level only."""
    chunks = (n + SCAN_CHUNK - 1) // SCAN_CHUNK
    ti.loop_config(serialize=ti.static(serial_loops()))
    for c in range(chunks):
        part = 0
        for h in range(c * SCAN_CHUNK, ti.min((c + 1) * SCAN_CHUNK, n)):
            part += values[h + 1]
        chunk_total[c] = part
    ti.loop_config(serialize=True)  # one thread; never the CPU thread pool (a forked worker hangs there)
    for _ in range(1):
        offset = 0
        for c in range(chunks):
            part = chunk_total[c]
            chunk_total[c] = offset
            offset += part
        total[slot] = offset
    ti.loop_config(serialize=ti.static(serial_loops()))
    for c in range(chunks):
        running = chunk_total[c]
        for h in range(c * SCAN_CHUNK, ti.min((c + 1) * SCAN_CHUNK, n)):
            running += values[h + 1]
            values[h + 1] = running
