"""Time bases of a replay: recorded streams held or interpolated onto the simulation's step times."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Interpolation:
    """Linear interpolation from step times to stamps: ``y(t_j) = (1 - w_j) Y[i_j] + w_j Y[i_j + 1]``."""

    index: np.ndarray
    weight: np.ndarray

    def apply(self, per_step: np.ndarray) -> np.ndarray:
        w = self.weight.reshape(-1, *(1,) * (per_step.ndim - 1))
        return (1.0 - w) * per_step[self.index] + w * per_step[self.index + 1]


def held(t_ns: np.ndarray, values: np.ndarray, at_ns: np.ndarray, dt_ns: int, initial: np.ndarray) -> np.ndarray:
    """Zero-order hold: at each ``at_ns`` the last of ``values`` logged at or before it (within half a
    step ``dt_ns``, for stamps rounded to the ns), ``initial`` before the first.

    Args:
        t_ns: log times ``(N,)`` int64, increasing. values: ``(N, ...)``. at_ns: query times ``(M,)``.
        dt_ns: the replay step, ns. initial: the value before the first sample, shaped like one value.

    Returns:
        ``(M, ...)``.
    """
    values = np.asarray(values, dtype=float)
    idx = np.searchsorted(np.asarray(t_ns), np.asarray(at_ns) + dt_ns // 2, side="right") - 1
    out = values[np.maximum(idx, 0)].copy()
    out[idx < 0] = initial
    return out


def interpolation(t_steps: np.ndarray, t_dst: np.ndarray) -> Interpolation:
    """The linear interpolation from step times ``t_steps`` ``(K + 1,)`` ns to stamps ``t_dst`` ``(M,)`` ns
    (clamped to the first and last step)."""
    xs = (t_steps - t_steps[0]).astype(np.float64)
    xd = (t_dst - t_steps[0]).astype(np.float64)
    i = np.clip(np.searchsorted(xs, xd, side="right") - 1, 0, xs.shape[0] - 2)
    w = np.clip((xd - xs[i]) / (xs[i + 1] - xs[i]), 0.0, 1.0)
    return Interpolation(i.astype(np.int64), w)
