"""Held-out rows by contact events: each repeated kind of event is seen by training and held-out data.

SYSID.md recipe step 6 validates a refit on held-out time segments: every other of ``2 * blocks``
equal time blocks (:func:`sysid.diagnose.residuals.holdout_rows`). An effect that acts only at a few
contact events (adhesion at lift-off) then lands wholly in training or wholly in held-out blocks,
depending on where the events fall, and no refit can be both fitted and validated on it
(docs/benchmarks_log.md, 2026-11-22: the bench's single lift-off lay in the last, held-out block).

The rule here is decided from the nominal replay before any candidate is tested, and is the same for
every effect: the gel is in contact while the nominal contact force exceeds
:data:`CONTACT_FRACTION` of its peak; a change of that state is a touch-down or a lift-off. For each
kind of event that occurs at least twice, the rows within half a block of each occurrence are given,
in time order, alternately to training and held-out (the first to training); rows near no repeated
event keep the equal blocks. Where the windows of two events overlap, the later event decides.

A kind of event none of whose occurrences has a training row within half a block after it (a single
lift-off that falls in the last block, which is a held-out one, as in every recording that ends by
lifting the gel) would leave the refit of an effect that acts there (adhesion: the sheet carried up
after the lift-off) nothing to be estimated from: the rows within half a block after its last
occurrence then alternate sample by sample between training and held-out, the first to training, so
that both see it (docs/benchmarks_log.md, 2026-11-26, session 40, 23loa: the benchmark's adhesion x4
on seed 2 clipped to 0 for that reason). A recording whose events all have training rows after them
keeps the equal blocks unchanged.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from sysid.diagnose.residuals import holdout_rows

CONTACT_FRACTION = 0.05
"""The gel counts as in contact while the nominal contact force exceeds this fraction of its peak."""


def contact_events(t_s: np.ndarray, wrench: np.ndarray, fraction: float = CONTACT_FRACTION) -> list[tuple[float, str]]:
    """Touch-downs and lift-offs of a (noise-free, nominal) replay.

    Args:
        t_s: sample times in s, shape ``(K,)``.
        wrench: contact wrench on the gel, ``(K, 6)`` (N, N m); only the force is used.
        fraction: contact threshold as a fraction of the peak force magnitude (0 < fraction < 1).

    Returns:
        ``[(time s, "touch" | "lift")]`` in time order; an event's time is the midpoint of the two
        samples it lies between. Empty when the force is zero throughout.

    Raises:
        ValueError: ``fraction`` outside (0, 1) or shapes that do not match.
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"contact fraction must lie in (0, 1), got {fraction}")
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(wrench, dtype=float)
    if w.ndim != 2 or w.shape[0] != t.shape[0] or w.shape[1] < 3:
        raise ValueError(f"wrench must be (K, 6) with K = {t.shape[0]} samples, got {w.shape}")
    f = np.linalg.norm(w[:, :3], axis=1)
    if not f.max() > 0:
        return []
    on = f > fraction * f.max()
    change = np.flatnonzero(on[1:] != on[:-1]) + 1
    return [(0.5 * (t[i - 1] + t[i]), "touch" if on[i] else "lift") for i in change]


def event_holdout_rows(t_s: np.ndarray, blocks: int, span: tuple[float, float],
                       events: Sequence[tuple[float, str]]) -> np.ndarray:
    """True on held-out rows: equal blocks, with repeated contact events alternated and the rows after a kind
    of event that no training row follows alternated sample by sample (module docstring).

    Args:
        t_s: stamps of a channel in s, shape ``(T,)``.
        blocks: held-out blocks (``2 * blocks`` equal blocks over ``span``).
        span: ``(start, end)`` of the recording in s.
        events: ``[(time s, kind)]`` from :func:`contact_events`.

    Returns:
        bool rows, shape ``(T,)``.
    """
    t = np.asarray(t_s, dtype=float)
    half = _half_block(blocks, span)
    rows = _repeated_alternated(t, blocks, span, events)
    for kind in _unseen_by_training(t, rows, half, events):
        last = max(te for te, k in events if k == kind)
        after = np.flatnonzero((t > last) & (t <= last + half))
        rows[after] = (np.arange(after.size) % 2) == 1
    return rows


def _half_block(blocks: int, span: tuple[float, float]) -> float:
    """Half the length of one of the ``2 * blocks`` equal blocks of ``span``, s: how near an event a row
    is alternated."""
    return 0.5 * (span[1] - span[0]) / (2 * blocks)


def _repeated_alternated(t: np.ndarray, blocks: int, span: tuple[float, float],
                         events: Sequence[tuple[float, str]]) -> np.ndarray:
    """Equal blocks, the rows within half a block of each repeated kind's occurrences alternated."""
    rows = holdout_rows(t, blocks, span)
    half = _half_block(blocks, span)
    kinds = [k for _, k in events]
    seen: dict[str, int] = {}
    for te, kind in sorted(events, key=lambda e: e[0]):
        j = seen.get(kind, 0)
        seen[kind] = j + 1
        if kinds.count(kind) < 2:
            continue
        rows[np.abs(t - te) <= half] = (j % 2) == 1
    return rows


def _unseen_by_training(t: np.ndarray, rows: np.ndarray, half: float,
                        events: Sequence[tuple[float, str]]) -> list[str]:
    """Kinds of event with rows after them, none of which (within ``half`` s after any occurrence) is a
    training row (``rows``: True = held out), in order of first occurrence."""
    out: list[str] = []
    for _, kind in sorted(events, key=lambda e: e[0]):
        if kind in out:
            continue
        after = [(t > te) & (t <= te + half) for te, k in events if k == kind]
        if any(m.any() for m in after) and all(rows[m].all() for m in after):
            out.append(kind)
    return out


def alternated_kinds(t_s: np.ndarray, blocks: int, span: tuple[float, float],
                     events: Sequence[tuple[float, str]]) -> list[str]:
    """Kinds of event whose rows after the last occurrence :func:`event_holdout_rows` alternates sample by
    sample (no training row after any occurrence otherwise); arguments as there."""
    t = np.asarray(t_s, dtype=float)
    return _unseen_by_training(t, _repeated_alternated(t, blocks, span, events), _half_block(blocks, span), events)


def heldout_label(blocks: int, events: Sequence[tuple[float, str]], alternated: Sequence[str] = ()) -> str:
    """Report line of the held-out split: ``time blocks (every other of N)`` plus the alternated events
    (``alternated``: the kinds of :func:`alternated_kinds`)."""
    kinds = [k for _, k in events]
    repeated = sorted({k for k in kinds if kinds.count(k) >= 2})
    base = f"time blocks (every other of {blocks})"
    if repeated:
        base += "; rows near repeated contact events alternate (" + ", ".join(
            f"{kinds.count(k)} {_event_name(k)}s" for k in repeated) + ")"
    if alternated:
        base += "; rows after the last " + " and the last ".join(_event_name(k) for k in alternated) + \
            " alternate sample by sample (no training row after it otherwise)"
    return base


def _event_name(kind: str) -> str:
    """A kind of contact event in words: ``touch`` a touch-down, else a lift-off."""
    return "touch-down" if kind == "touch" else "lift-off"
