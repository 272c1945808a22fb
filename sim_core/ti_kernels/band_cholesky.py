"""Exact blocks of a batched Newton matrix on the device, the preconditioner of the batched CG's larger blocks
(:class:`~sim_core.ti_kernels.pcg.BatchedPCG`), e.g. each copy's sheet: a banded Cholesky factorisation and the
block's solve ``S^-1 r`` by tiled substitutions.

A band block is a list of ``m`` DoFs of one copy in a band-limiting order (a sheet's vertices ordered along its long
axis, so that its bending stencil couples rows at most ``w`` apart). Its matrix ``S = P A P^T`` (``P`` selecting
the block's DoFs) is kept as its lower band, entries ``S_ij`` with ``0 <= i - j <= w``, ``w`` the largest distance
between two of the block's DoFs that the assembled pattern couples (contact blocks farther apart than ``w`` are
left out of the band). Its entries are gathered from the CSR values through each band entry's position in them,
found once a pattern. It is factorised ``S = L L^T`` by the banded elimination in outer-product form (Golub & Van
Loan, Matrix Computations, 4th ed., Alg. 4.3.5), blocked by panels of :data:`PANEL` columns: a panel's columns are
finished by its own earlier columns, then they update the ``w x w`` window after the panel at once, one thread an
entry; three device passes a panel instead of one a column, and every entry updated in the column-by-column order
(the same factor to the bit). A block whose elimination meets a pivot that is not positive (a band that left out a
coupling it needed) is marked not usable, and the CG keeps the vertex block-Jacobi preconditioner on its DoFs.

The solve ``L^-T L^-1 r`` is taken by tiles of ``t >= w`` rows (:func:`tiling`, at most :data:`TILES` a block), so
that ``L`` is block lower bidiagonal: diagonal tiles ``D_T`` (lower triangular) and, left of them, ``C_T``. Forward,
``y_T = D_T^-1 r_T - G_T y_{T-1}`` with ``G_T = D_T^-1 C_T``; back, ``x_T = D_T^-T y_T - H_T x_{T+1}`` with ``H_T =
D_T^-T C_{T+1}^T`` (block forward and back substitution, Golub & Van Loan, Sec. 3.1 and 4.5). The factorisation
forms ``D_T^-1``, ``G_T`` and ``H_T`` (one thread a column of a tile, chains of ``t^2 / 2``, then one thread an
entry); the solve is a pass over every tile for each ``D_T^-1`` product and ``nt - 1`` dependent passes each way
(one thread a row of a tile, ``t`` multiply-adds), every read coalesced: a dense inverse ``L^-T L^-1`` instead costs
``m^2`` reads a solve and, to form, a chain of ``2 m w`` dependent steps a column.

Storage: the band, float64 ``(nb, m, w + 1)`` (entry ``(b, i, k)`` at column ``j = i - w + k``), the tiles'
``D_T^-1``, ``G_T``, ``H_T`` ``(nb, nt, t, t)`` each, float64 or float32 (:class:`BandBlocks`' ``dtype``: computed in
float64 from the float64 factor, each entry rounded once where stored; 0.78 MB a block in float64 for a 16 x 8 sheet,
``m = 360``, ``w = 53``, ``t = 90``, ``nt = 4``, 0.39 MB in float32; a dense inverse 1.04 MB) and the solve's two
scratch vectors, float64 ``(nb, nt t)``, and the band entries' positions in the CSR values, int32 ``(nb, m, w + 1)``.
"""

import numpy as np

from sim_core.ti_backend import ti
from sim_core.ti_kernels import device_copy
from sim_core.ti_kernels.precision import VALUES, stored
from sim_core.unique import sorted_unique

_F64 = ti.types.ndarray(dtype=ti.f64, ndim=1)
_I32 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@ti.func
def _at(b: ti.i32, i: ti.i32, k: ti.i32, m: ti.i32, w: ti.i32) -> ti.i32:
    """Address of band entry ``(b, i, k)`` (row ``i``, column ``i - w + k`` of block ``b``)."""
    return (b * m + i) * (w + 1) + k


