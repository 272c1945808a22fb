"""The lockstep solver's per-copy backtracking line search (:class:`CopyLineSearch`, a part of
:class:`~sim_core.batch.lockstep.LockstepSolver`; the method in :mod:`sim_core.batch.lockstep`'s docstring).

Its vectors are the solver's (:mod:`sim_core.batch.iterates`): the trial points ``x + a_c d`` are made where the
update lives (on the device with the batched CG, downloaded once for the contact search and the energies), and the
slope test's per-copy dot products are read back as ``(B,)`` arrays, with each trial gradient's largest entries (the
next Newton iteration's force test, where the trial is accepted) in the same read; on the device, where each copy has
its own energy, the trial point's per-copy energies are launched before that read and come back in it too (one copy
back a trial point for the slope and Armijo tests; the energies are then measured even where no copy passes the slope
test, which changes no result). From a line search's second trial point on, the tests, acceptances and halvings can be
decided on the device (:attr:`CopyLineSearch.device_backtrack`, :class:`~sim_core.ti_kernels.backtrack.DeviceBacktrack`:
the next step sizes are never sent); it pays only where no host term adds energy (the contact pairs' penalties are
summed by copy where the pair batch's launch left their distances,
:mod:`sim_core.energies.contact.copy_energy_kernel`; a term without device sums, e.g. a table plane's penalty, sends its
energies up instead of the steps).
"""

from __future__ import annotations

import numpy as np

from sim_core.batch.iterates import Iterate
from sim_core.energies.base import CopyEnergies, DeviceCopyEnergies, declares
from sim_core.step_info import StepInfo


def armijo_accepts(candidates: np.ndarray, energy: np.ndarray, e0: np.ndarray, step: np.ndarray, slope: np.ndarray,
                   armijo_c: float) -> np.ndarray:
    """The copies of ``candidates`` (bool ``(B,)``, those that passed the slope test) that pass their own Armijo
    condition ``E_i(x + a_i d) - E_i(x) <= c a_i g_i.d_i + 1e-14 |E_i(x)|`` (``energy`` the trial's and ``e0`` the
    start's energies, J; ``step`` the steps ``a_i``; ``slope`` ``g_i.d_i``; NaN fails), bool ``(B,)``: the host's test,
    which :func:`sim_core.ti_kernels.backtrack._decide` makes on the device in the same operations."""
    return candidates & (energy - e0 <= armijo_c * step * slope + 1e-14 * np.abs(e0))


