"""The packed upper slot tables of the fused kernels add what the full slot maps add.

:func:`sim_core.ti_kernels.block_projection.upper_slot_table`, ``upper_index`` and
``add_upper_entry`` against :func:`~sim_core.ti_kernels.block_projection.add_blocks` over the full
map, for elements with repeated vertices and fixed DoFs.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np


def test_packed_upper_entries_add_the_full_blocks(ti_cpu):
    from sim_core.assembly import HessianAssembler
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.block_projection import add_blocks, add_upper_entry, upper_index, upper_slot_table
    from sim_core.ti_kernels.linalg import F64_1, F64_3, I32_2

    @ti.kernel
    def add_upper(blocks: F64_3, table: I32_2, values: F64_1):
        ti.loop_config(serialize=True)
        for e in range(blocks.shape[0]):
            for r in range(12):
                for s in range(r, 12):
                    add_upper_entry(values, table[e, upper_index(12, r, s)], blocks[e, r, s])

    n_vertices = 9
    rng = np.random.default_rng(5)
    vertices = np.array([rng.choice(n_vertices, 4, replace=False) for _ in range(10)])
    vertices[3, 3] = vertices[3, 1]  # repeated vertices: local DoF pairs on one global DoF
    vertices[7, 2] = vertices[7, 0]
    A = rng.standard_normal((10, 12, 12))
    blocks = A + np.swapaxes(A, 1, 2)
    free = np.ones(3 * n_vertices, bool)
    free[[1, 5, 6, 7, 8, 20]] = False
    pattern = HessianAssembler(3 * n_vertices).static_pattern([vertices], free)
    slots = pattern.slot_map(vertices)
    table = upper_slot_table(slots)
    assert table.shape == (10, 78) and table.dtype == np.int32
    assert np.any(table <= -2) and np.any(table == -1)
    packed, full = np.zeros(pattern.keys.size), np.zeros(pattern.keys.size)
    add_upper(blocks, table, packed)
    add_blocks(blocks, slots, full)
    assert np.allclose(packed, full, rtol=0, atol=1e-13 * np.abs(full).max())
