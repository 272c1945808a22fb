"""The elastic worker process (sim_core.elastic_worker): the same results as one process, bit for bit,
whether the worker is up, busy, reconfigured or gone; it shuts down cleanly."""

from __future__ import annotations

import logging
import os
import signal

import numpy as np
import pytest

from sim_core.assembly import HessianAssembler
from tests.support.forming import forming_simulation, step_benchmark_trajectory


@pytest.fixture(scope="module")
def cpu_arch(ti_cpu):
    """The tests' Taichi arch, which must be the CPU: the solver hands terms to an elastic worker only
    beside CPU kernels (the worker runs Taichi's CPU backend, and CUDA kernels sum in another order),
    so under ``TEST_ARCH=cuda`` there is nothing of the worker's to test."""
    if ti_cpu != "cpu":
        pytest.skip(f"TEST_ARCH={ti_cpu}: the elastic worker is used beside Taichi's CPU kernels only")
    return ti_cpu


@pytest.fixture(scope="module")
def worker(cpu_arch):
    """One worker for the module's tests (a start costs seconds), ready."""
    from sim_core.elastic_worker import ElasticWorker

    w = ElasticWorker()
    assert w.wait_ready(), f"the worker did not start: {w.failure}"
    yield w
    w.close()


def _forming_rollout(steps: int, worker=None, edit=None):
    """Final positions and Newton iterations of ``steps`` Forming steps (``edit(sim)`` after step 2)."""
    sim = forming_simulation(warm_up=True)
    sim.solver.elastic_worker = worker
    iterations = step_benchmark_trajectory(sim, 2)
    if edit is not None:
        edit(sim)
    iterations += step_benchmark_trajectory(sim, steps - 2)
    return sim.state.x.copy(), iterations


def test_forming_with_the_worker_equals_one_process_bit_for_bit(worker):
    """The gel's term evaluated in the worker (every evaluation of the run) gives the same states and
    iterations as the single-process loop; a Young's modulus edit reconfigures the worker."""
    before, configured = worker.evaluations, worker.configurations

    def stiffer(sim):
        sim.set_parameter("dome.youngs_modulus", 4.5e5)

    x_one, it_one = _forming_rollout(6, None, stiffer)
    x_two, it_two = _forming_rollout(6, worker, stiffer)
    assert worker.failure is None
    assert worker.evaluations - before >= sum(it_two)  # at least one per iteration, all in the worker
    # the gel's term, all terms at a step's first iterate, the gel's projected Hessian: configured once
    # each, and again after the edit (new Lame parameters), not every step
    assert 3 <= worker.configurations - configured <= 6
    assert it_one == it_two
    np.testing.assert_array_equal(x_two, x_one)
    x_soft, _ = _forming_rollout(6, worker)  # the edit mattered (the worker did not keep the old modulus)
    assert np.max(np.abs(x_soft - x_one)) > 1e-9


def _overlapping_terms():
    """A gel and a Maxwell branch on the same tets (parts sharing every vertex), a pattern and positions."""
    from sim_core.candidates.gel_viscoelasticity import MaxwellBranch
    from sim_core.energies.neohookean.reference import StableNeoHookean
    from sim_core.fused_elastic import FusedElastic
    from sim_core.mesh.tet import tet_box

    mesh = tet_box((0.01, 0.01, 0.01), (3, 3, 3), (0.0, 0.0, 0.0))
    gel = StableNeoHookean(mesh.tets, mesh.x, 3e5, 0.45)
    rng = np.random.default_rng(3)
    branch = MaxwellBranch(gel, np.eye(3) + rng.normal(scale=0.05, size=(gel.tets.shape[0], 3, 3)), 0.6)
    terms = [gel, branch.elastic_equivalent()]
    free = np.ones(mesh.x.size, dtype=bool)
    free[:6] = False
    fused = FusedElastic(terms)
    pattern = HessianAssembler(mesh.x.size).static_pattern(fused.block_vertex_arrays(mesh.x), free)
    x = mesh.x + 1e-3 * rng.standard_normal(mesh.x.shape)
    return terms, pattern, x


def _evaluation(terms, pattern, x, offload):
    from sim_core.fused_elastic import FusedElastic

    fused = FusedElastic(terms)
    fused.bind(pattern)
    fused.offload = offload
    return fused.energy(x), fused.gradient(x), fused.hessian_values(x).copy(), fused


