"""The peel read from the recorded sheet and the gel's face (sysid.diagnose.peel): a known answer."""

from __future__ import annotations

import numpy as np
import pytest

from sysid.diagnose.peel import face_gap, peel_time


def _lift(t_peel: float | None):
    """A 3 x 3 gel face over a 5 x 5 card: pressed until 0.5 s, then rising at 10 mm/s; the card's
    middle follows the face (tack) until ``t_peel`` and then falls back to a 2 mm set; times 0..1.5 s."""
    t = np.arange(0.0, 1.5001, 0.01)
    gx, gy = np.meshgrid(np.linspace(-0.004, 0.004, 3), np.linspace(-0.004, 0.004, 3))
    cx, cy = np.meshgrid(np.linspace(-0.02, 0.02, 5), np.linspace(-0.02, 0.02, 5))
    z_face = 0.0002 + 0.01 * np.maximum(t - 0.5, 0.0)
    face = np.stack([np.broadcast_to(gx.ravel(), (t.size, 9)), np.broadcast_to(gy.ravel(), (t.size, 9)),
                     np.repeat(z_face[:, None], 9, axis=1)], axis=-1)
    if t_peel is None:
        z_mid = np.zeros_like(t)
    else:
        z_mid = np.where(t <= t_peel, z_face - 0.0002, 0.002)
    bump = np.exp(-(cx.ravel() ** 2 + cy.ravel() ** 2) / 0.01 ** 2)
    sheet = np.stack([np.broadcast_to(cx.ravel(), (t.size, 25)), np.broadcast_to(cy.ravel(), (t.size, 25)),
                      z_mid[:, None] * bump[None, :]], axis=-1)
    return t, sheet, face


def test_the_peel_is_the_last_row_in_touch_before_the_card_falls_away():
    t, sheet, face = _lift(1.2)
    rng = np.random.default_rng(0)
    noisy = sheet + rng.normal(0.0, 5e-5, sheet.shape)  # the reference recordings' sheet-point noise
    assert peel_time(t, noisy, t, face, 1.25e-3) == pytest.approx(1.2, abs=1e-9)
    # the face sampled at other times (a replay's steps at 5 ms): nearest step per row
    tf = np.arange(0.0, 1.5001, 0.005)
    ff = np.stack([np.interp(tf, t, face[:, i, d]) for i in range(9) for d in range(3)], axis=-1).reshape(tf.size, 9, 3)
    assert peel_time(t, noisy, tf, ff, 1.25e-3) == pytest.approx(1.2, abs=1e-9)


def test_a_card_never_carried_peels_at_the_lift_off_and_one_never_left_has_no_peel():
    t, sheet, face = _lift(None)
    t_off = peel_time(t, sheet, t, face, 1.25e-3)
    # the face leaves the flat card 1.25 mm above its pressed height (0.2 mm gap at rest): 0.5 + 0.105 s
    assert 0.5 < t_off < 0.5 + 0.13
    t2, sheet2, face2 = _lift(10.0)  # carried to the end
    assert peel_time(t2, sheet2, t2, face2, 1.25e-3) is None
    assert face_gap(sheet[0], face[0] + np.array([1.0, 0.0, 0.0])) == float("inf")  # no point under the face
    with pytest.raises(ValueError, match="opening"):
        peel_time(t, sheet, t, face, 0.0)
