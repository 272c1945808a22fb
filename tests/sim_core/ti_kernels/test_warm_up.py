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


def _press_slide(warm_up: bool, monkeypatch) -> tuple[np.ndarray, list[tuple], int]:
    """Positions per step (m), (iterations, sleeping bodies) per step and the static patterns built
    during the steps of the bundled press_slide scene with sleeping bodies on the Taichi CPU path: rest,
    the pad 0.1 mm up and back (the card falls asleep), rest, then the pad descends 0.25 mm a step
    until it comes near the card (which wakes it) and presses it."""
    from sim_core import assembly
    from sim_core.bundled import config_dir
    from sim_core.control import Control
    from sim_core.simulation import Simulation
    from sim_core.solver import SolverConfig

    sim = Simulation.from_scene(config_dir() / "scenes" / "press_slide.yaml", solver_config=SolverConfig(
        backend="taichi-cpu", repeat_fixed_points=True, sleeping=True))
    if warm_up:
        sim.warm_up()
    pose = np.array(sim.state.effector_pose["ee"])
    heights = [pose[2]] * 8 + [pose[2] + 1e-4] + [pose[2]] * 7
    while len(heights) < 40:
        heights.append(heights[-1] - 0.25e-3)
    xs, steps, built = [], [], []
    with monkeypatch.context() as patch:
        init = assembly.StaticPattern.__init__
        patch.setattr(assembly.StaticPattern, "__init__", lambda self, *a: (built.append(1), init(self, *a))[1])
        for z in heights:
            control = Control()
            control.effector_pose_target["ee"] = np.concatenate([pose[:2], [z], pose[3:]])
            info = sim.step(control)
            xs.append(sim.state.x.copy())
            steps.append((info.iterations, info.sleeping))
    return np.array(xs), steps, len(built)


def test_warm_up_builds_the_sleeping_steps_pattern_and_a_woken_body_finds_its_own_kept(ti_cpu, monkeypatch):
    """With sleeping bodies the warm-up also builds the evaluator and pattern of the steps with the card
    asleep; the assembler keeps the awake pattern while the card sleeps, so waking it builds nothing
    either. The steps are the same bit for bit."""
    x_ref, steps_ref, built_ref = _press_slide(False, monkeypatch)
    x, steps, built = _press_slide(True, monkeypatch)
    np.testing.assert_array_equal(x, x_ref)
    assert steps == steps_ref
    asleep = [s for _, s in steps]
    assert ("sheet",) in asleep and asleep[-1] == ()  # the card slept, and was woken by the pad
    assert built_ref == 2 and built == 0  # awake and asleep, each once (none again at the wake)
