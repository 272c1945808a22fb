"""Held-out rows by contact events (sysid.diagnose.events): found from the nominal force, alternated per kind."""

from __future__ import annotations

import numpy as np
import pytest

from sysid.diagnose.events import alternated_kinds, contact_events, event_holdout_rows, heldout_label
from sysid.diagnose.residuals import holdout_rows


def _wrench(on: np.ndarray) -> np.ndarray:
    w = np.zeros((on.size, 6))
    w[:, 2] = np.where(on, -5.0, 0.0)
    w[:, 0] = 0.01  # below the contact fraction of the peak: no contact
    return w


def test_contact_events_are_the_threshold_crossings_of_the_force():
    t = np.arange(20) * 0.01
    on = np.zeros(20, bool)
    on[3:8] = on[12:15] = True
    ev = contact_events(t, _wrench(on))
    assert ev == [(pytest.approx(0.025), "touch"), (pytest.approx(0.075), "lift"),
                  (pytest.approx(0.115), "touch"), (pytest.approx(0.145), "lift")]
    assert contact_events(t, np.zeros((20, 6))) == []
    with pytest.raises(ValueError, match="fraction"):
        contact_events(t, _wrench(on), fraction=1.5)
    with pytest.raises(ValueError, match="wrench"):
        contact_events(t, np.zeros((19, 6)))


def test_one_event_of_each_kind_with_training_rows_after_it_keeps_the_equal_blocks():
    t = np.arange(47) * 0.01
    events = [(0.025, "touch"), (0.375, "lift")]  # the lift-off in block 6 (0.345-0.4025 s), a training block
    assert np.array_equal(event_holdout_rows(t, 4, (0.0, 0.46), events), holdout_rows(t, 4, (0.0, 0.46)))
    assert alternated_kinds(t, 4, (0.0, 0.46), events) == []
    assert heldout_label(8, events) == "time blocks (every other of 8)"


def test_a_single_lift_off_in_the_last_heldout_block_is_seen_by_training():
    """The benchmark's press-slide-lift (47 samples at 10 ms, lift-off at 0.425 s): the last of eight
    equal blocks (0.4025-0.46 s) is held out, so no training row follows the lift-off. The rows within
    half a block after it (0.43-0.45 s) alternate, the first to training; the touch-down (training
    rows after it) and every other row keep the equal blocks."""
    t = np.arange(47) * 0.01
    span = (0.0, 0.46)
    events = [(0.025, "touch"), (0.425, "lift")]
    eq = holdout_rows(t, 4, span)
    assert eq[t > 0.41].all()  # the equal blocks hold out everything after the lift-off
    rows = event_holdout_rows(t, 4, span, events)
    after = (t > 0.425) & (t <= 0.425 + 0.02875)
    assert np.flatnonzero(after).tolist() == [43, 44, 45]
    assert rows[[43, 44, 45]].tolist() == [False, True, False]
    assert np.array_equal(rows[~after], eq[~after])
    assert alternated_kinds(t, 4, span, events) == ["lift"]
    label = heldout_label(8, events, ["lift"])
    assert label.startswith("time blocks (every other of 8)") and "after the last lift-off alternate" in label


def test_repeated_lift_offs_alternate_between_training_and_heldout():
    """Three lift-offs (0.43, 0.59, 0.75 s of 0.78 s; equal blocks train on the first two and hold
    out the third) alternate: the first and third train, the second is held out; the rows far from
    any repeated event keep the equal blocks."""
    t = np.arange(79) * 0.01
    span = (0.0, 0.78)
    events = [(0.025, "touch"), (0.43, "lift"), (0.59, "lift"), (0.75, "lift")]
    eq = holdout_rows(t, 4, span)
    assert [bool(eq[np.argmin(np.abs(t - te))]) for te in (0.43, 0.59, 0.75)] == [False, False, True]
    rows = event_holdout_rows(t, 4, span, events)
    half = 0.5 * 0.78 / 8
    near = lambda te: np.abs(t - te) <= half  # noqa: E731
    assert not rows[near(0.43)].any() and rows[near(0.59)].all() and not rows[near(0.75)].any()
    far = ~(near(0.43) | near(0.59) | near(0.75))
    assert np.array_equal(rows[far], eq[far])
    assert rows.any() and (~rows).any()
    assert "3 lift-offs" in heldout_label(8, events)


def test_the_later_event_decides_where_windows_overlap():
    t = np.arange(41) * 0.01
    events = [(0.10, "touch"), (0.20, "touch"), (0.22, "lift"), (0.30, "lift")]
    rows = event_holdout_rows(t, 2, (0.0, 0.40), events)  # half-window 0.05 s
    # touch 2 (held out) covers 0.15-0.25, lift 1 (training) 0.17-0.27: lift 1 is later and wins,
    # lift 2 (held out, 0.25-0.35) wins over lift 1 after 0.25
    assert not rows[(t > 0.165) & (t < 0.245)].any()
    assert rows[(t > 0.155) & (t < 0.165)].all()
    assert rows[(t > 0.255) & (t <= 0.35)].all()  # lift 2 held out
