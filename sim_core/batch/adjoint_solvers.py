"""The batched adjoint's solvers of the stacked exact Hessians (block diagonal by copy), besides one LU of the
whole stacked matrix (:func:`sim_core.linsolve.make_linear_solver`).

The adjoint needs the EXACT Hessian at each converged step (:mod:`sim_core.adjoint`), which need not be
positive definite; the single path factorises it by LU (PARDISO's, matrix type 11).

* :class:`CopyBlockLU` (CPU): each copy's block by its own LU, kept per copy from step to step. PARDISO's
  symbolic analysis of the whole stacked matrix grows faster than its size (8 Folding-U copies: 64 ms a
  step against 8 x 2.6 ms), so on the CPU the copies' own factorisations are the faster way to one solve
  of all copies (``docs/benchmarks_log.md``, session 42, 28adj).
* :class:`StackedAdjointCG` (Taichi device): every copy's block by
  :class:`~sim_core.ti_kernels.pcg.BatchedPCG` (block-Jacobi preconditioned CG, one CG per copy, all
  copies in one launch) to the relative residual :data:`ADJOINT_CG_RTOL`. A copy whose CG meets
  non-positive curvature (``p.Ap <= 0``: its block is not positive definite) or does not converge is
  solved again by the LU of its own block, as the single path solves it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from sim_core.batch.stacked import StackedScene
from sim_core.linsolve import make_linear_solver

ADJOINT_CG_RTOL = 1e-10
"""Per copy, the CG stops at ``|r_c| <= rtol |b_c|``: the adjoint vector to about the precision of a direct solve
(unlike the Newton updates' forcing term :data:`sim_core.batch.lockstep.LOCKSTEP_CG_RTOL`, an error here goes
straight into the gradient)."""


class StackedAdjointCG:
    """A :class:`~sim_core.linsolve.LinearSolver` of a stacked scene's block-diagonal exact Hessians (module
    docstring); Taichi must be initialised (a Taichi solver backend).

    Args:
        scene: the stacked scene (its copies are the CG's blocks).
        rtol: the CG's relative residual per copy.
        max_iterations: CG iterations per solve at most.

    Attributes:
        name: ``"pcg"``.
        lu_copies: copies solved by LU so far (negative curvature or no convergence), counted over solves.
        cg_iterations: the CG iterations of every solve (of the copy that ran the most).
    """

    name = "pcg"

    def __init__(self, scene: StackedScene, rtol: float = ADJOINT_CG_RTOL, max_iterations: int = 5000) -> None:
        from sim_core.ti_kernels.pcg import BatchedPCG  # Taichi kernels: loaded on a Taichi backend only

        segments = np.zeros(scene.model.vertex_count, dtype=np.int32)
        segments[scene.index] = np.arange(scene.copies)[:, None]
        self.pcg = BatchedPCG(np.repeat(segments, 3), rtol=rtol, max_iterations=max_iterations)
        self.dofs = scene.dof_index
        self.lu_copies = 0
        self.cg_iterations: list[int] = []
        self._A: sp.csr_matrix | None = None

    def factorize(self, A: sp.csr_matrix) -> None:
        """Keep the symmetric matrix ``A`` (shape ``(3 N, 3 N)``) on the device (its upper triangle) and here."""
        self._A = sp.csr_matrix(A, dtype=float)
        upper = sp.triu(self._A, format="csr")
        upper.sort_indices()
        self.pcg.factorize(upper)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A x = b`` for ``b`` of shape ``(3 N,)`` or ``(3 N, r)``: every copy by the CG, the copies it flags
        (:attr:`~sim_core.ti_kernels.pcg.BatchedPCG.indefinite`, ``unconverged``) by the LU of their block."""
        b = np.asarray(b, dtype=float)
        if b.ndim == 2:
            return np.stack([self.solve(b[:, j]) for j in range(b.shape[1])], axis=1)
        x = np.array(self.pcg.solve(b))
        self.cg_iterations.append(int(self.pcg.iterations))
        for i in np.flatnonzero(self.pcg.indefinite | self.pcg.unconverged):
            idx = self.dofs[i]
            lu = make_linear_solver("pardiso")
            lu.factorize(self._A[idx][:, idx])
            x[idx] = lu.solve(b[idx])
            self.lu_copies += 1
        return x


class CopyBlockLU:
    """A :class:`~sim_core.linsolve.LinearSolver` of a stacked scene's block-diagonal matrices: each copy's block
    by its own LU (:func:`~sim_core.linsolve.make_linear_solver`), kept per copy from one matrix to the next, so
    that a copy whose sparsity pattern is unchanged skips the symbolic analysis (PARDISO's analysis of the
    whole stacked matrix grows faster than its size: its fill-reducing ordering).

    Args:
        scene: the stacked scene (its copies are the blocks).
        linear_solver: the copies' LU (``"pardiso"`` or ``"scipy"``).
    """

    name = "blocks"

    def __init__(self, scene: StackedScene, linear_solver: str = "pardiso") -> None:
        self.dofs = scene.dof_index
        self.solvers = [make_linear_solver(linear_solver) for _ in range(scene.copies)]
        self._order = np.concatenate(list(self.dofs))
        self._starts = np.concatenate([[0], np.cumsum([len(d) for d in self.dofs])])

    def factorize(self, A: sp.csr_matrix) -> None:
        """Factorise every copy's diagonal block of ``A`` (shape ``(3 N, 3 N)``, block diagonal by copy)."""
        P = sp.csr_matrix(A, dtype=float)[self._order][:, self._order].tocsr()
        for i, solver in enumerate(self.solvers):
            a, b = self._starts[i], self._starts[i + 1]
            solver.factorize(P[a:b, a:b])

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A x = b`` per copy block; ``b`` shape ``(3 N,)`` or ``(3 N, r)``."""
        b = np.asarray(b, dtype=float)
        x = np.zeros_like(b)
        for idx, solver in zip(self.dofs, self.solvers):
            x[idx] = np.asarray(solver.solve(b[idx])).reshape(b[idx].shape)
        return x
