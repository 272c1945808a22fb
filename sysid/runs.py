"""Runs of True in a boolean series: the sample windows where a condition holds.

One rule, used below the diagnosis and beside it: the signature tests' windows
(:mod:`sysid.diagnose.signatures`: loaded, carried, free, sliding phases) and the wrench check's
contradicting phases (:mod:`sysid.wrench_check`). A module of its own beneath both, so that
:mod:`sysid.wrench_check` (which :mod:`sysid.diagnose` imports) takes it without an import cycle.
"""

from __future__ import annotations

import numpy as np


def segments(mask: np.ndarray) -> list[tuple[int, int]]:
    """Runs of True in a boolean array as half-open index pairs ``[(i0, i1), ...]``.

    Args:
        mask: shape ``(n,)``, anything ``np.asarray(..., dtype=bool)`` takes.

    Returns:
        the runs in order, ``mask[i0:i1]`` all True and ``mask[i0 - 1]`` / ``mask[i1]`` False or outside.
    """
    m = np.asarray(mask, dtype=bool)
    if m.size == 0:
        return []
    d = np.diff(np.concatenate([[0], m.astype(np.int8), [0]]))
    starts, ends = np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]
    return list(zip(starts.tolist(), ends.tolist()))
