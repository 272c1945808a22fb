"""The stiction refit's held-out split chosen on a null model: the decay held out across channels.

Recordings: the stick-slip and brush press-slides of ``test_friction_signature`` (a kinematic effector
and a 3000 N/m impedance arm; 200 Hz wrench, 100 Hz markers, the reference bags' noise), 20 noise
seeds each. Null: Coulomb friction (``mu_s = mu_k``), where a kept name is a false keep; effect: a
breakaway excess of 50 % decaying in 10 ms (one marker sample, two wrench samples: the decay that
every other marker sample could not hold out) and the brush pad's partial-slip breakaway at 1.5, where
a withdrawn name is a false withdrawal. Measured (docs/benchmarks_log.md, session 52): every other
marker sample keeps 4/20 Coulomb recordings of each model, the other channel 1/20; both keep 20/20
of the effect's.
"""

from __future__ import annotations

import numpy as np
import pytest

from sysid.diagnose.gain_guard import heldout_gain
from sysid.diagnose.stiction_refit import cross_channel_refit, predicted_sse
from sysid.diagnose.signatures.friction import breakaways
from tests.sysid.diagnose.test_friction_signature import MU_K, brush_press_slide, press_slide

SEEDS = range(20)


def _kept(make) -> int:
    """Recordings (of ``SEEDS``) whose cross-channel refit gains on held-out data."""
    kept = 0
    for seed in SEEDS:
        g = heldout_gain(cross_channel_refit(make(np.random.default_rng(100 + seed))))
        kept += int(g is not None and g > 0.0)
    return kept


@pytest.mark.parametrize("make", [lambda rng: press_slide(rng, mu_s=MU_K), lambda rng: brush_press_slide(rng, mu_s=MU_K)],
                         ids=["stick_slip", "brush"])
def test_coulomb_friction_is_rarely_kept(make):
    assert _kept(make) <= 2  # 10 % at most (measured 1/20 on each)


@pytest.mark.parametrize("make", [lambda rng: press_slide(rng, mu_s=1.5 * MU_K, tau_b=0.01),
                                  lambda rng: brush_press_slide(rng, mu_s=1.5 * MU_K)], ids=["stick_slip", "brush"])
def test_a_breakaway_of_one_marker_sample_is_kept(make):
    assert _kept(make) == len(SEEDS)


def test_the_other_channels_level_is_its_own_and_no_decay_changes_nothing():
    rec = press_slide(np.random.default_rng(1), mu_s=1.5 * MU_K)
    (b,) = breakaways(rec)
    before, after = predicted_sse(b, 0.0, 0.03)
    assert before == after
    scaled = type(b)(b.t_command, b.t_slip, b.t0, b.direction, b.t, 7.0 * b.q, 7.0 * b.sigma, b.t_slide_end)
    np.testing.assert_allclose(predicted_sse(scaled, 0.5, 0.03), predicted_sse(b, 0.5, 0.03), rtol=1e-9)
