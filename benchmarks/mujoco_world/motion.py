"""Commanded effector motions of the reference world: ``press_slide`` and ``lift_fold``.

Pure numpy (no MuJoCo): the command is a sequence of minimum-jerk segments between rests,
``s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5`` (Flash & Hogan 1985), whose peak speed is 1.875 times
the mean, the shape the reference recordings' ``ee/pose_cmd`` shows (measured on nominal_s101:
peak/mean 1.87 in press, slide and lift). A segment of length ``L`` at mean speed ``v`` lasts
``L / v``. Rest durations are drawn per recording from the ranges seen in the nine reference
recordings' commands (initial rest 0.09-0.16 s, dwell after the press 0.35-0.6 s, after the slide
0.25-0.6 s, final rest 0.3 s for press_slide and 0.6 s for lift_fold).

Positions are in ``world`` (m); "first contact" is the height of the card's top surface
(``sheet.origin z + thickness / 2``) under the undeformed gel surface, which is the effector
frame's origin.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np


def min_jerk(tau: np.ndarray) -> np.ndarray:
    """Minimum-jerk progress ``10 tau^3 - 15 tau^4 + 6 tau^5`` for ``tau`` clipped to [0, 1]."""
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


@dataclass(frozen=True)
class Segment:
    """One min-jerk move of the commanded position: from ``t0`` for ``duration`` s by ``delta`` (m, shape (3,))."""

    t0: float
    duration: float
    delta: tuple[float, float, float]


@dataclass
class Motion:
    """A commanded trajectory: start position (m, world) and a list of min-jerk segments.

    Attributes:
        kind: ``press_slide`` or ``lift_fold``.
        start: commanded position at t = 0 (m, shape (3,)).
        segments: the moves, in time order, not overlapping.
        duration_s: total length of the recording (s).
        params: the motion's parameters, written to the labels (the reference labels' keys).
        tack_on_s / tack_off_s: lift_fold only: when the gel tacks to the card and when it peels.
    """

    kind: str
    start: tuple[float, float, float]
    segments: list[Segment]
    duration_s: float
    params: dict[str, Any] = field(default_factory=dict)
    tack_on_s: float | None = None
    tack_off_s: float | None = None

    def command(self, t: np.ndarray | float) -> np.ndarray:
        """Commanded position at times ``t`` (s): shape ``t.shape + (3,)`` (m, world)."""
        t = np.asarray(t, dtype=float)
        pos = np.broadcast_to(np.asarray(self.start, dtype=float), t.shape + (3,)).copy()
        for seg in self.segments:
            s = min_jerk((t - seg.t0) / seg.duration)
            pos += s[..., None] * np.asarray(seg.delta, dtype=float)
        return pos

    def labels(self) -> dict[str, Any]:
        """The ``motion`` entry of labels.yaml (reference format)."""
        out = {"kind": self.kind, **self.params, "duration_s": float(self.duration_s)}
        if self.tack_on_s is not None:
            out["t_tack_on"] = float(self.tack_on_s)
            out["t_tack_off"] = float(self.tack_off_s)
        return out


def _seg(t: float, delta: np.ndarray, speed: float) -> Segment:
    length = float(np.linalg.norm(delta))
    if not speed > 0.0 or not length > 0.0:
        raise ValueError(f"a move needs a positive length and speed, got {length} m at {speed} m/s")
    return Segment(t, length / speed, tuple(float(x) for x in delta))


def press_slide(start_xy, depth, slide, height, v_press, v_slide, v_lift, contact_z,
                rests=(0.12, 0.45, 0.4, 0.3)) -> Motion:
    """Approach from ``height`` above first contact, press ``depth`` past it, dwell, slide, dwell, lift.

    Args:
        start_xy: (x, y) of the press in world (m).
        depth: commanded press past first contact (m, 1-3 mm in the reference).
        slide: (dx, dy) of the slide (m).
        height: approach height of the gel surface above first contact (m).
        v_press, v_slide, v_lift: mean speeds of the three moves (m/s).
        contact_z: world z of first contact, the card's top surface (m).
        rests: initial rest, dwell after the press, dwell after the slide, final rest (s).

    Raises:
        ValueError: a non-positive length or speed.
    """
    t_rest0, dwell1, dwell2, tail = rests
    start = np.array([start_xy[0], start_xy[1], contact_z + height])
    t = t_rest0
    press = _seg(t, np.array([0.0, 0.0, -(height + depth)]), v_press)
    t += press.duration + dwell1
    sl = _seg(t, np.array([slide[0], slide[1], 0.0]), v_slide)
    t += sl.duration + dwell2
    lift = _seg(t, np.array([0.0, 0.0, height + depth]), v_lift)
    t += lift.duration + tail
    params = {"start_xy": [float(start_xy[0]), float(start_xy[1])], "depth": float(depth),
              "slide": [float(slide[0]), float(slide[1])], "height": float(height),
              "v_press": float(v_press), "v_slide": float(v_slide), "v_lift": float(v_lift)}
    return Motion("press_slide", tuple(start), [press, sl, lift], t, params)


LIFT_FIRST_FRACTION = 0.36
"""Share of a lift_fold's rise (depth + lift) made straight up before the fold moves back (the mean of
the three reference lift-folds' commands: 0.374, 0.340, 0.370)."""


