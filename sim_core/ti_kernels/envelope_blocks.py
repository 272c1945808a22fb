"""The envelope Cholesky of :class:`~sim_core.ti_kernels.envelope_cholesky.BatchedEnvelope` by panels of columns
(``schedule="blocks"``): fewer dependent steps a factorisation and a solve than a column (or a row) at a time.

Why. On the GPU the column-by-column factorisation (``"dots"``) is a chain of 1,698 dependent passes a Forming copy,
each a few trips to global memory and a block synchronisation (~4.8 us a column at B = 1024 on an H100: 8.1 ms a
factorisation against 0.35 ms of bytes), and the row-by-row substitution likewise (2 x 1,698 rows, ~3.7-4.5 ms against
0.29; docs/gpu_roofline.md). The design's premise: the time is the number of dependent global-memory steps, not
bytes or flops. A panel of
``P`` consecutive columns (a supernode in the sense of the left-looking blocked Cholesky: Ng & Peyton 1993; Golub &
Van Loan, Matrix Computations, 4th ed., Sec. 4.2.9) takes three of them instead of ``P``:

1. **the panel's outer products** (one pass, global memory): every row ``i`` of the panel and of its front (the rows
   ``i >= j1`` with ``first[i] < j1``; ``j0 .. j1 - 1`` the panel's columns) subtracts from its ``P`` entries of the
   panel their dot products with the panel's rows over the columns ``k < j0``, ``t_ic = a_ic - sum_(k < j0) w_ik w_ck
   / d_k``: one pass over row ``i`` for the ``P`` dot products (``group`` lanes a row, ``P`` sums in registers, a
   shuffle sum each), the panel's rows read by every task (from the L1);
2. **the panel's diagonal block** (shared memory): its lower triangle ``t`` read into the CUDA block's shared memory
   and factorised there right-looking, ``P`` steps of a block synchronisation each over shared memory only;
3. **the front's rows finished** (one pass, global memory): the panel's block written back with its pivots' inverses,
   and every front row's ``P`` entries by a forward substitution against the block in registers, ``w_ic = t_ic -
   sum_(s < c) w_is w_cs / d_s`` (a thread a row).

The arithmetic is that of ``"dots"`` (``A = W D^-1 W^T``, ``W_jj = d_j``, each entry's sum over ``k`` in a different
association): equal to a dense Cholesky to rounding. The substitutions likewise: forward, the panel's rows' sums over
``k < j0`` in one pass (``group`` lanes a row), then the panel's ``P x P`` triangle by one thread in registers; ``v =
D u``; backward, the panel's triangle by one thread in registers, then every ``k < j0`` the panel's rows reach updated
by its own lane (``v_k -= sum_r w_(j0 + r) k x_r``). Each ``2`` passes a panel instead of ``P`` rows.

Dependent steps a Forming factorisation (``m = 1,698``, ``P = 12``): 142 panels x 3 global-memory passes (426, and
``P`` shared-memory steps each, 1,704 synchronisations in all) against ``"dots"``' 1,698 passes (1,698
synchronisations) and ``"panels"``' 1,132; a solve 142 x 4 = 568 passes against 2 x 1,698 + 1. Launches unchanged: the
gather and one kernel a factorisation, one a solve.

Measured on the device (H200, one Forming Newton matrix at B = 1024, docs/gpu_roofline.md, session 58's lead
section): slower than ``"dots"``, gather + elimination 10.6-11.8 ms against 8.15 and a solve 7.9-8.2 against 7.25 (panel
12, 128 / 256 threads a copy): the premise does not hold (the shared-memory steps, the block synchronisations and the
``P`` sums a row keeps in registers cost more than the global passes saved), so ``"blocks"`` is opt-in.

CPU (no CUDA block). The same kernels with ``lanes`` run one after another inside a copy's thread, a phase (the code
between two synchronisations) for every lane before the next: the lanes' sharing of the work and the synchronisations'
places are what CI checks on the CPU (with ``group = 1``: the shuffles run on CUDA only, as ``"dots"``'); the panel's
block and its pivots' inverses in a scratch array of ``(B (P^2 + P),)`` float64 there, in shared memory on CUDA
(``8 (P^2 + P)`` bytes a copy: 1.2 KiB at ``P = 12``).
"""

import numpy as np

from sim_core.ti_backend import ti
from sim_core.ti_kernels.envelope_funcs import _F64, _I32, _gather_rhs, _group_sum, _pivot, _row_dot
from sim_core.ti_kernels.precision import VALUES, stored

