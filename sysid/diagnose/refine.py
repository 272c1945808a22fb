"""Refinement of physics refits after the linearised estimate (steps of :class:`~sysid.diagnose.engine.BagDiagnosis`).

The linearised refit (secant signature, least squares on the training rows) is refined by replays:
the probe replay when it fits better (:meth:`RefitRefinement._probe_if_better`), one secant step on
the training SSE (:meth:`RefitRefinement._secant`). The host class provides ``model``,
``settings``, ``notes``, ``_probe_out`` and ``_replays(parameter_sets)``.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from sysid.diagnose.residuals import residual


class RefitRefinement:
    """Mixin: replay-based refinement of physics refits (module docstring)."""

    def _probe_if_better(self, ctx, c, out, train) -> None:
        """Take the probe rollout as the refit when it fits the training rows better.

        An effect with an onset (plastic yield, stiction breakaway) has no first-order signature
        below the onset, so the linearised estimate can land where the effect does nothing (or
        be clipped to 0) while the probe, already replayed, fits better than both the nominal
        model and the estimate; the probe is then the better refit.
        """
        rf = out[c.name]
        probe = self._probe_out.get(c.name)
        if probe is None or float(rf.beta[0]) == c.probe_beta:
            return
        if self._train_sse(probe[1], train) < min(self._train_sse(ctx.prediction, train),
                                                 self._train_sse(rf.prediction, train)):
            rf.beta = np.array([c.probe_beta])
            rf.params = {c.report_name: c.probe_beta, **c.settings}
            rf.sim_params = c.sim_parameters(c.probe_beta)
            rf.prediction = probe[1]

    def _train_sse(self, pred: Mapping[str, np.ndarray], train) -> float:
        return sum(float(np.sum(residual(self.model, ch, pred[ch])[train[ch]] ** 2)) for ch in self.model.channels
                   if ch in pred)

    def _secant(self, ctx, physics, out, train, theta) -> None:
        """One more replay per physics candidate at the minimiser of the parabola through the training
        SSE at beta = 0 (nominal), the probe and the linearised estimate; the better of the two is kept."""
        sets, which = [], []
        for c in physics:
            rf = out[c.name]
            b1 = float(rf.beta[0])
            probe = self._probe_out.get(c.name)
            if probe is None or not rf.prediction or rf.prediction is ctx.prediction:
                continue
            xs = np.array([0.0, c.probe_beta, b1])
            if np.min(np.abs(np.diff(np.sort(xs)))) < 1e-3 * c.probe_beta:
                continue
            ys = np.array([self._train_sse(ctx.prediction, train), self._train_sse(probe[1], train),
                           self._train_sse(rf.prediction, train)])
            a2, a1, _ = np.polyfit(xs, ys, 2)
            if not a2 > 0.0:
                continue
            b2 = float(np.clip(-a1 / (2.0 * a2), 0.0 if c.one_sided else -c.bound, c.bound))
            if b2 == 0.0 or abs(b2 - b1) < 0.1 * max(abs(b1), 1e-12):
                continue
            dtheta = {k: v for k, v in rf.sim_params.items() if k != c.parameter}
            sets.append({**theta, **dtheta, **c.sim_parameters(b2)})
            which.append((c, b2, ys[2], dtheta))
        for (c, b2, sse1, dtheta), rep in zip(which, self._replays(sets) if sets else []):
            if rep is None or self._train_sse(rep[1], train) >= sse1:
                continue
            rf = out[c.name]
            rf.beta = np.array([b2])
            rf.params[c.report_name] = b2
            rf.sim_params = {**dtheta, **c.sim_parameters(b2)}
            rf.prediction = rep[1]
