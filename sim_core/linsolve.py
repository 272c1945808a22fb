"""Pluggable sparse direct solvers for the Newton system (and the adjoint's extra solve).

PARDISO through ``pypardiso`` (Intel MKL) is the default; SciPy's SuperLU is the fallback when
pypardiso is not importable (e.g. on aarch64) or when asked for by name. Both keep the last
factorisation so the adjoint can reuse it (DESIGN.md "Backward").
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from sim_core.errors import ConfigError, SimulationDivergedError


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
