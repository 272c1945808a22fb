"""The sensor-chain signature tests on the reference recordings of the independent engine: where the
gel is free of the sheet, read off the recording alone (no replay)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import yaml

from sysid.diagnose.signatures.base import Recording
from sysid.diagnose.signatures.null import STATISTIC_THRESHOLD, default_thresholds
from sysid.diagnose.signatures.sensor import force_bias_test, free_gel_rows, sheet_on_gel_rows
from sysid.evidence import load_evidence
from tests.sysid.conftest import reference_bag

CAMERA = (300.0, 300.0, 160.0, 120.0, 0.025)


@lru_cache(maxsize=None)
def recording(bag: Path) -> Recording:
    """The recording as the signature tests read it, without a replay."""
    ev = load_evidence(bag, include_image=False)
    t = {ch: (np.asarray(ev.t_ns[ch], dtype=np.int64) - ev.start_ns) * 1e-9 for ch in ev.channels_present
         if ch != "image"}
    data = {ch: np.asarray(ev.values(ch), dtype=float) for ch in t}
    sigma = {ch: np.asarray(ev.noise[ch], dtype=float) for ch in t if ch in ev.noise}
    return Recording(t=t, data=data, prediction=None, sigma=sigma, camera=CAMERA, name=bag.name)


def tack_window(bag: Path) -> tuple[float, float]:
    """The generator's tack on / off times of a lift-and-fold (its ``labels.yaml``), s."""
    motion = yaml.safe_load((bag.parent / "labels.yaml").read_text())[bag.name]["motion"]
    return float(motion["t_tack_on"]), float(motion["t_tack_off"])


@pytest.mark.parametrize("name", ["plastic_s102", "nominal_s109"])
def test_a_sheet_hanging_on_the_tacked_gel_is_not_free_gel(name):
    """Lift-and-fold: from the tack to the peel the card hangs on the gel (the generator's bonds);
    the recorded markers' whole-grid displacement is near rest in the hold, the sheet is not."""
    bag = reference_bag(name)
    rec = recording(bag)
    t_on, t_off = tack_window(bag)
    tw = rec.t["wrench"]
    on = sheet_on_gel_rows(rec, "wrench")
    hold = (tw >= t_on) & (tw <= t_off)
    # the tack forms while the pad presses the card (a pressed sheet lies at the gel's face, within
    # its noise of it); from the lift to the peel the card hangs on the gel
    assert on[hold].mean() > 0.95
    lifted = hold & (tw >= t_on + 0.5 * (t_off - t_on))
    assert on[lifted].all()
    # before the press (the pad hovers over the resting card) and at the end (the card dropped, the
    # pad lifted) the sheet is off the gel
    assert not on[tw <= 0.3].any()
    assert not on[tw >= tw[-1] - 0.3].any()
    free = free_gel_rows(rec)
    assert not free[hold].any()
    assert free[tw <= 0.3].all() and free[tw >= tw[-1] - 0.3].all()


def test_a_sheet_that_only_slid_is_off_the_lifted_gel():
    """Press-and-slide: the card is pressed and dragged in its plane; once the pad lifts, the card
    lies where it slid to, and the gel is free again (the force-bias test's free rows after the lift)."""
    rec = recording(reference_bag("nominal_s101"))
    tw = rec.t["wrench"]
    on = sheet_on_gel_rows(rec, "wrench")
    free = free_gel_rows(rec)
    assert not on[tw <= 0.3].any() and not on[tw >= tw[-1] - 0.3].any()
    assert free[tw >= tw[-1] - 0.3].all()


def test_force_bias_named_from_the_recording_alone():
    """force_bias_s107 (offset, drift and wobble on the wrench): the free rows before the press and
    after the lift carry it far beyond both thresholds; the reference lifts with nothing concealed
    stay below the statistic threshold now that their hold is not read as free gel."""
    rec = recording(reference_bag("force_bias_s107"))
    r = force_bias_test(rec)
    th = default_thresholds(rec)
    assert r.statistic > 10 * th.statistic["force_bias"] and r.effect_size > 2 * th.effect_size["force_bias"]
    for name in ("plastic_s102", "nominal_s109"):
        assert force_bias_test(recording(reference_bag(name))).statistic < STATISTIC_THRESHOLD


def test_the_gel_relaxes_after_a_release_not_after_a_marker_noise_excursion():
    """A contact from 1.0 to 2.0 s whose markers return to rest at 2.2 s, and two single samples
    of marker noise off rest at 0.4 and 3.0 s: only the release is followed by RELAXATION_S of
    relaxing gel, counted from the markers' return (the end of the gel's recorded deformation)."""
    from sysid.diagnose.signatures.sensor import RELAXATION_S, relaxing_rows

    t = np.arange(0.0, 4.0, 0.005)
    loaded = (t >= 1.0) & (t <= 2.0)
    engaged = (t >= 1.0) & (t <= 2.2) | np.isclose(t, 0.4) | np.isclose(t, 3.0)
    relaxing = relaxing_rows(t, engaged, loaded)
    assert np.array_equal(relaxing, (t > 2.2 + 1e-9) & (t <= 2.2 + RELAXATION_S + 1e-9))
    # without a known load every run of markers off rest is a release
    alone = relaxing_rows(t, engaged, engaged)
    assert alone[(t > 0.4) & (t <= 0.4 + RELAXATION_S - 1e-9)].all()
    assert alone[(t > 3.0) & (t < 3.0 + RELAXATION_S)].all()
