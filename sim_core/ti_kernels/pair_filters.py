"""Element-pair filters shared by the broad-phase kernels (:mod:`sim_core.ti_kernels.sweep_candidates`,
:mod:`sim_core.ti_kernels.hash_grid`): pairs of elements that share a vertex, and pairs in the
contact set's rest-distance exclusion (:class:`sim_core.collision.rest_exclusion.RestExclusion`,
sorted int64 keys ``first << 32 | second``), are not contact candidates.
"""

# No ``from __future__ import annotations`` here: Taichi reads ti.func annotations as objects.

from sim_core.ti_backend import ti


@ti.func
def shares_vertex(a_vertices: ti.template(), i: ti.i32, b_vertices: ti.template(), j: ti.i32) -> ti.i32:
    """1 if element ``i`` of A and element ``j`` of B have a vertex in common."""
    shared = 0
    for u in range(a_vertices.shape[1]):
        for w in range(b_vertices.shape[1]):
            if a_vertices[i, u] == b_vertices[j, w]:
                shared = 1
    return shared


@ti.func
def is_rest_close(rest_keys: ti.template(), key: ti.i64) -> ti.i32:
    """1 if ``key`` is in the sorted ``rest_keys`` (binary search)."""
    lo, hi = 0, rest_keys.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if rest_keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    found = 0
    if lo < rest_keys.shape[0]:
        if rest_keys[lo] == key:
            found = 1
    return found
