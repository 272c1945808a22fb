"""Simulation.warm_up builds the fused evaluator on its sparsity pattern before the first step: the
steps are the same bit for bit and the first one builds no pattern of its own."""

from __future__ import annotations

import numpy as np


def _forming(steps: int, warm_up: bool, monkeypatch) -> tuple[np.ndarray, list[int], int]:
    """Final positions (m), Newton iterations per step and the static patterns built during the steps
    of ``steps`` Forming benchmark steps on the Taichi path."""
    from sim_core import assembly
    from tests.support.forming import forming_simulation, step_benchmark_trajectory

    sim = forming_simulation(warm_up)
    built = []
    with monkeypatch.context() as patch:
        init = assembly.StaticPattern.__init__
        patch.setattr(assembly.StaticPattern, "__init__", lambda self, *a: (built.append(1), init(self, *a))[1])
        iterations = step_benchmark_trajectory(sim, steps)
    return sim.state.x.copy(), iterations, len(built)


def test_warm_up_gives_the_same_steps_and_the_first_builds_no_pattern(ti_cpu, monkeypatch):
    x_ref, it_ref, built_ref = _forming(3, False, monkeypatch)
    x, it, built = _forming(3, True, monkeypatch)
    np.testing.assert_array_equal(x, x_ref)
    assert it == it_ref
    assert built_ref == 1 and built == 0


def test_warm_up_on_the_numpy_path_does_nothing():
    from sim_core.scenes.task_scene import load_task_scene, task_initial_state
    from sim_core.simulation import Simulation
    from thinshell_ros.paths import bundled_scene

    model = load_task_scene(bundled_scene("forming"))
    sim = Simulation(model)
    sim.state = task_initial_state(model)
    sim.warm_up()
    assert sim.solver._fused is None
