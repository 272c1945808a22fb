"""The fit's replays are functions of their parameters only: cold by default (``FitOptions.warm_start`` False).

Warm-started from the best replay so far (the default until session 54), a replay kept the warming replay's card
where it rests on the table under static friction: nominal_s101 (the reference engine's press-slide) at the scene's
values warmed from a +30 % replay moved its sheet points by 0.117 whitened RMS (0.25 mm at most) from the cold
replay at the same values, so the fit's objective depended on its start (docs/benchmarks_log.md, session 53,
s53-49start; session 54, s54-49time). Warming only the pad and gel from the other replay, the card from its own last
step, was tried and is not safe: a guess mixing two replays' configurations sent the card 0.85 mm off (the
kinematic replay to 2 s below).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from sysid.evidence import load_evidence
from sysid.fit import FitProblem, parameter_spec
from sysid.fit_recording import FitOptions
from sysid.observation import ObservationModel
from tests.sysid.conftest import reference_bag

SCENE = {"sheet.bending_stiffness": 0.007418, "gel.youngs_modulus": 3.0e5, "friction.gel_sheet": 0.8}
"""nominal_s101's scene values (its engine's)."""

T_MAX = 2.0
"""Seconds of the recording replayed (kinematic): the press, the dwell and the slide's start, where the gel drags
the card (200 steps)."""


@pytest.fixture(scope="module")
def residuals():
    """Whitened residuals at the scene's values: a cold replay on its own, a cold one after a replay at +30 %, and
    one warm-started from that replay (the fit's path from a +30 % start to the scene's values), with the model."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(reference_bag("nominal_s101"), include_image="auto"), dt=0.01,
                                 t_max=T_MAX, arch="cpu")
    specs = [parameter_spec(n, v) for n, v in SCENE.items()]
    u0, u_off = np.zeros(3), np.full(3, np.log(1.3))
    alone = FitProblem(model, specs).residual(u0)
    out = {"alone": alone}
    for name, warm in (("cold", False), ("warm", True)):
        problem = FitProblem(model, specs, warm_start=warm)
        problem.residual(u_off)
        assert (model.warm_start is not None) == warm
        out[name] = problem.residual(u0)
        model.warm_start = None
    return model, out


def _rms(model: ObservationModel, a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Whitened RMS of the difference of two residual vectors, per channel (noise units)."""
    return {ch: float(np.sqrt(np.mean((a[s] - b[s]) ** 2))) for ch, s in model.channel_slices().items()}


def test_thinshell_sysid_replays_cold_by_default():
    assert FitOptions().warm_start is False


def test_a_cold_replay_after_another_gives_the_lone_replays_residuals(residuals):
    """A cold replay at the scene's values after one at +30 % gives the lone cold replay's residuals to 1e-9 noise
    units (the same steps from the same state: bit for bit in practice)."""
    model, out = residuals
    assert all(v < 1e-9 for v in _rms(model, out["cold"], out["alone"]).values())


def test_a_warm_started_replay_keeps_the_other_replays_card(residuals):
    """The warm start (``--warm-start``, the default before session 54) fails the same check on the card: its sheet
    points 0.19 whitened RMS from the lone replay (0.05 asserted), and the cost moves with them."""
    model, out = residuals
    diff = _rms(model, out["warm"], out["alone"])
    assert diff["sheet_points"] > 0.05, diff
    cost_alone, cost_warm = 0.5 * float(out["alone"] @ out["alone"]), 0.5 * float(out["warm"] @ out["warm"])
    assert abs(cost_warm - cost_alone) > 1e-3 * cost_alone, (cost_alone, cost_warm)
