"""Batched replays (sysid.replay_batch): B replays of one recording stepped together as copies of the scene give,
per replay and channel, what separate ``ObservationModel.simulate`` calls give, to the solver tolerance; a replay
that diverges gives None and the others finish; replays a batch cannot take run serially; a fit and the
diagnosis's replays with the option give the answers they give without it."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.solver_config import SolverConfig
from sysid.diagnose.parallel import replay_many
from sysid.evidence import load_evidence
from sysid.fit import fit
from sysid.observation import ObservationModel
from sysid.replay_batch import batch_refusal, simulate_batch
from sysid.replay_trace import PREDICTABLE_CHANNELS, Resume
from tests.sysid.simbag import DT, PRESS_ONLY, PRESS_SLIDE, TRUE_PARAMS, make_recording

NEWTON_TOL = SolverConfig().tol_velocity * DT
"""The Newton tolerance as a displacement per replay step, m."""

SETS = ({"gel.youngs_modulus": 3.0e5},
        {"gel.youngs_modulus": 4.5e5, "friction.gel_sheet": 0.5},
        {"sheet.bending_stiffness": 0.012, "sensor.normal_offset": 5.0e-5})
"""Three replays: other gel modulus, modulus and friction, bending stiffness and a sensor offset (own controls)."""


def _model(bag, t_max=None) -> ObservationModel:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObservationModel(load_evidence(bag), dt=DT, t_max=t_max)


@pytest.fixture(scope="module")
def slide_model(tmp_path_factory):
    """The press and first slide of the card recording (16 steps of 10 ms: contact, slip)."""
    bag = make_recording(tmp_path_factory.mktemp("slide") / "bag", segments=PRESS_SLIDE[:2], seed=2)
    return _model(bag)


@pytest.fixture(scope="module")
def press_bag(tmp_path_factory):
    return make_recording(tmp_path_factory.mktemp("press") / "bag", segments=PRESS_ONLY, seed=1)


def _whitened_gap(model, a, b, channel) -> float:
    """Largest |a - b| of a channel's per-step values in units of its noise level."""
    sigma = model.sigma[channel]
    return float(np.max(np.abs(a.channel(channel) - b.channel(channel)) / sigma))


def test_a_batch_of_three_replays_equals_three_separate_replays(slide_model):
    model = slide_model
    alone = [model.simulate(p) for p in SETS]
    traces, report = simulate_batch(model, SETS)
    assert report.batched == 3 and report.batches == [3] and not report.serial and not report.resumed
    for got, ref in zip(traces, alone):
        np.testing.assert_array_equal(got.t_ns, ref.t_ns)
        for ch in ("markers_xyz", "sheet_points"):  # positions: within a few Newton tolerances over the replay
            assert np.max(np.abs(got.channel(ch) - ref.channel(ch))) <= 5.0 * NEWTON_TOL, ch
        for ch in PREDICTABLE_CHANNELS:  # every channel far below its noise: the same prediction to the fit
            assert _whitened_gap(model, got, ref, ch) < 0.25, ch
        assert got.step_totals.steps == ref.step_totals.steps == model.step_count
    # each copy got its own parameters and controls: the replays differ by far more than the tolerance
    for i, j in ((0, 1), (0, 2), (1, 2)):
        assert _whitened_gap(model, alone[i], alone[j], "wrench") > 2.0
        assert _whitened_gap(model, traces[i], traces[j], "wrench") > 2.0
    # the predictions aligned to the recording (replay_many's) are the separate replays' too
    many = replay_many(model, SETS, batched=True)
    for (trace, prediction), ref in zip(many, alone):
        for ch, values in model.predict(ref).items():
            assert np.max(np.abs(prediction[ch] - values) / model.sigma[ch]) < 0.25, ch


def test_a_replay_that_diverges_gives_none_and_the_others_finish(press_bag):
    model = _model(press_bag)
    model.simulation().solver.config.dt_halvings_on_failure = 0  # the separate replays retry no substep either
    sets = [{}, {"sheet.thickness": 1e-12}, {"gel.youngs_modulus": 4.5e5}]
    with pytest.raises(Exception, match="did not converge"):  # a card a picometre thick: Newton cannot follow it
        model.simulate(sets[1])
    traces, report = simulate_batch(model, sets)
    assert traces[1] is None
    assert list(report.resumed) == [1]  # failed in the batch, went on alone from its last good step, failed there
    for i in (0, 2):
        ref = model.simulate(sets[i])
        for ch in PREDICTABLE_CHANNELS:
            assert _whitened_gap(model, traces[i], ref, ch) < 0.25, (i, ch)
    assert [r is None for r in replay_many(model, sets, batched=True)] == [False, True, False]


