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


@functools.lru_cache(maxsize=1)
def mkl_runtime() -> ctypes.CDLL:
    """MKL's runtime library as pypardiso locates it, found once per process.

    pypardiso looks for ``mkl_rt`` on every ``PyPardisoSolver()``; without a system MKL that is a
    recursive glob over the environment's ``lib`` tree (~0.4 s), which every new solver (each
    replay of a fit, each diagnosis probe) would pay again.

    Raises:
        ImportError: pypardiso is not installed or MKL's runtime library is not found.
    """
    import pypardiso

    return pypardiso.PyPardisoSolver().libmkl


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
    """PARDISO (MKL) via pypardiso; matrix type 11 (real, structurally general)."""

    name = "pardiso"

    def __init__(self) -> None:
        import pypardiso

        self._solver = pypardiso.PyPardisoSolver()
        self._A: sp.csr_matrix | None = None

    def factorize(self, A: sp.csr_matrix) -> None:
        A = sp.csr_matrix(A)
        A.sort_indices()
        self._A = A
        self._solver.factorize(A)

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._A is None:
            raise SimulationDivergedError("linear solve requested before factorisation")
        x = self._solver.solve(self._A, np.ascontiguousarray(b, dtype=float))
        return np.asarray(x).reshape(np.shape(b))


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
    """

    name: str
    detects_indefinite: bool

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


class PardisoCholesky:
    """PARDISO (MKL) sparse Cholesky, matrix type 2 (real symmetric positive definite).

    Differences from :class:`PardisoSolver` (pypardiso's wrapper, general LU, matrix type 11):
    only the upper triangle is factorised (about half the fill-in); the symbolic analysis
    (phase 11: fill-reducing ordering) is redone only when the sparsity pattern changes, the
    numerical factorisation (phase 22) runs every call; a matrix that is not positive definite
    makes PARDISO stop with error -4 (non-positive pivot), reported as ``False``. MKL runs with
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
        lib = mkl_runtime()
        self._pardiso = lib.pardiso
        i32 = ctypes.POINTER(ctypes.c_int32)
        self._pardiso.argtypes = [ctypes.POINTER(ctypes.c_int64), i32, i32, i32, i32, i32, ctypes.c_void_p,
                                  i32, i32, i32, i32, i32, i32, ctypes.c_void_p, ctypes.c_void_p, i32]
        self._pardiso.restype = None
        self._set_threads = getattr(lib, "MKL_Set_Num_Threads_Local", None)
        self.threads = int(threads)
        self._pt = np.zeros(64, dtype=np.int64)  # PARDISO's opaque handle
        # PARDISO's defaults for matrix type 2 (iparm[0] = 1: use these values), except iparm[7]:
        # no iterative refinement. The defaults refine twice per solve, which costs 2/3 of a solve
        # here and leaves the residual of these Newton systems at the same round-off (3e-11 with
        # and without on a Forming matrix).
        self._iparm = np.zeros(64, dtype=np.int32)
        self._iparm[0] = 1  # iparm supplied
        self._iparm[1] = 2  # nested-dissection ordering (METIS), the default
        self._iparm[7] = 0  # iterative refinement steps
        self._iparm[9] = 8  # pivot perturbation 1e-8 (default; not used by a Cholesky)
        self._iparm[17] = -1  # report the factor's non-zeros (default)
        self._perm = np.zeros(0, dtype=np.int32)
        self._pattern: tuple[np.ndarray, np.ndarray] | None = None  # (indptr, indices) analysed
        self._ia = self._ja = None
        self._data: np.ndarray | None = None
        self._n = 0
        self._factorized = False

    def _call(self, phase: int, data: np.ndarray, b: np.ndarray | None = None) -> tuple[int, np.ndarray | None]:
        nrhs = 1
        if b is None:
            b_arr = np.zeros(self._n)
        else:
            b_arr = np.asfortranarray(b, dtype=float)
            nrhs = 1 if b_arr.ndim == 1 else b_arr.shape[1]
        x = np.zeros_like(b_arr)
        err = ctypes.c_int32(0)
        c = ctypes.c_int32
        previous = self._set_threads(self.threads) if self._set_threads is not None else None
        try:
            self._pardiso(
                self._pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), ctypes.byref(c(1)), ctypes.byref(c(1)),
                ctypes.byref(c(2)), ctypes.byref(c(phase)), ctypes.byref(c(self._n)), data.ctypes.data,
                self._ia.ctypes.data_as(ctypes.POINTER(c)), self._ja.ctypes.data_as(ctypes.POINTER(c)),
                self._perm.ctypes.data_as(ctypes.POINTER(c)), ctypes.byref(c(nrhs)),
                self._iparm.ctypes.data_as(ctypes.POINTER(c)), ctypes.byref(c(0)), b_arr.ctypes.data,
                x.ctypes.data, ctypes.byref(err),
            )
        finally:
            if previous is not None:
                self._set_threads(previous)
        return int(err.value), (np.ascontiguousarray(x) if b is not None else None)

    def factorize(self, upper: sp.csr_matrix) -> bool:
        """Cholesky of the matrix whose upper triangle is ``upper``; False if not positive definite.

        Raises:
            SimulationDivergedError: any other PARDISO error (the code is in the message).
        """
        upper = sp.csr_matrix(upper)
        upper.sort_indices()
        data = np.ascontiguousarray(upper.data, dtype=float)
        pattern = self._pattern
        if pattern is None or not (np.array_equal(pattern[0], upper.indptr) and np.array_equal(pattern[1], upper.indices)):
            self._n = upper.shape[0]
            self._ia = (upper.indptr + 1).astype(np.int32)  # PARDISO's default is 1-based indexing
            self._ja = (upper.indices + 1).astype(np.int32)
            err, _ = self._call(11, data)
            if err != 0:
                self._pattern = None
                raise SimulationDivergedError(f"PARDISO symbolic analysis failed with error {err}")
            self._pattern = (upper.indptr.copy(), upper.indices.copy())
        err, _ = self._call(22, data)
        self._factorized = err == 0
        if err == self._NOT_POSITIVE_DEFINITE:
            return False
        if err != 0:
            self._pattern = None
            raise SimulationDivergedError(f"PARDISO Cholesky factorisation failed with error {err}")
        self._data = data
        return True

    def solve(self, b: np.ndarray) -> np.ndarray:
        if not self._factorized:
            raise SimulationDivergedError("linear solve requested without a successful factorisation")
        err, x = self._call(33, self._data, np.asarray(b, dtype=float))
        if err != 0:
            raise SimulationDivergedError(f"PARDISO solve failed with error {err}")
        return x.reshape(np.shape(b))

    def __del__(self) -> None:
        if getattr(self, "_pattern", None) is not None and self._ia is not None:
            # release PARDISO's internal memory; at interpreter shutdown the library may be gone already
            with contextlib.suppress(Exception):
                self._call(-1, np.zeros(1))


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

    def factorize(self, upper: sp.csr_matrix) -> bool:
        A = sp.csc_matrix(full_from_upper(sp.csr_matrix(upper)))
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
    unavailable) or ``"scipy"`` (:class:`ScipySymmetric`).

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
    raise ConfigError(f"unknown linear solver {name!r}; use 'pardiso' or 'scipy'")


def make_linear_solver(name: str = "pardiso") -> LinearSolver:
    """Create a solver by name: ``"pardiso"`` (falls back to SciPy if unavailable) or ``"scipy"``.

    Raises:
        ConfigError: unknown name.
    """
    if name == "pardiso":
        try:
            return PardisoSolver()
        except ImportError:
            return ScipySolver()
    if name == "scipy":
        return ScipySolver()
    raise ConfigError(f"unknown linear solver {name!r}; use 'pardiso' or 'scipy'")
