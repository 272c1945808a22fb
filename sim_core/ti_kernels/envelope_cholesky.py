"""A direct solve of the lockstep's block-diagonal Newton system on the device: each copy's whole system (sheet, gel,
contact and friction couplings) factorised by the envelope (profile) Cholesky in a reverse Cuthill-McKee order, one
copy a thread group (issue 52's design with a floor under the goal, docs/gpu_roofline.md).

:class:`BatchedEnvelope` is a :class:`~sim_core.ti_kernels.pcg.BatchedPCG` whose solve is exact: the same
``factorize`` contract and operator ``A = U + U^T - diag(U) + sum_t F E_t F`` (the assembled upper triangle ``U``,
the contact and friction vertex blocks ``E_t``, the free mask ``F``); per copy, ``A_c`` gathered into its lower
envelope straight from ``U``'s values where they are (a device array is read in place) with the inertia diagonal added
there, and the vertex blocks as the CG keeps them (:meth:`BatchedPCG._blocks_on_device`), then factorised; each solve a
forward and a back substitution. None of the CG's own set-up is made (its block-Jacobi preconditioner, its
both-triangle operator: that one only where it is used, for the refinements of ``precision="mixed"`` and for
:meth:`BatchedPCG.matvec`). Every copy has the same number of DoFs; all copies share one layout.

Order and envelope. The vertices of every copy are ordered by the reverse Cuthill-McKee order (Cuthill & McKee 1969;
George & Liu, Computer Solution of Large Sparse Positive Definite Systems, 1981, Sec. 4.3) of the union over copies
of their vertex graphs of ``U``'s pattern (a vertex's three DoFs consecutive), made again only when ``U``'s index
arrays are other objects than at the last call. Row ``i`` of the envelope holds columns ``first[i] .. i``, ``first[i]``
the smallest position ``i`` is coupled to, over every copy: the pattern's couplings, and the vertex blocks' of every
factorisation so far (a device pass marks a block outside the envelope, read with the next solve's flags, one wait
a Newton iteration; the host then widens the envelope, factorises and solves again, and the next factorisations keep
it: the envelope only grows). The Cholesky of an envelope matrix fills nothing outside it (George &
Liu, Ch. 4), so the factor has exactly these entries: 58,017 a Forming copy in the elastic pattern's order, 3.13 M
multiply-adds a factorisation (``benchmarks/roofline.py``).

Factorisation. Kept unscaled, ``A = W D^-1 W^T`` with ``W`` lower triangular, ``W_jj = d_j`` (the pivots; ``L = W
D^-1/2`` is the Cholesky factor, Golub & Van Loan, Matrix Computations, 4th ed., Sec. 4.2), ``lanes`` threads a copy
(one CUDA thread block, a block-level synchronisation a column), a copy ``m`` synchronised passes; on the CPU one
thread runs a copy's whole elimination (``lanes = 1``, no synchronisation). Four orders of the same arithmetic
(``schedule``):

- ``"dots"`` (the default elsewhere than on CUDA, :data:`SCHEDULE`), left-looking by columns (George & Liu,
  Sec. 4.2's inner-product form): column ``j``'s entries ``w_ij = a_ij - sum_k w_ik w_jk / d_k`` (``i = j`` and the
  rows of ``j``'s front, ``k`` from ``max(first[i], first[j])`` to ``j - 1``) are dot products of two contiguous segments of envelope rows, independent of each other;
  ``group`` lanes of a warp take one (``group`` consecutive ``k`` a pass, two sums in flight, then a shuffle sum), the
  copy's ``lanes / group`` groups share the column's entries, and each factor entry is written once. ``1 / d_j`` is
  kept per copy (``(B m,)`` float64) for the later columns.
- ``"panels"`` (the default on CUDA, :data:`CUDA_SCHEDULE`), left-looking by vertices (a supernode of three columns: a vertex's rows have one first column and its
  columns nested fronts, ``front(j + 1) = front(j) - {j + 1}``, so long as a row's first column is a vertex's first
  DoF, as the order makes it and a widening keeps it): two synchronised passes a vertex instead of three. In the
  first each row ``i`` of the vertex and of its front takes its three dot products with the vertex's rows over ``k <
  j`` in one pass over row ``i`` (``group`` lanes, three shuffle sums) and leaves its partial entries (the vertex's own
  six in the block's shared memory); in the second every task eliminates the vertex's 3x3 block (the same few
  operations in every thread) and finishes its row's three entries. The pivots' inverses in a ring of shared memory
  (a power of two above the widest row: 512 float64 for Forming); on the CPU the same arithmetic with both in
  scratch arrays.
- ``"blocks"`` (session 58; opt-in), left-looking by panels of ``panel`` columns
  (:mod:`sim_core.ti_kernels.envelope_blocks`): a panel in three passes through global memory (its and its front's
  rows' dot products over the earlier columns, ``P`` sums a row in one pass; the panel's triangle factorised in the
  block's shared memory; the front's rows finished against it) instead of one a column, both substitutions in two
  passes a panel; a Forming factorisation 426 dependent passes at ``P = 12`` against ``"dots"``' 1,698, a solve 570
  against 3,397. On the CPU a copy's lanes run one after another in its thread (CI checks the lanes' sharing there).
- ``"pairs"`` / ``"rows"`` (session 51), right-looking (outer-product) elimination: column ``j``'s update ``a_ik -=
  a_ij a_kj / d_j`` (``j < k <= i``, rows ``i, k`` in ``j``'s front) shared entry by entry (the pairs listed row by row,
  a lane every ``lanes``-th) or a thread a row; every update a read-modify-write of the envelope.

On the H100 (B = 1024, one Forming Newton matrix, ``benchmarks/bench_envelope.py``, session 52) :meth:`factorize`
takes 26-28 ms with ``"dots"`` at 256 threads a copy (group 4; ``"pairs"`` 36.5, 43.1 at 128), but its gather and
elimination kernels alone 8.1 ms (``"panels"`` 6.4; B = 256: 3.6 / 2.7). Without the CG's set-up (session 53) the
call took the same at B = 256 (12.5 -> 12.4 ms, kernels 3.5-3.7 ms): what is left outside the kernels is not the
preconditioner but the vertex blocks' upload and expansion, the outside check and the launches (not timed apart;
docs/gpu_roofline.md). In a lockstep Forming step (H200, B = 1024, session 62) ``"panels"``' kernels take 44.3 ms a
step against ``"dots"``' 58.4, each phase's device work synchronised in one process (:data:`CUDA_SCHEDULE`). A pivot that is not
positive (or not finite) marks its copy :attr:`BatchedPCG.indefinite` (the matrix is not positive definite: exact,
unlike the CG's ``p.Ap <= 0``); the elimination goes on with 1 in its place, and that copy's solution is not used.

Solve. With ``"dots"`` and ``"panels"``, both passes by the envelope's rows, one warp a copy: forward ``u_i = (b_i - sum_k w_ik u_k) /
d_i`` a row at a time (the row's sum shared by the warp's lanes, a shuffle sum), then ``v = D u`` and backward ``x_j =
v_j / d_j``, ``v_k -= w_jk x_j`` over row ``j`` (6.4 ms at B = 1024 against 7.1 by columns); a synchronised pass a
row (``substitution="rows"``) or a vertex's three rows a pass (``"vertices"``, :func:`_substitute_vertices`: they
share their first column, so the forward pass takes their three sums over the earlier positions in one pass over
``u`` and then solves the vertex's 3x3 triangle, the backward pass solves the triangle and then updates the earlier
positions with the three rows at once: 566 passes a Forming solve each way instead of 1,698, the same operations in
the same order on one thread); by default (:data:`SUBSTITUTION`) ``"vertices-ahead"``, which issues a pass's reads of
the factor (the vertex's triangle, each lane's first entries of its rows) one pass early, so that a pass waits on the
solution's reads only: a Forming step's substitution kernels 27.8 -> 15.3 ms at B = 1024 on the H200. Otherwise forward ``W u =
b`` by columns (``u_j = b_j / d_j``, then ``b_i -= a_ij u_j`` for the rows of ``j``'s front, one thread a row) and the
same backward pass. With ``precision="mixed"`` the envelope is stored and factorised in float32 (the dot products
summed in float64) and each solve is followed by ``refinements`` steps of iterative refinement in float64 (``x +=
A^-1 (b - A x)``, the residual by the CG's float64 operator product; Golub & Van Loan, Sec. 3.5.3): one "iteration" a
solve and one a refinement (:attr:`BatchedPCG.iterations`). CI runs both schedules and every substitution on the CPU
(one thread a copy); the lanes' sharing (the groups' shuffle sums, the synchronisations, the substitutions' early
reads) runs on CUDA only, checked there by the benchmark's residual against the float64 operator (1.2e-13) and, for
the substitutions, against SciPy on 1,024 copies (5.5e-15, session 63).

Storage a copy: the envelope, float64 or float32 ``(E,)`` (``E`` the envelope's entries), the solve's vector float64
``(m,)``, with ``"dots"`` the pivots' inverses float64 ``(m,)`` (``"panels"``: a ring of them and the vertex block's
six partial entries in a CUDA block's shared memory, 4.1 KiB for Forming); shared: ``off``, ``first``, ``fptr`` int32 ``(m,)``, the columns' fronts int32 ``(E - m,)``, each DoF's
position, int32 ``(n,)``, and each ``U`` entry's row, int32 ``(nnz,)`` (its place in the envelope found by the gather,
so that a widening moves no host array). Forming (``benchmarks/bench_envelope.py``, third step, all 1,698 DoFs of a
copy, its contacts inside): 58,926 entries, widest row 411, 0.45 MiB a copy in float64.
"""