def lift_fold(start_xy, depth, lift, fold_back, height, v_press, v_fold, contact_z,
              rests=(0.15, 0.35, 0.35, 0.6), tack_lead_s=0.05, peel_rise=0.006, v_peel=0.02,
              lift_first: float | None = None) -> Motion:
    """Press near the free edge, tack, lift, then lift further while moving ``fold_back`` toward the clamp, hold, peel.

    The rise of ``depth + lift`` is two back-to-back min-jerk moves at the mean speed ``v_fold``:
    ``lift_first`` m straight up (default ``LIFT_FIRST_FRACTION`` of the rise), then the rest of the
    rise together with ``fold_back`` (the reference commands show two speed peaks of the same
    height, the first move vertical). The tack bonds form ``tack_lead_s`` before the rise starts and
    are released (peel) at the start of the final rise of ``peel_rise`` m at ``v_peel`` m/s (the
    reference's last move: 6 mm at 20 mm/s).

    Raises:
        ValueError: a non-positive length or speed, or ``lift_first`` not inside the rise.
    """
    t_rest0, dwell1, hold, tail = rests
    rise = depth + lift
    if lift_first is None:
        lift_first = LIFT_FIRST_FRACTION * rise
    if not 0.0 < lift_first < rise:
        raise ValueError(f"lift_first {lift_first} m must lie inside the rise (0, {rise}) m")
    start = np.array([start_xy[0], start_xy[1], contact_z + height])
    t = t_rest0
    press = _seg(t, np.array([0.0, 0.0, -(height + depth)]), v_press)
    t += press.duration + dwell1
    up = _seg(t, np.array([0.0, 0.0, lift_first]), v_fold)
    tack_on = t - tack_lead_s
    t += up.duration
    fold = _seg(t, np.array([-fold_back, 0.0, rise - lift_first]), v_fold)
    t += fold.duration + hold
    peel = _seg(t, np.array([0.0, 0.0, peel_rise]), v_peel)
    tack_off = t
    t += peel.duration + tail
    params = {"start_xy": [float(start_xy[0]), float(start_xy[1])], "depth": float(depth),
              "lift": float(lift), "fold_back": float(fold_back), "height": float(height),
              "v_press": float(v_press), "v_fold": float(v_fold), "lift_first": float(lift_first)}
    return Motion("lift_fold", tuple(start), [press, up, fold, peel], t, params, tack_on, tack_off)


def lift_fold_like(m: dict[str, Any], contact_z: float, rest0: float = 0.15, tack_lead_s: float = 0.05) -> Motion:
    """The lift_fold of a labels ``motion`` entry, its rests recovered from ``t_tack_on``, ``t_tack_off`` and
    ``duration_s`` (the labels do not give them; the initial rest ``rest0`` s is assumed).

    Raises:
        ValueError: the labels' times leave a negative rest, or a bad move (see :func:`lift_fold`).
    """
    args = (m["start_xy"], m["depth"], m["lift"], m["fold_back"], m["height"], m["v_press"], m["v_fold"], contact_z)
    probe = lift_fold(*args, rests=(rest0, 0.0, 0.0, 0.0), tack_lead_s=tack_lead_s, lift_first=m.get("lift_first"))
    press, up, fold, peel = probe.segments
    dwell1 = float(m["t_tack_on"]) + tack_lead_s - (rest0 + press.duration)
    hold = float(m["t_tack_off"]) - (float(m["t_tack_on"]) + tack_lead_s + up.duration + fold.duration)
    tail = float(m["duration_s"]) - (float(m["t_tack_off"]) + peel.duration)
    if min(dwell1, hold, tail) < 0.0:
        raise ValueError(f"labels' times leave a negative rest: dwell {dwell1:.3f}, hold {hold:.3f}, tail {tail:.3f} s")
    return lift_fold(*args, rests=(rest0, dwell1, hold, tail), tack_lead_s=tack_lead_s, lift_first=m.get("lift_first"))