@ti.kernel
def _band_width(indptr: _I32, indices: _I32, band_dof: _I32, dof_pos: _I32, width: _I32, nb: ti.i32, m: ti.i32):
    """``width[0]`` = the largest ``|i - j|`` over the matrix entries ``(i, j)`` of a block's rows and columns
    (``width[0]`` zero on entry)."""
    for b, i in ti.ndrange(nb, m):
        g = band_dof[b * m + i]
        if g >= 0:
            for e in range(indptr[g], indptr[g + 1]):
                q = dof_pos[indices[e]]
                if q >= 0 and q // m == b:
                    ti.atomic_max(width[0], ti.abs(i - q % m))


@ti.kernel
def _band_add_vertex_blocks(brow: _I32, bcol: _I32, bval: VALUES, free: _F64, dof_pos: _I32, band: _F64,
                            nblocks: ti.i32, nb: ti.i32, m: ti.i32, w: ti.i32):
    """``band += F E_t F`` of the vertex blocks ``E_t`` (:class:`~sim_core.ti_kernels.pcg.VertexBlocks`) whose
    rows and columns fall in one block's band (atomic adds)."""
    for t in range(nblocks):
        for a in ti.static(range(3)):
            for c in ti.static(range(3)):
                gi = 3 * brow[t] + a
                gj = 3 * bcol[t] + c
                qi = dof_pos[gi]
                qj = dof_pos[gj]
                if qi >= 0 and qj >= 0 and qi // m == qj // m:
                    i = qi % m
                    j = qj % m
                    if j <= i and i - j <= w:
                        ti.atomic_add(band[_at(qi // m, i, w - (i - j), m, w)],
                                      free[gi] * free[gj] * bval[9 * t + 3 * a + c])


PANEL = 8
"""Columns of one panel of the blocked banded elimination (:func:`_eliminate_panels`; its diagonal block is one
thread's chain of about ``PANEL^3 / 6`` updates: on an H100 at 1024 blocks, ``m = 360``, ``w = 53``, 4 and 8 give
5.7 ms an elimination, 16 gives 10.0 and 32 29.8, against 7.7 column by column)."""

PANELS_PER_LAUNCH = 4
"""Panels of the blocked elimination in one launch of :func:`_eliminate_panels` (three device passes each)."""

_ZERO_ENTRY = -1  # a band entry's position in the CSR values where the pattern has none: the entry is 0
_ONE_ENTRY = -2  # a padding row's diagonal: the entry is 1


@ti.kernel
def _band_sources(indptr: _I32, indices: _I32, band_dof: _I32, dof_pos: _I32, src: _I32, nb: ti.i32, m: ti.i32,
                  w: ti.i32):
    """``src``, one entry a band entry: the position in the both-triangle CSR data of its matrix entry
    (``_ZERO_ENTRY`` where the pattern has none, ``_ONE_ENTRY`` on a padding row's diagonal); one thread a row,
    entries outside the block or the band left out."""
    for b, i in ti.ndrange(nb, m):
        for k in range(w + 1):
            src[_at(b, i, k, m, w)] = _ZERO_ENTRY
        g = band_dof[b * m + i]
        if g < 0:
            src[_at(b, i, w, m, w)] = _ONE_ENTRY
        else:
            for e in range(indptr[g], indptr[g + 1]):
                q = dof_pos[indices[e]]
                if q >= 0 and q // m == b:
                    j = q % m
                    if j <= i and i - j <= w:
                        src[_at(b, i, w - (i - j), m, w)] = e


@ti.kernel
def _compose_sources(src: _I32, data_index: _I32, size: ti.i32):
    """``src[k] = data_index[src[k]]`` where ``src[k]`` is a position (>= 0): positions in the both-triangle pattern
    made positions in another array of its values."""
    for k in range(size):
        s = src[k]
        if s >= 0:
            src[k] = data_index[s]


@ti.kernel
def _band_gather(data: _F64, src: _I32, band: _F64, size: ti.i32):
    """``band[k] = data[src[k]]`` (0 or 1 where ``src`` says so: :func:`_band_sources`)."""
    for k in range(size):
        s = src[k]
        v = 0.0
        if s >= 0:
            v = data[s]
        elif s == _ONE_ENTRY:
            v = 1.0
        band[k] = v


@ti.func
def _eliminate_entry(band: ti.template(), b: ti.i32, i: ti.i32, j: ti.i32, k0: ti.i32, k1: ti.i32, m: ti.i32,
                     w: ti.i32):
    """``S_ij -= S_ik S_jk / S_kk`` for the columns ``k0 <= k < k1`` that reach row ``i`` (``k >= i - w``), in
    increasing ``k``, those with a positive pivot ``S_kk`` only (the right-looking elimination's updates of
    entry ``(i, j)`` by these columns, in its order)."""
    s = band[_at(b, i, w - (i - j), m, w)]
    for k in range(ti.max(k0, i - w), k1):
        pivot = band[_at(b, k, w, m, w)]
        if pivot > 0.0:
            s = s - band[_at(b, i, w - (i - k), m, w)] * band[_at(b, j, w - (j - k), m, w)] / pivot
    band[_at(b, i, w - (i - j), m, w)] = s


@ti.kernel
def _eliminate_panels(band: _F64, wanted: _I32, first: ti.i32, nb: ti.i32, m: ti.i32, w: ti.i32):
    """Panels ``first .. first + PANELS_PER_LAUNCH - 1`` (columns ``p PANEL .. (p + 1) PANEL - 1`` each) of the
    banded elimination ``S_ij -= S_ik S_jk / S_kk`` (``k < j <= i <= k + w``), blocked: each panel's columns are
    finished by its own earlier columns (its diagonal block row by row, one thread a block; then the rows below
    it, one thread a row), then the panel's columns update the window after it at once (one thread an entry).
    Every entry receives the same updates in the same order as in the column-by-column elimination, so the
    factor is the same to the bit. A block whose pivot is not positive is left as it is from there
    (:func:`_scale_factor` marks it); so is a block with ``wanted[b] == 0``."""
    for pp in ti.static(range(PANELS_PER_LAUNCH)):
        k0 = (first + pp) * PANEL
        k1 = ti.min(k0 + PANEL, m)
        for b in range(nb):  # the diagonal block, row after row
            if wanted[b] != 0:
                for i in range(k0, k1):
                    for j in range(k0, i + 1):
                        _eliminate_entry(band, b, i, j, k0, j, m, w)
        for b, di in ti.ndrange(nb, w):  # the rows below it, each its own thread
            i = k1 + di
            if i < m and wanted[b] != 0:
                for j in range(ti.max(k0, i - w), k1):
                    _eliminate_entry(band, b, i, j, k0, j, m, w)
        for b, di, dj in ti.ndrange(nb, w, w):  # the window after the panel, by the panel's columns
            i = k1 + di
            j = k1 + dj
            if j <= i and i < m and wanted[b] != 0:
                _eliminate_entry(band, b, i, j, k0, k1, m, w)



@ti.kernel
def _scale_factor(band: _F64, pivots: _F64, usable: _I32, wanted: _I32, nb: ti.i32, m: ti.i32, w: ti.i32):
    """The eliminated band into ``L`` (``L_ij = S_ij / sqrt(S_jj)``, ``L_jj = sqrt(S_jj)``, ``S_jj`` the pivots);
    ``usable[b]`` 0 where a pivot is not positive, and for a block with ``wanted[b] == 0`` (not scaled)."""
    for b in range(nb):
        usable[b] = ti.select(wanted[b] != 0, 1, 0)
    for b, i in ti.ndrange(nb, m):
        if wanted[b] != 0:
            d = band[_at(b, i, w, m, w)]
            if not d > 0.0:
                usable[b] = 0
                d = 1.0
            pivots[b * m + i] = ti.sqrt(d)
    for b, i, k in ti.ndrange(nb, m, w + 1):  # one thread an entry (neighbouring threads, neighbouring entries)
        if wanted[b] != 0:
            j = i - w + k
            if k == w:
                band[_at(b, i, w, m, w)] = pivots[b * m + i]
            elif j >= 0:
                band[_at(b, i, k, m, w)] /= pivots[b * m + j]


TILES = 4
"""Tiles of a block at most (:func:`band_solve`): a block of ``m`` DoFs is cut into ``nt = ceil(m / t)`` tiles of
``t = max(w, ceil(m / TILES))`` rows, so that its factor couples only neighbouring tiles; the substitutions are
``TILES - 1`` dependent passes each way (one thread a row of a tile; those past ``nt - 1`` do nothing). Fewer tiles,
fewer passes but larger ones (about ``3 m t`` entries read a solve). On an H100 at 1024 blocks of ``m = 360``, ``w =
53`` (Forming's sheet): 4 tiles of 90 rows, a solve 0.41 ms and the tiles formed in 5.1 ms; 7 tiles of 53 rows, 0.58
and 3.4 ms (the dependent passes' latency outweighs the fewer bytes); a dense inverse, 0.44 and 13.5 ms."""


def tiling(m: int, w: int) -> tuple[int, int]:
    """``(t, nt)``: rows a tile and tiles a block of ``m`` DoFs and half-bandwidth ``w`` (:data:`TILES`)."""
    t = max(w, -(-m // TILES), 1)
    return t, -(-m // t)


@ti.func
def _factor_entry(band: ti.template(), b: ti.i32, i: ti.i32, j: ti.i32, m: ti.i32, w: ti.i32) -> ti.f64:
    """``L_ij`` of block ``b`` (0 outside the band; on the padding rows ``i >= m`` of the last tile, the identity's)."""
    v = 0.0
    if i >= m:
        if i == j:
            v = 1.0
    elif j <= i and i - j <= w:
        v = band[_at(b, i, w - (i - j), m, w)]
    return v


@ti.kernel
def _tile_inverses(band: _F64, usable: _I32, diag_inv: VALUES, nb: ti.i32, m: ti.i32, w: ti.i32, t: ti.i32,
                   nt: ti.i32):
    """Column ``c`` of ``D_T^-1`` of each usable block's tile ``T`` (``D_T`` the factor's diagonal tile, lower
    triangular), one thread a column: ``D_T y = e_c`` forward, into ``diag_inv[base + a t + c]`` (``base = (b nt
    + T) t^2``; 0 above the diagonal). Every thread takes the rows ``0 .. t-1`` in the same order (zeros stored, not
    skipped), so that a warp's threads read neighbouring addresses."""
    for b, tt, c in ti.ndrange(nb, nt, t):
        if usable[b] != 0:
            base = (b * nt + tt) * t * t
            top = tt * t
            for a in range(t):
                s = 0.0
                if a >= c:
                    s = 1.0 if a == c else 0.0
                    for k in range(ti.max(a - w, 0), a):
                        s -= _factor_entry(band, b, top + a, top + k, m, w) * diag_inv[base + k * t + c]
                    s /= _factor_entry(band, b, top + a, top + a, m, w)
                diag_inv[base + a * t + c] = stored(s, diag_inv)


@ti.kernel
def _mirror_tiles(diag_inv: VALUES, usable: _I32, nb: ti.i32, t: ti.i32, nt: ti.i32):
    """``diag_inv[base + p t + q] = diag_inv[base + q t + p]`` for ``p < q``: each tile's array then holds
    ``D_T^-1[a, c]`` at ``c t + a`` (``a >= c``) and ``D_T^-1[c, a]`` at ``c t + a`` (``c >= a``), so that both
    :func:`band_solve`'s products with ``D_T^-1`` and ``D_T^-T`` read it with neighbouring threads on neighbouring
    addresses."""
    for b, tt, p, q in ti.ndrange(nb, nt, t, t):
        if usable[b] != 0 and p < q:
            base = (b * nt + tt) * t * t
            diag_inv[base + p * t + q] = diag_inv[base + q * t + p]


@ti.kernel
def _tile_couplings(band: _F64, usable: _I32, diag_inv: VALUES, fwd: VALUES, back: VALUES, nb: ti.i32, m: ti.i32,
                    w: ti.i32, t: ti.i32, nt: ti.i32):
    """The tiles' coupling matrices of each usable block, entry ``(a, c)`` of tile ``T`` at ``base + c t + a``, one
    thread an entry: ``fwd`` ``G_T = D_T^-1 C_T`` (``T >= 1``) and ``back`` ``H_T = D_T^-T C_{T+1}^T``
    (``T < nt - 1``), ``C_T`` the factor's tile left of ``D_T`` (rows of tile ``T``, columns of tile ``T - 1``:
    upper triangular where ``t = w``); 0 elsewhere."""
    for b, tt, c, a in ti.ndrange(nb, nt, t, t):
        if usable[b] != 0:
            base = (b * nt + tt) * t * t
            top = tt * t
            g = 0.0
            if tt >= 1:  # sum_k D^-1[a, k] C_T[k, c], C_T[k, c] = L(top + k, top - t + c) (0 for t + k - c > w)
                for k in range(ti.min(a, c + w - t) + 1):
                    g += diag_inv[base + k * t + a] * _factor_entry(band, b, top + k, top - t + c, m, w)
            fwd[base + c * t + a] = stored(g, fwd)
            h = 0.0
            if tt + 1 < nt:  # sum_k D^-1[k, a] C_{T+1}[c, k], C_{T+1}[c, k] = L(top + t + c, top + k)
                for k in range(ti.max(t + c - w, 0), t):
                    if k >= a:
                        h += diag_inv[base + k * t + a] * _factor_entry(band, b, top + t + c, top + k, m, w)
            back[base + c * t + a] = stored(h, back)


@ti.func
def _solving(usable: ti.template(), band_copy: ti.template(), active: ti.template(), b: ti.i32) -> ti.i32:
    """Whether block ``b`` is applied: usable, and its copy active."""
    return usable[b] != 0 and active[band_copy[b]] != 0


@ti.func
def band_solve(diag_inv: ti.template(), fwd: ti.template(), back: ti.template(), y: ti.template(),
               x: ti.template(), usable: ti.template(), band_dof: ti.template(), band_copy: ti.template(),
               active: ti.template(), r: ti.template(), z: ti.template(), nb: ti.i32, m: ti.i32, t: ti.i32,
               nt: ti.i32):
    """``z = S^-1 r = L^-T L^-1 r`` on the DoFs of every usable block whose copy is active, by tiles of ``t`` rows
    (:meth:`BandBlocks.invert`): ``L y = r`` as ``y_T = D_T^-1 r_T - G_T y_{T-1}``, then ``L^T x = y`` as ``x_T =
    D_T^-T y_T - H_T x_{T+1}``; ``y``, ``x`` scratch of ``nb nt t`` entries. One thread a row of a tile: a pass
    over every tile (``D_T^-1 r_T``), ``TILES - 1`` dependent passes forward (one tile each), a pass over every
    tile (``D_T^-T y_T``), ``TILES - 1`` dependent passes back, each writing its tile's rows of ``z``. Called at
    a kernel's top level, each loop is one device pass."""
    for b, tt, a in ti.ndrange(nb, nt, t):
        if _solving(usable, band_copy, active, b):
            base = (b * nt + tt) * t * t
            acc = 0.0
            for c in range(a + 1):
                i = tt * t + c
                if i < m:
                    g = band_dof[b * m + i]
                    if g >= 0:
                        acc += diag_inv[base + c * t + a] * r[g]
            y[(b * nt + tt) * t + a] = acc
    for tt in ti.static(range(1, TILES)):
        for b, a in ti.ndrange(nb, t):
            if tt < nt and _solving(usable, band_copy, active, b):
                y[(b * nt + tt) * t + a] -= _tile_product(fwd, (b * nt + tt) * t * t, a, y, (b * nt + tt - 1) * t, t)
    for b, tt, a in ti.ndrange(nb, nt, t):
        if _solving(usable, band_copy, active, b):
            base = (b * nt + tt) * t * t
            acc = 0.0
            for c in range(t):
                if c >= a:
                    acc += diag_inv[base + c * t + a] * y[(b * nt + tt) * t + c]
            x[(b * nt + tt) * t + a] = acc
            if tt == nt - 1:
                _band_out(band_dof, x, z, b, tt, a, m, t, nt)
    for q in ti.static(range(TILES - 1)):
        for b, a in ti.ndrange(nb, t):
            tt = nt - 2 - q
            if tt >= 0 and _solving(usable, band_copy, active, b):
                x[(b * nt + tt) * t + a] -= _tile_product(back, (b * nt + tt) * t * t, a, x, (b * nt + tt + 1) * t, t)
                _band_out(band_dof, x, z, b, tt, a, m, t, nt)


CHAIN_UNROLL = 4
"""Independent partial sums of a thread's product in a dependent pass of :func:`band_solve` (one thread a row of a
tile, a few warps an SM: its loads issued ahead of the sums they feed)."""


@ti.func
def _tile_product(mat: ti.template(), base: ti.i32, a: ti.i32, v: ti.template(), off: ti.i32, t: ti.i32) -> ti.f64:
    """``sum_c mat[base + c t + a] v[off + c]`` over ``c < t``, in :data:`CHAIN_UNROLL` partial sums."""
    acc = ti.Vector.zero(ti.f64, CHAIN_UNROLL)
    for q in range((t + CHAIN_UNROLL - 1) // CHAIN_UNROLL):
        for u in ti.static(range(CHAIN_UNROLL)):
            c = CHAIN_UNROLL * q + u
            if c < t:
                acc[u] += mat[base + c * t + a] * v[off + c]
    return acc.sum()


@ti.func
def _band_out(band_dof: ti.template(), x: ti.template(), z: ti.template(), b: ti.i32, tt: ti.i32, a: ti.i32,
              m: ti.i32, t: ti.i32, nt: ti.i32):
    """``z`` at the DoF of row ``tt t + a`` of block ``b`` (none on padding) = its finished entry of ``x``."""
    i = tt * t + a
    if i < m:
        g = band_dof[b * m + i]
        if g >= 0:
            z[g] = x[(b * nt + tt) * t + a]


@ti.kernel
def _apply(diag_inv: VALUES, fwd: VALUES, back: VALUES, y: _F64, x: _F64, usable: _I32, band_dof: _I32, band_copy: _I32,
           active: _I32, r: _F64, z: _F64, nb: ti.i32, m: ti.i32, t: ti.i32, nt: ti.i32):
    """:func:`band_solve` as a kernel (:meth:`BandBlocks.apply`)."""
    band_solve(diag_inv, fwd, back, y, x, usable, band_dof, band_copy, active, r, z, nb, m, t, nt)


class BandBlocks:
    """The band blocks of a batched Newton matrix on the device (module docstring).

    Args:
        dofs: the blocks' DoFs, shape ``(nb, m)`` int, row ``b`` block ``b``'s DoFs in band order, -1 for padding
            (an identity row); every DoF in at most one block.
        segments: the copy of each DoF, shape ``(n,)`` int; a block's DoFs lie in one copy.
        max_width: the largest half-bandwidth ``w`` (DoFs) kept; a pattern whose band is wider leaves the blocks
            unused (:attr:`width` 0).
        dtype: the tiles' storage type (``ti.f64``, or ``ti.f32``: each tile entry computed in float64 from the
            float64 factor and rounded once, :mod:`~sim_core.ti_kernels.precision`).

    Raises:
        ValueError: a DoF outside ``0..n-1`` or in two blocks, or a block over two copies.

    Attributes:
        count: blocks ``nb``; size: DoFs a block ``m``.
        width: half-bandwidth ``w`` of the last :meth:`assemble` (0: not measured yet, or wider than
            ``max_width``: the blocks are then not used).
    """

    def __init__(self, dofs: np.ndarray, segments: np.ndarray, max_width: int = 128, dtype=ti.f64) -> None:
        dofs = np.asarray(dofs, dtype=np.int64)
        n = int(np.asarray(segments).shape[0])
        if dofs.ndim != 2 or dofs.size == 0:
            raise ValueError(f"BandBlocks: dofs of shape {dofs.shape}, expected (blocks, m) with m > 0")
        real = dofs[dofs >= 0]
        if real.size and (real.max() >= n or sorted_unique(real).size != real.size):
            raise ValueError("BandBlocks: a DoF outside the matrix or in two blocks")
        seg = np.asarray(segments)
        first = np.where(dofs >= 0, dofs, dofs.max(axis=1, keepdims=True))
        copy = seg[first]
        if np.any(copy != copy[:, :1]):
            raise ValueError("BandBlocks: a block's DoFs lie in more than one copy")
        self.count, self.size = int(dofs.shape[0]), int(dofs.shape[1])
        self.max_width = int(max_width)
        self.dtype = dtype
        self.width = 0
        pos = np.full(n, -1, dtype=np.int32)
        pos[real] = np.flatnonzero(dofs.reshape(-1) >= 0).astype(np.int32)
        self._dof = _device_i32(dofs.reshape(-1))
        self._pos = _device_i32(pos)
        self._copy = _device_i32(copy[:, 0])
        self._copy_of_block = copy[:, 0].copy()
        self._every = _device_i32(np.ones(self.count, np.int32))  # every block selected (select(None))
        self._wanted = _device_i32(np.ones(self.count, np.int32))  # the blocks of a selection of copies
        self._wanted_of: np.ndarray | None = None  # the copies mask whose blocks _wanted holds
        self._selected = False  # whether eliminate() takes _wanted (else every block)
        self._usable = device_copy.new_ndarray(ti.i32, (self.count,))
        self._pivots = device_copy.new_ndarray(ti.f64, (self.count * self.size,))
        self._band = None  # the bands, made once the width is known
        self.tile, self.tiles = 1, 1  # rows a tile, tiles a block (tiling), set with the width
        self._tile_arrays = None  # (diag_inv, fwd, back, y, x) of the tiles (invert, band_solve), with the bands
        self._sources = None  # each band entry's position in the CSR data (_band_sources), with the bands
        self._measured_for = None  # the full pattern's device indptr the width was measured on

    def assemble(self, indptr, indices, data, blocks: tuple | None, pattern_key: object, data_index=None,
                 copies: np.ndarray | None = None) -> bool:
        """The blocks' bands of ``A`` (the both-triangle CSR ndarrays ``indptr``, ``indices``, ``data``, an entry
        at most once a row, plus the vertex blocks ``blocks = (brow, bcol, bval, free, count)`` or None),
        factorised and inverted; the width and the band entries' positions in ``data`` are found again when
        ``pattern_key`` is another object than at the last call. With ``data_index`` (int32 ndarray, one entry
        an entry of the pattern), ``data`` is another float64 array of the values, the pattern's entry ``e`` at
        ``data[data_index[e]]`` (e.g. the upper triangle's values). With ``copies`` (bool, one entry a copy) only
        the blocks of the copies marked are factorised and inverted, the others marked not usable
        (:meth:`select`). Returns whether the blocks are used (the band no wider than ``max_width``)."""
        if self._measured_for is not pattern_key:
            width = device_copy.new_ndarray(ti.i32, (1,))
            _band_width(indptr, indices, self._dof, self._pos, width, self.count, self.size)
            w = int(width.to_numpy()[0])
            self.width = w if 0 < w <= self.max_width else 0
            self._measured_for = pattern_key
            if self.width:
                size = self.count * self.size * (w + 1)
                if self._band is None or self._band.shape[0] != size:
                    self._band = device_copy.new_ndarray(ti.f64, (size,))
                    self._sources = device_copy.new_ndarray(ti.i32, (size,))
                t, nt = tiling(self.size, w)
                if self._tile_arrays is None or (self.tile, self.tiles) != (t, nt):
                    self._tile_arrays = tuple(device_copy.new_ndarray(dtype, (k,)) for dtype, k in
                                              3 * ((self.dtype, self.count * nt * t * t),)
                                              + 2 * ((ti.f64, self.count * nt * t),))
                self.tile, self.tiles = t, nt
                _band_sources(indptr, indices, self._dof, self._pos, self._sources, self.count, self.size, w)
                if data_index is not None:
                    _compose_sources(self._sources, data_index, size)
        if not self.width:
            return False
        self.select(copies)
        self.gather(data, blocks)
        self.eliminate()
        self.invert()
        return True

    def gather(self, data, blocks: tuple | None) -> None:
        """The blocks' bands of the CSR values ``data`` (the pattern of the last width measurement) and of the
        vertex blocks ``blocks`` (:meth:`assemble`)."""
        nb, m, w = self.count, self.size, self.width
        _band_gather(data, self._sources, self._band, nb * m * (w + 1))
        if blocks is not None and blocks[4]:
            brow, bcol, bval, free, count = blocks
            _band_add_vertex_blocks(brow, bcol, bval, free, self._pos, self._band, count, nb, m, w)

    def select(self, copies: np.ndarray | None) -> None:
        """The blocks :meth:`eliminate` factorises from now on: those of the copies marked in ``copies`` (bool, one
        entry a copy: e.g. a Newton iteration's retried copies, the only ones with a right-hand side), or every
        block with None (a constant device array: no copy); a selection's mask travels to the device when it
        changes."""
        self._selected = copies is not None
        if copies is None or self._wanted_of is not None and np.array_equal(copies, self._wanted_of):
            return
        wanted = np.asarray(copies, bool)[self._copy_of_block].astype(np.int32)
        if not device_copy.to_device(self._wanted, wanted):
            self._wanted.from_numpy(wanted)
        self._wanted_of = np.array(copies, dtype=bool)

    def eliminate(self) -> None:
        """The gathered bands of the selected blocks (:meth:`select`) factorised into ``L`` (blocked elimination,
        then the scaling; :attr:`usable` set, 0 for the blocks not selected)."""
        nb, m, w = self.count, self.size, self.width
        wanted = self._wanted if self._selected else self._every
        for first in range(0, -(-m // PANEL), PANELS_PER_LAUNCH):
            _eliminate_panels(self._band, wanted, first, nb, m, w)
        _scale_factor(self._band, self._pivots, self._usable, wanted, nb, m, w)

    def invert(self) -> None:
        """What :func:`band_solve` takes of each usable block's factor ``L``, by tiles of :attr:`tile` rows: each
        diagonal tile's inverse ``D_T^-1`` and the couplings ``G_T = D_T^-1 C_T``, ``H_T = D_T^-T C_{T+1}^T``."""
        diag_inv, fwd, back = self._tile_arrays[:3]
        nb, m, w, t, nt = self.count, self.size, self.width, self.tile, self.tiles
        _tile_inverses(self._band, self._usable, diag_inv, nb, m, w, t, nt)
        _mirror_tiles(diag_inv, self._usable, nb, t, nt)
        _tile_couplings(self._band, self._usable, diag_inv, fwd, back, nb, m, w, t, nt)

    @property
    def usable(self) -> np.ndarray:
        """Blocks whose factorisation succeeded at the last :meth:`assemble`, shape ``(nb,)`` bool."""
        return self._usable.to_numpy().astype(bool)

    def arguments(self) -> tuple:
        """``(diag_inv, fwd, back, y, x, usable, band_dof, band_copy)``: the device arrays :func:`band_solve`
        takes (after :meth:`assemble` with a width)."""
        return (*self._tile_arrays, self._usable, self._dof, self._copy)

    def sizes(self) -> tuple[int, int, int, int]:
        """``(nb, m, t, nt)``: the sizes :func:`band_solve` takes."""
        return self.count, self.size, self.tile, self.tiles

    def apply(self, r, z, active) -> None:
        """``z = S^-1 r`` on the usable blocks' DoFs of the active copies (device ndarrays ``r``, ``z`` of size
        ``n``, ``active`` int32 per copy); other entries of ``z`` unchanged."""
        _apply(*self.arguments(), active, r, z, *self.sizes())


def _device_i32(host: np.ndarray):
    """A new int32 device ndarray with ``host``'s values (1-D)."""
    arr = device_copy.new_ndarray(ti.i32, (max(host.size, 1),))
    arr.from_numpy(np.ascontiguousarray(host, dtype=np.int32) if host.size else np.zeros(1, np.int32))
    return arr
