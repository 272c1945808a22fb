"""Batched evaluation (sim_core.optim.evaluators.BatchedEvaluator): a CMA-ES run whose populations are
evaluated as one batch of scene copies gives the same episodes and best reward as serial evaluation:
exactly when the copies are stepped one after another, to the Newton tolerance in lockstep (the
default; at a tight tolerance the scores agree to 1e-6)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.optim.actions import ControlPointDecoder
from sim_core.optim.evaluators import BatchedEvaluator, SerialEvaluator, make_evaluator
from sim_core.optim.search import ActionSpace, new_state, optimise
from sim_core.solver_config import SolverConfig
from tests.sim_core.optim.task_support import folding_task
from tests.support.emulated_cuda import emulate_cuda


TIGHT = SolverConfig(dt_halvings_on_failure=0, tol_velocity=1e-7)
"""Newton settings at which a lockstep batch and separate runs agree to about 1e-8 in the rewards."""


def test_batched_cma_population_matches_serial_evaluation():
    task = folding_task(horizon=3)
    decoder = ControlPointDecoder.for_task(task, control_points=1)
    serial = optimise(new_state("cma", 8, seed=7, sigma=2.5, population=4),
                      ActionSpace(decoder, SerialEvaluator(task, solver_config=TIGHT), task))
    evaluator = make_evaluator(task, batched=True, solver_config=TIGHT)
    assert evaluator.solver_config.lockstep  # the population is one lockstep batch
    batched = optimise(new_state("cma", 8, seed=7, sigma=2.5, population=4), ActionSpace(decoder, evaluator, task))
    assert batched.best_reward == pytest.approx(serial.best_reward, rel=1e-6)
    np.testing.assert_allclose([h.score for h in batched.history], [h.score for h in serial.history], rtol=1e-6)
    assert len({h.reward for h in serial.history}) > 1  # the candidates differ


def test_sequential_batch_matches_serial_evaluation_exactly():
    task = folding_task(horizon=2)
    rng = np.random.default_rng(3)
    actions = [rng.uniform(-1.0, 1.0, (2, task.action_dim)) * 0.5 * (task.action_high - task.action_low) / 2
               for _ in range(3)]
    want = SerialEvaluator(task).evaluate(actions)
    got = BatchedEvaluator(task, lockstep=False).evaluate(actions)
    assert [g.reward for g in got] == pytest.approx([w.reward for w in want], rel=1e-12)


def test_batched_parameters_per_sequence_match_serial():
    task = folding_task(horizon=2)
    a = np.zeros((2, task.action_dim))
    serial = SerialEvaluator(task)
    d0 = serial.episode.model.get_parameter("sheet.bending_stiffness")
    params = [{"sheet.bending_stiffness": d0}, {"sheet.bending_stiffness": 20.0 * d0}]
    want = serial.evaluate([a, a], params)
    # one after another (exactly the serial episodes): the stiff copy's fold has two equilibria within
    # reach of its second step, and which one Newton finds depends on rounding (the lockstep batch's
    # translated copy finds the other one)
    got = BatchedEvaluator(task, lockstep=False).evaluate([a, a], params)
    for g, w in zip(got, want):
        assert g.steps_done == w.steps_done and g.infeasible == w.infeasible
        assert g.reward == pytest.approx(w.reward, rel=1e-9, abs=1e-15)
        assert g.wrench_peak_N == pytest.approx(w.wrench_peak_N, rel=1e-6, abs=1e-9)
    assert got[0].reward != got[1].reward  # the parameters reach the copies
    with pytest.raises(ConfigError, match="batched"):
        make_evaluator(task, workers=2, batched=True)


def _population(task, n: int, seed: int = 5):
    rng = np.random.default_rng(seed)
    return [rng.uniform(-1.0, 1.0, (2, task.action_dim)) * 0.5 * (task.action_high - task.action_low) / 2
            for _ in range(n)]


def _record_chunks(monkeypatch) -> list[int]:
    """Sizes of the batches the evaluator rolls out (its ``_rollout`` calls: not the size probes' batches)."""
    sizes, real = [], BatchedEvaluator._rollout

    def spy(self, seqs, *args, **kwargs):
        sizes.append(len(seqs))
        return real(self, seqs, *args, **kwargs)

    monkeypatch.setattr(BatchedEvaluator, "_rollout", spy)
    return sizes


@pytest.mark.parametrize("path", ["numpy", "numpy sequential", "taichi-cpu", "cuda emulated"])
def test_resident_batch_gives_each_population_the_results_of_separate_rollouts(monkeypatch, path):
    """The batch built for the first population is restarted for the next ones (one build, one stacked
    solver): each population's episodes equal, bit for bit, those of a batch built for it alone, and the
    separate (serial) rollouts to the Newton tolerance; the first population again gives its first results.
    On NumPy (in lockstep, and copy after copy: each copy's own solver caches cleared), on taichi-cpu and on CUDA's
    paths (device line search, CG, friction rows; emulated on the CPU arch)."""
    import dataclasses

    import sim_core.batch.lockstep as lockstep
    from tests.support.counting import counting

    task = folding_task(horizon=2)
    first_actions, next_actions = _population(task, 3, seed=5), _population(task, 3, seed=6)
    config = dataclasses.replace(TIGHT, backend="numpy" if path.startswith("numpy") else "taichi-cpu")
    lockstep_batch = path != "numpy sequential"
    if path == "cuda emulated":  # the modules loaded (a first batch and episode run), then their arch queries
        BatchedEvaluator(task, solver_config=config).evaluate(first_actions[:2])
        SerialEvaluator(task, solver_config=config).evaluate(first_actions[:1])
        emulate_cuda(monkeypatch)
    solvers = counting(monkeypatch, lockstep, "LockstepSolver")
    evaluator = BatchedEvaluator(task, solver_config=config, lockstep=lockstep_batch)
    first = evaluator.evaluate(first_actions)
    later = evaluator.evaluate(next_actions)
    again = evaluator.evaluate(first_actions)
    assert len(solvers) == int(lockstep_batch)  # one batch, restarted twice
    alone = BatchedEvaluator(task, solver_config=config, lockstep=lockstep_batch).evaluate(next_actions)
    assert len(solvers) == 2 * int(lockstep_batch)
    fields = lambda results: [(r.reward, r.steps_done, r.infeasible, r.wrench_peak_N) for r in results]
    assert fields(later) == fields(alone)
    assert fields(again) == fields(first)
    serial = SerialEvaluator(task, solver_config=config).evaluate(next_actions)
    assert [r.reward for r in later] == pytest.approx([r.reward for r in serial], rel=1e-6)
    assert [r.steps_done for r in later] == [r.steps_done for r in serial] == [2, 2, 2]
    assert len({r.reward for r in later} | {r.reward for r in first}) == 6  # the populations differ
    with pytest.raises(ConfigError, match="2 action sequences for a batch of 3"):
        evaluator._resident[3][1].restart(next_actions[:2])


def test_chunked_population_matches_one_batch(monkeypatch):
    task = folding_task(horizon=2)
    actions = _population(task, 3)
    one = BatchedEvaluator(task, lockstep=False).evaluate(actions)
    chunks = _record_chunks(monkeypatch)
    got = BatchedEvaluator(task, lockstep=False, batch_size=2).evaluate(actions)
    assert chunks == [2, 1]
    assert [g.reward for g in got] == pytest.approx([w.reward for w in one], rel=1e-12)
    assert [g.steps_done for g in got] == [w.steps_done for w in one]
    locked_one = BatchedEvaluator(task, solver_config=TIGHT).evaluate(actions)  # lockstep: one batch of 3
    locked = BatchedEvaluator(task, solver_config=TIGHT, batch_size=2).evaluate(actions)  # lockstep: 2 and 1
    assert [g.reward for g in locked] == pytest.approx([w.reward for w in locked_one], rel=1e-6)
    assert len({g.reward for g in got}) == 3  # the sequences differ
    with pytest.raises(ConfigError, match="batch_size"):
        BatchedEvaluator(task, batch_size=0)
    with pytest.raises(ConfigError, match="--batched"):
        make_evaluator(task, batch_size=2)


def test_auto_batch_size_fits_the_free_memory(monkeypatch):
    """With 100 MiB measured per copy and 250 MiB free (20 % reserve: 200 usable) the population of 3
    runs as batches of 2 and 1; with 100 MiB free not one copy fits."""
    from sim_core.batch import sizing
    from sim_core.errors import InsufficientMemoryError

    task = folding_task(horizon=2)
    actions = _population(task, 3)
    readings = iter(range(100))
    monkeypatch.setattr(sizing, "used_memory", lambda r: 100.0 * sizing.MIB * next(readings))
    monkeypatch.setattr(sizing, "free_memory", lambda r: 250.0 * sizing.MIB)
    chunks = _record_chunks(monkeypatch)
    evaluator = BatchedEvaluator(task, lockstep=False, batch_size="auto")
    got = evaluator.evaluate(actions)
    assert evaluator.sizing.B == 2 and evaluator.sizing.limit == "host"
    assert evaluator.sizing.per_copy_bytes["host"] == pytest.approx(100.0 * sizing.MIB)
    assert chunks == [2, 1]
    want = BatchedEvaluator(task, lockstep=False).evaluate(actions)
    assert [g.reward for g in got] == pytest.approx([w.reward for w in want], rel=1e-12)
    monkeypatch.setattr(sizing, "free_memory", lambda r: 100.0 * sizing.MIB)
    with pytest.raises(InsufficientMemoryError, match="not even one copy fits in host memory"):
        BatchedEvaluator(task, lockstep=False, batch_size="auto").evaluate(actions)


def test_auto_batch_size_measured_on_this_host():
    """A real probe (resident set growth of one-step batches): at least one copy per batch, every
    sequence evaluated."""
    task = folding_task(horizon=2)
    actions = _population(task, 2)
    evaluator = BatchedEvaluator(task, lockstep=False, batch_size="auto")
    got = evaluator.evaluate(actions)
    assert evaluator.sizing.B >= 1 and evaluator.sizing.per_copy_bytes["host"] > 0
    assert len(got) == 2 and all(g.steps_done == 2 for g in got)


def test_gradient_phase_releases_the_resident_batch():
    """A hybrid search's gradient phase does not keep the CMA-ES populations' batch: the first gradient drops it,
    and a later population builds a batch again with the same results."""
    task = folding_task(horizon=2)
    decoder = ControlPointDecoder.for_task(task, control_points=1)
    evaluator = BatchedEvaluator(task, solver_config=TIGHT)
    space = ActionSpace(decoder, evaluator, task)
    points = [np.full(decoder.dim, 0.3), np.full(decoder.dim, -0.2)]
    first = space.cma_evaluate(points)
    assert list(evaluator._resident) == [2]
    res, grad = space.gd_gradient(np.zeros(decoder.horizon * task.action_dim))
    assert evaluator._resident == {} and np.all(np.isfinite(grad)) and np.any(grad != 0.0)
    assert [r.reward for r in space.cma_evaluate(points)] == [r.reward for r in first]
