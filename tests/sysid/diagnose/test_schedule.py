"""Pipelined replay chains (sysid.diagnose.schedule): same results whatever the workers and the
finishing order, divergences handed to the chain, worker errors named, workers kept between runs."""

from __future__ import annotations

import os
import time
from types import SimpleNamespace

import numpy as np
import pytest

from sim_core.errors import CalibrationError, SimulationDivergedError
from sysid.diagnose import engine
from sysid.diagnose.candidates import PhysicsParameterCandidate
from sysid.diagnose.schedule import ReplayScheduler, _advance, _start, run_in_rounds


class FakeModel:
    """A replay is ``y = 2 x`` after ``x`` ms (later sets finish first); ``x < 0`` diverges,
    ``x == 13`` raises a configuration error; each process counts its replays."""

    def __init__(self) -> None:
        self.count = 0

    def simulate(self, params):
        x = params["x"]
        if x == 13:
            raise ValueError("x = 13 is outside its physical range")
        if x < 0:
            raise SimulationDivergedError("diverged at step 3")
        time.sleep(0.001 * x)
        self.count += 1
        return SimpleNamespace(pid=os.getpid(), count=self.count)

    def predict(self, trace):
        return {"pid": trace.pid, "count": trace.count}


def _halving(start: float, steps: int):
    """A chain whose next request depends on the previous replay: x, x / 2, ... (None: diverged)."""
    x, seen = start, []
    for _ in range(steps):
        rep = yield {"x": x}
        if rep is None:
            seen.append(None)
            x = abs(x)
            continue
        seen.append(x)
        x = x / 2.0
    return seen


def _results(workers: int) -> list:
    with ReplayScheduler(FakeModel(), workers) as sched:
        return sched.run([_halving(x, n) for x, n in ((40.0, 3), (2.0, 1), (-8.0, 3), (30.0, 2), (1.0, 0))])


def test_chain_results_do_not_depend_on_workers_or_finishing_order():
    serial = _results(1)
    assert serial == [[40.0, 20.0, 10.0], [2.0], [None, 8.0, 4.0], [30.0, 15.0], []]
    assert _results(2) == serial
    # by rounds: the same results, the k-th replays of every chain in round k
    rounds = []

    def batch(sets):
        rounds.append([p["x"] for p in sets])
        return [None if p["x"] < 0 else (None, {}) for p in sets]

    assert run_in_rounds([_halving(x, n) for x, n in ((40.0, 3), (2.0, 1), (-8.0, 3))], batch) == \
        [[40.0, 20.0, 10.0], [2.0], [None, 8.0, 4.0]]
    assert rounds == [[40.0, 2.0, -8.0], [20.0, 8.0], [10.0, 4.0]]


def test_a_chain_is_fed_as_soon_as_its_replay_returns():
    """A short chain's second replay starts before a long first replay of another chain ends."""
    order = []

    def chain(name, xs):
        for x in xs:
            rep = yield {"x": x}
            order.append((name, x, rep[1]["count"]))
        return name

    with ReplayScheduler(FakeModel(), 2) as sched:
        assert sched.run([chain("slow", [300.0]), chain("fast", [1.0, 2.0, 3.0])]) == ["slow", "fast"]
    assert [o[0] for o in order] == ["fast", "fast", "fast", "slow"]
    assert sched.replays == 4


def test_priority_orders_the_first_replays_but_not_the_results():
    """Two workers, three equal one-replay chains: the two of lowest priority start at once, the third
    only when one of them returns (so it finishes last); results are as without priorities."""

    def chains():
        return [_halving(60.0 + 1e-6 * k, 1) for k in range(3)]

    with ReplayScheduler(FakeModel(), 2) as sched:
        plain = sched.run(chains())
    assert sched.log[-1]["chain"] == 2
    with ReplayScheduler(FakeModel(), 2) as sched:
        assert sched.run(chains(), priority=[(1, 0), (0, 1), (0, 2)]) == plain
    assert sched.log[-1]["chain"] == 0
    with ReplayScheduler(FakeModel(), 2) as sched, pytest.raises(ValueError, match="2 priorities for 3 chains"):
        sched.run(chains(), priority=[0, 1])


def test_workers_persist_between_runs_and_keep_their_state():
    with ReplayScheduler(FakeModel(), 2) as sched:
        first = sched.batch([{"x": 5.0}, {"x": 5.0}, {"x": 5.0}, {"x": 5.0}])
        second = sched.batch([{"x": 1.0}, {"x": 1.0}])
    pids = {r[1]["pid"] for r in first + second}
    assert len(pids) <= 2 and os.getpid() not in pids
    # the workers' models count on from the first run: nothing was forked again
    assert sum(r[1]["count"] for r in second) >= 3
    assert sched.replays == 6