PANEL = 12
"""Columns a panel (:class:`~sim_core.ti_kernels.envelope_cholesky.BatchedEnvelope` given none with ``"blocks"``):
four vertices."""


def panel_rows(first: np.ndarray, panel: int) -> tuple[np.ndarray, np.ndarray]:
    """The rows each panel of ``panel`` columns touches in an envelope with rows ``first[i] .. i``.

    Args:
        first: each row's first column, ``(m,)`` int.
        panel: columns a panel, >= 1.

    Returns:
        ``(pptr, prows)``: panel ``p`` (columns ``p panel .. min((p + 1) panel, m) - 1``) touches the rows
        ``prows[pptr[p]:pptr[p + 1]]``, increasing: its own rows first, then its front, the rows ``i >= (p + 1) panel``
        with ``first[i] < (p + 1) panel``; ``pptr`` int64 ``(ceil(m / panel) + 1,)``, ``prows`` int64.
    """
    first = np.asarray(first, dtype=np.int64)
    m = first.size
    rows_of = np.arange(m, dtype=np.int64)
    low, high = first // panel, rows_of // panel  # a row's panels: those whose columns reach first[i] .. its own
    counts = high - low + 1
    rows = np.repeat(rows_of, counts)
    starts = np.cumsum(counts) - counts
    panels = np.repeat(low, counts) + np.arange(rows.size) - np.repeat(starts, counts)
    by_panel = np.lexsort((rows, panels))
    npanels = -(-m // panel)
    pptr = np.zeros(npanels + 1, dtype=np.int64)
    np.cumsum(np.bincount(panels, minlength=npanels), out=pptr[1:])
    return pptr, rows[by_panel]


def dependent_steps(m: int, panel: int) -> dict:
    """The dependent steps of one copy's factorisation and solve by panels (module docstring): ``passes`` through
    global memory (each waits for the one before) and block ``syncs`` (the panel's ``P`` shared-memory steps
    included), against a column at a time (``"dots"``)."""
    npanels = -(-m // panel)
    return {"panels": npanels, "factor_passes": 3 * npanels, "factor_syncs": 3 * npanels + m,
            "solve_passes": 4 * npanels + 2, "dots_factor_passes": m, "dots_solve_passes": 2 * m + 1}


def launch_shape(lanes: int, panel: int, shared: bool) -> tuple[int, int, int]:
    """``(threads, serial, width)`` of :func:`factor_blocks` and :func:`substitute_blocks`: threads a copy (``lanes`` a
    CUDA block, else 1), lanes run one after another by each (1, else ``lanes``), the panel's block and its pivots'
    inverses ``P^2 + P``."""
    return (lanes, 1, panel * panel + panel) if shared else (1, lanes, panel * panel + panel)


@ti.func
def _sync(lanes: ti.template(), shared: ti.template()):
    """A block synchronisation where a copy's lanes are a CUDA block (elsewhere they run one after another)."""
    if ti.static(shared and lanes > 1):
        ti.simt.block.sync()


@ti.func
def _outer(env: ti.template(), inv: ti.template(), off: ti.template(), first: ti.template(), pptr: ti.template(),
           prows: ti.template(), base, vb, p, m, lane, lanes: ti.template(), group: ti.template(),
           panel: ti.template()):
    """Pass 1 of panel ``p``: ``t_ic = a_ic - sum_(k < j0) w_ik w_ck / d_k`` in place for every row ``i`` of the panel
    and its front and the panel's columns ``c`` in row ``i``'s envelope, ``group`` lanes a row."""
    j0 = p * panel
    pc = ti.min(panel, m - j0)
    start = pptr[p]
    nrows = pptr[p + 1] - start
    sub = lane % group
    rowc = ti.Vector([0] * panel, dt=ti.i32)
    fc = ti.Vector([0] * panel, dt=ti.i32)
    lowest = j0
    for q in ti.static(range(panel)):
        cq = ti.min(j0 + q, m - 1)
        fc[q] = first[cq]
        rowc[q] = base + off[cq] - fc[q]
        if q < pc:
            lowest = ti.min(lowest, fc[q])
    task = lane // group
    while task < nrows:
        i = prows[start + task]
        fi = first[i]
        rowi = base + off[i] - fi
        s = ti.Vector([0.0] * panel, dt=ti.f64)
        k = ti.max(fi, lowest) + sub
        while k < j0:
            wi = ti.cast(env[rowi + k], ti.f64) * inv[vb + k]
            for q in ti.static(range(panel)):
                if q < pc and k >= fc[q]:
                    s[q] += wi * ti.cast(env[rowc[q] + k], ti.f64)
            k += group
        for q in ti.static(range(panel)):
            s[q] = _group_sum(s[q], lane, group)
        if sub == 0:
            for q in ti.static(range(panel)):
                c = j0 + q
                if q < pc and c <= i and c >= fi:
                    env[rowi + c] = stored(ti.cast(env[rowi + c], ti.f64) - s[q], env)
        task += lanes // group


@ti.func
def _triangle_entry(e, j0, pc, first: ti.template(), panel: ti.template()):
    """Entry ``e`` of the panel's ``P x P`` block: ``(a, b, i, lower, inside)``, its row ``a`` and column ``b`` in the
    panel, ``i = j0 + a``, whether it is in the panel's lower triangle (``b <= a < pc``) and, then, in row ``i``'s
    envelope."""
    a = e // panel
    b = e % panel
    lower = a < pc and b <= a
    i = j0 + ti.min(a, pc - 1)
    return a, b, i, lower, lower and j0 + b >= first[i]


@ti.func
def _load_block(env: ti.template(), off: ti.template(), first: ti.template(), blk: ti.template(), bb, base, j0, pc,
                lane, lanes: ti.template(), panel: ti.template()):
    """The panel's lower triangle ``t`` (pass 1's) into ``blk[bb + a P + b]`` (0 outside the envelope)."""
    e = lane
    while e < panel * panel:
        a, b, i, lower, inside = _triangle_entry(e, j0, pc, first, panel)
        if lower:
            v = 0.0
            if inside:
                v = ti.cast(env[base + off[i] - first[i] + j0 + b], ti.f64)
            blk[bb + e] = v
        e += lanes


@ti.func
def _block_step(env: ti.template(), blk: ti.template(), bb, r, pc, lane, lanes: ti.template(), panel: ti.template()):
    """Step ``r`` of the panel's block right-looking: ``t_ab -= w_ar w_br / d_r`` for ``r < b <= a < pc`` (rounded as
    the envelope stores); the inverse pivot ``1 / d_r`` at ``blk[bb + P^2 + r]`` (lane 0)."""
    d = _pivot(blk[bb + r * panel + r])
    if lane == 0:
        blk[bb + panel * panel + r] = 1.0 / d
    e = lane
    while e < panel * panel:
        a = e // panel
        b = e % panel
        if r < b and b <= a and a < pc:
            blk[bb + e] = ti.cast(stored(blk[bb + e] - blk[bb + a * panel + r] * blk[bb + b * panel + r] / d, env),
                                  ti.f64)
        e += lanes


@ti.func
def _finish(env: ti.template(), inv: ti.template(), off: ti.template(), first: ti.template(), pptr: ti.template(),
            prows: ti.template(), blk: ti.template(), bad: ti.template(), bb, c, base, vb, p, m, lane,
            lanes: ti.template(), panel: ti.template()):
    """Pass 3 of panel ``p``: its block written back with its pivots' inverses (``bad[c] = 1`` where a pivot is not
    positive), then each front row's ``P`` entries forward-substituted against the block (a lane a row)."""
    j0 = p * panel
    pc = ti.min(panel, m - j0)
    start = pptr[p]
    nrows = pptr[p + 1] - start
    e = lane
    while e < panel * panel:
        a, b, i, lower, inside = _triangle_entry(e, j0, pc, first, panel)
        if inside:
            env[base + off[i] - first[i] + j0 + b] = stored(blk[bb + e], env)
        if lower and a == b:
            inv[vb + i] = blk[bb + panel * panel + a]
            if not blk[bb + e] > 0.0:
                bad[c] = 1
        e += lanes
    task = pc + lane
    while task < nrows:
        i = prows[start + task]
        fi = first[i]
        rowi = base + off[i] - fi
        w = ti.Vector([0.0] * panel, dt=ti.f64)
        for q in ti.static(range(panel)):
            if q < pc and j0 + q >= fi:
                v = ti.cast(env[rowi + j0 + q], ti.f64)
                for s in ti.static(range(q)):
                    v -= w[s] * blk[bb + q * panel + s] * blk[bb + panel * panel + s]
                w[q] = ti.cast(stored(v, env), ti.f64)
                env[rowi + j0 + q] = stored(v, env)
        task += lanes


@ti.func
def _factor_copy(env: ti.template(), off: ti.template(), first: ti.template(), pptr: ti.template(),
                 prows: ti.template(), todo: ti.template(), bad: ti.template(), inv: ti.template(), blk: ti.template(),
                 bb, c, lane0, m, size, npanels, serial: ti.template(), lanes: ti.template(), group: ti.template(),
                 panel: ti.template(), shared: ti.template()):
    """Copy ``c``'s factorisation by panels (module docstring), its lanes from ``lane0``, ``serial`` of them one after
    another (CPU) or one (a CUDA block's thread)."""
    if lane0 == 0:
        bad[c] = 0
    if todo[c] != 0:
        base = c * size
        vb = c * m
        for p in range(npanels):
            j0 = p * panel
            pc = ti.min(panel, m - j0)
            for e in range(serial):
                _outer(env, inv, off, first, pptr, prows, base, vb, p, m, lane0 + e, lanes, group, panel)
            _sync(lanes, shared)
            for e in range(serial):
                _load_block(env, off, first, blk, bb, base, j0, pc, lane0 + e, lanes, panel)
            _sync(lanes, shared)
            for r in range(pc):
                for e in range(serial):
                    _block_step(env, blk, bb, r, pc, lane0 + e, lanes, panel)
                _sync(lanes, shared)
            for e in range(serial):
                _finish(env, inv, off, first, pptr, prows, blk, bad, bb, c, base, vb, p, m, lane0 + e, lanes, panel)
            _sync(lanes, shared)


@ti.kernel
def factor_blocks(env: VALUES, off: _I32, first: _I32, pptr: _I32, prows: _I32, todo: _I32, bad: _I32, inv: _F64,
                  scratch: _F64, m: ti.i32, size: ti.i32, copies: ti.i32, npanels: ti.i32, lanes: ti.template(),
                  group: ti.template(), panel: ti.template(), shared: ti.template(), threads: ti.template(),
                  serial: ti.template(), width: ti.template()):
    """Each copy's envelope factorised in place into ``W`` by panels of ``panel`` columns (module docstring):
    ``inv[c m + j] = 1 / d_j``, ``bad[c] = 1`` where a pivot of copy ``c`` is not positive (1 used in its place),
    copies with ``todo[c] == 0`` skipped. ``shared``: a CUDA block of ``lanes`` threads a copy, the panel's block in
    its shared memory; else one thread a copy running its ``lanes`` in turn, the block in ``scratch`` (``(copies (P^2 +
    P),)``); ``threads``, ``serial``, ``width``: :func:`launch_shape`'s."""
    ti.loop_config(block_dim=threads)
    for t in range(copies * threads):
        c = t // threads
        if ti.static(shared):
            blk = ti.simt.block.SharedArray((width,), ti.f64)
            _factor_copy(env, off, first, pptr, prows, todo, bad, inv, blk, 0, c, t % threads, m, size, npanels,
                         serial, lanes, group, panel, shared)
        else:
            _factor_copy(env, off, first, pptr, prows, todo, bad, inv, scratch, c * width, c, 0, m, size, npanels,
                         serial, lanes, group, panel, shared)


@ti.func
def _forward_outer(env: ti.template(), off: ti.template(), first: ti.template(), w: ti.template(), base, vb, j0, pc,
                   lane, lanes: ti.template(), group: ti.template()):
    """The forward pass's panel rows ``i``: ``w_i -= sum_(k < j0) w_ik u_k``, ``group`` lanes a row."""
    sub = lane % group
    task = lane // group
    while task < pc:
        i = j0 + task
        fi = first[i]
        acc = _group_sum(_row_dot(env, w, base + off[i] - fi, vb, fi + sub, j0, group), lane, group)
        if sub == 0:
            w[vb + i] -= acc
        task += lanes // group


@ti.func
def _forward_block(env: ti.template(), off: ti.template(), first: ti.template(), w: ti.template(), base, vb, j0, pc,
                   panel: ti.template()):
    """The forward pass's panel triangle, one thread: ``u_i = (w_i - sum_(j0 <= k < i) w_ik u_k) / d_i``."""
    u = ti.Vector([0.0] * panel, dt=ti.f64)
    for r in ti.static(range(panel)):
        if r < pc:
            i = j0 + r
            fi = first[i]
            row = base + off[i] - fi
            v = w[vb + i]
            for q in ti.static(range(r)):
                if j0 + q >= fi:
                    v -= ti.cast(env[row + j0 + q], ti.f64) * u[q]
            u[r] = v / _pivot(env[row + i])
            w[vb + i] = u[r]


@ti.func
def _backward_block(env: ti.template(), off: ti.template(), first: ti.template(), w: ti.template(), base, vb, j0, pc,
                    panel: ti.template()):
    """The backward pass's panel triangle, one thread: ``x_j = (v_j - sum_(j < i < j1) w_ij x_i) / d_j``, ``j``
    descending (the rows after the panel already in ``v``); ``x`` in ``w``."""
    x = ti.Vector([0.0] * panel, dt=ti.f64)
    for rr in ti.static(range(panel)):
        r = ti.static(panel - 1 - rr)
        if r < pc:
            j = j0 + r
            v = w[vb + j]
            for s in ti.static(range(r + 1, panel)):
                if s < pc:
                    i = j0 + s
                    if j >= first[i]:
                        v -= ti.cast(env[base + off[i] - first[i] + j], ti.f64) * x[s]
            x[r] = v / _pivot(env[base + off[j + 1] - 1])
            w[vb + j] = x[r]


@ti.func
def _backward_outer(env: ti.template(), off: ti.template(), first: ti.template(), w: ti.template(), base, vb, j0, pc,
                    lane, lanes: ti.template(), panel: ti.template()):
    """The backward pass's update of every ``k < j0`` the panel's rows reach, a lane each: ``v_k -= sum_r w_(j0 + r) k
    x_r``."""
    lowest = j0
    for r in ti.static(range(panel)):
        if r < pc:
            lowest = ti.min(lowest, first[j0 + r])
    k = lowest + lane
    while k < j0:
        acc = 0.0
        for r in ti.static(range(panel)):
            if r < pc:
                i = j0 + r
                if k >= first[i]:
                    acc += ti.cast(env[base + off[i] - first[i] + k], ti.f64) * w[vb + i]
        w[vb + k] -= acc
        k += lanes


@ti.func
def _substitute_copy(env: ti.template(), off: ti.template(), first: ti.template(), todo: ti.template(),
                     order: ti.template(), b: ti.template(), x: ti.template(), w: ti.template(), c, lane0, m, size,
                     npanels, serial: ti.template(), lanes: ti.template(), group: ti.template(), panel: ti.template(),
                     shared: ti.template()):
    """Copy ``c``'s two substitutions by panels (module docstring), its lanes as in :func:`_factor_copy`."""
    base = c * size
    vb = c * m
    for e in range(serial):
        _gather_rhs(order, todo, b, x, w, c, vb, m, lane0 + e, lanes)
    _sync(lanes, shared)
    if todo[c] != 0:
        for p in range(npanels):
            j0 = p * panel
            pc = ti.min(panel, m - j0)
            for e in range(serial):
                _forward_outer(env, off, first, w, base, vb, j0, pc, lane0 + e, lanes, group)
            _sync(lanes, shared)
            if lane0 == 0:
                _forward_block(env, off, first, w, base, vb, j0, pc, panel)
            _sync(lanes, shared)
        for e in range(serial):
            q = lane0 + e
            while q < m:
                w[vb + q] = w[vb + q] * _pivot(env[base + off[q + 1] - 1])  # (v = D u: row q's last entry, d_q)
                q += lanes
        _sync(lanes, shared)
        for pp in range(npanels):
            p = npanels - 1 - pp
            j0 = p * panel
            pc = ti.min(panel, m - j0)
            if lane0 == 0:
                _backward_block(env, off, first, w, base, vb, j0, pc, panel)
            _sync(lanes, shared)
            for e in range(serial):
                _backward_outer(env, off, first, w, base, vb, j0, pc, lane0 + e, lanes, panel)
            _sync(lanes, shared)
        for e in range(serial):
            q = lane0 + e
            while q < m:
                dof = order[vb + q]
                if dof >= 0:
                    x[dof] = w[vb + q]
                q += lanes


@ti.kernel
def substitute_blocks(env: VALUES, off: _I32, first: _I32, todo: _I32, order: _I32, b: _F64, x: _F64, w: _F64,
                      m: ti.i32, size: ti.i32, copies: ti.i32, npanels: ti.i32, lanes: ti.template(),
                      group: ti.template(), panel: ti.template(), shared: ti.template(), threads: ti.template(),
                      serial: ti.template()):
    """``x = A^-1 b`` per copy from the factor ``W`` by panels (module docstring; ``b``, ``x``, ``order``, ``w`` and
    ``todo`` as for :func:`~sim_core.ti_kernels.envelope_cholesky._substitute`); lanes as for
    :func:`factor_blocks`."""
    ti.loop_config(block_dim=threads)
    for t in range(copies * threads):
        _substitute_copy(env, off, first, todo, order, b, x, w, t // threads, t % threads, m, size, npanels, serial,
                         lanes, group, panel, shared)
