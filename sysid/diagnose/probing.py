"""Physics probes of the diagnosis (steps of :class:`~sysid.diagnose.engine.BagDiagnosis`).

Every physics candidate gets a secant signature from one probe replay; a probe that diverged is
retried smaller, and a probe whose prediction change is far from ``probe_target`` noise units is
rescaled (:meth:`ProbeCalibration._calibration_chain`). The replays of one candidate form a chain
(:mod:`sysid.diagnose.schedule`), run on the host's scheduler; notes are merged in the order barrier
batches would give. The host class provides ``model``, ``settings``, ``tested``, ``notes``,
``_replays(parameter_sets)``, ``_run_chains(chains, phase)`` and ``_speculative_refit``.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from sysid.diagnose import candidates as cands
from sysid.diagnose.residuals import whiten


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

        A replay chain (:mod:`sysid.diagnose.schedule`): ``rep`` is the probe's replay (None:
        diverged, left alone), the result the replay kept. Notes go to ``notes`` as
        ``((round, kind, index), text)`` for :meth:`_merge_notes`.
        """
        s = self.settings
        if not hasattr(c, "grow_probe"):
            return rep
        for k in range(2):
            if rep is None:
                return rep
            m = self._probe_change(ctx, rep[1])
            old = (c.probe_beta, c.bound)
            if m < 0.25 * s.probe_target:
                factor = s.probe_max_growth if m <= 0.0 else min(s.probe_target / m, s.probe_max_growth)
                changed = factor > 1.0 and c.grow_probe(factor)
            elif m > 4.0 * s.probe_target:
                c.shrink_probe(max(s.probe_target / m, 1.0 / s.probe_max_growth))
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