def test_a_single_replay_before_the_pool_runs_in_this_process():
    with ReplayScheduler(FakeModel(), 2) as sched:
        (rep,) = sched.batch([{"x": 1.0}])
        assert rep[1]["pid"] == os.getpid() and sched._pool is None


def test_a_prefetched_replay_is_taken_by_the_chain_that_asks_for_it():
    """Prefetch: with one of two workers reserved (for this process's nominal replay), one set is
    replayed ahead on the pool; the chain asking for it takes that replay (no second one), with the
    same results as without prefetching; a prefetched set no chain asks for is only counted; without
    a pool (one worker) nothing is prefetched."""
    chains = lambda: [_halving(40.0, 2), _halving(6.0, 1)]  # noqa: E731 - two fresh chains per run
    with ReplayScheduler(FakeModel(), 2) as sched:
        assert sched.prefetch([{"x": 6.0}, {"x": 40.0}, {"x": 99.0}]) == 1
        assert sched.replays == 1 and list(sched._prefetched) == [(("x", 6.0),)]
        replays = []

        def watching(name, xs):
            for x in xs:
                replays.append((yield {"x": x}))
            return name

        assert sched.run(chains()) == [[40.0, 20.0], [6.0]]
        assert sched.replays == 3 and not sched._prefetched
        assert sched.run([watching("new", [3.0])]) == ["new"] and sched.replays == 4
        assert replays[0][1]["pid"] != os.getpid()
    with ReplayScheduler(FakeModel(), 2) as sched:
        assert sched.prefetch([{"x": 7.0}]) == 1
        assert sched.run(chains()) == [[40.0, 20.0], [6.0]]
        assert sched.replays == 4  # the unused prefetch + 3
    with ReplayScheduler(FakeModel(), 1) as sched:
        assert sched.prefetch([{"x": 6.0}]) == 0
        assert sched.replays == 0 and sched._pool is None


@pytest.mark.parametrize("workers", [1, 2])
def test_a_parameter_set_is_replayed_once(workers):
    """Replays are deterministic: a set asked for again (by the same or another chain, in a later
    run, or by batch) and a set handed in with remember() are answered without a replay, with the
    very replay (diverged ones too)."""
    seen = []

    def chain(xs):
        for x in xs:
            seen.append((yield {"x": x}))
        return len(seen)

    with ReplayScheduler(FakeModel(), workers) as sched:
        nominal = (SimpleNamespace(pid=-1, count=0), {"pid": -1, "count": 0})
        sched.remember({"x": 0.0}, nominal)
        sched.run([chain([1.0, -2.0, 1.0, 0.0])])
        assert sched.replays == 2 and sched.reused == 2
        assert seen[2] is seen[0] and seen[1] is None and seen[3] is nominal
        sched.run([chain([-2.0, 4.0])])
        assert seen[4] is None and sched.replays == 3 and sched.reused == 3
        again = sched.batch([{"x": 4.0}, {"x": 0.0}, {"x": 5.0}])
        assert again[0] is seen[5] and again[1] is nominal and again[2][1]["count"] >= 1
        assert sched.replays == 4 and sched.reused == 5
        assert len(sched.log) == (0 if workers == 1 else 4)  # the pool logs its replays (one worker: none)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_worker_error_names_the_parameter_set(workers):
    expect = (ValueError, CalibrationError)[workers - 1]
    sched = ReplayScheduler(FakeModel(), workers)
    with pytest.raises(expect, match="13 is outside its physical range") as info:
        sched.run([_halving(20.0, 2), _halving(13.0, 1)])
    if workers == 2:
        assert "x=13" in str(info.value) and "ValueError" in str(info.value)
        assert sched._pool is None  # shut down, queued replays dropped
    sched.close()


def _wrench_bare(workers: int):
    T = 40
    steps = np.arange(T, dtype=np.int64) * 10_000_000
    model = SimpleNamespace(sigma={"wrench": np.full(6, 0.5)}, step_times_ns=steps, data=lambda ch: np.zeros((T, 6)),
                            evidence=SimpleNamespace(t_ns={"wrench": steps}))
    d = engine.BagDiagnosis.__new__(engine.BagDiagnosis)
    d.model, d.settings, d.notes, d.timings = model, engine.Settings(workers=workers), [], {}
    d.tested = ("wrench",)
    return d


class WrenchModel:
    """Probe replays of two candidates: a response linear in beta; stiction below 0.1 diverges."""

    gain = {"damping": 1e-5, "stiction": 20.0, "adhesion": 0.5}  # noise units 2e-5, 40, 1 per beta

    def simulate(self, params):
        name = next(k.split(".")[1] for k in params if k.startswith("candidate."))
        beta = params[f"candidate.{name}"]
        if name == "stiction" and beta < 0.1:
            raise SimulationDivergedError("stiction probe diverged")
        time.sleep(0.02 if name == "damping" else 0.0)
        return self.gain[name] * beta

    def predict(self, trace):
        return {"wrench": np.zeros((40, 6)) + trace}