def test_replays_a_batch_cannot_take_run_serially_with_the_reason(press_bag):
    model = _model(press_bag)
    start = model.simulate({}, keep_states=True)
    resume = Resume(step=2, state=start.states[2], prefix=start)
    sets = [{"gel.youngs_modulus": 4e5}, {"candidate.stiction": 0.5}, {"gel.youngs_modulus": 2e5}, {}]
    resumes = [None, None, None, resume]
    assert batch_refusal(model, sets[0]) is None and batch_refusal(model, sets[1], None).startswith("missing-physics")
    assert batch_refusal(model, {}, resume).startswith("a resumed replay")
    _, report = simulate_batch(model, [sets[0], sets[2], sets[3]], resumes=[None, None, resume])
    assert report.serial == {2: "a resumed replay (it starts from another replay's state)"} and report.batched == 2
    # through replay_many (candidates cleared between replays): the serial path's results, bit for bit
    batched = replay_many(model, sets, resumes=resumes, batched=True)
    serial = replay_many(model, sets, resumes=resumes)
    for i in (1, 3):
        np.testing.assert_array_equal(batched[i][0].wrench, serial[i][0].wrench)
    assert _whitened_gap(model, batched[1][0], start, "wrench") > 0.01  # the candidate's term acted
    np.testing.assert_array_equal(batched[3][0].wrench, start.wrench)  # the resumed nominal replay is the nominal
    # replays that differ in what the stacked copies share go to batches of their own
    _, report = simulate_batch(model, [{}, {"damping": 0.1}, {"gel.youngs_modulus": 2e5}, {"damping": 0.1}])
    assert sorted(report.batches) == [2, 2] and not report.serial
    # a series drive has no kinematic controls: serial
    model.set_drive_stiffness(2000.0)
    assert batch_refusal(model, {}).startswith("a replay through a series drive")
    with pytest.raises(ConfigError, match="batch_size"):
        simulate_batch(model, [{}, {}], batch_size=0)


def test_a_fit_with_batched_jacobians_gives_the_same_values(press_bag):
    """The finite-difference Jacobian's 2p replays as one batch: with cold replays on both sides (the batch takes no
    warm start), the fit reaches the same values (within 1e-6 of their 1-sigma) with the same number of replays."""
    true = TRUE_PARAMS["gel.youngs_modulus"]
    results = []
    for batched in (False, True):
        model = _model(press_bag)
        results.append(fit(model, ["gel.youngs_modulus", "friction.gel_sheet"],
                           initial={"gel.youngs_modulus": 2.0 * true, "friction.gel_sheet": 0.8},
                           jacobian="fd", max_nfev=6, batched=batched, warm_start=False))
    serial, batched = results
    assert serial.status == batched.status == "converged" and batched.sim_runs == serial.sim_runs
    for name in serial.names:  # measured: 2e-10 and 7e-10 sigma apart
        assert abs(batched.values[name] - serial.values[name]) < 1e-6 * serial.sigma[name], name
    assert batched.cost_final == pytest.approx(serial.cost_final, rel=1e-3)
    assert abs(serial.values["gel.youngs_modulus"] / true - 1.0) < 0.1


def _stiffer(modulus: float):
    """A diagnosis-like chain: a replay at ``modulus``, then one at a modulus scaled by its peak normal force."""
    first = yield {"gel.youngs_modulus": modulus}
    peak = float(np.max(np.abs(first[1]["wrench"][:, 2])))
    second = yield {"gel.youngs_modulus": modulus * (1.0 + peak / 10.0)}
    return peak, float(np.max(np.abs(second[1]["wrench"][:, 2])))


def test_the_diagnosis_scheduler_batches_each_round_and_gives_the_serial_results(press_bag, monkeypatch):
    from sysid.diagnose import parallel
    from sysid.diagnose.schedule import ReplayScheduler

    model = _model(press_bag)
    calls = []

    def counted(*args, **kwargs):
        calls.append(len(args[1]))
        return simulate_batch(*args, **kwargs)

    monkeypatch.setattr(parallel, "simulate_batch", counted)
    starts = (2.0e5, 3.0e5, 4.5e5)
    serial = ReplayScheduler(model).run([_stiffer(m) for m in starts])
    sched = ReplayScheduler(model, workers=2, batched=True)
    assert not sched.pooled
    batched = sched.run([_stiffer(m) for m in starts])
    assert calls == [3, 3]  # two rounds, each one batch of the three chains' replays
    sigma_z = model.sigma["wrench"][2]
    for got, ref in zip(batched, serial):
        assert np.max(np.abs(np.subtract(got, ref))) < 0.25 * sigma_z


def test_batches_of_a_given_or_automatic_size_chunk_the_replays(press_bag):
    model = _model(press_bag)
    sets = [{"gel.youngs_modulus": m} for m in (2.0e5, 3.0e5, 4.0e5)]
    alone = [model.simulate(p) for p in sets]
    traces, report = simulate_batch(model, sets, batch_size=2)
    assert report.batches == [2, 1]
    _, auto = simulate_batch(model, sets, batch_size="auto")
    sizing = model.batch_sizing  # measured on the first call (host memory per copy of probe batches), then kept
    assert sizing is not None and sizing.B >= 1 and sizing.per_copy_bytes["host"] > 0
    assert sum(auto.batches) == 3 and max(auto.batches) <= sizing.B
    for got, ref in zip(traces, alone):
        for ch in PREDICTABLE_CHANNELS:
            assert _whitened_gap(model, got, ref, ch) < 0.25, ch
