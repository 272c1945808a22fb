"""The Taichi kernels of a step run in a forked process (the diagnosis replay pools fork workers).

Taichi's CPU thread pool does not survive ``fork``: a kernel loop that Taichi runs in parallel
(any top-level loop not serialised) waits for pool threads that the child does not have and hangs
the worker forever. The spatial-hash kernel had three such one-thread loops; ``thinshell diagnose``
then hung in its first pooled replay. As the replay scheduler does, the parent builds the model on
the Taichi backend and compiles every kernel of a step (building Taichi arrays in a child would
hang in Taichi's own copy kernels), then a forked worker steps it from the start again and must
give the result of the parent doing the same after the fork, bit for bit (same caches: the contact
set keeps its candidate lists across steps, and a different list sums in another order).
"""

from __future__ import annotations

import multiprocessing

import numpy as np
import pytest

from tests.sim_core.ti_kernels.conftest import TEST_ARCH

pytestmark = pytest.mark.skipif(
    TEST_ARCH != "cpu",
    reason="checks Taichi's CPU thread pool, which a forked process lacks; on CUDA (THINSHELL_TEST_ARCH=cuda) "
           "the kernels run on the GPU, and the CPU case is covered by the default run")


_PARENT: dict = {}  # the simulation built in the parent, inherited by the forked worker


def _forming_steps(steps: int) -> tuple[np.ndarray, list[int]]:
    """Final positions (m) and Newton iterations of ``steps`` Forming benchmark steps of the parent's
    simulation (Taichi path), from its initial state."""
    from sim_core.scenes.task_scene import task_initial_state
    from tests.support.forming import step_benchmark_trajectory

    sim = _PARENT["sim"]
    sim.state = task_initial_state(sim.model)
    iterations = step_benchmark_trajectory(sim, steps)
    return sim.state.x.copy(), iterations


def test_forming_steps_in_a_forked_worker_equal_the_parents(ti_cpu):
    from tests.support.forming import forming_simulation

    sim = forming_simulation()
    _PARENT["sim"] = sim
    _forming_steps(3)  # compiles (or loads) every kernel of a step, then forks
    with multiprocessing.get_context("fork").Pool(1) as pool:
        try:
            x_child, it_child = pool.apply_async(_forming_steps, (3,)).get(timeout=120)
        except multiprocessing.TimeoutError:
            pytest.fail("a forked worker hung in a Taichi kernel (a parallel loop on the CPU backend)")
    x_parent, it_parent = _forming_steps(3)
    assert it_child == it_parent
    assert np.array_equal(x_child, x_parent)