def _probe_phase(workers: int):
    d = _wrench_bare(workers)
    d._scheduler = ReplayScheduler(WrenchModel(), workers)
    ctx = SimpleNamespace(prediction={"wrench": np.zeros((40, 6))}, params={})
    probes = [PhysicsParameterCandidate("damping", "candidate.damping", 1.0),
              PhysicsParameterCandidate("stiction", "candidate.stiction", 0.5),
              PhysicsParameterCandidate("adhesion", "candidate.adhesion", 4.0)]
    try:
        out = d._probe_all(ctx, probes)
    finally:
        d._scheduler.close()
    return out, [c.probe_beta for c in probes], d.notes, d.timings["replays"]


def test_probe_phase_gives_the_same_probes_and_notes_with_one_and_two_workers():
    out1, betas1, notes1, n1 = _probe_phase(1)
    out2, betas2, notes2, n2 = _probe_phase(2)
    assert betas1 == betas2 and notes1 == notes2 and n1 == n2
    for k in out1:
        assert np.array_equal(out1[k][1]["wrench"], out2[k][1]["wrench"])
    # damping grew twice (round-off probe), stiction's shrink (to 0.025) diverged and kept its first
    # size, adhesion (4 noise units, within [0.5, 8]) was not re-probed
    assert betas1[1] == pytest.approx(0.5) and betas1[0] > 1.0 and betas1[2] == pytest.approx(4.0)
    assert sum("rescaled probe diverged" in n for n in notes1) == 1
    # the notes come in batch order: first calibration round of every candidate, then the second
    assert [n.split(":")[0] for n in notes1] == ["damping", "stiction", "stiction", "damping"]


def _without_timings(report: dict) -> dict:
    extra = {k: v for k, v in report["extra"].items() if k != "timings_s"}
    extra["settings"] = {k: v for k, v in extra["settings"].items() if k != "workers"}
    return {**report, "extra": extra}


def _diagnose(bag, workers: int, speculate: bool, monkeypatch, names, **settings) -> dict:
    monkeypatch.setattr(engine.BagDiagnosis, "speculative_refits", speculate)
    return engine.BagDiagnosis(bag, settings=engine.Settings(arch="cpu", workers=workers, **settings),
                               candidate_names=names).run()


@pytest.mark.parametrize("t_max, names, replays", [
    (0.3, ("latency", "stiction", "damping"), 2),
    pytest.param(1.2, None, 10, marks=pytest.mark.slow)])
def test_a_diagnosis_gives_the_same_report_with_one_and_two_workers(t_max, names, replays, monkeypatch):
    """The pipelined scheduler (persistent pool, chains, speculative refits) reports exactly what
    barrier rounds in one process report: same probes, notes, tests, refits and decisions, bit for bit."""
    from tests.sysid.conftest import reference_bag

    bag = reference_bag("latency_s103")
    pipelined = _diagnose(bag, 2, True, monkeypatch, names, t_max=t_max)
    rounds = _diagnose(bag, 1, False, monkeypatch, names, t_max=t_max)
    assert pipelined["extra"]["timings_s"]["replays"] == rounds["extra"]["timings_s"]["replays"] >= replays
    assert _without_timings(pipelined) == _without_timings(rounds)


