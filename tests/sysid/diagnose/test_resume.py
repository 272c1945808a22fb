"""Replays resumed from the nominal replay (sysid.diagnose.resume, ObservationModel.simulate(resume=)):
a plasticity replay shares the nominal steps before its yield angle is first exceeded, and the
resumed replay equals the full one."""

from __future__ import annotations

import dataclasses
import math
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from sim_core.errors import CalibrationError
from sysid.diagnose.candidates import hinge_angle_history
from sysid.diagnose.resume import MARGIN_STEPS, NominalResume
from sysid.diagnose.schedule import ReplayScheduler
from sysid.observation import Resume, SimTrace


def _trace(K: int, theta_bar: float = 0.0) -> SimTrace:
    states = [SimpleNamespace(step_index=k, hinge_theta_bar={"sheet": np.full(4, theta_bar)}) for k in range(K + 1)]
    z = np.zeros((K + 1, 2, 3))
    return SimTrace(np.arange(K + 1), z, z[..., :2], np.zeros((K + 1, 6)), z, 0.0, states=states)


def test_start_step_only_for_a_yield_angle_change_and_before_the_first_exceedance():
    angles = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.5, 0.4, 0.3])  # K = 8
    r = NominalResume({"sheet.bending_stiffness": 1.0}, _trace(8), angles)
    nominal = {"sheet.bending_stiffness": 1.0}
    # exceeded first at step 4 (0.4 > 0.35): steps 0..3 are shared, less the margin
    assert r.start_step({**nominal, "sheet.yield_angle": 0.35}) == 3 - MARGIN_STEPS
    res = r({**nominal, "sheet.yield_angle": 0.35})
    assert isinstance(res, Resume) and res.step == 3 - MARGIN_STEPS and res.state is r.trace.states[res.step]
    assert res.prefix.markers_xyz.shape[0] == res.step + 1
    # never exceeded: every step is the nominal one
    assert r.start_step({**nominal, "sheet.yield_angle": 0.6}) == 8
    # anything else changed as well, or instead, or a yield angle that is not a finite angle: from the start
    assert r.start_step({**nominal, "sheet.yield_angle": 0.35, "candidate.stiction": 0.1}) == 0
    assert r.start_step({"sheet.bending_stiffness": 1.1, "sheet.yield_angle": 0.35}) == 0
    assert r.start_step({"sheet.yield_angle": 0.35}) == 0
    assert r.start_step(nominal) == 0 and r(nominal) is None
    assert r.start_step({**nominal, "sheet.yield_angle": math.inf}) == 0
    # exceeded at once: nothing to share
    assert r.start_step({**nominal, "sheet.yield_angle": 0.05}) == 0
    # a plastic nominal sheet, or one bent at rest: the criterion does not hold
    assert NominalResume({"sheet.yield_angle": 0.5}, _trace(8), angles).start_step({"sheet.yield_angle": 0.35}) == 0
    assert NominalResume({}, _trace(8, theta_bar=0.1), angles).start_step({"sheet.yield_angle": 0.35}) == 0
    with pytest.raises(ValueError, match="angles"):
        NominalResume({}, _trace(8), angles[:-1])
    with pytest.raises(ValueError, match="states"):
        NominalResume({}, SimTrace(np.arange(2), *(np.zeros((2, 1, 3)),) * 2, np.zeros((2, 6)), np.zeros((2, 1, 3)), 0.0),
                      np.zeros(2))


class ResumingModel:
    """A replay is ``y = x``; records the resume it was given."""

    def simulate(self, params, resume=None):
        return SimpleNamespace(x=params["x"], resume=None if resume is None else resume.step)

    def predict(self, trace):
        return {"x": trace.x, "resume": trace.resume}


@pytest.mark.parametrize("workers", [1, 2])
def test_the_scheduler_hands_each_replay_its_resume(workers):
    with ReplayScheduler(ResumingModel(), workers) as sched:
        sched.resume = lambda p: Resume(int(p["x"]), None, None) if p["x"] > 1 else None

        def chain(xs):
            got = []
            for x in xs:
                got.append((yield {"x": x})[1]["resume"])
            return got

        assert sched.run([chain([1.0, 3.0]), chain([2.0])]) == [[None, 3], [2]]
        assert [r[1]["resume"] for r in sched.batch([{"x": 5.0}])] == [5]


