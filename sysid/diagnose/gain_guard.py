"""Names kept only where the effect's own term gains on held-out data.

A signature names an effect from the shape of the residual; the refit then fits the effect's own
term on training data and evaluates it on held-out data. A term that predicts the held-out data no
better than the model without it does not explain the mismatch, whatever the signature says: the
mismatch is then reported as unexplained in the effect's windows instead of under a wrong name
(SYSID.md; issue 23: "judge each candidate by what it gains on held-out data"). Example: on a
press-and-slide whose damped gel leaves a buckled card held off the table by friction after the
lift, the sheet-set signature names bending plasticity, but no yield angle fits the training sheet
points better than the elastic replay, so the held-out residual is unchanged.

Refits that report no held-out figure after (effects located but not refitted with their term in
this engine) are not judged here.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence


def heldout_gain(refit: Mapping[str, Any]) -> float | None:
    """``1 - after / before`` of a refit's held-out whitened RMS; None when it has no held-out figure
    before and after (not refitted with its term) or a non-positive / non-finite one before."""
    before, after = refit.get("heldout_rms_before"), refit.get("heldout_rms_after")
    if before is None or after is None:
        return None
    before, after = float(before), float(after)
    if not (math.isfinite(before) and before > 0.0 and math.isfinite(after)):
        return None
    return 1.0 - after / before


def split_by_gain(named: Sequence[str], refits: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], list[dict]]:
    """The named effects whose refit gains on held-out data, and the others.

    Args:
        named: effects named by the signatures, in rank order.
        refits: effect -> its refit block (``heldout_rms_before``, ``heldout_rms_after``).

    Returns:
        ``(kept, unexplained)``: ``kept`` in the order of ``named``: those whose held-out gain
        (:func:`heldout_gain`) is positive or not measured; ``unexplained``:
        ``[{"effect", "heldout_rms_before", "heldout_rms_after", "reason"}]`` for the others.
    """
    kept: list[str] = []
    dropped: list[dict] = []
    for effect in named:
        r = refits.get(effect, {})
        g = heldout_gain(r)
        if g is None or g > 0.0:
            kept.append(effect)
            continue
        dropped.append({"effect": effect, "heldout_rms_before": float(r["heldout_rms_before"]),
                        "heldout_rms_after": float(r["heldout_rms_after"]),
                        "reason": (f"{effect}'s own term, refitted on training data, does not lower the held-out "
                                   f"residual ({float(r['heldout_rms_before']):.4g} -> "
                                   f"{float(r['heldout_rms_after']):.4g}): the mismatch in its windows is "
                                   f"left unexplained rather than named {effect}")})
    return kept, dropped
