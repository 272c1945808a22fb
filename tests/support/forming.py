"""The Forming scene on the Taichi path, stepped along the benchmark trajectory (``thinshell bench
forming``'s set-up, shared by the tests that compare Newton-loop variants step for step)."""

from __future__ import annotations


def forming_simulation(warm_up: bool = False):
    """A :class:`sim_core.simulation.Simulation` of ``config/scenes/forming.yaml`` on the ``taichi-cpu``
    backend (the bench's ``--arch cpu``), at the task's initial state;
    ``warm_up``: call :meth:`Simulation.warm_up` first."""
    from sim_core.scenes.task_scene import load_task_scene, task_initial_state
    from sim_core.bench.forming import bench_simulation
    from thinshell_ros.paths import bundled_scene

    model = load_task_scene(bundled_scene("forming"))
    sim = bench_simulation(model, "cpu")
    sim.state = task_initial_state(model)
    if warm_up:
        sim.warm_up()
    return sim


def step_benchmark_trajectory(sim, steps: int) -> list[int]:
    """Step ``sim`` (a :func:`forming_simulation`) ``steps`` times along the benchmark trajectory of
    the dome (DESIGN.md); returns the Newton iterations of each step."""
    from sim_core.control import Control
    from sim_core.tasks import forming_benchmark_offsets, pose_targets

    targets = pose_targets(sim.model.effectors["dome"].initial_pose, forming_benchmark_offsets(steps))
    iterations = []
    for k in range(steps):
        control = Control()
        control.effector_pose_target["dome"] = targets[k]
        iterations.append(sim.step(control).iterations)
    return iterations
