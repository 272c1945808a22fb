"""Held-out data of the stiction refit: the breakaway decay fitted on one channel, predicted on the other.

Stiction's signature lives in a few samples at each breakaway: the tangential load's overshoot over
its sliding level, decaying within 1-3 marker samples on another engine's recordings. Holding out every
other marker sample of the breakaway window (the engine's former split) leaves the decay one or two
training samples and one or two held-out ones, where a fitted decay cannot gain; on the own MuJoCo
world it withdrew a true stiction (closing note, session 51). Two channels measure the same load at
every breakaway: the friction ratio along the slide from the wrench (200 Hz;
:func:`~sysid.diagnose.signatures.friction.breakaways`) and the mean marker shear against the slide
(:func:`~sysid.diagnose.signatures.friction.shear_breakaway`), with independent noise. Here the
decay's shape (relative excess ``A / a`` and decay time) is fitted on one channel's whole window and
predicts the other's, both ways: the held-out channel's sliding level and trend are fitted there
before and after alike (a level in N/N or m is the channel's own), so the held-out test asks whether
the breakaway excess one sensor shows is where and how large the other shows it. The marker shear's
relative excess includes the normal load's own excess at the breakaway, the friction ratio does not
(:func:`~sysid.diagnose.signatures.friction.normal_load_excess` converts).

Which split to use was chosen on a null model (``tests/sysid/diagnose/test_stiction_refit.py``;
docs/benchmarks_log.md, session 52): the held-out gain of the decay on Coulomb-friction press-slides
(a kept name there is a false keep; the friction tests' stick-slip and brush recordings, 20 noise draws
each: every other marker sample keeps 4/20, the other channel 1/20) and on stiction recordings (a
withdrawn name is a false withdrawal: 0/20 and at most 2/20 on the same models; on this simulator's
press-slide with a Stribeck friction of static 1.5 times kinetic, 3/10 and 1/10).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sysid.diagnose.signatures.friction import (Breakaway, breakaways, decay_columns, decay_taus, fit_breakaway,
                                                normal_load_excess, shear_breakaway)


def _wsse(cols: list[np.ndarray], b: Breakaway) -> float:
    """Whitened SSE of the weighted least-squares fit of ``b.q`` on the columns ``cols``."""
    X = np.stack(cols, axis=1) / b.sigma[:, None]
    z = b.q / b.sigma
    c, *_ = np.linalg.lstsq(X, z, rcond=None)
    r = z - X @ c
    return float(r @ r)


def predicted_sse(held: Breakaway, relative_excess: float, tau: float) -> tuple[float, float]:
    """Whitened SSE of the held-out channel's window with its sliding level and trend fitted, without
    and with a decay of the given shape: ``a (1 + r exp(-(t - t0) / tau)) + b (t - t0)``.

    Args:
        held: the held-out channel's breakaway window.
        relative_excess: ``r = A / a`` from the other channel (<= 0: no decay).
        tau: decay time from the other channel, s (<= 0: no decay).

    Returns:
        ``(before, after)``; equal where there is no decay.
    """
    level, trend = decay_columns(held.t, held.t0, 0.0)[:2]
    before = _wsse([level, trend], held)
    if not (relative_excess > 0.0 and tau > 0.0):
        return before, before
    shape = level + relative_excess * np.exp(-(held.t - held.t0) / tau)
    return before, _wsse([shape, trend], held)


def _shape(fit: dict) -> tuple[float, float]:
    """``(A / a, tau)`` of a breakaway fit (``(0, 0)`` without a positive level or decay)."""
    if not (fit["level"] > 0.0 and fit["tau_s"] > 0.0):
        return 0.0, 0.0
    return fit["excess"] / fit["level"], fit["tau_s"]


def cross_channel_refit(rec: Any) -> dict[str, Any]:
    """Stiction's breakaway decay fitted on each channel and evaluated on the other (module docstring).

    Args:
        rec: the :class:`~sysid.diagnose.signatures.Recording` (wrench, pose, markers).

    Returns:
        ``params`` (``static_over_kinetic``: 1 + the marker shear's relative excess less the normal
        load's, median over breakaways; ``decay_s``), ``heldout_rms_before`` / ``_after`` (whitened, over
        both channels' held-out windows; None without a breakaway seen by both), ``rms`` (the marker
        shear's training fit), ``per_breakaway`` (held-out SSE before / after per channel) and ``held_out_values``.
    """
    taus = decay_taus(rec)
    before = after = fit_sse = 0.0
    n_held = n_fit = 0
    ratios, decays, rows = [], [], []
    for b in breakaways(rec):
        bs = shear_breakaway(rec, b)
        if bs is None:
            continue
        fm, fw = fit_breakaway(bs, taus), fit_breakaway(b, taus)
        (rm, tm), (rw, tw) = _shape(fm), _shape(fw)
        nm = normal_load_excess(rec, bs, tm)[0] if tm > 0.0 else 0.0
        nw = normal_load_excess(rec, b, tw)[0] if tw > 0.0 else 0.0
        # markers -> friction ratio (less the normal load's excess), friction ratio -> markers (plus it)
        on_wrench = predicted_sse(b, rm - nm, tm)
        on_markers = predicted_sse(bs, rw + nw, tw)
        before += on_wrench[0] + on_markers[0]
        after += on_wrench[1] + on_markers[1]
        n_held += len(b.t) + len(bs.t)
        fit_sse += fm["sse1"]
        n_fit += len(bs.t)
        rows.append({"t_s": float(b.t0), "friction_ratio": list(on_wrench), "marker_shear": list(on_markers),
                     "shape_markers": [rm, tm], "shape_friction_ratio": [rw, tw]})
        if fm["level"] > 0.0:
            ratios.append(1.0 + max(rm - nm, 0.0))
            decays.append(tm)
    return {"params": {"static_over_kinetic": float(np.median(ratios)) if ratios else 1.0,
                       "decay_s": float(np.median(decays)) if decays else 0.0},
            "rms": {"markers_xyz": math.sqrt(fit_sse / max(n_fit, 1))},
            "heldout_rms_before": math.sqrt(before / n_held) if n_held else None,
            "heldout_rms_after": math.sqrt(after / n_held) if n_held else None,
            "per_breakaway": rows, "held_out_values": n_held}
