"""Discriminating test of stiction: does the wrench mismatch have a tangential line of action?

SYSID.md step 5 names a candidate only when it explains the held-out data; effects whose prediction
changes are nearly collinear in a recording pass that criterion alike. In the benchmark's
press-slide scene a thickness step of the card (an effect outside the library), the benchmark's
own stiction law and the library's stiction candidate all delay the second breakaway and change
how the card buckles in the long slide (noise-free cosine of the thickness step's change with the
benchmark's stiction law at a = 0.2: 0.94; a 2 % static-friction excess of the library
model explains 87 % of the thickness step's held-out excess). What stiction alone cannot do is
move the centre of pressure.

**Line of action** (:func:`line_of_action`, for the candidates in :data:`LINE_OF_ACTION_EFFECTS`).
Stiction changes the *tangential* traction at the gel-sheet contact patch. The moment that change
exerts about the sensor follows from the force through the patch geometry, which the nominal model
shares with the recording, so the recorded wrench must support the refit's wrench change at one
common scale on the force axes and on the moment axes:
:func:`sysid.diagnose.stats.scale_equality_test` with the two columns "refit change on the force
axes" and "refit change on the moment axes", on every sample where the refit changes the wrench (the
refit fixed only the overall scale, which the test leaves free; an equal-weighted cosine variance of
twelve degrees of freedom). A mismatch whose moment does not follow its force (a shifted centre of
pressure, i.e. a changed *normal* traction distribution, as a stiffer card under the gel gives: force
scale 1.18, moment scale 0.48, p 0.006 on the benchmark's thickness step x4 of seed 2; true stiction x2
and x4 of seeds 0-2: p 0.13-0.96; docs/benchmarks_log.md, session 40, 23loa) is not stiction.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from sysid.diagnose import stats
from sysid.diagnose.residuals import residual, whiten

LINE_OF_ACTION_EFFECTS = ("stiction",)
"""Candidates that act as a tangential contact traction (their force and moment change together)."""

ACTIVE_FRACTION = 0.01
"""A sample takes part in the test when the refit's whitened wrench change there (mean square over
the axes) exceeds this fraction of its peak."""

FORCE_AXES = (0, 1, 2)
"""Force components of the wrench channel ``(fx, fy, fz, tx, ty, tz)``; the others are moments."""


def line_of_action(model: Any, ctx: Any, prediction: Mapping[str, np.ndarray], rows: np.ndarray | None = None
                   ) -> stats.EqualityResult | None:
    """Force/moment consistency of a refit's wrench change (module docstring).

    Args:
        model: observation model (``data``, ``sigma``).
        ctx: diagnosis context (nominal prediction).
        prediction: the refit's prediction (channel -> array).
        rows: wrench samples to use, bool ``(n,)`` (default all).

    Returns:
        the :class:`~sysid.diagnose.stats.EqualityResult` (coefficients: the scale the recording
        supports on the force axes, on the moment axes), or None when the refit does not change the
        wrench or leaves a group unchanged on these rows.
    """
    if "wrench" not in prediction or "wrench" not in ctx.prediction:
        return None
    n = ctx.prediction["wrench"].shape[0]
    rows = np.ones(n, dtype=bool) if rows is None else np.asarray(rows, dtype=bool)
    r = residual(model, "wrench", ctx.prediction["wrench"])
    d = whiten(model, "wrench", prediction["wrench"] - ctx.prediction["wrench"])
    # the samples where the refit changes the wrench: the others carry no information on the contrast
    # and would only dilute the block sums
    energy = np.mean(d.reshape(d.shape[0], -1) ** 2, axis=1)
    rows = rows & (energy > ACTIVE_FRACTION * energy.max()) if energy.max() > 0 else rows & False
    r, d = r[rows], d[rows]
    force = np.zeros(d.shape[-1])
    force[list(FORCE_AXES)] = 1.0
    X = np.stack([d * force, d * (1.0 - force)], axis=-1)
    try:
        return stats.scale_equality_test(r, X)
    except ValueError:
        return None
