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


def test_slot_tables_of_stacked_copies_are_those_of_the_whole_map():
    """SlotTables over the elements of six stacked copies (each copy's elements the first copy's moved, some with
    a repeated vertex, so that the packed table has entries ``-2 - slot``; one copy held, which ends the first
    run of translated chunks): its packed upper table and its full map equal upper_slot_table of the map made
    element by element over every copy, and the full map is made at its first read."""
    from sim_core.static_pattern import StaticPattern
    from sim_core.ti_kernels.block_projection import SlotTables, upper_slot_table

    rng = np.random.default_rng(11)
    copies, per_copy = 6, 10
    base = np.array([rng.choice(per_copy, 4, replace=False) for _ in range(9)])
    base[2, 3] = base[2, 0]  # a repeated vertex
    vertices = np.concatenate([base + i * per_copy for i in range(copies)])
    vertex_free = np.ones(copies * per_copy, dtype=bool)
    vertex_free[[1, 4]] = False  # fixed vertices of every copy
    vertex_free[per_copy + 1::per_copy] = False
    vertex_free[per_copy + 4::per_copy] = False
    vertex_free[3 * per_copy:4 * per_copy] = False  # copy 3 held
    free = np.repeat(vertex_free, 3)
    pattern = StaticPattern([vertices], free, free.size)
    assert len(pattern.slot_runs(vertices)) >= 2 and pattern.slot_runs(vertices)[0][1].size == 3
    whole = pattern._pair_slot_map(vertices)  # element by element, no runs
    tables = SlotTables(pattern, vertices)
    assert tables._full is None
    assert tables.upper.dtype == np.int32 and np.any(tables.upper <= -2)
    np.testing.assert_array_equal(tables.upper, upper_slot_table(whole))
    np.testing.assert_array_equal(tables.full, whole)
    assert tables.full is tables.full
    empty = SlotTables(pattern, np.zeros((0, 4), dtype=np.int64))
    assert empty.upper.shape == (0, 78) and empty.full.shape == (0, 12, 12)