SHORT_PRESS_SLIDE = {"length": (0.010, 0.012), "rests": (0.10, 0.30, 0.20, 0.20), "depth": (0.0015, 0.0025),
                     "height": (0.0035, 0.0040), "v_press": (0.007, 0.008), "v_slide": (0.018, 0.020),
                     "v_lift": (0.017, 0.019)}
"""Ranges of a short press_slide (``sample_press_slide(short=True)``, 2.3-2.7 s instead of 3-5 s): the
shortest rests, approach and fastest speeds of the reference's ranges, and a 10-12 mm slide (past gross
slip: the patch slides after 1-3 mm at these depths). For a small bundled test recording."""


def sample_press_slide(rng: np.random.Generator, contact_z: float, direction: str | None = None,
                       short: bool = False) -> Motion:
    """A random press_slide in the reference's ranges (labels.yaml of the nine recordings).

    Start x 40-72 mm, y -15..17 mm; depth 1-3 mm; slide 13-28 mm along +-x, +-y or a diagonal
    (``direction`` one of ``+x -x +y -y diag``, drawn when None), kept on the card's interior;
    approach height 3.5-7.5 mm; mean speeds press 4-8, slide 8-20, lift 9-19 mm/s. ``short``: the
    ranges of :data:`SHORT_PRESS_SLIDE` (rests fixed) instead.
    """
    dirs = {"+x": (1.0, 0.0), "-x": (-1.0, 0.0), "+y": (0.0, 1.0), "-y": (0.0, -1.0)}
    if direction is None:
        direction = str(rng.choice(["+x", "-x", "+y", "-y", "diag"]))
    for _ in range(1000):
        x0, y0 = rng.uniform(0.040, 0.072), rng.uniform(-0.015, 0.017)
        length = rng.uniform(*SHORT_PRESS_SLIDE["length"]) if short else rng.uniform(0.013, 0.028)
        if direction == "diag":
            ang = rng.uniform(0, 2 * np.pi)
            u = (np.cos(ang), np.sin(ang))
        else:
            u = dirs[direction]
        x1, y1 = x0 + length * u[0], y0 + length * u[1]
        if 0.035 <= x1 <= 0.085 and -0.018 <= y1 <= 0.018:
            break
    else:
        raise ValueError(f"no slide {direction} fits on the card")
    if short:
        r = SHORT_PRESS_SLIDE
        return press_slide((x0, y0), rng.uniform(*r["depth"]), (length * u[0], length * u[1]),
                           rng.uniform(*r["height"]), rng.uniform(*r["v_press"]), rng.uniform(*r["v_slide"]),
                           rng.uniform(*r["v_lift"]), contact_z, r["rests"])
    rests = (rng.uniform(0.09, 0.16), rng.uniform(0.35, 0.6), rng.uniform(0.25, 0.6), 0.3)
    return press_slide((x0, y0), rng.uniform(0.001, 0.003), (length * u[0], length * u[1]),
                       rng.uniform(0.0035, 0.0075), rng.uniform(0.004, 0.008), rng.uniform(0.008, 0.020),
                       rng.uniform(0.009, 0.019), contact_z, rests)


def sample_lift_fold(rng: np.random.Generator, contact_z: float) -> Motion:
    """A random lift_fold in the reference's ranges: start x 87-89 mm, y -10..10 mm, depth 1-2 mm,
    lift 10-18 mm, fold back 10-18 mm, approach 3.5-5 mm, press 5-8.5 mm/s, fold 13-15.5 mm/s."""
    rests = (rng.uniform(0.1, 0.16), rng.uniform(0.3, 0.5), rng.uniform(0.3, 0.4), 0.6)
    return lift_fold((rng.uniform(0.087, 0.089), rng.uniform(-0.01, 0.01)), rng.uniform(0.001, 0.002),
                     rng.uniform(0.010, 0.018), rng.uniform(0.010, 0.018), rng.uniform(0.0035, 0.005),
                     rng.uniform(0.005, 0.0085), rng.uniform(0.013, 0.0155), contact_z, rests)
