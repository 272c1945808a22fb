"""One declared backend (SolverConfig.backend) reaches every part of the solver: the fused elastic
path and the contact set's kernels; ``auto`` takes the process's Taichi runtime."""

from __future__ import annotations

import pytest

from sim_core.backend import resolve_backend
from sim_core.errors import ConfigError
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig


def _forming_model():
    from sim_core.scenes.task_scene import load_task_scene
    from thinshell_ros.paths import bundled_scene

    return load_task_scene(bundled_scene("forming"))


def test_the_solver_backend_reaches_the_fused_path_and_the_contact_set(ti_cpu):
    backend = f"taichi-{ti_cpu}"
    numpy_sim = Simulation(_forming_model())
    ti_sim = Simulation(_forming_model(), solver_config=SolverConfig(backend=backend))
    assert (numpy_sim.solver.backend, ti_sim.solver.backend) == ("numpy", backend)
    assert not numpy_sim.solver._fused_path() and ti_sim.solver._fused_path()
    assert not numpy_sim.solver.contact.taichi and ti_sim.solver.contact.taichi
    # kept through a parameter change (new elastic terms) and a reset (new contact set)
    ti_sim.set_parameter(ti_sim.parameter_names[0], 1.01 * ti_sim.get_parameter(ti_sim.parameter_names[0]))
    ti_sim.step()
    assert ti_sim.solver._fused is not None  # the step ran the fused evaluator
    ti_sim.reset()
    assert ti_sim.solver._fused_path() and ti_sim.solver.contact.taichi


def test_auto_takes_the_taichi_runtime_of_the_process(ti_cpu):
    assert resolve_backend("auto") == f"taichi-{ti_cpu}"
    assert Simulation(_forming_model(), solver_config=SolverConfig(backend="auto")).solver.backend == f"taichi-{ti_cpu}"


def test_a_backend_of_another_arch_than_the_process_runtime_is_a_config_error(ti_cpu):
    other = "taichi-cuda" if ti_cpu == "cpu" else "taichi-cpu"
    with pytest.raises(ConfigError, match="init_backend: Taichi is already initialised with arch"):
        Simulation(_forming_model(), solver_config=SolverConfig(backend=other))