def test_a_resumed_plasticity_replay_equals_the_full_one():
    """latency_s103 for 2.2 s: the sheet first bends past half its largest angle late in the press;
    the replay at that yield angle resumed from the nominal state differs from the full replay by
    round-off only (the plastic effect itself moves the markers by a good fraction of a pixel) and
    simulates only the steps after the shared ones."""
    from sysid.diagnose.engine import BagDiagnosis
    from sysid.diagnose.settings import Settings
    from tests.sysid.conftest import reference_bag

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = BagDiagnosis(reference_bag("latency_s103"), settings=Settings(arch="cpu", workers=1, t_max=2.2)).model
    nominal = model.simulate({}, keep_states=True)
    angles = hinge_angle_history(model, nominal.sheet_points)
    params = {"sheet.yield_angle": 0.5 * float(angles.max())}
    resume = NominalResume({}, nominal, angles)(params)
    K = model.step_count
    assert resume is not None and K // 2 < resume.step < K
    full = model.simulate(params)
    steps = []
    resumed = model.simulate(params, resume=resume, on_step=lambda k, n: steps.append(k))
    assert steps == list(range(resume.step + 1, K + 1))
    moved = np.abs(full.markers_uv - nominal.markers_uv).max()
    assert moved > 0.05
    for ch in ("markers_xyz", "markers_uv", "wrench", "sheet_points"):
        a, b = getattr(full, ch), getattr(resumed, ch)
        assert a.shape == b.shape
        assert np.abs(a - b).max() <= 1e-9 * max(np.abs(a).max(), 1e-12), ch
    with pytest.raises(CalibrationError, match="state is of step"):
        model.simulate(params, resume=Resume(resume.step + 1, resume.state, nominal))
    with pytest.raises(CalibrationError, match="cannot keep"):
        model.simulate(params, resume=resume, keep_positions=True)


def test_shared_steps_before_a_yield_angle_is_exceeded_and_before_a_release_time():
    from sysid.diagnose.resume import elastic_steps, steps_before

    angles = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.5, 0.4, 0.3])  # K = 8
    assert elastic_steps(angles, 0.35) == 3 - MARGIN_STEPS  # 0.4 at step 4 exceeds it
    assert elastic_steps(angles, 0.6) == 8 and elastic_steps(angles, 0.05) == 0
    assert elastic_steps(angles, math.inf) == 0 and elastic_steps(angles, -0.1) == 0
    t = 0.01 * np.arange(9)
    # a setting acting from 0.045 s on changes the steps from 0.05 s (step 5) on: steps 0..4 shared, less the margin
    assert steps_before(t, 0.045) == 4 - MARGIN_STEPS
    assert steps_before(t, 0.0) == 0 and steps_before(t, 1.0) == 8 - MARGIN_STEPS


@pytest.fixture(scope="module")
def plastic_card(tmp_path_factory):
    """The benchmark card recorded by this simulator with a yield angle of 0.05 rad (press, slide, lift,
    wait; the card keeps a buckle), as an observation model of the scene without plasticity."""
    from sysid.evidence import load_evidence
    from sysid.observation import ObservationModel
    from tests.sysid.simbag import (PRESS_SLIDE, TRUE_PARAMS, add_noise, scene_with, simulate_streams,
                                    targets_from_segments, write_bag)

    scene = scene_with(TRUE_PARAMS)
    lift_and_wait = (((0.0, 0.0, 0.004), 6), ((0.0, 0.0, 0.0), 22))
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), PRESS_SLIDE + lift_and_wait)
    streams = add_noise(simulate_streams(scene, {**TRUE_PARAMS, "sheet.yield_angle": 0.05}, targets), seed=3)
    bag = write_bag(tmp_path_factory.mktemp("plastic") / "bag", scene, streams)
    return ObservationModel(load_evidence(bag, include_image="auto"), dt=float(scene["dt"]), arch="cpu")


