"""The Taichi functions the envelope Cholesky's schedules share (:mod:`sim_core.ti_kernels.envelope_cholesky`'s by
columns and vertices, :mod:`sim_core.ti_kernels.envelope_blocks`' by panels): a pivot as the elimination uses it, a
sum over a warp's group of lanes, a lane's share of a row's dot product, the right-hand side gathered into the
envelope's order."""

from sim_core.ti_backend import ti

_F64 = ti.types.ndarray(dtype=ti.f64, ndim=1)
_I32 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@ti.func
def _pivot(value):
    """A pivot as the elimination uses it: ``value`` where positive, 1 where not (its copy is then reported)."""
    d = ti.cast(value, ti.f64)
    if not d > 0.0:
        d = 1.0
    return d


@ti.func
def _group_sum(value, lane, group: ti.template()):
    """The sum of ``value`` over the ``group`` consecutive lanes of a warp that hold ``lane`` (a power of two, at most
    32; every lane of the group gets it): a butterfly of warp shuffles of the float64's two 32-bit halves (Taichi's
    shuffles are 32-bit), the group's lanes only in the mask, so that other groups of the warp may have left."""
    total = value
    if ti.static(group > 1):
        low = (lane % 32) // group * group
        mask = ti.cast(-1, ti.u32)
        if ti.static(group < 32):
            mask = ti.cast((1 << group) - 1, ti.u32) << ti.cast(low, ti.u32)
        for offset in ti.static([group >> s for s in range(1, group.bit_length())]):
            bits = ti.bit_cast(total, ti.i64)
            lo = ti.simt.warp.shfl_xor_i32(mask, ti.cast(bits, ti.i32), offset)
            hi = ti.simt.warp.shfl_xor_i32(mask, ti.cast(bits >> 32, ti.i32), offset)
            other = (ti.cast(hi, ti.i64) << 32) | ti.cast(ti.cast(lo, ti.u32), ti.i64)
            total += ti.bit_cast(other, ti.f64)
    return total


@ti.func
def _row_dot(env: ti.template(), w: ti.template(), row, vb, k, stop, stride):
    """``sum w_ik w[vb + k]`` over ``k`` from ``k`` to ``stop - 1`` by ``stride`` (a lane's share of a row's sum; the
    row's column ``k`` at ``env[row + k]``)."""
    acc = 0.0
    while k < stop:
        acc += ti.cast(env[row + k], ti.f64) * w[vb + k]
        k += stride
    return acc


@ti.func
def _gather_rhs(order: ti.template(), todo: ti.template(), b: ti.template(), x: ti.template(), w: ti.template(), c, vb,
                m, lane, lanes):
    """A lane's share of copy ``c``'s right-hand side into ``w[vb:vb + m]`` in the envelope's order (0 where the copy
    is not factorised, ``todo[c] == 0``, or a position is padding) and its solution ``x`` zeroed."""
    p = lane
    while p < m:
        dof = order[vb + p]
        w[vb + p] = 0.0
        if dof >= 0:
            if todo[c] != 0:
                w[vb + p] = b[dof]
            x[dof] = 0.0
        p += lanes
