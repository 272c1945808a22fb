"""A series spring's compression as one more unknown of the step's Newton solve (the joint drive step).

:mod:`sim_core.series_drive` holds an effector on a spring of stiffness ``k_s`` along a unit axis ``n``
(world, into the contact) with a damper ``c`` on the tool's velocity along ``n``: the tool ends the step at
``p(b) = a - b n`` (``a`` the anchor, ``b`` the spring's compression) and the driven (base) vertices move
rigidly with it, ``x_base(b) = X_base - b n`` (``X_base`` their positions with the tool at the anchor). Here
``b`` joins the step's positions as an unknown of one incremental potential,

    ``E(x, b) = E_step(x; x_base(b)) + k_s b^2 / 2 + (c / 2 dt) (b - d)^2 - b n . G``,

``E_step`` the step's potential (:mod:`sim_core.solver`), ``d = (a - p_prev) . n`` the anchor's reach past
the tool's position at the step's start (the damper's energy: ``c / (2 dt) ((p(b) - p_prev) . n)^2``) and
``G = sum_i m_i g`` the weight of the load vertices (the driven body; the arm compensates its tool's weight,
so that in free motion at rest ``b = 0`` as with :class:`~sim_core.series_drive.SeriesSpringDrive`'s secant).
Its stationarity in ``b``,

    ``dE/db = -n . sum_base dE_step/dx_i + K b - (c / dt) d - n . G = 0``,    ``K = k_s + c / dt``,

is the secant's balance ``h(b) = F - K b + c d / dt = 0`` with the load ``F`` read as the base's reaction:
where the free vertices are at rest in ``E`` (``dE/dx_i = 0``) and the load body's elastic energy does not
change under its rigid translation, ``-n . sum_base dE_step/dx_i = F + N - n . G``, with ``F`` the contact
and friction load (``SeriesSpringDrive.load``) and ``N = n . sum_load [m_i / dt^2 (x_i - x_hat_i) +
gamma m_i / dt (x_i - x_i^n)]`` the load body's inertia and mass-proportional damping (``gamma`` the model's
``damping``): the spring carries the driven body's inertia too (``m a``; a few mN for a gel pad of grams in
a replay, against the secant's force tolerance of about 1 mN). The step's minimiser over ``(x, b)`` is the
branch the Newton path reaches from its start, so a fold of ``F(b)`` (lift-off: the buckled card follows the
pad or lies down) is decided by the energy, and a drive step costs one Newton solve.

Newton system: the base vertices are kept free in the step's assembly (their rows and columns in the
Newton matrix ``H``) and tied to ``b``: with ``S`` the map ``(x_free, b) -> x`` (``dx_base = -n db``) the
reduced matrix is ``S^T H S + K`` on ``b``, i.e. the kinematic step's constrained matrix ``A`` (base rows and
columns cleared, 1 on their diagonal) bordered by the column ``u = -H_{free, base} n`` and the corner
``c = n^T H_{base, base} n + K`` (:meth:`CompressionPotential.border`). The border is eliminated
(:meth:`CompressionPotential.direction`): ``A`` is factorised as in a kinematic step (its pattern, its cost;
a dense border column in the factorisation would be ordered anywhere and fill), two solves give ``A^-1 g`` and
``A^-1 u``, and the Schur complement ``c - u^T A^-1 u`` gives ``db``. The step's last factorisation is then
the kinematic step's exact Hessian at the accepted positions, which the tangents reuse. ``S^T H S`` is
positive semidefinite wherever ``H`` is (a projected Hessian), and ``K > 0``: the projected matrix is as safe
as the step's. The spring's energy is spread over
the base vertices as a potential of their positions (:meth:`CompressionPotential.energy`, ``gradient``:
``b(x)`` the base's mean displacement along ``-n``), so the step's line search and Armijo test read ``E(x,
b)`` unchanged.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from sim_core.errors import ConfigError


@dataclass(frozen=True)
class CompressionUnknown:
    """The series spring of one step whose compression the step's Newton solve takes as an unknown
    (``Control.compression``; module docstring).

    Attributes:
        effector: the driven effector's name (its vertices are the base that moves with ``b``).
        axis: unit axis ``n`` (3,), world, pointing into the contact.
        stiffness: the spring's ``k_s``, N/m (> 0, finite).
        rate: the damper's ``c / dt``, N/m (>= 0).
        reach: ``d = (a - p_prev) . n``, m: the anchor's reach past the tool's position at the step's start.
        start: the compression ``b`` (m) the Newton iterations start from.
        load_vertices: global indices of the driven body's vertices (the load vertices), ``(l,)``: their weight
            is compensated.
    """

    effector: str
    axis: np.ndarray
    stiffness: float
    rate: float
    reach: float
    start: float
    load_vertices: np.ndarray

    def __post_init__(self) -> None:
        axis = np.asarray(self.axis, dtype=float)
        if axis.shape != (3,) or abs(float(np.linalg.norm(axis)) - 1.0) > 1e-9:
            raise ConfigError(f"compression of {self.effector!r}: axis must be a unit 3-vector, got {axis.tolist()}")
        if not (np.isfinite(self.stiffness) and self.stiffness > 0.0):
            raise ConfigError(f"compression of {self.effector!r}: stiffness must be finite and > 0 N/m, "
                              f"got {self.stiffness!r}")
        if not (np.isfinite(self.rate) and self.rate >= 0.0):
            raise ConfigError(f"compression of {self.effector!r}: damper rate c/dt must be finite and >= 0 N/m, "
                              f"got {self.rate!r}")
        if not (np.isfinite(self.reach) and np.isfinite(self.start)):
            raise ConfigError(f"compression of {self.effector!r}: reach and start must be finite, got "
                              f"{self.reach!r} m, {self.start!r} m")

    @property
    def curvature(self) -> float:
        """``K = k_s + c / dt``, N/m: the spring's energy's second derivative in ``b``."""
        return float(self.stiffness + self.rate)

    def spring_energy(self, b: float, weight: float) -> float:
        """``k_s b^2 / 2 + (c / 2 dt) (b - d)^2 - b w`` (J), ``w = n . G`` (N) the compensated weight."""
        return 0.5 * self.stiffness * b * b + 0.5 * self.rate * (b - self.reach) ** 2 - b * weight

    def spring_force(self, b: float, weight: float) -> float:
        """The spring energy's derivative in ``b``: ``K b - (c / dt) d - w`` (N)."""
        return self.curvature * b - self.rate * self.reach - weight


