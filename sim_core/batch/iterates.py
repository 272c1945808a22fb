"""The lockstep solver's iterates and their stacked gradient, kept cheap for the host.

An iterate is an :class:`Iterate`: its positions on the host as a read-only array of their own (the terms' caches key
it by identity, :func:`~sim_core.energies.base.positions_key`, instead of reading its bytes: 28 ms a Newton iteration
at 1024 Forming copies on the H200 host, docs/benchmarks_log.md, session 40, 28lock) and, on a Taichi backend with the
batched CG, the same positions as a device array. The Newton loop's vectors (iterate, update, gradient) and their
per-copy operations have two homes with one interface:

* :class:`HostIterates`: NumPy arrays (``(3 N,)`` gradients and updates) and the per-copy reductions of
  :class:`~sim_core.batch.copy_runs.CopyRuns`; the direct linear solvers' path;
* ``DeviceIterates`` (:mod:`sim_core.batch.device_iterates`): ``(N, 3)`` float64 Taichi ndarrays and the kernels of
  :class:`~sim_core.ti_kernels.copy_vectors.CopyVectors`; the host reads back per-copy scalars, and each trial
  point's positions once (the contact search, the caches' keys). The stacked gradient is summed on the device
  (:meth:`~sim_core.batch.device_iterates.DeviceIterates.gradient`): a term declaring
  :class:`~sim_core.energies.base.DeviceGradient` adds into it there, the others' host gradients travel up (the dense
  ones summed first: one upload).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim_core.batch.copy_runs import CopyRuns
from sim_core.energies.base import SparseGradient, declares


class Iterate(NamedTuple):
    """Stacked positions of a lockstep iterate or trial point.

    Attributes:
        host: the positions ``(N, 3)`` in m, a frozen array (:func:`frozen`).
        device: the same positions as a float64 Taichi ndarray ``(N, 3)``, or None (:class:`HostIterates`).
    """

    host: np.ndarray
    device: object | None = None


def summed_gradient(terms: list, x: np.ndarray, fresh_first: bool = False) -> np.ndarray:
    """The sum of the ``terms``' gradients at ``x`` ``(N, 3)``, in term order, as a new ``(3 N,)`` array (J/m): the
    first two dense gradients summed into it (the terms' kept gradients are left as they are), each further term's
    added into it, the rows of a term declaring :class:`~sim_core.energies.base.SparseGradient` at its vertices only
    (no ``(N, 3)`` array a term; the same sums: the other entries would add 0). ``fresh_first``: the first term's
    gradient is a new float64 array of each call (:class:`~sim_core.batch.lumped.LumpedQuadratic`), so the sum is
    accumulated into it (one stacked array fewer; the same sums)."""
    g, owned = None, False  # the sum so far; owned: an array of this function's (else a term's, not written)
    if fresh_first and terms:
        g, owned = terms[0].gradient(x).reshape(-1), True
        terms = terms[1:]
    for p in terms:
        vertices, rows = p.gradient_rows(x) if declares(p, SparseGradient) else (None, p.gradient(x))
        if vertices is None:
            g, owned = add_dense(g, owned, rows.reshape(-1))
        else:
            if not owned:
                g, owned = (np.zeros(3 * len(x)) if g is None else np.array(g, dtype=np.float64)), True
            g.reshape(-1, 3)[vertices] += rows
    if g is None:
        return np.zeros(3 * len(x))
    return g if owned else np.array(g, dtype=np.float64)


def add_dense(g: np.ndarray | None, owned: bool, rows: np.ndarray) -> tuple[np.ndarray, bool]:
    """``g + rows`` (a dense gradient's ``(3 N,)`` entries, J/m) and whether the result is an array of the caller's
    own: ``rows`` itself when ``g`` is None (a term's array, not to be written), into ``g`` when ``g`` is owned, else a
    new array."""
    if g is None:
        return rows, False
    if owned:
        g += rows
        return g, True
    return np.add(g, rows, dtype=np.float64), True


def frozen(x: np.ndarray) -> np.ndarray:
    """``x``, a new positions array ``(N, 3)`` that owns its memory, made read-only for good: the terms' caches then
    key it by identity (:func:`~sim_core.energies.base.positions_key`) instead of reading its bytes."""
    x.flags.writeable = False
    return x


class HostIterates(CopyRuns):
    """The Newton loop's vectors as NumPy arrays: :class:`~sim_core.batch.copy_runs.CopyRuns`'s per-copy operations
    on ``(3 N,)`` gradients and updates, iterates without a device copy.

    Args:
        index: stacked vertex of copy ``i``'s vertex ``v``, shape ``(B, n)`` int.
    """

    def start(self, x: np.ndarray, x_n: np.ndarray | None = None, fixed_dofs: np.ndarray | None = None) -> Iterate:
        """The first iterate: ``x`` ``(N, 3)``, a new array of the caller's, frozen (``x_n`` and ``fixed_dofs``: the
        device iterates' hint, not needed here)."""
        return Iterate(frozen(x))

    def resident(self, host: np.ndarray | None) -> None:
        """No device copies on the host: None (the device iterates keep the step's result there)."""
        return None

    def velocities(self, x: Iterate, x_n: np.ndarray, dt: float) -> None:
        """None: the caller computes the step's velocities on the host (the device iterates make them there)."""
        return None

    def keep_resident(self, *pairs) -> None:
        """Nothing is kept on the host (the device iterates keep the step's result on the device)."""

    def forget_resident(self) -> None:
        """Nothing is kept on the host."""

    def copy_rows(self, arrays: list, copies: np.ndarray, offsets: np.ndarray) -> list:
        """Not made on the host (:meth:`resident` keeps nothing, so no caller asks)."""
        raise NotImplementedError("HostIterates keeps no device arrays")

    def trial(self, x: Iterate, d: np.ndarray, alphas: np.ndarray) -> Iterate:
        """``x + alpha_i d`` on copy ``i``'s vertices (``d`` ``3 N`` entries, ``alphas`` ``(B,)``)."""
        return Iterate(frozen(self.moved(x.host, d.reshape(-1, 3), alphas)))

    def gradient(self, terms: list, x: Iterate, fixed_dofs: np.ndarray, fresh_first: bool) -> np.ndarray:
        """:func:`summed_gradient` of ``terms`` at ``x``, zero at the flat DoFs ``fixed_dofs``, shape ``(3 N,)``."""
        g = summed_gradient(terms, x.host, fresh_first=fresh_first)
        g[fixed_dofs] = 0.0
        return g

    def slope_and_norm(self, g: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per copy ``(g.d, max_v |d_v|)``, each ``(B,)`` (:meth:`dot`, :meth:`largest_norm`: NaN where ``d`` is not
        finite)."""
        return self.dot(g, d), self.largest_norm(d)

    def slope_and_largest(self, g: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per copy ``(g.d, max_k |g_k|)``, each ``(B,)`` (:meth:`dot`, :meth:`largest_abs`: NaN where ``g`` has a
        NaN, infinite where it has an infinity)."""
        return self.dot(g, d), self.largest_abs(g)

    def copy(self, a: np.ndarray) -> np.ndarray:
        """A copy of ``a``."""
        return a.copy()

    def new(self) -> np.ndarray:
        """A zero ``(3 N,)`` array."""
        return np.zeros(3 * self.vertex_count)

    def take_steepest(self, d: np.ndarray, g: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``d`` with the copies in ``mask`` (bool ``(B,)``) set to ``-g``, in place; returns ``d``."""
        return self.copy_where(d, -g, mask)

    def zero_dofs(self, a: np.ndarray, dofs: np.ndarray) -> np.ndarray:
        """``a`` zero at the flat DoFs ``dofs``, in place; returns ``a``."""
        a[dofs] = 0.0
        return a
