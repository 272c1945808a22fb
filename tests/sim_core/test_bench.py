"""``thinshell bench``: a few Forming steps run, the JSON line parses, unsupported options fail clearly."""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest

from sim_core.bench.process import process_start_time
from sim_core.bench.scale import scale_model
from thinshell_ros.bench import bench_main

REQUIRED = {"dofs", "steps_per_s", "newton_iters_mean", "linear_solve_share", "assembly_share", "cold_start_s"}


def test_forming_bench_json_line(capsys):
    assert bench_main(["forming", "--steps", "2", "--json", "--elastic-worker"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    r = json.loads(lines[0])
    assert REQUIRED <= r.keys()
    assert r["dofs"] == 1698 and r["steps"] == 2
    assert r["steps_per_s"] > 0 and r["newton_iters_mean"] >= 1
    assert 0 < r["assembly_share"] + r["linear_solve_share"] <= 1.0
    assert r["cold_start_s"] >= r["forward_total_s"] / 2  # the first step is inside the cold start
    # the record names the interpreter binary that ran it (its build moves the figures)
    assert os.path.isfile(r["python_executable"]) and not os.path.islink(r["python_executable"])
    assert os.path.samefile(r["python_executable"], sys.executable)
    # the gel's term ran in the worker process, which reports its own memory
    assert r["elastic_worker"] is True and r["worker_peak_rss_mib"] > 10.0


def test_forming_steps_move_the_dome_along_the_trajectory():
    from sim_core.control import Control
    from sim_core.scenes.task_scene import load_task_scene, task_initial_state
    from sim_core.simulation import Simulation
    from sim_core.tasks import forming_benchmark_offsets, pose_targets
    from thinshell_ros.paths import bundled_scene

    model = load_task_scene(bundled_scene("forming"))
    sim = Simulation(model)
    sim.state = task_initial_state(model)
    targets = pose_targets(model.effectors["dome"].initial_pose, forming_benchmark_offsets(3))
    for k in range(3):
        c = Control()
        c.effector_pose_target["dome"] = targets[k]
        sim.step(c)
    assert np.allclose(sim.state.effector_pose["dome"], targets[2])
    assert np.all(np.isfinite(sim.state.x))
    table = model.bodies["table"].vertices
    assert np.array_equal(sim.state.x[table], model.x_rest[table])  # frozen box does not move


def _cuda_available() -> bool:
    import subprocess

    try:
        return subprocess.run(["nvidia-smi"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


@pytest.mark.skipif(_cuda_available(), reason="this machine has a CUDA GPU: --arch cuda is expected to work")
def test_cuda_arch_without_gpu_exits_2_with_reason(capsys):
    assert bench_main(["forming", "--arch", "cuda", "--steps", "1"]) == 2
    assert "--arch cuda" in capsys.readouterr().err


def test_forming_backward_reports_backward_rate(capsys):
    assert bench_main(["forming", "--arch", "numpy", "--backward", "--steps", "2", "--json"]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["backward_steps_per_s"] > 0 and line["backward_total_s"] > 0


def test_scale_model_sizes_and_small_case(capsys):
    for target in (1_000, 10_000, 100_000):
        assert abs(scale_model(target).dof_count - target) / target < 0.05
    assert bench_main(["scale", "--steps", "1", "--max-dofs", "1000", "--json"]) == 0
    cases = json.loads(capsys.readouterr().out)["cases"]
    assert [c["target_dofs"] for c in cases] == [1000]
    assert cases[0]["step_time_s"] > 0 and cases[0]["peak_rss_mib"] > 10


def test_process_start_time_is_in_the_past():
    import time

    assert 0 <= time.time() - process_start_time() < 3600


def test_repeat_reports_the_median_run_and_the_first_runs_cold_start(capsys):
    from sim_core.bench.forming import repeat_forming

    runs = [{"steps_per_s": v, "step_time_mean_s": 1 / v, "forward_total_s": 2 / v, "assembly_share": 0.1 * k,
             "linear_solve_share": 0.2, "cold_start_s": 9.0 - k, "jit_s": 5.0 - k, "peak_rss_mib": 100.0 + k}
            for k, v in enumerate([30.0, 50.0, 40.0, 20.0])]
    r = repeat_forming(runs)
    assert r["repeat"] == 4 and r["steps_per_s_runs"] == [30.0, 50.0, 40.0, 20.0]
    assert r["steps_per_s"] == 30.0 and r["step_time_mean_s"] == 1 / 30.0  # lower middle of 20, 30, 40, 50
    assert r["assembly_share"] == 0.0 and r["steps_per_s_best"] == 50.0
    assert r["cold_start_s"] == 9.0 and r["jit_s"] == 5.0 and r["peak_rss_mib"] == 103.0
    with pytest.raises(ValueError, match="no runs"):
        repeat_forming([])
    assert bench_main(["forming", "--steps", "2", "--repeat", "2", "--json"]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["repeat"] == 2 and len(line["steps_per_s_runs"]) == 2
    assert line["elastic_worker"] is False and line["worker_peak_rss_mib"] is None
    assert line["steps_per_s"] in line["steps_per_s_runs"]
    assert bench_main(["forming", "--steps", "2", "--repeat", "0"]) == 2
    assert "--repeat must be >= 1" in capsys.readouterr().err