class CopyLineSearch:
    """The per-copy line search of :class:`~sim_core.batch.lockstep.LockstepSolver` (which provides ``config``,
    ``scene``, ``contact``, ``_vectors``, ``_copy_of_vertex``, ``_copy_sums``, ``_trial_energy``, ``_energy`` and
    ``_stacked_gradient``)."""

    device_backtrack: str = "auto"
    """Where the line search's trial points after the first are decided when the vectors and every term's per-copy
    energies are on the device: ``"always"`` there (:meth:`_backtrack_on_device`), ``"never"`` on the host (one read
    of the slopes and energies a trial point, the next step sizes sent), ``"auto"`` there where the first trial
    point's host terms had no energy (then a trial point sends nothing; the contact pairs' penalties are device terms
    where the pair batch measured the trial point; else each would send the host terms' energies, one upload a trial
    point as the host's step sizes are, plus the state once). The
    same results bit for bit."""

    def _line_search_copies(self, step, x: Iterate, d, alpha: np.ndarray, slope: np.ndarray, open_: np.ndarray,
                            contact_terms: list, x_search: np.ndarray | None, info: StepInfo):
        """Per-copy backtracking (halving) from ``alpha`` ``(B,)`` along the stacked update ``d`` (the solver's
        vector, zero on the copies not in ``open_``): accepted copies keep their step while the others halve theirs
        (:mod:`sim_core.batch.lockstep`'s docstring). Where every term splits its energy by copy
        (:meth:`_copy_energies`), each copy passes on its own Armijo condition
        ``E_i(x + a_i d) <= E_i(x) + c a_i g_i.d_i`` (plus ``1e-14 |E_i(x)|`` of round-off), as in its separate run,
        one energy evaluation a trial point; else the slope test, then the energy test of the copies that passed
        it (:meth:`_armijo_groups`).

        ``e0``, the energy at ``x`` (per copy, or the stacked sum), is the one measured there when ``x`` was the last
        line search's result with these ``contact_terms`` (no contact side released since). A trial point's contact
        potentials are asked for with ``x`` as the segment's start, so that a candidate search it needs also covers
        the first halving where one search can (:meth:`~sim_core.contact_set.ContactSet._search_position`).

        Returns:
            ``(x_new, (x_new, g_new, g_max), contact_terms, x_search, accepted, backtracks)``: the :class:`Iterate`
            with every accepted copy moved and the others where they were, the gradient at ``x_new`` and its per-copy
            largest ``|g_k|`` ``(B,)`` where it was read with the slope test (else None), its contact terms and
            search position, accepted copies ``(B,)`` bool and halvings per copy ``(B,)``.
        """
        cfg = self.config
        B = self.scene.copies
        vectors = self._vectors
        kept = self._trial_energy  # the accepted trial point of the last line search is this x: its energy
        if kept is not None and kept[0] is x.host and kept[1] is contact_terms:
            e0 = kept[2]
        else:
            e0 = self._copy_energies(step, x.host, contact_terms, x_search, x.device)
            if e0 is None:
                e0 = self._energy(step, x.host, contact_terms, x_search)
        per_copy = isinstance(e0, np.ndarray)  # each copy's own energy (else one stacked sum: the Armijo groups)
        device = per_copy and x.device is not None and self.device_backtrack != "never"  # further trials there
        e_new = e0  # per copy: the energy where each copy stands after the accepted steps
        pending = open_ & (alpha > 0)
        accepted = open_ & (alpha == 0)
        a = np.where(pending, alpha, 0.0)
        taken = np.zeros(B)  # the accepted copies' step sizes
        backtracks = np.zeros(B, dtype=np.int64)
        bound = (1.0 - 2.0 * cfg.armijo_c) * np.abs(slope)
        last = None  # (alphas, x, (terms, x_search, g)) of the last evaluated trial
        for k in range(cfg.max_backtracks):
            if not pending.any():
                break
            trial = np.where(pending, a, 0.0) + taken
            x_try = vectors.trial(x, d, trial)
            terms, xs, g_try = self._stacked_gradient(step, x_try, info, x.host)  # a search covering the segment
            launched = (self._launch_copy_energies(step, x_try.host, terms, xs, x_try.device)
                        if per_copy and x_try.device is not None else None)
            e_try = None
            if launched is not None:  # the energies read with the slope: one copy back (with x_device, sums are made)
                s_try, g_try_max, device_sums = vectors.slope_largest_and_sums(g_try, d, launched[1])
                e_try = launched[0] + device_sums
            else:
                s_try, g_try_max = vectors.slope_and_largest(g_try, d)  # the slope and the next iteration's max |g|
            last = (trial, x_try, (terms, xs, g_try, g_try_max))
            cand = pending & np.isfinite(s_try) & (s_try <= bound)
            if per_copy and cand.any():  # each copy's Armijo test on its own energy
                if e_try is None:
                    e_try = self._copy_energies(step, x_try.host, terms, xs, x_try.device)
                ok = armijo_accepts(cand, e_try, e0, a, slope, cfg.armijo_c)
                e_new = np.where(ok, e_try, e_new)
                accepted |= ok
                taken[ok] = a[ok]
                pending &= ~ok
            elif cand.any():
                e_base = e0 if not np.any(taken) else self._energy_with(step, x, d, taken)
                if np.array_equal(cand, pending):
                    e_try = self._energy(step, x_try.host, terms, xs)
                    self._trial_energy = (x_try.host, terms, e_try)
                    delta = e_try - e_base
                else:
                    delta = self._energy_with(step, x, d, taken + np.where(cand, a, 0.0)) - e_base
                ok = self._armijo_groups(step, x, d, taken, e_base, cand, delta, a, slope, e0)
                accepted |= ok
                taken[ok] = a[ok]
                pending &= ~ok
            backtracks[pending] += 1
            info.backtracks += int(pending.sum())
            a[pending] *= 0.5
            if (device and launched is not None and pending.any() and k + 1 < cfg.max_backtracks
                    and (self.device_backtrack == "always" or not (np.any(launched[0])
                                                                   or np.any(launched[1].host_values)))):
                search = vectors.backtrack  # the state up in the upload that the next trial's steps would take
                trial = search.start(e0, slope, bound, a, pending, accepted, taken, e_new, backtracks)
                return self._backtrack_on_device(step, x, d, cfg.max_backtracks - k - 1, trial, last, info)
        return self._line_search_end(step, x, d, last, taken, e_new, accepted, backtracks, info)

    def _backtrack_on_device(self, step, x: Iterate, d, trials: int, trial: np.ndarray, last, info: StepInfo):
        """:meth:`_line_search_copies`' further trial points (at most ``trials``, the first at the steps ``trial``
        ``(B,)``) where the vectors and every term's per-copy energies are on the device and the state is in
        :attr:`~sim_core.batch.device_iterates.DeviceIterates.backtrack`: each trial point's slope and Armijo tests,
        acceptances, halvings and next step sizes decided there (:class:`~sim_core.ti_kernels.backtrack.DeviceBacktrack`,
        the host branch's :func:`armijo_accepts` and halvings bit for bit), so that a trial point sends no step sizes
        and reads one array back (the host terms' energies sent where one is not zero); ``last``: the last trial
        evaluated on the host. Same results as :meth:`_line_search_copies`."""
        cfg = self.config
        vectors = self._vectors
        search = vectors.backtrack
        for _ in range(trials):
            x_try = vectors.trial_by(x, d, search.state)
            terms, xs, g_try = self._stacked_gradient(step, x_try, info, x.host)  # a search covering the segment
            launched = self._launch_copy_energies(step, x_try.host, terms, xs, x_try.device)
            if launched is None:
                raise RuntimeError("CopyLineSearch: a trial point's contact terms cannot split their energy by copy "
                                   "where the line search's start could")
            host_energies, sums = launched
            device_sums = vectors.launch_scalars(g_try, d, sums)
            out = search.decide(vectors.scalars_out, device_sums is not None, host_energies, sums.host_values,
                                cfg.armijo_c)
            last = (trial, x_try, (terms, xs, g_try, out["largest"]))
            trial = out["alpha"]
            info.backtracks += out["halved"]
            if not out["pending"].any():
                break
        return self._line_search_end(step, x, d, last, out["taken"], out["energy"], out["accepted"], out["backtracks"],
                                     info)

    def _line_search_end(self, step, x: Iterate, d, last, taken: np.ndarray, e_new, accepted: np.ndarray,
                         backtracks: np.ndarray, info: StepInfo):
        """:meth:`_line_search_copies`' result from its ``last`` evaluated trial (or None) and the copies' accepted
        steps ``taken`` ``(B,)``: that trial where its steps are ``taken``, else the point ``x + taken d`` and its
        gradient; the energies ``e_new`` where the copies stand are kept for the next line search where per copy."""
        vectors = self._vectors
        if last is not None and np.array_equal(last[0], taken):
            x_new, (terms, xs, g_new, g_max) = last[1], last[2]
        else:
            x_new = vectors.trial(x, d, taken)
            terms, xs, g_new = self._stacked_gradient(step, x_new, info, x.host)
            g_max = None
        if isinstance(e_new, np.ndarray):  # a copy's energy depends on its own positions only: x_new's, per copy
            self._trial_energy = (x_new.host, terms, e_new)
        return x_new, (x_new, g_new, g_max), terms, xs, accepted, backtracks

    def _copy_energies(self, step, x: np.ndarray, contact_terms: list, x_search: np.ndarray | None,
                       x_device=None) -> np.ndarray | None:
        """The stacked incremental potential at ``x`` ``(N, 3)`` split by copy (J, ``(B,)``): each term's
        :meth:`~sim_core.energies.base.CopyEnergies.copy_energies` (the contact terms those of a new search where
        ``x_search``'s candidates do not cover ``x``, as :meth:`NewtonSolver._energy`); None when a term cannot split
        its energy (then the line search tests the stacked sum by groups). With ``x_device`` (``x`` as a Taichi
        float64 ndarray: the batched CG's iterates), the terms declaring
        :class:`~sim_core.energies.base.DeviceCopyEnergies` add theirs where their kernels run, into one
        :class:`~sim_core.ti_kernels.copy_vectors.CopySums` read back once after the others (the sum in another
        order: equal to round-off): :meth:`_launch_copy_energies`, then that read."""
        launched = self._launch_copy_energies(step, x, contact_terms, x_search, x_device)
        if launched is None:
            return None
        total, sums = launched
        if sums is not None:
            total += sums.read()
        return total

    def _launch_copy_energies(self, step, x: np.ndarray, contact_terms: list, x_search: np.ndarray | None,
                              x_device=None) -> tuple[np.ndarray, object] | None:
        """:meth:`_copy_energies` up to its read: ``(total, sums)``, the host terms' energies by copy (J, ``(B,)``)
        and, with ``x_device``, the :class:`~sim_core.ti_kernels.copy_vectors.CopySums` the device terms added into
        (its :meth:`~sim_core.ti_kernels.copy_vectors.CopySums.read` added to ``total`` gives the energies; else
        None); None when a term cannot split its energy."""
        B = self.scene.copies
        total = np.zeros(B)
        if not self.contact.covers(x_search, x):
            contact_terms = self.contact.potentials(x, step.x_n, step.memory)
        sums = None
        if x_device is not None:
            sums = self._copy_sums
            if sums is None:
                from sim_core.ti_kernels.copy_vectors import CopySums  # Taichi kernels: a Taichi backend only

                sums = self._copy_sums = CopySums(self._copy_of_vertex, B)
            sums.zero()
        for p in step.loop_terms + contact_terms:
            if sums is not None and declares(p, DeviceCopyEnergies) and p.add_copy_energies_on_device(
                    x, x_device, self._copy_of_vertex, sums):
                continue
            part = p.copy_energies(x, self._copy_of_vertex, B) if declares(p, CopyEnergies) else None
            if part is None:
                return None
            total += part
        return total, sums

    def _energy_with(self, step, x: Iterate, d, alphas: np.ndarray) -> float:
        """The stacked incremental potential (J) with copy ``i`` moved by ``alphas[i]`` times its part of the
        stacked update ``d``."""
        xm = self._vectors.trial(x, d, alphas) if np.any(alphas) else x
        terms = self.contact.potentials(xm.host, step.x_n, step.memory, xm.device)  # covers read on the device
        return self._energy(step, xm.host, terms, self.contact.search_position)

    def _armijo_groups(self, step, x: Iterate, d, base: np.ndarray, e_base: float, group: np.ndarray, delta: float,
                       a: np.ndarray, slope: np.ndarray, e0: float) -> np.ndarray:
        """The copies of ``group`` ``(B,)`` whose steps ``a`` meet the Armijo condition, tested by groups:
        ``delta`` (J) is the energy change of moving the whole group from the copies' positions ``x`` moved
        by ``base`` (energy ``e_base``, J); the group passes when ``delta <= c sum_i a_i g_i.d_i`` (plus the round-off
        of the stacked sum, ``1e-14 |E|``), else it is split in halves (one more evaluation: the other half's
        change is the difference, the energy being a sum over copies) down to single copies, each then
        tested alone. A single copy is thus held to its own Armijo condition whenever its group's is not
        met."""
        c = self.config.armijo_c
        if delta <= c * float(np.sum(a[group] * slope[group])) + 1e-14 * abs(e0):
            return group
        members = np.flatnonzero(group)
        if len(members) == 1:
            return np.zeros_like(group)
        half = np.zeros_like(group)
        half[members[: len(members) // 2]] = True
        rest = group & ~half
        d_half = self._energy_with(step, x, d, base + np.where(half, a, 0.0)) - e_base
        return (self._armijo_groups(step, x, d, base, e_base, half, d_half, a, slope, e0)
                | self._armijo_groups(step, x, d, base, e_base, rest, delta - d_half, a, slope, e0))