def test_offloaded_sums_do_not_depend_on_where_the_term_ran(worker, monkeypatch):
    """Parts that share vertices: the offloaded part's sums are added after the others', the same
    whether the worker evaluated it or this process did (a worker that is not ready); they equal the
    single-process loop's to round-off."""
    import sim_core.fused_elastic as fe
    from sim_core.elastic_worker import ElasticWorker

    monkeypatch.setattr(fe, "OFFLOAD_MIN_ELEMENTS", 1)
    terms, pattern, x = _overlapping_terms()
    before = worker.evaluations
    e_w, g_w, h_w, fused = _evaluation(terms, pattern, x, worker)
    assert fused.offloaded_part() is not None and worker.evaluations == before + 1
    not_ready = ElasticWorker(python="/bin/false")  # exits at once: never ready
    e_l, g_l, h_l, _ = _evaluation(terms, pattern, x, not_ready)
    assert not not_ready.wait_ready(10.0) and "exited" in not_ready.failure
    assert e_w == e_l
    np.testing.assert_array_equal(g_w, g_l)
    np.testing.assert_array_equal(h_w, h_l)
    e_1, g_1, h_1, single = _evaluation(terms, pattern, x, None)
    assert single.offloaded_part() is None
    assert e_w == pytest.approx(e_1, rel=1e-14)
    np.testing.assert_allclose(g_w, g_1, rtol=0, atol=1e-12 * np.max(np.abs(g_1)))
    np.testing.assert_allclose(h_w, h_1, rtol=0, atol=1e-12 * np.max(np.abs(h_1)))


def test_a_dead_worker_is_given_up_and_the_run_goes_on(cpu_arch, caplog):
    """The worker killed mid-run: a warning names the failure, the term is evaluated here from then on,
    and the run ends with the single-process states bit for bit; the worker is not used again."""
    from sim_core.elastic_worker import ElasticWorker

    doomed = ElasticWorker()
    assert doomed.wait_ready()

    def kill(sim):
        os.kill(doomed.pid, signal.SIGKILL)

    with caplog.at_level(logging.WARNING, logger="sim_core.elastic_worker"):
        x_two, it_two = _forming_rollout(5, doomed, kill)
    assert doomed.failure is not None and not doomed.ready
    assert any("given up" in r.getMessage() for r in caplog.records)
    x_one, it_one = _forming_rollout(5, None, lambda sim: None)
    assert it_two == it_one
    np.testing.assert_array_equal(x_two, x_one)
    from sim_core.elastic_worker import Recipe

    assert doomed.begin(Recipe((("x:y", ()),)), x_one, 1) is False


def test_close_ends_the_process_and_leaves_no_file(cpu_arch):
    """close() stops the process; the shared region's file is gone once configured."""
    from sim_core.elastic_worker import ElasticWorker, Recipe
    from sim_core.energies.neohookean.fused_kernel import remote_evaluate

    w = ElasticWorker()
    assert w.wait_ready()
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.2]])
    dFdx = np.zeros((1, 4, 3))
    dFdx[0, 1:] = np.eye(3)
    dFdx[0, 0] = -1.0
    args = (np.arange(4, dtype=np.int32)[None], dFdx, np.full(1, 1.0 / 6.0), np.arange(78, dtype=np.int32)[None],
            2.0, 3.0)
    assert w.begin(Recipe(((f"{remote_evaluate.__module__}:remote_evaluate", args),)), x, 78)
    energy, grad, values = w.finish()
    g, v = np.zeros((4, 3)), np.zeros(78)
    assert energy == remote_evaluate(args, x, g, v) and energy > 0.0
    np.testing.assert_array_equal(grad, g)
    np.testing.assert_array_equal(values, v)
    assert w.peak_rss_mib() > 10.0
    shm = "/dev/shm" if os.path.isdir("/dev/shm") else None
    if shm:
        assert not [f for f in os.listdir(shm) if f.startswith("thinshell-worker-")]
    pid = w.pid
    w.close()
    assert not w.ready and w.failure == "closed"
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_socket_signalling_gives_the_same_results(cpu_arch, monkeypatch):
    """Requests and replies as socket messages (the path of machines without x86's store order,
    chosen with ``signal="socket"``): the same Forming states as one process; a bad signal name is
    refused."""
    import sim_core.elastic_worker as ew
    from sim_core.errors import ConfigError

    with pytest.raises(ConfigError, match="unknown signal 'carrier-pigeon'"):
        ew.ElasticWorker(signal="carrier-pigeon")
    w = ew.ElasticWorker(signal="socket")
    assert w.signal == "socket"
    try:
        assert w.wait_ready()
        x_two, it_two = _forming_rollout(4, w)
        assert w.failure is None and w.evaluations >= sum(it_two)
    finally:
        w.close()
    x_one, it_one = _forming_rollout(4, None)
    assert it_two == it_one
    np.testing.assert_array_equal(x_two, x_one)