import numpy as np

from sim_core.ti_backend import require_backend, ti
from sim_core.ti_kernels import transfer
from sim_core.ti_kernels.envelope_blocks import PANEL, factor_blocks, launch_shape, panel_rows, substitute_blocks
from sim_core.ti_kernels.envelope_funcs import _F64, _I32, _gather_rhs, _group_sum, _pivot, _row_dot
from sim_core.ti_kernels.pcg import BatchedPCG, _apply, _copy_in, _copy_out
from sim_core.ti_kernels.precision import VALUES, stored


CUDA_LANES = 256
"""Threads of one copy (one CUDA thread block) in the factorisation on CUDA (and the column solve; the row solve of
``"dots"`` takes one warp): 27.7 ms a Forming factorisation at B = 1024 on the H100 against 32.1 at 128 (session 52);
its gather and elimination kernels alone 8.1 against 12.9 (``"panels"`` 6.4 against 7.4)."""

CUDA_GROUP = 4
"""Lanes of one dot product in the left-looking factorisation (``schedule="dots"``) on CUDA: at 256 threads a copy 4
and 8 tie (27.7 / 27.6 ms), 2 and 16 are slower (32.6 / 34.3; H100, B = 1024, session 52)."""

SCHEDULES = ("pairs", "rows", "dots", "panels", "blocks")
"""How a copy's threads share its factorisation (:class:`BatchedEnvelope`)."""

CUDA_SCHEDULE = "panels"
"""The schedule of a :class:`BatchedEnvelope` given none on CUDA. ``"panels"``' gather and factorisation kernels take
24 % less than ``"dots"``' in a lockstep Forming step (H200, B = 1024, the same process, each phase's device work
synchronised: 44.3 against 58.4 ms a step, 6.0 against 8.1 ms a factorisation at the fourth step; the same Newton
iterations and factorisations; docs/gpu_roofline.md, session 62), as on one matrix (6.4 against 8.1 ms at B = 1024, 2.7
against 3.6 at 256, H100, session 52). ``"blocks"`` (panels of columns,
:mod:`sim_core.ti_kernels.envelope_blocks`) is slower on the device: gather + elimination 10.6-11.8 ms against 8.15,
solve 7.9-8.2 against 7.25 (panel 12 at 128 / 256 threads a copy, one Forming Newton matrix at B = 1024, H200;
docs/gpu_roofline.md, session 58's lead section): opt-in."""

SUBSTITUTIONS = ("rows", "vertices", "vertices-ahead")
"""How the forward and back substitutions of the left-looking schedules (``"dots"``, ``"panels"``) take a copy's rows
(:class:`BatchedEnvelope`'s ``substitution``)."""

SUBSTITUTION = "vertices-ahead"
"""The substitution of a :class:`BatchedEnvelope` given none with ``schedule="dots"`` or ``"panels"``: by vertices, a
vertex's three rows a synchronised pass, each pass's reads of the factor issued one pass early
(:func:`_substitute_vertices`); ``"vertices"``: issued at the pass's start; ``"rows"``: a row a pass
(:func:`_substitute`). On CUDA (H200, B = 1024, one process, session 63) a lockstep Forming step's substitution
kernels take 15.3 ms against ``"rows"``' 27.8 (each phase's device work synchronised; the same Newton iterations and
factorisations) and the steady rate rises 2,379 -> 2,729 scene-steps/s (B = 256: 1,557 -> 1,818); a solve of B =
1024 copies of a 561-vertex grid matrix 1.62 ms (``"vertices"`` 2.14, ``"rows"`` 3.79; docs/gpu_roofline.md). On the
CPU arch (one thread a copy) all three are the same operations in the same order, the same bits."""

SCHEDULE = "dots"
"""The schedule of a :class:`BatchedEnvelope` given none elsewhere than on CUDA (one thread a copy). ``"blocks"``
factorises a Forming matrix ~1.5x faster there (59 against 91 ms at B = 8 on the VM, session 58) but its kernels'
unrolled panels take ~120 s to compile into an empty cache against ~17 s (the float64 and float32 kernels, VM under
load): not worth every CI process's first envelope on the CPU, where the envelope is opt-in
(docs/gpu_roofline.md, "The envelope by panels of columns")."""



@ti.kernel
def _mark_outside(brow: _I32, bcol: _I32, free: _F64, nblocks: ti.i32, pos: _I32, first: _I32, need: _I32,
                  flags: _I32, m: ti.i32, copies: ti.i32):
    """``need = first``, then ``need[i] = min(need[i], j)`` and ``flags[copies] = 1`` (else 0) for each vertex blocks'
    coupling ``(i, j)`` (positions, ``i >= j``, both DoFs free) left of the envelope row ``i`` (``j < first[i]``)."""
    for i in range(m):
        need[i] = first[i]
    for _ in range(1):
        flags[copies] = 0
    for t in range(nblocks):
        for a in ti.static(range(3)):
            for b in ti.static(range(3)):
                r = 3 * brow[t] + a
                c = 3 * bcol[t] + b
                if free[r] * free[c] != 0.0:
                    i = ti.max(pos[r], pos[c])
                    j = ti.min(pos[r], pos[c])
                    if j < first[i]:
                        ti.atomic_min(need[i], j)
                        flags[copies] = 1


@ti.func
def _place(urow: ti.template(), indices: ti.template(), pos: ti.template(), seg: ti.template(), off: ti.template(),
           first: ti.template(), size, k):
    """The envelope index of ``U``'s entry ``k`` (row ``urow[k]``, column ``indices[k]``) in its copy's envelope."""
    r = urow[k]
    i = ti.max(pos[r], pos[indices[k]])
    j = ti.min(pos[r], pos[indices[k]])
    return seg[r] * size + off[i] + j - first[i]


@ti.kernel
def _selected(source: _I32, todo: _I32, copies: ti.i32):
    """``todo[c] = 1`` where ``source[c]`` is 1 (:data:`~sim_core.ti_kernels.copy_vectors.TAKE`), else 0."""
    for c in range(copies):
        todo[c] = 1 if source[c] == 1 else 0


