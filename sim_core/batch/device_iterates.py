"""The lockstep Newton loop's vectors on a Taichi device (:mod:`sim_core.batch.iterates` for the interface): iterate,
update and stacked gradient as ``(N, 3)`` float64 ndarrays, the per-copy operations of
:class:`~sim_core.ti_kernels.copy_vectors.CopyVectors`, and the stacked gradient summed on the device."""

from __future__ import annotations

import numpy as np

from sim_core.batch.iterates import Iterate, add_dense, frozen
from sim_core.energies.base import DeviceGradient, FrozenPositionsKey, SparseGradient, declares
from sim_core.ti_kernels.copy_vectors import CopyVectors
from sim_core.ti_kernels.device_copy import PinnedBlocks


class DeviceIterates(CopyVectors):
    """:class:`~sim_core.ti_kernels.copy_vectors.CopyVectors` with the Newton loop's iterates and gradient sums
    (Taichi initialised).

    Args:
        index: stacked vertex of copy ``i``'s vertex ``v``, shape ``(B, n)`` int.

    Attributes:
        trial_blocks: the host blocks trial points are downloaded into
            (:class:`~sim_core.ti_kernels.device_copy.PinnedBlocks`: page-locked on CUDA, reused once a trial point
            and its views are gone), or None (a new array each; the default where no page-locked memory is made).

    Raises:
        ValueError: ``index`` is not a permutation of the stacked vertices.
    """

    def __init__(self, index: np.ndarray) -> None:
        super().__init__(index)
        blocks = PinnedBlocks((max(self.vertex_count, 1), 3))  # the shape of the device arrays (new_vectors)
        self.trial_blocks: PinnedBlocks | None = blocks if blocks.page_locked else None
        self._backtrack = None  # the line search's DeviceBacktrack (backtrack)
        self.compile_state_kernels()  # (first called at the second and third steps: compiled here, at the first)
        self._resident: list[tuple[np.ndarray, object]] = []  # (frozen host array, its device copy): resident()
        # (host force, its device array or None where a host term was subtracted on the host) of contact_force
        self.last_force: tuple | None = None

    def resident(self, host: np.ndarray | None):
        """The device copy kept of the frozen host array ``host`` (the last step's result ``x`` or velocities ``v``,
        :meth:`keep_resident`), or None where none is kept for that array object."""
        return next((device for kept, device in self._resident if kept is host), None)

    def keep_resident(self, *pairs: tuple[np.ndarray, object]) -> None:
        """Keep ``(host, device)`` pairs, each a frozen host array (one that owns its memory or is registered with
        :class:`~sim_core.energies.base.FrozenPositionsKey`: its values never change while it exists) and the float64
        ndarray holding the same values, in place of the ones kept before, for :meth:`resident`: the step's result and
        velocities, so that the next step starting from them reads them where they are."""
        self._resident = [(host, device) for host, device in pairs if FrozenPositionsKey.holds(host)]

    def forget_resident(self) -> None:
        """Drop the kept device copies (:meth:`keep_resident`)."""
        self._resident = []

    def start(self, x: np.ndarray, x_n: np.ndarray | None = None, fixed_dofs: np.ndarray | None = None) -> Iterate:
        """The first iterate: ``x`` ``(N, 3)`` (a new array of the caller's, frozen) and its device copy: with
        ``x_n`` (positions ``(N, 3)``) kept resident (:meth:`resident`) and ``fixed_dofs`` (int ``(f,)``, ``3 v + j``),
        where the caller's ``x`` equals ``x_n`` but at those DoFs, that copy made on the device from ``x_n``'s with
        the values of ``x`` at ``fixed_dofs`` sent up (:meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors
        .copied_with_dofs`: ``f`` entries in place of ``3 N``); else ``x`` uploaded whole. The same values either
        way."""
        base = self.resident(x_n) if fixed_dofs is not None else None
        if base is None:
            return Iterate(frozen(x), self.upload(x))
        return Iterate(frozen(x), self.copied_with_dofs(base, fixed_dofs, x.reshape(-1)[fixed_dofs]))

    def velocities(self, x: Iterate, x_n: np.ndarray, dt: float) -> tuple[np.ndarray, object] | None:
        """The step's velocities ``(x - x^n) / dt`` (m/s) made on the device, where ``x`` has its device copy and
        ``x_n`` (m, ``(N, 3)``) is kept resident (:meth:`resident`): ``(host, device)``, the host array a new frozen
        one downloaded once (NumPy's ``(x - x_n) / dt`` bit for bit); else None (the caller computes them)."""
        base = self.resident(x_n)
        if base is None or x.device is None:
            return None
        v = self.difference_quotient(x.device, base, dt)
        return frozen(self.download(v)), v

    def trial(self, x: Iterate, d, alphas: np.ndarray) -> Iterate:
        """``x + alpha_i d`` on copy ``i``'s vertices (``alphas`` ``(B,)``), made on the device and downloaded once
        into a frozen host array: over a block of :attr:`trial_blocks` (registered with
        :meth:`~sim_core.energies.base.FrozenPositionsKey.register`) where set, else a new array of its own."""
        return self._downloaded(self.moved(x.device, d, alphas))

    def trial_by(self, x: Iterate, d, alphas) -> Iterate:
        """:meth:`trial` with the step sizes on the device (``alphas``: a float64 ndarray whose first ``B`` entries are
        the copies', :meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors.moved_by`): nothing sent."""
        return self._downloaded(self.moved_by(x.device, d, alphas))

    @property
    def backtrack(self):
        """The line search's per-copy backtrack on the device
        (:class:`~sim_core.ti_kernels.backtrack.DeviceBacktrack`, made at the first use)."""
        if self._backtrack is None:
            from sim_core.ti_kernels.backtrack import DeviceBacktrack

            self._backtrack = DeviceBacktrack(self.copies)
        return self._backtrack

    def _downloaded(self, device) -> Iterate:
        """The :class:`Iterate` of the trial positions ``device`` (:meth:`trial`'s download)."""
        if self.trial_blocks is None:
            return Iterate(frozen(self.download(device)), device)
        return Iterate(FrozenPositionsKey.register(self.download(device, self.trial_blocks.take())), device)

    def slope_and_norm(self, g, d) -> tuple[np.ndarray, np.ndarray]:
        """Per copy ``(g.d, max_v |d_v|)``, each ``(B,)`` (NaN where ``d`` is not finite), in one launch and one read
        back (:meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors.scalars`)."""
        dot, _, _, norm = self.scalars(g, d)
        return dot, norm

    def slope_and_largest(self, g, d) -> tuple[np.ndarray, np.ndarray]:
        """Per copy ``(g.d, max_k |g_k|)``, each ``(B,)`` (NaN where ``g`` has a NaN, infinite where it has an
        infinity), in one launch and one read back (:meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors.scalars`)."""
        dot, largest, _, _ = self.scalars(g, d)
        return dot, largest

    def slope_largest_and_sums(self, g, d, sums) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`slope_and_largest` and the per-copy sums ``(B,)`` of ``sums`` (a
        :class:`~sim_core.ti_kernels.copy_vectors.CopySums`, :meth:`~sim_core.ti_kernels.copy_vectors.CopySums.read`)
        in one launch and one read back: a line search's trial point's slope test and energies together."""
        dot, largest, _, _, read = self.scalars(g, d, sums)
        return dot, largest, read

    def take_steepest(self, d, g, mask: np.ndarray):
        """``d`` with the copies in ``mask`` (bool ``(B,)``) set to ``-g``, in place; returns ``d``."""
        return self.copy_where(d, g, mask, scale=-1.0)

    def contact_force(self, terms: list, x: Iterate) -> np.ndarray:
        """Minus the sum of the ``terms``' gradients at ``x`` (N, a new host ``(N, 3)`` array): the gradients of the
        leading terms that declare :class:`~sim_core.energies.base.DeviceGradient` added into one zeroed device array
        in the terms' order, downloaded once and negated (``0 - g``) on the host, then the other terms' host gradients
        subtracted in order. The values are :func:`~sim_core.step_terms.contact_force`'s bit for bit: the same
        additions at each vertex in the same order, and ``((0 - a) - b) - c = 0 - ((a + b) + c)`` in IEEE arithmetic
        (rounding is symmetric under negation, and neither side's partial sums are ever ``-0``)."""
        lead = next((k for k, p in enumerate(terms) if not declares(p, DeviceGradient)), len(terms))
        g = self.new()
        for p in terms[:lead]:
            p.add_gradient_on_device(x.host, x.device, g)
        negated = self.negated(g)  # 0 - g on the device: no pass over the host array
        force = self.download(negated)
        for p in terms[lead:]:
            force -= p.gradient(x.host)
        self.last_force = (force, negated if lead == len(terms) else None)
        return force

    def gradient(self, terms: list, x: Iterate, fixed_dofs: np.ndarray, fresh_first: bool = False):
        """The sum of the ``terms``' gradients at ``x`` (J/m) as a new ``(N, 3)`` ndarray, zero at the flat DoFs
        ``fixed_dofs``: the host terms first, their dense gradients summed on the host and uploaded once as the
        array's start (no zero fill, no second array), a :class:`~sim_core.energies.base.SparseGradient` term's rows
        uploaded and added at their vertices, then each term declaring :class:`~sim_core.energies.base.DeviceGradient`
        adding its own on the device. The sums are :func:`~sim_core.batch.iterates.summed_gradient`'s in another order
        (equal to round-off). ``fresh_first``: that function's hint, not needed here."""
        dense, owned, sparse, on_device = None, False, [], []
        for p in terms:
            if declares(p, DeviceGradient):
                on_device.append(p)
                continue
            vertices, rows = p.gradient_rows(x.host) if declares(p, SparseGradient) else (None, p.gradient(x.host))
            if vertices is None:
                dense, owned = add_dense(dense, owned, rows.reshape(-1))
            else:
                sparse.append((vertices, rows))
        g = self.new() if dense is None else self.upload(dense)
        for vertices, rows in sparse:
            self.add_rows(g, vertices, rows)
        for p in on_device:
            p.add_gradient_on_device(x.host, x.device, g)
        return self.zero_dofs(g, fixed_dofs)
