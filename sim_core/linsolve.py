"""Pluggable sparse direct solvers for the Newton system (and the adjoint's extra solve).

PARDISO through ``pypardiso`` (Intel MKL) is the default; SciPy's SuperLU is the fallback when
pypardiso is not importable (e.g. on aarch64) or when asked for by name. Both keep the last
factorisation so the adjoint can reuse it (DESIGN.md "Backward").

The Newton loop uses the symmetric variants (:class:`PardisoCholesky`, :class:`ScipySymmetric`,
from :func:`make_symmetric_solver`): they take the upper triangle of a symmetric matrix, and the
Cholesky one reports a matrix that is not positive definite instead of factorising it, which the
solver uses to decide between the exact and the PSD-projected Hessian.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
from typing import Protocol

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.symmetric_pattern import both_triangles


@functools.lru_cache(maxsize=1)
def mkl_runtime() -> ctypes.CDLL:
    """MKL's runtime library as pypardiso locates it, found once per process.

    pypardiso looks for ``mkl_rt`` on every ``PyPardisoSolver()``; without a system MKL that is a
    recursive glob over the environment's ``lib`` tree (~0.4 s), which every new solver (each
    replay of a fit, each diagnosis probe) would pay again. Importing pypardiso already builds one
    (its module-level solver, ``pypardiso.scipy_aliases.pypardiso_solver``): its library is taken, so
    the search runs once per process.

    Raises:
        ImportError: pypardiso is not installed or MKL's runtime library is not found.
    """
    import pypardiso.scipy_aliases  # optional heavy dependency: MKL PARDISO, loaded on first use

    return pypardiso.scipy_aliases.pypardiso_solver.libmkl


class LinearSolver(Protocol):
    """Factorise once, solve many right-hand sides."""

    name: str

    def factorize(self, A: sp.csr_matrix) -> None:
        """Factorise the square sparse matrix ``A`` (shape ``(n, n)``)."""
        ...

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` with the last factorisation; ``b`` shape ``(n,)`` or ``(n, r)``."""
        ...