@ti.kernel
def _assemble(data: _F64, urow: _I32, indices: _I32, nnz: ti.i32, slots: _I32, diag: _F64, nslots: ti.i32,
              fixed: _I32, nfixed: ti.i32, brow: _I32, bcol: _I32, bval: VALUES, free: _F64, nblocks: ti.i32,
              pos: _I32, seg: _I32, off: _I32, first: _I32, env: VALUES, total: ti.i32, padded: _I32, npadded: ti.i32,
              size: ti.i32, todo: _I32):
    """The envelopes of ``A`` of the copies ``c`` with ``todo[c] != 0`` (the others' left as they are): zeroed,
    ``U``'s entries (row ``urow[k]``, column ``indices[k]``) at their place, then ``diag[s]`` added at ``U``'s entries
    ``slots[s]`` and 1 put at its entries ``fixed`` (the diagonal of :meth:`BatchedPCG.factorize`, straight into the
    envelope), the vertex blocks' entries in the lower triangle of the order added (free DoFs only), 1 on the diagonal
    of padded rows (``padded``: envelope indices)."""
    for k in range(total):
        if todo[k // size] != 0:
            env[k] = stored(0.0, env)
    for k in range(nnz):
        if todo[seg[urow[k]]] != 0:
            env[_place(urow, indices, pos, seg, off, first, size, k)] = stored(data[k], env)
    for s in range(nslots):
        if todo[seg[urow[slots[s]]]] != 0:
            at = _place(urow, indices, pos, seg, off, first, size, slots[s])
            env[at] = stored(ti.cast(env[at], ti.f64) + diag[s], env)
    for s in range(nfixed):
        if todo[seg[urow[fixed[s]]]] != 0:
            env[_place(urow, indices, pos, seg, off, first, size, fixed[s])] = stored(1.0, env)
    for t in range(nblocks):
        if todo[seg[3 * brow[t]]] != 0:
            for a in ti.static(range(3)):
                for b in ti.static(range(3)):
                    r = 3 * brow[t] + a
                    c = 3 * bcol[t] + b
                    w = free[r] * free[c] * ti.cast(bval[9 * t + 3 * a + b], ti.f64)
                    i = pos[r]
                    j = pos[c]
                    if w != 0.0 and i >= j and j >= first[i]:  # (one outside: the envelope widened, this done again)
                        ti.atomic_add(env[seg[r] * size + off[i] + j - first[i]], stored(w, env))
    for k in range(npadded):
        if todo[padded[k] // size] != 0:
            env[padded[k]] = stored(1.0, env)


@ti.func
def _pair(t):
    """The ``t``-th pair ``(p, q)``, ``0 <= q <= p``, of the lower triangle listed row by row (``t = p (p + 1) / 2 +
    q``)."""
    p = ti.cast((ti.sqrt(8.0 * ti.cast(t, ti.f64) + 1.0) - 1.0) * 0.5, ti.i32)
    while (p + 1) * (p + 2) // 2 <= t:
        p += 1
    while p * (p + 1) // 2 > t:
        p -= 1
    return p, t - p * (p + 1) // 2


@ti.func
def _update(env: ti.template(), off: ti.template(), first: ti.template(), base, i, k, j, d):
    """``a_ik -= a_ij a_kj / d_j`` in a copy's envelope (``base`` its first entry)."""
    row = base + off[i] - first[i]
    a = ti.cast(env[row + j], ti.f64)
    if a != 0.0:
        env[row + k] = stored(env[row + k] - a / d * env[base + off[k] - first[k] + j], env)


@ti.kernel
def _factor(env: VALUES, off: _I32, first: _I32, fptr: _I32, frows: _I32, todo: _I32, bad: _I32, m: ti.i32,
            size: ti.i32, copies: ti.i32, lanes: ti.template(), by_rows: ti.template()):
    """Each copy's envelope eliminated in place into ``W`` (module docstring); ``bad[c] = 1`` where a pivot of copy
    ``c`` is not positive; copies with ``todo[c] == 0`` skipped. Column ``j``'s front, the rows below it that reach it,
    is ``frows[fptr[j]:fptr[j + 1]]`` (increasing); ``lanes`` threads a copy (a CUDA block) share the column's update:
    ``by_rows``, a lane a row of the front (its entries ``k <= i`` in turn), else entry by entry (the pairs ``k <= i``
    of the front listed row by row, a lane every ``lanes``-th, so that the front's longest row is not one thread's
    chain)."""
    ti.loop_config(block_dim=lanes)
    for t in range(copies * lanes):
        c = t // lanes
        lane = t % lanes
        if lane == 0:
            bad[c] = 0
        if todo[c] != 0:
            base = c * size
            for j in range(m):
                raw = env[base + off[j] + j - first[j]]
                d = _pivot(raw)
                if lane == 0 and not ti.cast(raw, ti.f64) > 0.0:
                    bad[c] = 1
                start = fptr[j]
                front = fptr[j + 1] - start
                if ti.static(by_rows):
                    p = lane
                    while p < front:
                        i = frows[start + p]
                        for q in range(p + 1):
                            _update(env, off, first, base, i, frows[start + q], j, d)
                        p += lanes
                else:
                    p, q = _pair(lane)
                    while p < front:
                        _update(env, off, first, base, frows[start + p], frows[start + q], j, d)
                        q += lanes
                        while q > p:
                            p += 1
                            q -= p
                if ti.static(lanes > 1):
                    ti.simt.block.sync()


@ti.kernel
def _factor_dots(env: VALUES, off: _I32, first: _I32, fptr: _I32, frows: _I32, todo: _I32, bad: _I32, inv: _F64,
                 m: ti.i32, size: ti.i32, copies: ti.i32, lanes: ti.template(), group: ti.template()):
    """Each copy's envelope factorised in place into ``W`` by columns, left-looking (module docstring, "dots"):
    column ``j``'s entries ``w_ij = a_ij - sum_k w_ik w_jk / d_k`` (``i = j`` and the rows of its front, ``k`` from
    ``max(first[i], first[j])`` to ``j - 1``: two contiguous row segments of the envelope) are independent dot
    products, each taken by ``group`` lanes of a warp (``group`` consecutive ``k`` a pass, a shuffle sum), the
    ``lanes / group`` groups of a copy sharing the column's entries; a block synchronisation a column, each factor
    entry written once. ``inv[c m + j] = 1 / d_j`` (the pivots as :func:`_pivot` uses them); ``bad`` and ``todo`` as
    for :func:`_factor`."""
    ti.loop_config(block_dim=lanes)
    for t in range(copies * lanes):
        c = t // lanes
        lane = t % lanes
        sub = lane % group
        groups = lanes // group
        if lane == 0:
            bad[c] = 0
        if todo[c] != 0:
            base = c * size
            vb = c * m
            for j in range(m):
                fj = first[j]
                rowj = base + off[j] - fj
                start = fptr[j]
                front = fptr[j + 1] - start
                task = lane // group
                while task <= front:  # task 0 the pivot, task p the front's p-th row
                    i = j
                    if task > 0:
                        i = frows[start + task - 1]
                    fi = first[i]
                    rowi = base + off[i] - fi
                    acc = 0.0
                    other = 0.0  # (a second sum: two chains of loads in flight)
                    k = ti.max(fi, fj) + sub
                    while k + group < j:
                        acc += ti.cast(env[rowi + k], ti.f64) * ti.cast(env[rowj + k], ti.f64) * inv[vb + k]
                        other += (ti.cast(env[rowi + k + group], ti.f64) * ti.cast(env[rowj + k + group], ti.f64)
                                  * inv[vb + k + group])
                        k += 2 * group
                    if k < j:
                        acc += ti.cast(env[rowi + k], ti.f64) * ti.cast(env[rowj + k], ti.f64) * inv[vb + k]
                    acc = _group_sum(acc + other, lane, group)
                    if sub == 0:
                        v = ti.cast(env[rowi + j], ti.f64) - acc
                        env[rowi + j] = stored(v, env)
                        if task == 0:
                            stored_v = ti.cast(env[rowi + j], ti.f64)
                            inv[vb + j] = 1.0 / _pivot(stored_v)
                            if not stored_v > 0.0:
                                bad[c] = 1
                    task += groups
                if ti.static(lanes > 1):
                    ti.simt.block.sync()


@ti.func
def _dot3(env: ti.template(), piv: ti.template(), pb, rowi, rowj, rowj1, rowj2, k, j, sub, lane,
          group: ti.template(), pmask: ti.template()):
    """``(s0, s1, s2)``: ``sum_k w_ik w_(j+q)k / d_k`` for ``q = 0, 1, 2`` over ``k`` from ``k`` (this lane's first,
    ``sub`` past the group's) to ``j - 1``, the three pivot rows' column 0 at ``rowj``, ``rowj1``, ``rowj2`` of the
    envelope (a vertex's rows, of one first column), summed over the ``group`` lanes."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    k += sub
    while k < j:
        wi = ti.cast(env[rowi + k], ti.f64) * piv[pb + (k & pmask)]
        s0 += wi * ti.cast(env[rowj + k], ti.f64)
        s1 += wi * ti.cast(env[rowj1 + k], ti.f64)
        s2 += wi * ti.cast(env[rowj2 + k], ti.f64)
        k += group
    return _group_sum(s0, lane, group), _group_sum(s1, lane, group), _group_sum(s2, lane, group)


@ti.func
def _panels_copy(env: ti.template(), piv: ti.template(), blk: ti.template(), pb, bb, c, lane, off: ti.template(),
                 first: ti.template(), fptr: ti.template(), frows: ti.template(), todo: ti.template(),
                 bad: ti.template(), m, size, lanes: ti.template(), group: ti.template(), pcap: ti.template()):
    """One copy's factorisation by :func:`_factor_panels` (its docstring), ``piv`` the copy's ring of pivots' inverses
    from ``pb``, ``blk`` its vertex block's six partial entries from ``bb``."""
    sub = lane % group
    groups = lanes // group
    pmask = ti.static(pcap - 1)
    if lane == 0:
        bad[c] = 0
    if todo[c] != 0:
        base = c * size
        for v in range(m // 3):
            j = 3 * v
            fj = first[j]
            rowj = base + off[j] - fj  # (the vertex's three rows share their first column)
            rowj1 = base + off[j + 1] - fj
            rowj2 = base + off[j + 2] - fj
            start = fptr[j]
            front = fptr[j + 1] - start  # rows j + 1 and j + 2 its first two
            task = lane // group
            while task <= front:  # the three columns' dot products over k < j, one pass over row i
                i = j
                if task > 0:
                    i = frows[start + task - 1]
                fi = first[i]
                rowi = base + off[i] - fi
                s0, s1, s2 = _dot3(env, piv, pb, rowi, rowj, rowj1, rowj2, ti.max(fi, fj), j, sub, lane, group,
                                    pmask)
                if sub == 0:
                    t0 = ti.cast(env[rowi + j], ti.f64) - s0
                    if i == j:
                        blk[bb] = t0
                    elif i == j + 1:
                        blk[bb + 1] = t0
                        blk[bb + 2] = ti.cast(env[rowi + j + 1], ti.f64) - s1
                    elif i == j + 2:
                        blk[bb + 3] = t0
                        blk[bb + 4] = ti.cast(env[rowi + j + 1], ti.f64) - s1
                        blk[bb + 5] = ti.cast(env[rowi + j + 2], ti.f64) - s2
                    else:
                        env[rowi + j] = stored(t0, env)
                        env[rowi + j + 1] = stored(ti.cast(env[rowi + j + 1], ti.f64) - s1, env)
                        env[rowi + j + 2] = stored(ti.cast(env[rowi + j + 2], ti.f64) - s2, env)
                task += groups
            if ti.static(lanes > 1):
                ti.simt.block.sync()
            # the vertex block's W D^-1 W^T (every task the same arithmetic), then each row's three entries
            d0 = ti.cast(stored(blk[bb], env), ti.f64)
            inv0 = 1.0 / _pivot(d0)
            w10 = ti.cast(stored(blk[bb + 1], env), ti.f64)
            w20 = ti.cast(stored(blk[bb + 3], env), ti.f64)
            d1 = ti.cast(stored(blk[bb + 2] - w10 * w10 * inv0, env), ti.f64)
            inv1 = 1.0 / _pivot(d1)
            w21 = ti.cast(stored(blk[bb + 4] - w20 * w10 * inv0, env), ti.f64)
            d2 = ti.cast(stored(blk[bb + 5] - w20 * w20 * inv0 - w21 * w21 * inv1, env), ti.f64)
            task = lane // group
            while task <= front:
                if sub == 0:
                    i = j
                    if task > 0:
                        i = frows[start + task - 1]
                    rowi = base + off[i] - first[i]
                    if i == j:
                        env[rowi + j] = stored(d0, env)
                        piv[pb + (j & pmask)] = inv0
                        piv[pb + ((j + 1) & pmask)] = inv1
                        piv[pb + ((j + 2) & pmask)] = 1.0 / _pivot(d2)
                        if not (d0 > 0.0 and d1 > 0.0 and d2 > 0.0):
                            bad[c] = 1
                    elif i == j + 1:
                        env[rowi + j] = stored(w10, env)
                        env[rowi + j + 1] = stored(d1, env)
                    elif i == j + 2:
                        env[rowi + j] = stored(w20, env)
                        env[rowi + j + 1] = stored(w21, env)
                        env[rowi + j + 2] = stored(d2, env)
                    else:
                        w0 = ti.cast(env[rowi + j], ti.f64)
                        w1 = ti.cast(stored(ti.cast(env[rowi + j + 1], ti.f64) - w0 * w10 * inv0, env), ti.f64)
                        env[rowi + j + 1] = stored(w1, env)
                        env[rowi + j + 2] = stored(ti.cast(env[rowi + j + 2], ti.f64) - w0 * w20 * inv0
                                                   - w1 * w21 * inv1, env)
                task += groups
            if ti.static(lanes > 1):
                ti.simt.block.sync()


@ti.kernel
def _factor_panels(env: VALUES, off: _I32, first: _I32, fptr: _I32, frows: _I32, todo: _I32, bad: _I32,
                   pscratch: _F64, bscratch: _F64, m: ti.i32, size: ti.i32, copies: ti.i32, lanes: ti.template(),
                   group: ti.template(), pcap: ti.template(), shared: ti.template()):
    """Each copy's envelope factorised in place into ``W`` left-looking by vertices (module docstring,
    ``"panels"``): the three columns ``j = 3 v .. 3 v + 2`` of vertex ``v`` (one first column, nested fronts) in two
    synchronised passes: each row ``i`` of the vertex and its front takes its three dot products with the vertex's
    rows over ``k < j`` in one pass (``group`` lanes, a shuffle sum each) and leaves the partial entries (the vertex's
    own six in ``blk``); then every task eliminates the vertex's 3x3 block and finishes its row's three entries. The
    pivots' inverses in a ring of ``pcap`` (a power of two above the widest row). ``shared``: ``piv`` and ``blk`` in
    the CUDA block's shared memory, else in ``pscratch`` / ``bscratch`` (``(copies pcap,)``, ``(copies 8,)``); ``bad``
    and ``todo`` as for :func:`_factor`; the envelope's first columns equal over a vertex's DoFs."""
    ti.loop_config(block_dim=lanes)
    for t in range(copies * lanes):
        c = t // lanes
        lane = t % lanes
        if ti.static(shared):
            piv = ti.simt.block.SharedArray((pcap,), ti.f64)
            blk = ti.simt.block.SharedArray((8,), ti.f64)
            _panels_copy(env, piv, blk, 0, 0, c, lane, off, first, fptr, frows, todo, bad, m, size, lanes, group,
                         pcap)
        else:
            _panels_copy(env, pscratch, bscratch, c * pcap, c * 8, c, lane, off, first, fptr, frows, todo, bad, m,
                         size, lanes, group, pcap)


@ti.func
def _back_substitute(env: ti.template(), off: ti.template(), first: ti.template(), order: ti.template(),
                     x: ti.template(), w: ti.template(), base, vb, m, lane, lanes: ti.template()):
    """The back substitution ``W^T x = v`` of a copy (``v`` in ``w[vb:vb + m]`` on entry, overwritten) by rows of
    ``W``: ``x_j = v_j / d_j``, then ``v_k -= w_jk x_j`` over row ``j``, the ``lanes`` sharing a row, a synchronisation
    a row; ``x`` at the DoFs of ``order`` (lane 0)."""
    for jj in range(m):
        j = m - 1 - jj
        fj = first[j]
        row = base + off[j] - fj
        xj = w[vb + j] / _pivot(env[row + j])
        if lane == 0:
            dof = order[vb + j]
            if dof >= 0:
                x[dof] = xj
        k = fj + lane
        while k < j:
            w[vb + k] -= ti.cast(env[row + k], ti.f64) * xj
            k += lanes
        if ti.static(lanes > 1):
            ti.simt.block.sync()


@ti.kernel
def _substitute(env: VALUES, off: _I32, first: _I32, fptr: _I32, frows: _I32, todo: _I32, order: _I32, b: _F64,
                x: _F64, w: _F64, m: ti.i32, size: ti.i32, copies: ti.i32, lanes: ti.template(),
                by_rows: ti.template()):
    """``x = A^-1 b`` per copy from the factor ``W`` (forward, then back substitution; module docstring); ``b`` and
    ``x`` over the stacked DoFs, ``order[c m + i]`` the DoF at position ``i`` of copy ``c`` (-1: padding), the fronts
    as for :func:`_factor`; copies with ``todo[c] == 0`` get ``x = 0``. The forward pass ``W u = b`` by columns
    (``u_j = b_j / d_j``, then ``b_i -= w_ij u_j`` over ``j``'s front, a lane a row), or ``by_rows`` (``u_i = (b_i -
    sum_k w_ik u_k) / d_i`` a row at a time, the row's sum shared by the ``lanes``, at most 32: one warp a copy, a
    shuffle sum; then ``v = D u``); the backward pass by rows (:func:`_back_substitute`)."""
    ti.loop_config(block_dim=lanes)
    for t in range(copies * lanes):
        c = t // lanes
        lane = t % lanes
        base = c * size
        vb = c * m
        _gather_rhs(order, todo, b, x, w, c, vb, m, lane, lanes)
        if ti.static(lanes > 1):
            ti.simt.block.sync()
        if todo[c] != 0:
            if ti.static(by_rows):
                for i in range(m):
                    fi = first[i]
                    row = base + off[i] - fi
                    acc = _group_sum(_row_dot(env, w, row, vb, fi + lane, i, lanes), lane, lanes)
                    if lane == 0:
                        w[vb + i] = (w[vb + i] - acc) / _pivot(env[row + i])
                    if ti.static(lanes > 1):
                        ti.simt.block.sync()
                p = lane
                while p < m:
                    w[vb + p] = w[vb + p] * _pivot(env[base + off[p] + p - first[p]])
                    p += lanes
                if ti.static(lanes > 1):
                    ti.simt.block.sync()
            else:
                for j in range(m):
                    u = w[vb + j] / _pivot(env[base + off[j] + j - first[j]])
                    e = fptr[j] + lane
                    while e < fptr[j + 1]:
                        i = frows[e]
                        w[vb + i] -= ti.cast(env[base + off[i] - first[i] + j], ti.f64) * u
                        e += lanes
                    if ti.static(lanes > 1):
                        ti.simt.block.sync()
            _back_substitute(env, off, first, order, x, w, base, vb, m, lane, lanes)


@ti.func
def _vertex_block(env: ti.template(), off: ti.template(), first: ti.template(), base, j, lane):
    """What a substitution's pass over vertex rows ``j .. j + 2`` (one first column ``f``) reads of the factor and does
    not depend on the solution: ``(f, row0, row1, row2, e0, e1, e2, a00, a10, a11, a20, a21, a22)``, the rows' column
    0 in a copy's envelope (from ``base``), their entries at this lane's first column ``f + lane`` (0 at or past
    ``j``), and the vertex's 3x3 triangle ``a_pq = w_(j+p)(j+q)``, float64."""
    fj = first[j]
    row0 = base + off[j] - fj
    row1 = base + off[j + 1] - fj
    row2 = base + off[j + 2] - fj
    k = fj + lane
    e0 = 0.0
    e1 = 0.0
    e2 = 0.0
    if k < j:
        e0 = ti.cast(env[row0 + k], ti.f64)
        e1 = ti.cast(env[row1 + k], ti.f64)
        e2 = ti.cast(env[row2 + k], ti.f64)
    return (fj, row0, row1, row2, e0, e1, e2, ti.cast(env[row0 + j], ti.f64), ti.cast(env[row1 + j], ti.f64),
            ti.cast(env[row1 + j + 1], ti.f64), ti.cast(env[row2 + j], ti.f64), ti.cast(env[row2 + j + 1], ti.f64),
            ti.cast(env[row2 + j + 2], ti.f64))


@ti.kernel
def _substitute_vertices(env: VALUES, off: _I32, first: _I32, todo: _I32, order: _I32, b: _F64, x: _F64, w: _F64,
                         m: ti.i32, size: ti.i32, copies: ti.i32, lanes: ti.template(), ahead: ti.template()):
    """``x = A^-1 b`` per copy from the factor ``W`` by vertices (module docstring, ``substitution="vertices"``): the
    forward pass ``W u = b`` a vertex's three rows ``j .. j + 2`` (one first column ``f``) at a time, their three sums
    ``sum_k w_(j+q)k u_k`` over ``f <= k < j`` in one pass over the copy's ``u`` (the ``lanes``, at most 32: one warp
    a copy, three shuffle sums), then the vertex's 3x3 triangle (lane 0); ``v = D u``; the backward pass ``W^T x = v``
    a vertex at a time from the last: the vertex's 3x3 triangle (every lane), then ``v_k -= w_(j+2)k x_(j+2) +
    w_(j+1)k x_(j+1) + w_jk x_j`` over ``f <= k < j`` (the lanes sharing ``k``); one synchronisation a vertex in each
    pass instead of one a row. A pass first issues its reads of the factor that do not depend on the solution
    (:func:`_vertex_block`: the triangle, each lane's first entries of the three rows), so that they are in flight
    together with the solution's; ``ahead``: the next vertex's, one pass early, before this pass's synchronisation.
    The same operations in the same order as :func:`_substitute` ``by_rows`` with one lane. Arguments as for
    :func:`_substitute`; ``m`` a multiple of 3, the envelope's first columns equal over a vertex's rows."""
    ti.loop_config(block_dim=lanes)
    for t in range(copies * lanes):
        c = t // lanes
        lane = t % lanes
        base = c * size
        vb = c * m
        nv = m // 3
        _gather_rhs(order, todo, b, x, w, c, vb, m, lane, lanes)
        if ti.static(lanes > 1):
            ti.simt.block.sync()
        if todo[c] != 0 and nv > 0:
            fj, row0, row1, row2, e0, e1, e2, a00, a10, a11, a20, a21, a22 = _vertex_block(env, off, first, base, 0,
                                                                                           lane)
            for v in range(nv):
                j = 3 * v
                if ti.static(not ahead):
                    fj, row0, row1, row2, e0, e1, e2, a00, a10, a11, a20, a21, a22 = _vertex_block(
                        env, off, first, base, j, lane)
                nxt = _vertex_block(env, off, first, base, ti.min(j + 3, m - 3), lane) if ti.static(ahead) else 0
                s0 = 0.0
                s1 = 0.0
                s2 = 0.0
                k = fj + lane
                if k < j:
                    u = w[vb + k]
                    s0 = e0 * u
                    s1 = e1 * u
                    s2 = e2 * u
                    k += lanes
                    while k < j:
                        u = w[vb + k]
                        s0 += ti.cast(env[row0 + k], ti.f64) * u
                        s1 += ti.cast(env[row1 + k], ti.f64) * u
                        s2 += ti.cast(env[row2 + k], ti.f64) * u
                        k += lanes
                s0 = _group_sum(s0, lane, lanes)
                s1 = _group_sum(s1, lane, lanes)
                s2 = _group_sum(s2, lane, lanes)
                if lane == 0:  # (the writer of the vertex's three entries reads them: no other lane does)
                    u0 = (w[vb + j] - s0) / _pivot(a00)
                    s1 += a10 * u0
                    u1 = (w[vb + j + 1] - s1) / _pivot(a11)
                    s2 += a20 * u0
                    s2 += a21 * u1
                    w[vb + j] = u0
                    w[vb + j + 1] = u1
                    w[vb + j + 2] = (w[vb + j + 2] - s2) / _pivot(a22)
                if ti.static(lanes > 1):
                    ti.simt.block.sync()
                if ti.static(ahead):
                    fj, row0, row1, row2, e0, e1, e2, a00, a10, a11, a20, a21, a22 = nxt
            p = lane
            while p < m:
                w[vb + p] = w[vb + p] * _pivot(env[base + off[p] + p - first[p]])
                p += lanes
            if ti.static(lanes > 1):
                ti.simt.block.sync()
            fj, row0, row1, row2, e0, e1, e2, a00, a10, a11, a20, a21, a22 = _vertex_block(env, off, first, base,
                                                                                           m - 3, lane)
            for vv in range(nv):
                j = m - 3 - 3 * vv
                if ti.static(not ahead):
                    fj, row0, row1, row2, e0, e1, e2, a00, a10, a11, a20, a21, a22 = _vertex_block(
                        env, off, first, base, j, lane)
                nxt = _vertex_block(env, off, first, base, ti.max(j - 3, 0), lane) if ti.static(ahead) else 0
                x2 = w[vb + j + 2] / _pivot(a22)
                x1 = (w[vb + j + 1] - a21 * x2) / _pivot(a11)
                x0 = ((w[vb + j] - a20 * x2) - a10 * x1) / _pivot(a00)
                if lane == 0:
                    dof0 = order[vb + j]
                    dof1 = order[vb + j + 1]
                    dof2 = order[vb + j + 2]
                    if dof0 >= 0:
                        x[dof0] = x0
                    if dof1 >= 0:
                        x[dof1] = x1
                    if dof2 >= 0:
                        x[dof2] = x2
                k = fj + lane
                if k < j:
                    w[vb + k] = ((w[vb + k] - e2 * x2) - e1 * x1) - e0 * x0
                    k += lanes
                    while k < j:
                        w[vb + k] = ((w[vb + k] - ti.cast(env[row2 + k], ti.f64) * x2)
                                     - ti.cast(env[row1 + k], ti.f64) * x1) - ti.cast(env[row0 + k], ti.f64) * x0
                        k += lanes
                if ti.static(lanes > 1):
                    ti.simt.block.sync()
                if ti.static(ahead):
                    fj, row0, row1, row2, e0, e1, e2, a00, a10, a11, a20, a21, a22 = nxt


@ti.kernel
def _residual_step(b: _F64, ax: _F64, r: _F64, n: ti.i32):
    """``r = b - A x``."""
    for i in range(n):
        r[i] = b[i] - ax[i]


@ti.kernel
def _add(x: _F64, dx: _F64, n: ti.i32):
    """``x += dx``."""
    for i in range(n):
        x[i] += dx[i]


def envelope_order(indptr: np.ndarray, indices: np.ndarray, seg: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                        np.ndarray]:
    """Each copy's DoFs in the reverse Cuthill-McKee order of the union of the copies' vertex graphs of a pattern, and
    the envelope of that union in it.

    Args:
        indptr, indices: CSR arrays of a pattern over the stacked DoFs (one triangle or both), ``n + 1`` and ``nnz``.
        seg: the copy of each DoF, ``(n,)`` int, constant over a vertex's three DoFs; every copy the same count.

    Returns:
        ``(order, pos, first)``: ``order`` int64 ``(B, m)``, row ``c`` copy ``c``'s DoFs in that order (a vertex's
        three DoFs consecutive); ``pos`` int64 ``(n,)``, each DoF's position in its copy's row; ``first`` int64
        ``(m,)``, the first column of each position's envelope row (the vertex graph's: a coupled vertex pair couples
        its six DoFs, a vertex its three).

    Raises:
        ValueError: copies with different numbers of DoFs.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    seg = np.asarray(seg, dtype=np.int64)
    n = seg.size
    vcopy = seg[::3]
    counts = np.bincount(vcopy)
    if counts.size and (counts != counts[0]).any():
        raise ValueError(f"BatchedEnvelope: copies with different vertex counts {sorted(set(counts.tolist()))}")
    copies, nv = counts.size, int(counts[0]) if counts.size else 0
    local = np.empty(n // 3, dtype=np.int64)  # a vertex's index within its copy (vertices in increasing order)
    by_copy = np.argsort(vcopy, kind="stable")
    local[by_copy] = np.tile(np.arange(nv), copies)
    rows = local[np.repeat(np.arange(n // 3, dtype=np.int64), np.diff(np.asarray(indptr)).reshape(-1, 3).sum(1))]
    cols = local[np.asarray(indices, dtype=np.int64)[: rows.size] // 3]
    if nv * nv <= 1 << 27:  # the local vertex pairs marked in a dense (nv, nv) mask: no sort of the stacked entries
        mask = np.zeros((nv, nv), dtype=bool)
        mask[rows, cols] = True
        a, c = np.nonzero(mask | mask.T)
    else:
        keys = np.unique(rows * nv + cols)
        a, c = np.concatenate([keys // nv, keys % nv]), np.concatenate([keys % nv, keys // nv])
    graph = coo_matrix((np.ones(a.size), (a, c)), shape=(nv, nv)).tocsr()
    vorder = reverse_cuthill_mckee(graph, symmetric_mode=True).astype(np.int64)  # local vertices in order
    rank = np.empty(nv, dtype=np.int64)
    rank[vorder] = np.arange(nv)
    stacked = by_copy.reshape(copies, nv)  # copy c's vertices by local index
    order = (3 * stacked[:, vorder][:, :, None] + np.arange(3)).reshape(copies, 3 * nv)
    pos = (3 * rank[local][:, None] + np.arange(3)).reshape(-1)
    vfirst = np.arange(nv)
    np.minimum.at(vfirst, np.maximum(rank[a], rank[c]), np.minimum(rank[a], rank[c]))
    first = np.repeat(3 * vfirst, 3)
    return order, pos, first


def envelope_rows(first: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(off, fptr, frows)`` of an envelope with rows ``first[i] .. i``: ``off`` int64 ``(m + 1,)`` each row's start
    (row ``i``'s entry of column ``j`` at ``off[i] + j - first[i]``; ``off[m]`` the entries); column ``j``'s front, the
    rows ``i > j`` with ``first[i] <= j``, increasing, is ``frows[fptr[j]:fptr[j + 1]]`` (``fptr`` int64 ``(m + 1,)``,
    ``frows`` int64 ``(off[m] - m,)``)."""
    m = first.size
    widths = np.arange(m) - first  # entries left of the diagonal a row
    off = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(widths + 1, out=off[1:])
    rows = np.repeat(np.arange(m, dtype=np.int64), widths)
    cols = np.repeat(first.astype(np.int64), widths) + (np.arange(rows.size) - np.repeat(off[:-1] - np.arange(m),
                                                                                         widths))
    by_column = np.lexsort((rows, cols))
    fptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(np.bincount(cols, minlength=m), out=fptr[1:])
    return off, fptr, rows[by_column]


class BatchedEnvelope(BatchedPCG):
    """Each copy's Newton system solved directly by the envelope Cholesky on the device (module docstring); Taichi
    must be initialised.

    Args:
        segments: the copy of each DoF, shape ``(n,)`` int, ``0..B-1``, constant over a vertex's three DoFs, every copy
            the same count; None: one copy.
        precision: ``"double"`` (float64 envelope and factor) or ``"mixed"`` (float32 envelope and factor, float64
            iterative refinement).
        refinements: refinement steps a solve with ``precision="mixed"`` (ignored with ``"double"``).
        lanes: threads a copy; None: :data:`CUDA_LANES` on CUDA, 1 elsewhere (where ``"blocks"`` runs more, they run one
            after another in a copy's thread: :mod:`sim_core.ti_kernels.envelope_blocks`).
        schedule: how a copy's threads share its factorisation: right-looking, a column's update ``"pairs"`` (entry
            by entry) or ``"rows"`` (a thread a row); or left-looking ``"dots"`` (a column's entries as dot products of
            two rows, ``group`` lanes each, and both substitutions by rows or vertices, ``substitution``, a warp a copy) or
            ``"panels"`` (a vertex's three columns at once, the same substitutions) or ``"blocks"`` (panels of ``panel`` columns, three passes a panel,
            the substitutions by panels too: :mod:`sim_core.ti_kernels.envelope_blocks`); None: :data:`CUDA_SCHEDULE`
            on CUDA, :data:`SCHEDULE` elsewhere.
        group: lanes of one dot product with ``schedule="dots"``, ``"panels"`` or ``"blocks"`` (on CUDA), a power of two
            of at most 32 dividing the lanes; None: :data:`CUDA_GROUP` with several threads a copy (at most the lanes),
            1 with one.
        panel: columns a panel with ``schedule="blocks"``, at least 1; None:
            :data:`~sim_core.ti_kernels.envelope_blocks.PANEL`.
        substitution: with ``schedule="dots"`` or ``"panels"``, both substitutions ``"rows"`` (a row a synchronised
            pass) or ``"vertices"`` (a vertex's three rows a pass, their sums in one pass over the solution so far;
            ``"vertices-ahead"``: each pass's reads of the factor issued one pass early); None: :data:`SUBSTITUTION`. Ignored by the other schedules.

    Raises:
        ConfigError: an unknown ``precision``.
        ValueError: an unknown ``schedule`` or ``substitution``, a ``group`` that is not a power of two of at most 32 dividing the
            lanes, or a ``panel`` under 1.

    Attributes:
        name: ``"envelope"``.
        entries: the envelope's entries a copy (0 before the first :meth:`factorize`).
        widenings: times a factorisation's vertex blocks widened the envelope (found by the solve after it).
        iterations: solves of the last :meth:`solve` (1, plus its refinements).
        indefinite: copies whose last factorisation met a pivot that is not positive, ``(B,)`` bool (set by the solve
            after it).
        unconverged: all False ``(B,)`` (a direct solve).
    """

    name = "envelope"
    device_copies = True
    """:meth:`factorize` takes its ``copies`` as a device array too (:meth:`_select`)."""
    direct = True
    """Each copy's factors of the last :meth:`factorize` stay on the device until the next: a later solve (the
    lockstep's simplified Newton test) substitutes with them, no factorisation (with ``precision="double"``: the
    ``"mixed"`` refinements read the operator of that factorisation too)."""

    def __init__(self, segments: "np.ndarray | None" = None, precision: str = "double", refinements: int = 2,
                 lanes: int | None = None, schedule: str | None = None, group: int | None = None,
                 panel: int | None = None, substitution: str | None = None) -> None:
        super().__init__(segments, precision="double")  # the operator (for the refinement's residual) in float64
        from sim_core.ti_kernels.precision import storage_dtype

        self.envelope_precision = precision
        self._env_dtype = storage_dtype(precision)
        self.refinements = int(refinements) if precision != "double" else 0
        self.lanes = lanes
        if schedule not in (None, *SCHEDULES):
            raise ValueError(f"BatchedEnvelope: schedule must be one of {'|'.join(SCHEDULES)}, got {schedule!r}")
        self._schedule = schedule
        if substitution not in (None, *SUBSTITUTIONS):
            raise ValueError(f"BatchedEnvelope: substitution must be one of {'|'.join(SUBSTITUTIONS)}, got "
                             f"{substitution!r}")
        self._substitution = substitution
        self._group = group
        self.panel = int(panel) if panel is not None else PANEL
        if self.panel < 1:
            raise ValueError(f"BatchedEnvelope: panel must be at least 1 column, got {panel}")
        self._npanels = 0
        if group is not None:
            self.group  # (checked against the lanes now)
        self._pcap = 1
        self.entries = 0
        self.widenings = 0
        self._layout: tuple | None = None  # (indptr_h, indices_h): the pattern the order and slots belong to
        self._first: np.ndarray | None = None
        self._todo = np.ones(0, dtype=np.int32)
        self._nnz = 0
        self._checked = True
        self._pending: tuple | None = None  # factorize's (indptr, indices, data, diagonal), for _operator
        self._operator_made = False
        self._source: tuple | None = None  # (U's values on the device, the diagonal's arrays or None): _eliminate's

    @property
    def schedule(self) -> str:
        """``"pairs"``, ``"rows"``, ``"dots"``, ``"panels"`` or ``"blocks"`` (the class docstring)."""
        if self._schedule is not None:
            return self._schedule
        return CUDA_SCHEDULE if require_backend("BatchedEnvelope") == "cuda" else SCHEDULE

    @property
    def substitution(self) -> str:
        """``"rows"``, ``"vertices"`` or ``"vertices-ahead"``: how the substitutions of ``"dots"`` and ``"panels"`` take a copy's rows (the
        class docstring); ``"columns"`` with ``"pairs"`` and ``"rows"``, ``"panels of columns"`` with ``"blocks"``."""
        schedule = self.schedule
        if schedule in ("pairs", "rows"):
            return "columns"
        if schedule == "blocks":
            return "panels of columns"
        return self._substitution if self._substitution is not None else SUBSTITUTION

    @property
    def group(self) -> int:
        """Lanes of one dot product with ``schedule="dots"`` (the class docstring)."""
        lanes = self._lane_count()
        group = self._group if self._group is not None else min(CUDA_GROUP, lanes) if lanes > 1 else 1
        if group < 1 or group > 32 or group & (group - 1) or lanes % group:
            raise ValueError(f"BatchedEnvelope: group must be a power of two of at most 32 dividing the {lanes} lanes, "
                             f"got {group}")
        return group

    def _lane_count(self) -> int:
        if self.lanes is not None:
            return int(self.lanes)
        return CUDA_LANES if require_backend("BatchedEnvelope") == "cuda" else 1

    def factorize(self, upper, blocks=None, diagonal: tuple | None = None, copies=None,
                  keep_bands: bool = False) -> bool:
        """Each copy's envelope Cholesky factor of ``A`` (:meth:`BatchedPCG.factorize`'s arguments and operator; of the
        copies in ``copies`` only, where given: a bool ``(B,)`` host mask or an int32 device array whose entries 1 mark
        them, e.g. :meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors.blend_actions`; the others' envelopes are
        neither gathered nor factorised, their next solves give 0 and their :attr:`indefinite` is False);
        ``keep_bands`` is ignored. ``U``'s
        values and ``diagonal`` go straight into the envelope on the device (``data`` a Taichi ndarray is read where it
        is: it must stay unchanged until the next solve, which may gather it again after a widening); none of the CG's
        set-up is made (its block-Jacobi preconditioner, its both-triangle operator: that one only for the refinements
        of ``precision="mixed"`` and :meth:`matvec`, on their first use after this call). True; nothing is read back
        here: the next solve's one read gives :attr:`indefinite` (the copies whose matrix is not positive definite) and
        whether the vertex blocks fell outside the envelope (then widened, this factorisation and that solve done
        again)."""
        indptr_h, indices_h, data_h, n = self._checked_csr(upper, blocks)
        self._pending = (indptr_h, indices_h, data_h, diagonal)  # the CG's operator, made on first use (_operator)
        self._operator_made = False
        nnz = int(indptr_h[-1])
        seg = self._upload_segments()
        self._blocks_on_device(blocks)
        self._upload("indptr", indptr_h, ti.i32)
        self._upload("indices", indices_h if indices_h.size == nnz else indices_h[:nnz], ti.i32)
        if self.refinements:  # the refinements' float64 operator: its values with the diagonal, gathered from there
            self._operator()
            self._source = (self._arrays["data"], None)
        else:
            if isinstance(data_h, np.ndarray):
                data = self._array("env_data", max(nnz, 1))
                if nnz:
                    transfer.upload(data, data_h[:nnz])
            else:
                data = data_h
            self._source = (data, None if diagonal is None or not nnz else (
                self._upload("diag_slots", diagonal[0], ti.i32), self._upload("diag", diagonal[1], ti.f64),
                int(np.size(diagonal[0])), self._upload("fixed_slots", diagonal[2], ti.i32), int(np.size(diagonal[2]))))
        if self._layout is None or self._layout[0] is not indptr_h or self._layout[1] is not indices_h:
            self._new_layout(indptr_h, indices_h, seg)
        a = self._arrays
        B = self._copies
        flags = self._array("env_flags", B + 1, ti.i32)  # each copy's "not positive definite", then "outside"
        _mark_outside(a["brow"], a["bcol"], a["free"], self._nblocks, a["env_pos"], a["env_first"],
                      self._array("env_need", self._m, ti.i32), flags, self._m, B)
        self._select(copies)
        self._nnz = nnz
        self._eliminate()
        self._checked = False  # the "outside" flag is read with the next solve's (one wait for both)
        self.unconverged = np.zeros(B, dtype=bool)
        return True

    def _select(self, copies) -> None:
        """The copies to factorise (:meth:`factorize`'s ``copies``) in the device array ``env_todo`` (1: factorise):
        every copy (None: the same host array each time, uploaded once), a host mask (uploaded), or a device array
        whose entries 1 mark them (copied there by a kernel: nothing travels)."""
        B = self._copies
        if copies is None:
            if self._todo.shape != (B,) or not self._todo.all():
                self._todo = np.ones(B, dtype=np.int32)
            self._upload("env_todo", self._todo, ti.i32)
        elif isinstance(copies, np.ndarray):
            self._todo = np.asarray(copies, dtype=np.int32)
            self._upload("env_todo", self._todo, ti.i32)
        else:
            todo = self._array("env_todo", max(B, 1), ti.i32)
            self._uploaded["env_todo"] = None  # (a host mask given next is sent)
            _selected(copies, todo, B)

    def _eliminate(self) -> None:
        """Gather the envelopes of the copies of ``env_todo`` (:meth:`_select`) and factorise them."""
        a = self._arrays
        B, m, size = self._copies, self._m, self.entries
        env = self._array("env", max(B * size, 1), self._env_dtype)
        data, diagonal = self._source
        if diagonal is None:
            none_i, none_f = self._array("env_none_i", 1, ti.i32), self._array("env_none_f", 1)
            diagonal = (none_i, none_f, 0, none_i, 0)
        todo = a["env_todo"]
        _assemble(data, a["env_urow"], a["indices"], self._nnz, *diagonal, a["brow"], a["bcol"], a["bval"], a["free"],
                  self._nblocks, a["env_pos"], a["seg"], a["env_off"], a["env_first"], env, B * size,
                  a["env_padded"], self._npadded, size, todo)
        if self.schedule == "panels":
            shared = require_backend("BatchedEnvelope") == "cuda"
            pcap = self._pcap
            _factor_panels(env, a["env_off"], a["env_first"], a["env_fptr"], a["env_frows"], todo, a["env_flags"],
                           self._array("env_pring", 1 if shared else B * pcap),
                           self._array("env_blk", 1 if shared else 8 * B), m, size, B, self._lane_count(), self.group,
                           pcap, shared)
        elif self.schedule == "blocks":
            shared, lanes, group, shape = self._blocks_launch(self._lane_count())
            factor_blocks(env, a["env_off"], a["env_first"], a["env_pptr"], a["env_prows"], todo, a["env_flags"],
                          self._array("env_inv", max(B * m, 1)), self._array("env_blk", 1 if shared else B * shape[2]),
                          m, size, B, self._npanels, lanes, group, self.panel, shared, *shape)
        elif self.schedule == "dots":
            _factor_dots(env, a["env_off"], a["env_first"], a["env_fptr"], a["env_frows"], todo, a["env_flags"],
                         self._array("env_inv", max(B * m, 1)), m, size, B, self._lane_count(), self.group)
        else:
            _factor(env, a["env_off"], a["env_first"], a["env_fptr"], a["env_frows"], todo, a["env_flags"], m, size,
                    B, self._lane_count(), self.schedule == "rows")

    def _new_layout(self, indptr_h: np.ndarray, indices_h: np.ndarray, seg: np.ndarray) -> None:
        """The order and the envelope of ``U``'s pattern (module docstring), on the device."""
        order, pos, first = envelope_order(indptr_h, indices_h, seg)
        self._order = order
        self._m = order.shape[1]
        rows = np.repeat(np.arange(self._n, dtype=np.int32), np.diff(np.asarray(indptr_h)))
        _copy_in(self._array("env_urow", max(rows.size, 1), ti.i32), rows if rows.size else np.zeros(1, np.int32))
        _copy_in(self._array("env_pos", max(self._n, 1), ti.i32), pos.astype(np.int32))
        _copy_in(self._array("env_order", max(order.size, 1), ti.i32), order.reshape(-1).astype(np.int32))
        self._layout = (indptr_h, indices_h)
        self._set_envelope(first)

    def _set_envelope(self, first: np.ndarray) -> None:
        """The envelope with rows ``first[i] .. i``: its offsets and reach on the device."""
        self._first = first.astype(np.int64)
        off, fptr, frows = envelope_rows(self._first)
        self.entries = int(off[-1])
        if self._copies * self.entries >= 2 ** 31:
            raise ValueError(f"BatchedEnvelope: {self._copies} copies of {self.entries} envelope entries exceed int32 "
                             f"indices")
        for name, host in (("env_off", off), ("env_first", self._first), ("env_fptr", fptr), ("env_frows", frows)):
            _copy_in(self._array(name, max(host.size, 1), ti.i32), host.astype(np.int32))
        if self.schedule == "blocks":
            pptr, prows = panel_rows(self._first, self.panel)
            self._npanels = pptr.size - 1
            for name, host in (("env_pptr", pptr), ("env_prows", prows)):
                _copy_in(self._array(name, max(host.size, 1), ti.i32), host.astype(np.int32))
        widest = int((np.arange(self._m) - self._first).max()) + 1 if self._m else 1
        self._pcap = 1 << widest.bit_length()  # (the pivots' ring of "panels": a power of two above the widest row)
        padded = np.flatnonzero(self._order.reshape(-1) < 0)  # (none while every copy has the same count)
        row = padded % self._m
        diag = (padded // self._m) * self.entries + off[row] + row - self._first[row]
        self._npadded = int(diag.size)
        _copy_in(self._array("env_padded", max(diag.size, 1), ti.i32),
                 diag.astype(np.int32) if diag.size else np.zeros(1, np.int32))

    def _operator(self) -> tuple:
        """The CG's both-triangle operator of the last factorisation (:meth:`BatchedPCG._operator`), made at its first
        use after :meth:`factorize` from the arguments kept there (for the refinements and :meth:`matvec`)."""
        if not self._operator_made:
            indptr_h, indices_h, data_h, diagonal = self._pending
            self._full_operator(indptr_h, indices_h, self._csr_on_device(indptr_h, indices_h, data_h, diagonal),
                                self._n)
            self._operator_made = True
        return super()._operator()

    def _solve_into(self, b, x) -> None:
        """``x = A^-1 b`` from the factors, refined in ``"mixed"``."""
        n = self._n
        self._substitute_into(b, x)
        if self.refinements:
            ax, r, dx = self._array("env_ax", n), self._array("env_r", n), self._array("env_dx", n)
            for _ in range(self.refinements):
                _apply(*self._operator(), x, ax, n, self._nblocks)
                _residual_step(b, ax, r, n)
                self._substitute_into(r, dx)
                _add(x, dx, n)

    def _blocks_launch(self, lanes: int) -> tuple:
        """``(shared, lanes, group, (threads, serial, width))`` of the ``"blocks"`` kernels with ``lanes`` threads a
        copy: on CUDA a block of them, the dot products' groups of :attr:`group`; elsewhere the lanes one after
        another in a copy's thread, groups of 1 (no shuffles on the CPU)."""
        shared = require_backend("BatchedEnvelope") == "cuda"
        group = min(self.group, lanes) if shared else 1
        return shared, lanes, group, launch_shape(lanes, self.panel, shared)

    def _substitute_into(self, b, x) -> None:
        a = self._arrays
        if self.schedule == "blocks":
            shared, lanes, group, shape = self._blocks_launch(min(self._lane_count(), 32))
            substitute_blocks(a["env"], a["env_off"], a["env_first"], a["env_todo"], a["env_order"], b, x,
                              self._array("env_w", max(self._copies * self._m, 1)), self._m, self.entries,
                              self._copies, self._npanels, lanes, group, self.panel, shared, *shape[:2])
            return
        by_rows = self.schedule in ("dots", "panels")
        if by_rows and self.substitution != "rows":
            _substitute_vertices(a["env"], a["env_off"], a["env_first"], a["env_todo"], a["env_order"], b, x,
                                 self._array("env_w", max(self._copies * self._m, 1)), self._m, self.entries,
                                 self._copies, min(self._lane_count(), 32), self.substitution == "vertices-ahead")
            return
        _substitute(a["env"], a["env_off"], a["env_first"], a["env_fptr"], a["env_frows"], a["env_todo"],
                    a["env_order"], b, x, self._array("env_w", max(self._copies * self._m, 1)), self._m, self.entries,
                    self._copies, min(self._lane_count(), 32) if by_rows else self._lane_count(), by_rows)

    def _run(self) -> None:
        """``x = A^-1 b`` per copy from the ``b`` array into ``x`` (with the refinements in ``"mixed"``); then the
        flags, one read: where the last factorisation's vertex blocks fell outside the envelope, it is widened, the
        factorisation and this solve done again; :attr:`indefinite`."""
        n, B = self._n, self._copies
        b, x = self._array("b", n), self._array("x", n)
        self._solve_into(b, x)
        flags = _copy_out(self._arrays["env_flags"])
        if not self._checked and flags[B]:
            self.widenings += 1
            need = np.minimum(self._first, _copy_out(self._arrays["env_need"]).astype(np.int64))
            self._set_envelope(np.repeat(need.reshape(-1, 3).min(axis=1) // 3 * 3, 3))  # (a vertex's rows one first
            # column, a vertex's first DoF: as the order makes them, so that "panels" takes a vertex's columns at once)
            self._eliminate()
            self._solve_into(b, x)
            flags = _copy_out(self._arrays["env_flags"])
        self._checked = True
        self.indefinite = flags[:B].astype(bool)
        self.iterations = 1 + self.refinements
        self.total_iterations += self.iterations
