"""Refinement of physics refits after the linearised estimate (steps of :class:`~sysid.diagnose.engine.BagDiagnosis`).

The linearised refit (secant signature, least squares on the training rows) is refined by replays:
the probe replay when it fits better (:meth:`RefitRefinement._probe_if_better`), one secant step on
the training SSE (:meth:`RefitRefinement._secant`). The host class provides ``model``, ``project``,
``settings``, ``notes``, ``_probe_out``, ``_replays(parameter_sets)`` and ``_candidate_tests``; the
replays of one candidate form a chain (:mod:`sysid.diagnose.schedule`).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from sysid.diagnose import candidates as cands
from sysid.diagnose.residuals import residual, whiten


class RefitRefinement:
    """Mixin: replay-based refinement of physics refits (module docstring)."""

    def _training_rows(self, ctx, sig, J_theta, train) -> tuple[np.ndarray, np.ndarray]:
        """The whitened training rows of the linearised refits: ``(A, b)``, ``b`` the nominal
        residual, ``A`` the columns ``[sig, J_theta]`` (``sig`` None: the ``J_theta`` columns alone).

        Shapes: ``A`` ``(R, 1 + p)`` or ``(R, p)``, ``b`` ``(R,)``, R the training values of every
        channel, p the projected nominal parameters (columns per unit of ln theta)."""
        model = self.model
        rows_r, rows_J = [], []
        for ch in model.channels:
            tr = train[ch]
            T = int(tr.sum())
            rows_r.append(residual(model, ch, ctx.prediction[ch])[tr].reshape(-1))
            Jt = whiten(model, ch, J_theta[ch])[tr]
            Jt = Jt.reshape(int(np.prod(Jt.shape[:-1])), -1)
            if sig is None:
                rows_J.append(Jt)
            else:
                Jk = whiten(model, ch, sig[ch])[tr].reshape(-1, 1)
                rows_J.append(np.concatenate([Jk, Jt], axis=1))
        return np.concatenate(rows_J), np.concatenate(rows_r)

    def _log_steps(self, theta, steps) -> dict[str, float]:
        """The nominal parameters moved by log steps ``steps`` (one a projected parameter, clipped to [-1, 1])."""
        return {n: theta.get(n, self.model.parameter_value(n)) * math.exp(float(np.clip(d, -1.0, 1.0)))
                for n, d in zip(self.project, steps)}

    def _linearised_refit(self, ctx, c, sig, J_theta, train, theta) -> tuple[dict[str, float], Any]:
        """The linearised refit of physics candidate ``c``: least squares of the whitened training
        residual on its secant signature ``sig`` and the ``J_theta`` columns (per unit of ln theta).

        beta is clipped to ``[0 or -bound, bound]`` (the linearisation is only trusted up to a few
        probe sizes), the log steps of the nominal parameters to ``[-1, 1]``.

        Returns:
            ``(parameters of its verifying replay, cands.Refit without prediction)``.
        """
        A, b = self._training_rows(ctx, sig, J_theta, train)
        sol, *_ = np.linalg.lstsq(A, b, rcond=None)
        beta = float(sol[0])
        if c.one_sided:
            beta = max(beta, 0.0)
        beta = float(np.clip(beta, -c.bound, c.bound))
        dtheta = self._log_steps(theta, sol[1:])
        params = {**theta, **dtheta, **c.sim_parameters(beta)}
        return params, cands.Refit(np.array([beta]), {c.report_name: beta, **c.settings,
                                                      **{k: float(v) for k, v in dtheta.items()}},
                                   {}, sim_params={**dtheta, **c.sim_parameters(beta)})

    def _reestimate(self, ctx, J_theta, train, theta) -> tuple[dict[str, float], Any] | None:
        """The nominal parameters re-estimated without any effect: the restricted model of every
        physics refit (least squares of the whitened training residual on the ``J_theta`` columns
        alone, log steps clipped to [-1, 1], as in :meth:`_linearised_refit`).

        Each physics refit fits its effect's strength together with these columns, so its change
        holds the nominal parameters' own move, which the score tests project out; judged against
        the nominal prediction alone, that move would count as the effect's (a calibration stopped
        at its replay budget leaves it large). The re-estimate, replayed once, is the null model a
        refit must improve on (the likelihood-ratio logic of nested models, judged out of sample).

        Returns:
            ``(parameters of its replay, cands.Refit with beta ``(0,)`` and no prediction)``, or None
            when no nominal parameter is projected (the nominal prediction is the restricted model).
        """
        if not self.project or not any(J_theta[ch].shape[-1] for ch in self.model.channels):
            return None
        A, b = self._training_rows(ctx, None, J_theta, train)
        sol, *_ = np.linalg.lstsq(A, b, rcond=None)
        dtheta = self._log_steps(theta, sol)
        return ({**theta, **dtheta},
                cands.Refit(np.zeros(0), {k: float(v) for k, v in dtheta.items()}, {}, sim_params=dict(dtheta)))

    def _reestimate_chain(self, ctx, params, rf, index: int, notes: list):
        """The re-estimate's replay (a chain of one replay, :mod:`sysid.diagnose.schedule`); sets
        ``rf.prediction`` (the nominal prediction when it diverged, noted: no null beyond the nominal)."""
        rep = yield params, "reestimate"
        if rep is None:
            notes.append(((0, 0, index), "the nominal parameters' re-estimate diverged: physics refits are "
                                          "judged against the nominal prediction alone"))
            rf.prediction = dict(ctx.prediction)
        else:
            rf.prediction = rep[1]

    def _refit_chain(self, ctx, c, params, out, train, theta, index: int, notes: list, probe=None):
        """Replays of one physics refit: the verifying replay at the linearised estimate ``params``,
        then, when it did not diverge, the secant replay (:meth:`_secant_chain`) and the probe (default ``_probe_out[c.name]``)
        when it fits better (:meth:`_probe_if_better`). A replay chain (:mod:`sysid.diagnose.schedule`);
        updates ``out[c.name]`` in place, notes ``((0, 0, index), text)`` to ``notes``."""
        rep = yield params, "refit"
        if rep is None:
            notes.append(((0, 0, index), f"{c.name}: refit replay diverged"))
            out[c.name].prediction = dict(ctx.prediction)
        else:
            out[c.name].prediction = rep[1]
        if self.settings.secant and rep is not None:
            # a diverged refit has no training SSE at its beta: no parabola through it
            yield from self._secant_chain(ctx, c, out, train, theta, probe)
        self._probe_if_better(ctx, c, out, train, probe)

    def _speculative_refit(self, ctx, c, probe, spec: dict[str, Any]):
        """Refit a candidate as soon as its probe is in, when its test is significant whatever the
        other candidates' tests give (a replay chain; the result goes to ``spec["refits"]``).

        Holm's procedure rejects every hypothesis whose p-value is at most ``alpha / m``, m the number
        of tests; ``spec["tests_bound"]`` (effects x tested channels) bounds m from above, so a
        candidate with a test at ``p_family <= alpha / tests_bound`` is significant in the report. A
        member of a family (``spec["members"]``: effect -> its members, library order) waits for its
        siblings' probes; the last one in keeps the member
        :func:`~sysid.diagnose.candidates.select_family_members` keeps (largest statistic, p-values
        times the family size). The refit depends only on that probe, the nominal rollout and
        ``J_theta``: the same replays as after the barrier, started while the other probes still run.
        """
        if c.level != "physics":
            return
        members = spec["members"].get(c.name, [c])
        size = len(members)
        if size > 1:
            done = spec["family_probes"].setdefault(c.name, {})
            done[cands.member_key(c)] = probe
            if len(done) < size:
                return
            best, tests = {}, {}
            for m in members:
                k = cands.member_key(m)
                rep = done[k]
                tests[k] = ([] if rep is None else
                            self._candidate_tests(ctx, m, m.signature(ctx, rep[1]), spec["J_theta"], []))
                best[k] = max((t["result"].statistic for t in tests[k]), default=-math.inf)
            c = max(members, key=lambda m: best[cands.member_key(m)])
            probe, tests = done[cands.member_key(c)], tests[cands.member_key(c)]
        elif probe is not None:
            tests = self._candidate_tests(ctx, c, c.signature(ctx, probe[1]), spec["J_theta"], [])
        if probe is None or not any(min(1.0, size * float(t["result"].p_value)) <= self.settings.alpha / spec["tests_bound"]
                                    for t in tests):
            return
        sig = c.signature(ctx, probe[1])
        params, rf = self._linearised_refit(ctx, c, sig, spec["J_theta"], spec["train"], spec["theta"])
        out, notes = {c.name: rf}, []
        yield from self._refit_chain(ctx, c, params, out, spec["train"], spec["theta"], 0, notes, probe)
        spec["refits"][c.name] = (cands.member_key(c), rf, [text for _, text in notes])

    def _probe_if_better(self, ctx, c, out, train, probe=None) -> None:
        """Take the probe rollout as the refit when it fits the training rows better.

        An effect with an onset (plastic yield, stiction breakaway) has no first-order signature
        below the onset, so the linearised estimate can land where the effect does nothing (or
        be clipped to 0) while the probe, already replayed, fits better than both the nominal
        model and the estimate; the probe is then the better refit.
        """
        rf = out[c.name]
        probe = self._probe_out.get(c.name) if probe is None else probe
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
        """:meth:`_secant_chain` of every candidate of ``physics``, by rounds through ``_replays``."""
        from sysid.diagnose.schedule import run_in_rounds

        run_in_rounds([self._secant_chain(ctx, c, out, train, theta) for c in physics], self._replays)

    def _secant_chain(self, ctx, c, out, train, theta, probe=None):
        """One more replay of candidate ``c`` at the minimiser of the parabola through the training
        SSE at beta = 0 (nominal), the probe and the linearised estimate; the better of the two is kept.

        A replay chain (:mod:`sysid.diagnose.schedule`): yields at most one parameter set, updates
        ``out[c.name]`` in place."""
        rf = out[c.name]
        b1 = float(rf.beta[0])
        probe = self._probe_out.get(c.name) if probe is None else probe
        if probe is None or not rf.prediction or rf.prediction is ctx.prediction:
            return
        xs = np.array([0.0, c.probe_beta, b1])
        if np.min(np.abs(np.diff(np.sort(xs)))) < 1e-3 * c.probe_beta:
            return
        ys = np.array([self._train_sse(ctx.prediction, train), self._train_sse(probe[1], train),
                       self._train_sse(rf.prediction, train)])
        a2, a1, _ = np.polyfit(xs, ys, 2)
        if not a2 > 0.0:
            return
        b2 = float(np.clip(-a1 / (2.0 * a2), 0.0 if c.one_sided else -c.bound, c.bound))
        if b2 == 0.0 or abs(b2 - b1) < 0.1 * max(abs(b1), 1e-12):
            return
        dtheta = {k: v for k, v in rf.sim_params.items() if k != c.parameter}
        rep = yield {**theta, **dtheta, **c.sim_parameters(b2)}, "secant"
        if rep is None or self._train_sse(rep[1], train) >= ys[2]:
            return
        rf.beta = np.array([b2])
        rf.params[c.report_name] = b2
        rf.sim_params = {**dtheta, **c.sim_parameters(b2)}
        rf.prediction = rep[1]