def test_early_refits_only_for_candidates_significant_whatever_the_others_give():
    """A single candidate is refitted from its own chain when p <= alpha / tests_bound; a family waits
    for its last member, keeps the one with the largest statistic and multiplies its p by the family
    size (as select_family_members and Holm would)."""
    d = _wrench_bare(1)
    d.settings.secant = False
    ctx = SimpleNamespace(prediction={"wrench": np.zeros((40, 6))}, params={}, channels=("wrench",))
    strong = PhysicsParameterCandidate("stiction", "candidate.stiction", 0.5)
    weak = PhysicsParameterCandidate("adhesion", "candidate.adhesion", 0.05)
    fam = [PhysicsParameterCandidate("gel_viscoelasticity", "candidate.gel_viscoelasticity", 0.5,
                                     settings={"candidate.gel_viscoelasticity.tau": tau}, family_size=2)
           for tau in (0.1, 0.3)]
    # statistic and p-value of each member's (single) test; bound 10 tests -> alpha / 10 = 1e-3
    figures = {"stiction": (50.0, 1e-4), "adhesion": (9.0, 2e-3),
               fam[0].key: (30.0, 4e-4), fam[1].key: (40.0, 3e-4)}

    def tests(ctx_, c, sig, J_theta, notes):
        stat, p = figures[c.key]
        return [{"effect": c.name, "key": c.key, "channel": "wrench",
                 "result": SimpleNamespace(statistic=stat, p_value=p)}]

    refitted = []

    def linearised(ctx_, c, sig, J_theta, train, theta):
        refitted.append(c.key)
        return {c.parameter: 1.0}, SimpleNamespace(beta=np.array([1.0]), prediction={}, params={}, sim_params={})

    d._candidate_tests, d._linearised_refit = tests, linearised
    d._probe_if_better = lambda *a, **k: None
    spec = {"J_theta": {}, "train": {}, "theta": {}, "refits": {}, "family_probes": {}, "tests_bound": 10,
            "members": {"stiction": [strong], "adhesion": [weak], "gel_viscoelasticity": fam}}
    probe = (None, {"wrench": np.ones((40, 6))})
    replays = []

    def drive(c):
        chain = d._speculative_refit(ctx, c, probe, spec)
        request = next(chain, None)
        while request is not None:
            replays.append(request[1])
            try:
                request = chain.send(probe)
            except StopIteration:
                return

    drive(strong)
    drive(weak)                   # p 2e-3 > alpha / 10: waits for Holm over every test
    drive(fam[0])                 # first member in: nothing yet
    assert refitted == ["stiction"] and replays == ["refit"]
    drive(fam[1])                 # last member: keeps tau 0.3 (S 40), p 2 x 3e-4 <= 1e-3
    assert refitted == ["stiction", fam[1].key] and replays == ["refit", "refit"]
    assert set(spec["refits"]) == {"stiction", "gel_viscoelasticity"}
    assert spec["refits"]["gel_viscoelasticity"][0] == fam[1].key
    # a family whose kept member's p times the family size exceeds alpha / bound waits
    figures[fam[1].key] = (40.0, 6e-4)
    spec["refits"].clear(), spec["family_probes"].clear(), refitted.clear()
    drive(fam[1])
    drive(fam[0])
    assert refitted == [] and spec["refits"] == {}


class CompilingModel(FakeModel):
    """:class:`FakeModel` whose replays need a "kernel" compiled in the process before the fork:
    a child that would compile it itself raises (Taichi hangs there instead)."""

    def __init__(self) -> None:
        super().__init__()
        self.compiled_in = None

    def compile_kernels(self) -> float:
        self.compiled_in = os.getpid()
        return 0.0

    def simulate(self, params):
        if self.compiled_in is None:
            raise RuntimeError("kernel compiled inside a forked worker")
        return super().simulate(params)


def test_pools_compile_the_kernels_before_they_fork():
    from sysid.diagnose.parallel import replay_many

    model = CompilingModel()
    with ReplayScheduler(model, 2) as sched:
        assert sched.run([_halving(x, n) for x, n in ((4.0, 2), (2.0, 2), (1.0, 2))]) == [[4.0, 2.0], [2.0, 1.0], [1.0, 0.5]]
    assert model.compiled_in == os.getpid()
    model = CompilingModel()
    out = replay_many(model, [{"x": 1.0}, {"x": 2.0}], workers=2)
    assert [rep[1]["pid"] != os.getpid() for rep in out] == [True, True]  # replayed in the workers
    assert model.compiled_in == os.getpid()


def test_a_refit_whose_replay_diverged_asks_for_no_secant_replay():
    """The secant parabola needs the training SSE at the refitted beta: after a diverged refit
    replay the chain ends (it used to replay a secant point from the nominal SSE put in its place);
    after one that replays, the parabola's minimiser is replayed."""
    from sysid.diagnose import candidates as cands

    d = _wrench_bare(1)
    d._probe_out = {}
    d.model.channels = ("wrench",)
    c = PhysicsParameterCandidate("stiction", "candidate.stiction", 0.5)
    ones = np.ones((40, 6))
    ctx = SimpleNamespace(prediction={"wrench": ones}, params={})
    probe = (None, {"wrench": 0.0 * ones})  # the data (zeros) exactly: SSE 0 at the probe beta
    train = {"wrench": np.ones(40, bool)}

    def chain(refit_replay):
        out = {c.name: cands.Refit(np.array([0.9]), {"stiction": 0.9}, {}, {"candidate.stiction": 0.9})}
        notes = []
        gen = d._refit_chain(ctx, c, {"candidate.stiction": 0.9}, out, train, {}, 0, notes, probe)
        replies, tags = iter([refit_replay, None]), []
        more, request = _start(gen)
        while more:
            tags.append(request[1])
            more, request = _advance(gen, next(replies))
        return tags, notes

    tags, notes = chain(None)
    assert tags == ["refit"] and notes == [((0, 0, 0), "stiction: refit replay diverged")]
    tags, notes = chain((None, {"wrench": 0.6 * ones}))
    assert tags == ["refit", "secant"] and notes == []