class CompressionPotential:
    """The spring's part of the joint step's potential, a function of the base vertices' positions, and the
    bordered Newton matrix of the tied base (module docstring).

    Args:
        unknown: the :class:`CompressionUnknown`.
        base: global indices of the effector's driven vertices, ``(m,)``.
        anchored: their positions with the tool at the anchor (``b = 0``), ``(m, 3)`` m.
        weight: ``w = n . G``, N: the load vertices' weight along ``n``.
        free: the kinematic step's free DoFs (the base held), ``(3 n,)`` bool.

    Attributes:
        free: ``free``, read-only.
        base_dofs: the base vertices' DoFs, ``(3 n,)`` bool.
        tied: ``S_b = dx / db``, ``(3 n,)``: ``-n`` on each base vertex, zero elsewhere.
        last_border: ``(u, c)`` of :meth:`border` of the matrix the step's solver factorised last (its simplified
            Newton test solves with them), None before one.
    """

    def __init__(self, unknown: CompressionUnknown, base: np.ndarray, anchored: np.ndarray, weight: float,
                 free: np.ndarray) -> None:
        self.unknown = unknown
        self.axis = np.asarray(unknown.axis, dtype=float)
        self.base = np.asarray(base, dtype=np.int64).reshape(-1)
        if self.base.size == 0:
            raise ConfigError(f"compression of {unknown.effector!r}: the effector drives no vertices")
        self.anchored = np.asarray(anchored, dtype=float).reshape(-1, 3)
        self.weight = float(weight)
        self.base_dofs = np.zeros(free.size, dtype=bool)
        self.base_dofs[(3 * self.base[:, None] + np.arange(3)).reshape(-1)] = True
        self.tied = np.zeros(free.size)  # dx / db on the base's DoFs: -n on each base vertex
        self.tied.reshape(-1, 3)[self.base] = -self.axis
        self.free = np.asarray(free, dtype=bool) & ~self.base_dofs
        self.free.flags.writeable = False
        self._kept: tuple | None = None  # (indptr, indices, maps, indptr seen, indices seen) of the last pattern (_maps)
        self.last_border: tuple[np.ndarray, float] | None = None  # the last factorised matrix's (the solver's)
        self._solved: tuple | None = None  # (column, solve, A^-1 column) of the last direction()

    def positions(self, b: float) -> np.ndarray:
        """The base vertices at compression ``b`` (m): ``X_base - b n``, ``(m, 3)`` m."""
        return self.anchored - b * self.axis

    def start_poses(self, poses: dict) -> dict:
        """``poses`` (effector name -> pose ``(7,)``) with the effector's at the start compression: ``b_0`` behind
        its anchor along ``n`` (a new dict)."""
        pose = np.array(poses[self.unknown.effector], dtype=float)
        pose[:3] -= self.unknown.start * self.axis
        return {**poses, self.unknown.effector: pose}

    def compression(self, x: np.ndarray) -> float:
        """``b`` (m) of positions ``x`` ``(n, 3)``: the base's mean displacement from its anchored positions along
        ``-n``."""
        return float(np.mean((self.anchored - x[self.base]) @ self.axis))

    def energy(self, x: np.ndarray) -> float:
        """The spring and damper's energy at the compression of ``x`` (J), the compensated weight's included."""
        return self.unknown.spring_energy(self.compression(x), self.weight)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """:meth:`energy`'s gradient in ``x``, ``(n, 3)`` J/m: ``-n E_s'(b) / m`` on each of the ``m`` base
        vertices, zero elsewhere."""
        g = np.zeros_like(x)
        g[self.base] = (-self.unknown.spring_force(self.compression(x), self.weight) / self.base.size) * self.axis
        return g

    def reduced_gradient(self, g: np.ndarray) -> np.ndarray:
        """The gradient in ``(x_free, b)``, ``(3 n + 1,)``: ``g`` ``(3 n,)`` (the step's, with the base free and
        :meth:`gradient` in it) on the kinematic step's free DoFs, zero elsewhere, and ``dE/db = S_b^T g``
        last."""
        reduced = np.zeros(g.size + 1)
        reduced[:-1][self.free] = g[self.free]
        reduced[-1] = float(self.tied @ g)
        return reduced

    def update(self, reduced: np.ndarray) -> np.ndarray:
        """The positions' update ``S q`` ``(3 n,)`` of a reduced update ``q = (dx_free, db)`` ``(3 n + 1,)``."""
        d = np.where(self.free, reduced[:-1], 0.0)
        return d + reduced[-1] * self.tied

    def _maps(self, upper: sp.csr_matrix) -> tuple[np.ndarray, ...]:
        """Index maps of ``upper``'s pattern, kept while the pattern is (the assembler's union pattern changes
        rarely): the entries in a base row or column (``touching``), their rows and columns, which of them are off
        the diagonal; and :meth:`constrained`'s pattern: the entries it keeps (every entry outside the base's rows
        and columns, and the base's diagonal), its ``indptr`` and ``indices`` (read-only: the linear solver then
        knows the pattern without comparing it), the slots of the base's diagonal in it and a CSR matrix of that
        pattern (values zero) whose shallow copies :meth:`constrained` returns.

        The pattern counts as the kept one when ``upper``'s index arrays are the very read-only arrays of the last
        call (the assembler's matrices of one union pattern share them, :meth:`sim_core.dynamic_slots.UnionPattern.
        matrix`), else when they are equal to it."""
        kept = self._kept
        indptr_in, indices_in = upper.indptr, upper.indices
        if kept is not None and kept[3] is indptr_in and kept[4] is indices_in and not (
                indptr_in.flags.writeable or indices_in.flags.writeable):
            return kept[2]
        if kept is None or not (np.array_equal(kept[0], indptr_in) and np.array_equal(kept[1], indices_in)):
            n = upper.shape[0]
            rows = np.repeat(np.arange(n), np.diff(upper.indptr))
            cols = upper.indices
            touches = self.base_dofs[rows] | self.base_dofs[cols]
            touching = np.flatnonzero(touches)
            r, c = rows[touching], cols[touching]
            keep = np.flatnonzero(~touches | (self.base_dofs[rows] & (rows == cols)))
            indptr = np.zeros(n + 1, dtype=upper.indptr.dtype)
            np.cumsum(np.bincount(rows[keep], minlength=n), out=indptr[1:])
            indices = cols[keep].astype(upper.indices.dtype)
            ones = np.flatnonzero(self.base_dofs[rows[keep]])
            for a in (indptr, indices):
                a.flags.writeable = False
            template = sp.csr_matrix((np.zeros(keep.size), indices, indptr), shape=upper.shape)
            template.has_sorted_indices = True  # a subset of upper's sorted rows
            for a in (template.indptr, template.indices):
                a.flags.writeable = False
            kept = (upper.indptr.copy(), upper.indices.copy(),
                    (touching, r, c, r != c, keep, template.indptr, template.indices, ones, template))
        self._kept = (*kept[:3], indptr_in, indices_in)
        return kept[2]

    def constrained(self, upper: sp.csr_matrix) -> sp.csr_matrix:
        """The kinematic step's constrained matrix from ``upper`` (the upper triangle with the base free): the base's
        rows and columns left out of the pattern, 1 on their diagonal (identity rows, as the assembler makes a fixed
        DoF's; a new matrix)."""
        maps = self._maps(upper)
        keep, ones, template = maps[4], maps[7], maps[8]
        data = upper.data[keep]
        data[ones] = 1.0
        # a shallow copy of the pattern's matrix with these values: SciPy's constructor would check (and copy) the
        # index arrays on every call; shared read-only arrays let the linear solver know the pattern without comparing
        matrix = copy.copy(template)
        matrix.data = data
        return matrix

    def border(self, upper: sp.csr_matrix) -> tuple[sp.csr_matrix, np.ndarray, float]:
        """The reduced Newton matrix ``S^T H S + K e_b e_b^T`` of ``upper`` (the step's Newton matrix with the base
        free, upper triangle with the diagonal) in its three parts: the kinematic step's matrix
        (:meth:`constrained`), the border ``u = (H S_b)`` on its free DoFs ``(3 n,)`` and the corner
        ``S_b^T H S_b + K`` (N/m)."""
        touching, rows, cols, off = self._maps(upper)[:4]
        tied, values = self.tied, upper.data[touching]  # H S_b reads the entries in a base row or column only
        column = np.bincount(rows, values * tied[cols], minlength=upper.shape[0])
        column += np.bincount(cols[off], (values * tied[rows])[off], minlength=upper.shape[0])
        corner = float(tied @ column) + self.unknown.curvature
        return self.constrained(upper), np.where(self.free, column, 0.0), corner

    def bordered(self, upper: sp.csr_matrix) -> sp.csr_matrix:
        """The reduced Newton matrix (:meth:`border`) whole: ``(3 n + 1, 3 n + 1)``, the compression last (a dense
        reference for checks; the solver eliminates the border instead, :meth:`direction`)."""
        inner, column, corner = self.border(upper)
        full = inner + sp.triu(inner, k=1).T
        return sp.bmat([[full, sp.csr_matrix(column[:, None])],
                        [sp.csr_matrix(column[None, :]), sp.csr_matrix([[corner]])]], format="csr")

    def direction(self, solve, g: np.ndarray, column: np.ndarray, corner: float,
                  definite: bool = True) -> np.ndarray | None:
        """The Newton update ``S q`` ``(3 n,)`` of the reduced system ``[A u; u^T c] q = -(g_f, g_b)`` by its border's
        elimination: ``A`` the kinematic step's matrix, factorised (``solve`` its solve), ``db = (u^T A^-1 g_f -
        g_b) / (c - u^T A^-1 u)``, ``dx_f = -A^-1 (g_f + u db)``; None where the Schur complement ``c - u^T A^-1 u``
        is not positive (the reduced matrix not positive definite though ``A`` is) and ``definite``.

        Args:
            solve: ``B -> A^-1 B`` for ``(3 n,)`` and ``(3 n, 2)`` right-hand sides (zero on the kinematic step's fixed
                DoFs); ``A^-1 u`` is kept for the next call with the same ``column`` and ``solve`` (the simplified
                Newton test's, with the last factorisation).
            g: the step's gradient ``(3 n,)`` with the base free and :meth:`gradient` in it.
            column, corner: :meth:`border`'s.
            definite: ``A`` was factorised as positive definite (a Cholesky factorisation); False: a general one (the
                Newton direction of an indefinite matrix, whatever the complement's sign).
        """
        reduced = self.reduced_gradient(g)
        g_f, g_b = reduced[:-1], reduced[-1]
        solved = self._solved
        if solved is not None and solved[0] is column and solved[1] == solve:  # the same matrix: A^-1 u kept
            z_g, z_u = solve(g_f), solved[2]
        else:
            z_g, z_u = solve(np.column_stack([g_f, column])).T
            self._solved = (column, solve, z_u)
        schur = corner - float(column @ z_u)
        if definite and not schur > 0.0:
            return None
        db = (float(column @ z_g) - g_b) / schur
        return self.update(np.append(-(z_g + db * z_u), db))
