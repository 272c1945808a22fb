"""Physics probes of the diagnosis (steps of :class:`~sysid.diagnose.engine.BagDiagnosis`).

Every physics candidate gets a secant signature from one probe replay; a probe that diverged is
retried smaller, and a probe whose prediction change is far from ``probe_target`` noise units is
rescaled (:meth:`ProbeCalibration._calibration_chain`). The replays of one candidate form a chain
(:mod:`sysid.diagnose.schedule`), run on the host's scheduler; notes are merged in the order barrier
batches would give. The host class provides ``model``, ``settings``, ``tested``, ``notes``,
``_replays(parameter_sets)``, ``_run_chains(chains, phase)`` and ``_speculative_refit``.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from sysid.diagnose import candidates as cands
from sysid.diagnose.residuals import whiten


def rescale_factor(seen: Sequence[tuple[float, float]], target: float, max_growth: float,
                   largest: float = math.inf) -> float:
    """Factor on the last probe of a chain that brings its change towards ``target`` (1: keep it).

    Args:
        seen: ``(|beta|, change)`` of the chain's probes so far, the current one last (change: the
            largest whitened RMS of the prediction change over the tested channels, noise units).
        target: the change aimed at; a probe in ``[target / 4, 4 target]`` is kept.
        max_growth: largest factor (up or down) of one rescale.
        largest: largest ``|beta|`` a grow may give (the parameter's bound; inf: none).

    Returns:
        ``target / change`` clipped to ``[1 / max_growth, max_growth]`` (linear response), except: a
        rescale that would reach or pass an earlier probe on the other side of the range lands inside
        that bracket, on the power law through its two ends (the geometric mean where a change is 0);
        a grow that ``largest`` caps short of ``target / 4`` on the linear response gives 1.
    """
    beta, m = seen[-1]
    low, high = 0.25 * target, 4.0 * target
    if low <= m <= high or not beta > 0.0:
        return 1.0
    factor = max_growth if m <= 0.0 else float(np.clip(target / m, 1.0 / max_growth, max_growth))
    grow = m < low
    if grow and factor * beta > largest and m * largest / beta < low:
        return 1.0
    if grow:
        ends = [(b, c) for b, c in seen[:-1] if c > high and beta < b <= factor * beta]
    else:
        ends = [(b, c) for b, c in seen[:-1] if c < low and factor * beta <= b < beta]
    if not ends:
        return factor
    b2, m2 = min(ends) if grow else max(ends)
    if m > 0.0 and m2 > 0.0:
        inside = beta * (target / m) ** (math.log(b2 / beta) / math.log(m2 / m))
        if min(beta, b2) < inside < max(beta, b2):
            return inside / beta
    return math.sqrt(b2 / beta)


class ProbeCalibration:
    """Mixin: probe replays, their retries and rescaling (module docstring)."""

    def _probe_change(self, ctx, probe_prediction: Mapping[str, np.ndarray]) -> float:
        """Largest whitened RMS (noise units) over the tested channels of a probe's prediction change."""
        return max((float(np.sqrt(np.mean(whiten(self.model, ch, probe_prediction[ch] - ctx.prediction[ch]) ** 2)))
                    for ch in self.tested if ch in probe_prediction), default=0.0)

    def _calibrate_probes(self, ctx, probes, probe_out) -> None:
        """Re-run probes whose prediction change is far from ``probe_target`` noise units
        (:meth:`_calibration_chain` of every probe, by rounds through ``_replays``; ``probe_out``,
        member key -> replay, is updated in place)."""
        from sysid.diagnose.schedule import run_in_rounds

        notes: list = []
        keys = [cands.member_key(c) for c in probes]
        reps = run_in_rounds([self._calibration_chain(ctx, c, probe_out.get(k), i, notes)
                              for i, (c, k) in enumerate(zip(probes, keys))], self._replays)
        probe_out.update((k, rep) for k, rep in zip(keys, reps) if k in probe_out)
        self._merge_notes(notes)

    def _calibration_chain(self, ctx, c, rep, index: int, notes: list):
        """Rescale one probe whose prediction change is far from ``probe_target`` noise units.

        The secant signature ``(y(beta_p) - y(0)) / beta_p`` is the derivative the score test and the
        linearised refit need only when the probe is in the linear range and above round-off. A probe
        that barely moves the simulation (mass-proportional damping of a few 1/s on a quasi-static
        press: 1e-4 noise units) gives round-off, and the refit, bounded by a few probe sizes, cannot
        reach an effect that is there; a probe that changes the prediction by tens of noise units
        (an anisotropy of 0.3 that makes the card buckle differently) gives a secant unrelated to the
        tangent at 0, and a refit several times too small. Probes outside ``[target / 4, 4 target]``
        (strongest channel, whitened RMS) are rescaled towards ``target`` (linear response assumed; a
        factor within ``[1 / probe_max_growth, probe_max_growth]`` per round, two rounds); a rescaled
        probe that diverges leaves the previous one in place and is not rescaled again (replays are
        deterministic: the second round would repeat the same rescale and the same divergence).

        The chain's own replays bound the rescaling (:func:`rescale_factor`): a rescale stays inside
        the bracket of an earlier probe on the other side of the range (a power law through the two
        ends), and a probe is not grown where the parameter's bound (``largest_probe``) caps it short
        of ``target / 4`` on the same linear response: that grow could not reach the range, and it
        replays the most nonlinear probe there is. On the demo's recording anisotropic bending grew
        from 0.3 (0.16 noise units) to 0.855, 0.9 of its bound, where the card buckled (292 units,
        17 CPU s, a sixth of the diagnosis), and was then shrunk to 0.0059, where a linear response
        gives 0.003 units; adhesion shrunk from 1.0e-3 (58 units) to 3.6e-5 (1.3e-3 units) was then
        grown to 3.6e-2, 35 times past the probe known to overshoot (docs/benchmarks_log.md,
        2026-11-27, session 52, 51fast).

        A replay chain (:mod:`sysid.diagnose.schedule`): ``rep`` is the probe's replay (None:
        diverged, left alone), the result the replay kept. Notes go to ``notes`` as
        ``((round, kind, index), text)`` for :meth:`_merge_notes`.
        """
        s = self.settings
        if not hasattr(c, "grow_probe"):
            return rep
        seen: list[tuple[float, float]] = []
        for k in range(2):
            if rep is None:
                return rep
            m = self._probe_change(ctx, rep[1])
            seen.append((abs(c.probe_beta), m))
            old = (c.probe_beta, c.bound)
            factor = rescale_factor(seen, s.probe_target, s.probe_max_growth, getattr(c, "largest_probe", math.inf))
            if factor > 1.0:
                changed = c.grow_probe(factor)
            elif factor < 1.0:
                c.shrink_probe(factor)
                c.bound = old[1]  # the refit may still go as far as the first probe did
                changed = True
            else:
                changed = False
            if not changed:
                return rep
            notes.append(((2 + k, 0, index), f"{cands.member_key(c)}: probe change {m:.3g} noise units at beta "
                                              f"{old[0]:.3g}; re-probed at beta {c.probe_beta:.3g}"))
            new = yield c.probe(ctx), f"rescale{k + 1}"
            if new is None:
                c.probe_beta, c.bound = old
                notes.append(((2 + k, 1, index), f"{cands.member_key(c)}: rescaled probe diverged; the previous "
                                                  f"one is kept"))
                return rep
            rep = new
        return rep

    def _probe_chain(self, ctx, c, index: int, notes: list):
        """All replays of one physics candidate's probe: the probe, up to two retries at a quarter of
        its size when it diverged (a probe the simulator cannot finish, e.g. a strong Maxwell branch at
        lift-off: the secant signature only needs a change well above round-off), then
        :meth:`_calibration_chain`. A replay chain; returns the probe's replay (None: diverged)."""
        rep = yield c.probe(ctx), "probe"
        for r in range(2):
            if rep is not None or not hasattr(c, "shrink_probe"):
                break
            c.shrink_probe(0.25)
            notes.append(((r, 0, index), f"{cands.member_key(c)}: probe replay diverged; retried at beta "
                                         f"{c.probe_beta:.3g}"))
            rep = yield c.probe(ctx), f"retry{r + 1}"
        rep = yield from self._calibration_chain(ctx, c, rep, index, notes)
        spec = getattr(self, "_speculation", None)
        if spec is not None:
            yield from self._speculative_refit(ctx, c, rep, spec)
        return rep

    def _probe_all(self, ctx, probes) -> dict[str, Any]:
        """Every probe's replay chain (:meth:`_probe_chain`), pipelined on the scheduler.

        Returns:
            member key -> the probe's ``(trace, prediction)``, None where it diverged.
        """
        notes: list = []
        reps = self._run_chains([self._probe_chain(ctx, c, i, notes) for i, c in enumerate(probes)], "probes",
                                [cands.start_rank(c, i) for i, c in enumerate(probes)])
        self._merge_notes(notes)
        return dict(zip([cands.member_key(c) for c in probes], reps))

    def _merge_notes(self, notes: list) -> None:
        """Append chain notes ``(key, text)`` in key order: the order barrier batches would give
        (stage, then candidate), whatever order the replays finished in."""
        self.notes.extend(text for _, text in sorted(notes, key=lambda n: n[0]))