def test_yield_search_replays_start_from_the_first_one_and_equal_full_replays(plastic_card):
    """A replay at a yield angle takes the steps of a kept replay (the search's first one) for as long as
    that one is elastic and the angle is not exceeded, and equals the replay simulated from the start to
    round-off. A kept replay that is plastic from its first step on shares nothing."""
    from sysid.diagnose.resume import YIELD_PARAMETER, YieldReplays, elastic_steps

    model = plastic_card
    elastic = model.simulate({YIELD_PARAMETER: 1e3})  # never exceeded
    angles = hinge_angle_history(model, elastic.sheet_points)
    y1, y2 = 0.3 * float(angles.max()), 0.6 * float(angles.max())
    replays = YieldReplays(model, {})
    first = replays(y1)  # plastic from the first exceedance of y1 on
    steps = []
    model_simulate = model.simulate

    def counting(params, **kwargs):
        return model_simulate(params, on_step=lambda k, n: steps.append(k), **kwargs)

    model.simulate = counting
    try:
        second = replays(y2)  # shares the first's steps before y1 is exceeded
    finally:
        del model.simulate
    # shared: the states before the first one the plastic update changed (before the elastic replay
    # first exceeds y1); only the steps after them are simulated
    first_over = int(np.flatnonzero(angles > y1)[0])
    k = replays.shared_steps[1]
    assert replays.shared_steps[0] == 0 and elastic_steps(angles, y1) <= k < first_over
    assert steps == list(range(k + 1, model.step_count + 1))
    full = np.asarray(model.predict(model.simulate({YIELD_PARAMETER: y2}))["sheet_points"], dtype=float)
    assert np.abs(full - first).max() > 1e-4  # the smaller angle leaves a larger set
    assert np.abs(second - full).max() <= 1e-9 * np.abs(full).max()
    # a kept replay whose rest angles moved from its first step on (plastic at once): nothing is shared
    states = [SimpleNamespace(step_index=j, hinge_theta_bar={"sheet": np.full(4, 0.01 * j)})
              for j in range(model.step_count + 1)]
    plastic = YieldReplays(model, {}, base=dataclasses.replace(elastic, states=states))
    assert plastic.base is not None and plastic.elastic_until == 0


class _HereWorker:
    """A worker that makes the submitted replay in this process when it is collected (the requests and
    replies of :class:`sysid.diagnose.probe_worker.ProbeWorker`, without its process)."""

    def __init__(self, model):
        self.model, self.requests, self._request = model, [], None

    def submit(self, nominal, params, resume=None) -> bool:
        if self._request is not None:
            return False
        self._request = (dict(nominal), dict(params), resume)
        self.requests.append(self._request)
        return True

    def collect(self):
        nominal, params, resume = self._request
        self._request = None
        self.model.set_nominal(nominal)
        return dataclasses.replace(self.model.simulate(params, resume=resume), states=None)


def test_a_prefetched_yield_replay_is_made_by_the_worker_from_the_kept_replay(plastic_card):
    """:meth:`YieldReplays.prefetch` asks the worker for the replay this process would make (resumed from the
    kept replay at the same step); it is taken only for that very angle, and equals the replay made here."""
    from sysid.diagnose.resume import YIELD_PARAMETER, YieldReplays

    model = plastic_card
    elastic = model.simulate({YIELD_PARAMETER: 1e3}, keep_states=True)
    angles = hinge_angle_history(model, elastic.sheet_points)
    y1, y2 = 0.3 * float(angles.max()), 0.6 * float(angles.max())
    here = YieldReplays(model, {}, base=elastic)
    worker = _HereWorker(model)
    replays = YieldReplays(model, {}, base=elastic, worker=worker, nominal={})
    replays.prefetch(y2)
    replays.prefetch(y1)  # one at a time: not asked
    assert len(worker.requests) == 1
    nominal, params, resume = worker.requests[0]
    assert params == {YIELD_PARAMETER: y2} and resume.step == here._start(y2) > 0
    first = replays(y1)  # made here
    assert replays.prefetched == [] and np.array_equal(first, here(y1))
    second = replays(y2)  # the worker's
    assert replays.prefetched == [y2] and np.array_equal(second, here(y2))
    assert replays.shared_steps == here.shared_steps
    # without a kept replay nothing is prefetched (the search's first replay becomes the kept one here)
    alone = YieldReplays(model, {}, worker=worker, nominal={})
    alone.prefetch(y2)
    assert len(worker.requests) == 1