def _add_scaled(args, x, grad, values):
    """A recipe function for the tests: adds ``args[0] * x`` to ``grad`` and ``args[0]`` to ``values``."""
    grad += args[0] * x
    values += args[0]
    return float(args[0])


def test_run_recipe_sums_in_part_order_with_one_part_apart():
    """The worker's sums: parts in order into the buffers, the part apart into zeroed scratch added
    after them, the energies summed in part order."""
    from sim_core.elastic_worker import run_recipe

    x = np.arange(6.0).reshape(2, 3) / 7.0
    grad, values = np.full((2, 3), 9.0), np.full(4, 9.0)  # zeroed by run_recipe
    scratch = (np.full((2, 3), 5.0), np.full(4, 5.0))
    args = [(0.1,), (1e-17,), (0.3,)]
    energy = run_recipe([_add_scaled] * 3, args, 1, x, grad, values, scratch)
    assert energy == (0.0 + 0.1) + 1e-17 + 0.3
    np.testing.assert_array_equal(grad, (0.1 * x + 0.3 * x) + 1e-17 * x)
    np.testing.assert_array_equal(values, np.full(4, (0.1 + 0.3) + 1e-17))
    run_recipe([_add_scaled] * 3, args, None, x, grad, values)
    np.testing.assert_array_equal(values, np.full(4, (0.1 + 1e-17) + 0.3))


def test_recipes_are_the_same_when_their_arrays_are_the_same_objects():
    """Recipe identity: arrays by object (an in-place change is not looked for), other values by value."""
    from sim_core.elastic_worker import Recipe, part_recipe, same_recipe

    a, b = np.zeros(3), np.zeros(3)
    first = part_recipe(None, "m:f", (a, 1.0))
    assert part_recipe(first, "m:f", (a, 1.0)) is first
    assert part_recipe(first, "m:f", (b, 1.0)) is not first  # an equal but other array
    assert part_recipe(first, "m:f", (a, 2.0)) is not first
    assert part_recipe(first, "m:g", (a, 1.0)) is not first
    r = Recipe((first,), None)
    assert same_recipe(r, Recipe((("m:f", (a, 1.0)),), None))
    assert not same_recipe(r, Recipe((("m:f", (a, 1.0)),), 0))
    assert not same_recipe(r, Recipe((("m:f", (b, 1.0)),), None))
    assert not same_recipe(None, r)


def test_start_evaluates_every_part_in_the_worker(worker, monkeypatch):
    """``FusedElastic.start``: one request evaluates all parts in the worker, the next evaluation at
    the same positions runs no kernel here, and the sums are those of the split evaluation (the gel's
    part apart), bit for bit; at other positions the result is dropped."""
    import sim_core.fused_elastic as fe
    from sim_core.energies.neohookean.fused_kernel import FusedStableNeoHookean
    from sim_core.fused_elastic import FusedElastic

    monkeypatch.setattr(fe, "OFFLOAD_MIN_ELEMENTS", 1)
    terms, pattern, x = _overlapping_terms()
    e_split, g_split, h_split, _ = _evaluation(terms, pattern, x, worker)
    local = []
    evaluate = FusedStableNeoHookean.evaluate
    monkeypatch.setattr(FusedStableNeoHookean, "evaluate", lambda self, *a: local.append(1) or evaluate(self, *a))
    fused = FusedElastic(terms)
    fused.bind(pattern)
    fused.offload = worker
    before = worker.evaluations
    fused.start(x)
    g = fused.gradient(x)
    assert worker.evaluations == before + 1 and not local
    assert fused.energy(x) == e_split
    np.testing.assert_array_equal(g, g_split)
    np.testing.assert_array_equal(fused.hessian_values(x), h_split)
    fused.start(x + 1e-4)
    y = x + 2e-4
    g_y = fused.gradient(y)  # not the started positions: evaluated anew (split), the start dropped
    _, g_ref, _, _ = _evaluation(terms, pattern, y, None)
    np.testing.assert_allclose(g_y, g_ref, rtol=0, atol=1e-12 * np.max(np.abs(g_ref)))