class PardisoSolver:
    """PARDISO (MKL) sparse LU, matrix type 11 (real, structurally general), for matrices that are
    not positive definite (the exact Hessian's fallback, the adjoint's solves).

    Called through ctypes like :class:`PardisoCholesky` (a :class:`PardisoHandle`) with PARDISO's
    default settings for matrix type 11 (``iparm[0] = 0``: weighted matching, scaling, pivot
    perturbation 1e-13, two steps of iterative refinement), the settings pypardiso's wrapper uses.
    Unlike that wrapper it does not search the disk for MKL on every new solver (each replay of a
    fit built one: ~1 s), and it redoes the symbolic analysis (phase 11) only when the sparsity
    pattern changes; the numerical factorisation (phase 22) runs on every call.

    Args:
        threads: MKL threads for PARDISO calls (>= 1).

    Raises:
        ImportError: pypardiso is not installed or MKL's runtime library is not found.
    """

    name = "pardiso"

    def __init__(self, threads: int = 1) -> None:
        self._handle = PardisoHandle(matrix_type=11, threads=threads)
        self._factorized = False

    def factorize(self, A: sp.csr_matrix) -> None:
        """LU-factorise the square sparse matrix ``A`` (shape ``(n, n)``, any sparse format).

        Raises:
            SimulationDivergedError: PARDISO reports an error (structurally singular matrix, ...).
        """
        A = sp.csr_matrix(A, dtype=float)
        if A.shape[0] != A.shape[1]:
            raise ValueError(f"PardisoSolver.factorize: matrix is not square, shape {A.shape}")
        A.sort_indices()
        self._factorized = False
        err = self._handle.factorize(A.indptr, A.indices, A.data)
        if err != 0:
            raise SimulationDivergedError(f"PARDISO LU factorisation failed with error {err}")
        self._factorized = True

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` with the last factorisation; ``b`` shape ``(n,)`` or ``(n, r)``.

        Raises:
            SimulationDivergedError: no factorisation, or PARDISO reports an error.
        """
        if not self._factorized:
            raise SimulationDivergedError("linear solve requested before factorisation")
        err, x = self._handle.solve(np.asarray(b, dtype=float))
        if err != 0:
            raise SimulationDivergedError(f"PARDISO solve failed with error {err}")
        return x.reshape(np.shape(b))


class ScipySolver:
    """SciPy SuperLU (``scipy.sparse.linalg.splu``)."""

    name = "scipy"

    def __init__(self) -> None:
        self._lu = None

    def factorize(self, A: sp.csr_matrix) -> None:
        try:
            self._lu = spla.splu(sp.csc_matrix(A))
        except RuntimeError as err:  # singular matrix
            raise SimulationDivergedError(f"sparse LU failed: {err}") from err

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._lu is None:
            raise SimulationDivergedError("linear solve requested before factorisation")
        return self._lu.solve(np.asarray(b, dtype=float))


class SymmetricSolver(Protocol):
    """Factorise a symmetric matrix given by its upper triangle; solve with the factorisation.

    Attributes:
        name: solver name reported by the benchmark.
        detects_indefinite: True when :meth:`factorize` returns False for a matrix that is not
            positive definite (a Cholesky factorisation); False when it factorises any
            non-singular matrix and always returns True.
        factorizations: calls of :meth:`factorize` so far.
    """

    name: str
    detects_indefinite: bool
    factorizations: int

    def factorize(self, upper: sp.csr_matrix) -> bool:
        """Factorise ``A = U + U^T - diag(U)`` from ``U`` (CSR, upper triangle with the full
        diagonal, sorted indices, shape ``(n, n)``); False when ``A`` is not positive definite."""
        ...

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` with the last successful factorisation; ``b`` shape ``(n,)``."""
        ...


def full_from_upper(upper: sp.csr_matrix) -> sp.csr_matrix:
    """The symmetric matrix ``U + U^T - diag(U)`` of an upper triangle ``U`` (CSR, sorted)."""
    strict = sp.triu(upper, k=1, format="csr")
    full = (upper + strict.T).tocsr()
    full.sort_indices()
    return full


class SymmetricExpansion:
    """:func:`full_from_upper` with the index map of the last sparsity pattern kept.

    The full matrix's entries are copies of the upper triangle's (the strict upper part and its
    transpose do not overlap), so for a known pattern the full CSR matrix is one gather
    ``full.data = upper.data[source]``: the Newton matrices keep their pattern for many steps
    (sticky union pattern of :mod:`sim_core.assembly`), where SciPy's ``triu`` + transpose + sum +
    sort cost milliseconds per step. Values equal :func:`full_from_upper`'s exactly; entries stored
    as explicit zeros in ``upper`` stay stored (SciPy's sum drops them).
    """

    def __init__(self) -> None:
        self._pattern: tuple[np.ndarray, np.ndarray] | None = None
        self._map: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # source, indptr, indices

    def __call__(self, upper: sp.csr_matrix) -> sp.csr_matrix:
        """The full symmetric matrix (CSR, sorted indices) of ``upper`` (CSR upper triangle with
        sorted indices, shape ``(n, n)``).

        Raises:
            ValueError: ``upper`` has entries below the diagonal or is not square.
        """
        upper = sp.csr_matrix(upper)
        if upper.shape[0] != upper.shape[1]:
            raise ValueError(f"SymmetricExpansion: matrix is not square, shape {upper.shape}")
        upper.sort_indices()
        pattern = self._pattern
        if pattern is None or not (np.array_equal(pattern[0], upper.indptr) and np.array_equal(pattern[1], upper.indices)):
            self._map = self._index_map(upper)
            self._pattern = (upper.indptr.copy(), upper.indices.copy())
        source, indptr, indices = self._map
        return sp.csr_matrix((upper.data[source], indices.copy(), indptr.copy()), shape=upper.shape)

    @staticmethod
    def _index_map(upper: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        try:
            indptr, indices, source = both_triangles(upper.indptr, upper.indices, upper.shape[0])
        except ValueError as err:
            raise ValueError(f"SymmetricExpansion: {err}") from None
        return source, indptr.astype(upper.indptr.dtype, copy=False), indices.astype(upper.indices.dtype, copy=False)


class PardisoHandle:
    """One PARDISO instance (MKL, through ctypes): handle, settings, and the analysed pattern.

    The symbolic analysis (phase 11: fill-reducing ordering) is redone only when the sparsity
    pattern changes; :meth:`factorize` runs the numerical factorisation (phase 22), :meth:`solve`
    the solve (phase 33). MKL runs with ``threads`` threads during the calls (thread-local setting,
    restored afterwards). Indices are passed 1-based (PARDISO's default).

    Args:
        matrix_type: PARDISO's ``mtype`` (2: real symmetric positive definite, upper triangle
            given; 11: real structurally general).
        threads: MKL threads (>= 1).
        iparm: PARDISO's settings (64 int32); None: all zero, i.e. PARDISO's defaults for
            ``matrix_type``.

    Raises:
        ImportError: pypardiso is not installed or MKL's runtime library is not found.
    """

    def __init__(self, matrix_type: int, threads: int = 1, iparm: np.ndarray | None = None) -> None:
        lib = mkl_runtime()
        self._pardiso = lib.pardiso
        i32 = ctypes.POINTER(ctypes.c_int32)
        self._pardiso.argtypes = [ctypes.POINTER(ctypes.c_int64), i32, i32, i32, i32, i32, ctypes.c_void_p,
                                  i32, i32, i32, i32, i32, i32, ctypes.c_void_p, ctypes.c_void_p, i32]
        self._pardiso.restype = None
        self._set_threads = getattr(lib, "MKL_Set_Num_Threads_Local", None)
        self.matrix_type = int(matrix_type)
        self.threads = int(threads)
        self._pt = np.zeros(64, dtype=np.int64)  # PARDISO's opaque handle
        self.iparm = np.zeros(64, dtype=np.int32) if iparm is None else np.asarray(iparm, dtype=np.int32).copy()
        self._perm = np.zeros(0, dtype=np.int32)
        # (indptr, indices) analysed (copies), and the arrays of the last call
        self._pattern: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._ia = self._ja = None
        self._data: np.ndarray | None = None
        self._n = 0
        # the call's constant arguments as ctypes objects, made once (about 40 us a call otherwise)
        i32 = ctypes.POINTER(ctypes.c_int32)
        self._pt_p = self._pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64))
        self._iparm_p = self.iparm.ctypes.data_as(i32)
        self._perm_p = self._perm.ctypes.data_as(i32)
        self._one = ctypes.byref(ctypes.c_int32(1))
        self._zero = ctypes.byref(ctypes.c_int32(0))
        self._ia_p = self._ja_p = None
        self._scratch = np.zeros(0)  # b and x of the analysis and factorisation phases (not read)

    def _call(self, phase: int, data: np.ndarray, b: np.ndarray | None = None) -> tuple[int, np.ndarray | None]:
        if b is None:  # analysis / factorisation: PARDISO reads neither b nor x
            b_arr, x, nrhs = self._scratch, self._scratch, 1
        else:
            b_arr = np.asfortranarray(b, dtype=float)
            nrhs = 1 if b_arr.ndim == 1 else b_arr.shape[1]
            x = np.empty_like(b_arr)  # written in full by the solve
        err = ctypes.c_int32(0)
        c = ctypes.c_int32
        previous = self._set_threads(self.threads) if self._set_threads is not None else None
        try:
            self._pardiso(
                self._pt_p, self._one, self._one, ctypes.byref(c(self.matrix_type)), ctypes.byref(c(phase)),
                ctypes.byref(c(self._n)), data.ctypes.data, self._ia_p, self._ja_p, self._perm_p, ctypes.byref(c(nrhs)),
                self._iparm_p, self._zero, b_arr.ctypes.data, x.ctypes.data, ctypes.byref(err),
            )
        finally:
            if previous is not None:
                self._set_threads(previous)
        return int(err.value), (np.ascontiguousarray(x) if b is not None else None)

    def factorize(self, indptr: np.ndarray, indices: np.ndarray, data: np.ndarray) -> int:
        """Analyse (when the pattern is new) and factorise the CSR matrix (sorted indices, shape
        ``(n, n)`` with ``n = indptr.size - 1``); PARDISO's error code (0: success; the symbolic
        analysis' errors as well).

        The pattern counts as the analysed one when the arrays are equal to it, or are the very
        arrays of the last call and read-only (as :class:`IdentityRows` passes them: no comparison).
        """
        data = np.ascontiguousarray(data, dtype=float)
        pattern = self._pattern
        self._data = None
        same = pattern is not None and (
            (pattern[2] is indptr and pattern[3] is indices and not indptr.flags.writeable
             and not indices.flags.writeable)
            or (np.array_equal(pattern[0], indptr) and np.array_equal(pattern[1], indices)))
        if not same:
            self._n = indptr.size - 1
            self._ia = (indptr + 1).astype(np.int32)
            self._ja = (indices + 1).astype(np.int32)
            self._ia_p = self._ia.ctypes.data_as(ctypes.POINTER(ctypes.c_int32))
            self._ja_p = self._ja.ctypes.data_as(ctypes.POINTER(ctypes.c_int32))
            self._scratch = np.zeros(self._n)
            err, _ = self._call(11, data)
            if err != 0:
                self._pattern = None
                return err
            self._pattern = (indptr.copy(), indices.copy(), indptr, indices)
        else:
            self._pattern = (pattern[0], pattern[1], indptr, indices)
        err, _ = self._call(22, data)
        if err == 0:
            self._data = data
        return err

    def forget_pattern(self) -> None:
        """Force a new symbolic analysis at the next :meth:`factorize`."""
        self._pattern = None

    def solve(self, b: np.ndarray) -> tuple[int, np.ndarray | None]:
        """Solve with the last successful factorisation, ``b`` shape ``(n,)`` or ``(n, r)``;
        (error code, x). Error -100 (this class's own): no successful factorisation."""
        if self._data is None:
            return -100, None
        return self._call(33, self._data, b)

    def __del__(self) -> None:
        if getattr(self, "_pattern", None) is not None and self._ia is not None:
            # release PARDISO's internal memory; at interpreter shutdown the library may be gone already
            with contextlib.suppress(Exception):
                self._call(-1, np.zeros(1))


class IdentityRows:
    """The DoFs of a symmetric matrix (upper triangle, CSR) that are decoupled identity rows, and the
    CSR arrays of the matrix without them.

    A Dirichlet DoF of the constrained Newton matrix has a row and column of zeros with 1 on the
    diagonal (:mod:`sim_core.assembly`): ``x_i = b_i`` exactly, and the other unknowns do not see
    it. A DoF counts when its row of the upper triangle holds only the diagonal, no other row holds
    its column, and the diagonal value is exactly 1. Dropping these rows and columns leaves the
    same linear system on the other DoFs (Forming: 1698 -> 825 rows); PARDISO's solution of it is
    bit for bit the one of the whole matrix (its fill-reducing ordering eliminates the isolated
    rows first; checked on 242 Newton matrices of the Forming bench), in less time.

    Args:
        indptr, indices: CSR arrays of the upper triangle (sorted indices), ``(n + 1,)`` and ``(nnz,)``.
        data: its values, ``(nnz,)``.
    """

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, data: np.ndarray) -> None:
        n = indptr.size - 1
        rows = np.repeat(np.arange(n), np.diff(indptr))
        off = indices != rows
        coupled = np.zeros(n, dtype=bool)
        coupled[rows[off]] = True
        coupled[indices[off]] = True
        diagonal = np.flatnonzero(~off)
        unit = np.zeros(n, dtype=bool)
        unit[rows[diagonal]] = data[diagonal] == 1.0
        candidates = ~coupled & unit
        self.identity = candidates  # bool (n,)
        self.kept = np.flatnonzero(~candidates)  # the other DoFs, (m,)
        keep_slots = ~candidates[rows]
        self.slots = np.flatnonzero(keep_slots)  # entries of the reduced matrix, (nnz_r,)
        new_index = np.cumsum(~candidates) - 1
        self.indptr = np.zeros(self.kept.size + 1, dtype=np.int64)
        np.cumsum(np.diff(indptr)[self.kept], out=self.indptr[1:])
        self.indices = new_index[indices[self.slots]]
        for reduced in (self.indptr, self.indices):  # the same read-only objects every factorisation:
            reduced.flags.writeable = False  # PardisoHandle then knows the pattern without comparing it
        self._pattern = (indptr, indices)
        self._unit_slots = diagonal[candidates[rows[diagonal]]]  # the identity rows' diagonal entries
        self._reduced: np.ndarray | None = None  # reduced_data()'s array

    def reduced_data(self, data: np.ndarray) -> np.ndarray:
        """The values of the reduced matrix, ``data[slots]`` ``(nnz_r,)`` (float64), gathered into an array
        kept by this split: the next call overwrites it."""
        reduced = self._reduced
        if reduced is None:
            reduced = self._reduced = np.empty(self.slots.size)
        # mode "clip": the slots are in range by construction, and take() then writes out directly
        np.take(np.asarray(data, dtype=np.float64), self.slots, out=reduced, mode="clip")
        return reduced

    def matches(self, indptr: np.ndarray, indices: np.ndarray, data: np.ndarray) -> bool:
        """Whether this split holds for the matrix ``(indptr, indices, data)``: the same pattern
        (the same array objects, or equal ones) and a diagonal of exactly 1 on every identity row
        (a Dirichlet DoF of every step; a decoupled free DoF with another diagonal value is kept)."""
        pattern = self._pattern
        same = (pattern[0] is indptr and pattern[1] is indices) or (
            np.array_equal(pattern[0], indptr) and np.array_equal(pattern[1], indices))
        if not same:
            return False
        self._pattern = (indptr, indices)
        return bool(np.all(data[self._unit_slots] == 1.0))


class PardisoCholesky:
    """PARDISO (MKL) sparse Cholesky, matrix type 2 (real symmetric positive definite).

    Differences from :class:`PardisoSolver` (general LU, matrix type 11):
    only the upper triangle is factorised (about half the fill-in); the symbolic analysis
    (phase 11: fill-reducing ordering) is redone only when the sparsity pattern changes, the
    numerical factorisation (phase 22) runs every call; a matrix that is not positive definite
    makes PARDISO stop with error -4 (non-positive pivot), reported as ``False``. The decoupled
    identity rows of the Dirichlet DoFs are split off first (:class:`IdentityRows`): PARDISO
    factorises the matrix of the other DoFs only, with the same solution. MKL runs with
    ``threads`` threads during the calls (thread-local setting, restored afterwards): the Newton
    matrices of a few thousand DoFs factorise in about a millisecond, where extra threads cost
    more than they give.

    Args:
        threads: MKL threads for PARDISO calls (>= 1).
    """

    name = "pardiso"
    detects_indefinite = True
    _NOT_POSITIVE_DEFINITE = -4

    def __init__(self, threads: int = 1) -> None:
        # PARDISO's defaults for matrix type 2 (iparm[0] = 1: use these values), except iparm[7]:
        # no iterative refinement. The defaults refine twice per solve, which costs 2/3 of a solve
        # here and leaves the residual of these Newton systems at the same round-off (3e-11 with
        # and without on a Forming matrix). And iparm[1]: minimum-degree ordering instead of METIS
        # nested dissection. On 31 Newton matrices of a sheet-gel replay (n 1539) it gives 9 % less
        # fill, 16 % less factorisation time (0.91 vs 1.08 ms) and 14 % less analysis + factorisation
        # (4.0 vs 4.7 ms); on Forming's (n 1698) the same times within 4 % (docs/benchmarks_log.md).
        iparm = np.zeros(64, dtype=np.int32)
        iparm[0] = 1  # iparm supplied
        iparm[1] = 0  # minimum-degree ordering (METIS nested dissection, 2, is PARDISO's default)
        iparm[7] = 0  # iterative refinement steps
        iparm[9] = 8  # pivot perturbation 1e-8 (default; not used by a Cholesky)
        iparm[17] = -1  # report the factor's non-zeros (default)
        self._handle = PardisoHandle(matrix_type=2, threads=threads, iparm=iparm)
        self._factorized = False
        self._split: IdentityRows | None = None  # identity rows of the last pattern
        self._n = 0
        self.factorizations = 0

    @property
    def threads(self) -> int:
        """MKL threads used during PARDISO calls."""
        return self._handle.threads

    @threads.setter
    def threads(self, value: int) -> None:
        self._handle.threads = int(value)

    def factorize(self, upper: sp.csr_matrix) -> bool:
        """Cholesky of the matrix whose upper triangle is ``upper``; False if not positive definite.

        Raises:
            SimulationDivergedError: any other PARDISO error (the code is in the message).
        """
        self.factorizations += 1
        if not (sp.issparse(upper) and upper.format == "csr"):
            upper = sp.csr_matrix(upper)
        upper.sort_indices()  # a no-op for the assembler's matrices (flagged sorted)
        split = self._split
        if split is None or not split.matches(upper.indptr, upper.indices, upper.data):
            split = self._split = IdentityRows(upper.indptr, upper.indices, upper.data)
        self._factorized = False
        self._n = upper.shape[0]
        if split.kept.size == 0:  # the identity: nothing to factorise
            self._factorized = True
            return True
        err = self._handle.factorize(split.indptr, split.indices, split.reduced_data(upper.data))
        self._factorized = err == 0
        if err == self._NOT_POSITIVE_DEFINITE:
            return False
        if err != 0:
            self._handle.forget_pattern()
            raise SimulationDivergedError(f"PARDISO Cholesky factorisation failed with error {err}")
        return True

    def solve(self, b: np.ndarray) -> np.ndarray:
        if not self._factorized:
            raise SimulationDivergedError("linear solve requested without a successful factorisation")
        b = np.asarray(b, dtype=float)
        if b.shape[0] != self._n:
            raise ValueError(f"PardisoCholesky.solve: right-hand side has {b.shape[0]} rows, the matrix {self._n}")
        x = b.copy()  # identity rows: x_i = b_i
        kept = self._split.kept
        if kept.size:
            err, x_kept = self._handle.solve(b[kept])
            if err != 0:
                raise SimulationDivergedError(f"PARDISO solve failed with error {err}")
            x[kept] = x_kept.reshape((kept.size,) + b.shape[1:])
        return x


class ScipySymmetric:
    """:class:`SymmetricSolver` on SciPy's SuperLU with diagonal pivoting, which detects indefinite
    matrices.

    With ``diag_pivot_thresh=0`` and ``SymmetricMode`` SuperLU pivots on the diagonal of the
    symmetrically permuted matrix (same row and column order), so ``P A P^T = L U`` with
    ``U = D L^T``: an LDL^T factorisation whose pivots ``D`` have the signs of the eigenvalues of A
    (Sylvester's law of inertia). ``A`` is positive definite iff every pivot is positive; a zero pivot
    (singular matrix) or an off-diagonal pivot (no LDL^T) counts as "not positive definite". This
    lets the Newton solver use the exact Hessian first without PARDISO (``exact_hessian_first``),
    as it does with PARDISO's Cholesky.
    """

    name = "scipy"
    detects_indefinite = True

    def __init__(self) -> None:
        self._lu = None
        self._full_from_upper = SymmetricExpansion()
        self.factorizations = 0

    def factorize(self, upper: sp.csr_matrix) -> bool:
        self.factorizations += 1
        A = sp.csc_matrix(self._full_from_upper(upper))
        try:
            lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError:  # exactly singular
            return False
        if not (np.array_equal(lu.perm_r, lu.perm_c) and np.all(lu.U.diagonal() > 0.0)):
            return False
        self._lu = lu
        return True

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._lu is None:
            raise SimulationDivergedError("linear solve requested before factorisation")
        return self._lu.solve(np.asarray(b, dtype=float))


def make_symmetric_solver(name: str = "pardiso") -> SymmetricSolver:
    """Symmetric solver by name: ``"pardiso"`` (:class:`PardisoCholesky`, SciPy when pypardiso is
    unavailable), ``"scipy"`` (:class:`ScipySymmetric`), ``"pcg"`` (the block-Jacobi conjugate
    gradient in Taichi, :class:`sim_core.ti_kernels.pcg.BatchedPCG`; Taichi must be initialised) or ``"envelope"``
    (the envelope Cholesky in Taichi, :class:`sim_core.ti_kernels.envelope_cholesky.BatchedEnvelope`).

    Raises:
        ConfigError: unknown name.
    """
    if name == "pardiso":
        try:
            return PardisoCholesky()
        except (ImportError, OSError, AttributeError):
            return ScipySymmetric()
    if name == "scipy":
        return ScipySymmetric()
    if name == "pcg":
        from sim_core.ti_kernels.pcg import BatchedPCG  # optional heavy dependency: Taichi

        return BatchedPCG()
    if name == "envelope":
        from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope  # optional heavy dependency: Taichi

        return BatchedEnvelope()
    raise ConfigError(f"unknown linear solver {name!r}; use 'pardiso', 'scipy', 'pcg' or 'envelope'")


def make_linear_solver(name: str = "pardiso") -> LinearSolver:
    """Create a solver by name: ``"pardiso"`` (falls back to SciPy if unavailable) or ``"scipy"``;
    ``"pcg"`` and ``"envelope"`` (configurations whose Newton systems take a batched Taichi solver) get PARDISO's LU.

    Raises:
        ConfigError: unknown name.
    """
    if name in ("pardiso", "pcg", "envelope"):
        try:
            return PardisoSolver()
        except (ImportError, OSError, AttributeError):
            return ScipySolver()
    if name == "scipy":
        return ScipySolver()
    raise ConfigError(f"unknown linear solver {name!r}; use 'pardiso', 'scipy' or 'pcg'")
