"""thinshell bench batch: one JSON line per batch size, every copy stepped, memory per copy reported."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from thinshell_ros.bench import bench_main

REPO = Path(__file__).resolve().parents[3]


def test_bench_batch_json_lines_per_size():
    """Run as the command runs, in a process of its own: ``rss_per_copy_mib`` is the growth of the
    process's resident memory, which stays 0 in a long-lived test process whose allocator reuses the
    memory that earlier tests freed (the order and the xdist worker then decide the figure)."""
    proc = subprocess.run([sys.executable, "-m", "thinshell_ros.bench", "batch", "--arch", "numpy", "--sizes", "1", "2",
                           "--steps", "2", "--json"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rows = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [r["B"] for r in rows] == [1, 2]
    for r in rows:
        assert r["scene"] == "forming" and r["dofs"] == 1698 and r["backend"] == "numpy"
        assert r["scene_steps"] == 2 * r["B"] and r["failed_copies"] == 0  # every copy took its steps
        assert r["scene_steps_per_s"] > 0 and r["newton_iters_mean"] >= 1
        # the steady rate counts the second step alone: B scene-steps over that step's wall time
        second_wall = r["B"] / r["steady_scene_steps_per_s"]
        assert 0 < r["first_step_s"] and 0 < second_wall and r["first_step_s"] + second_wall <= r["wall_s"]
        assert r["steps_per_s_per_copy"] == r["scene_steps_per_s"] / r["B"]
        assert r["rss_per_copy_mib"] > 0  # a copy holds its own model, solver and state
        assert r["gpu_mib_per_copy"] is None or r["gpu_mib_per_copy"] >= 0


def test_bench_batch_with_the_envelope_solve_counts_one_direct_solve_a_factorisation():
    """``--linear-solver envelope``: the lockstep batch's Newton systems solved by the envelope Cholesky, its record
    naming the device solver and its linear iterations (one direct solve a Newton matrix, and one a simplified Newton
    test with the kept factors, which may end a step without a factorisation in its last iteration) a step."""
    proc = subprocess.run([sys.executable, "-m", "thinshell_ros.bench", "batch", "--arch", "cpu", "--lockstep",
                           "--sizes", "2", "--steps", "2", "--json", "--linear-solver", "envelope"], cwd=REPO,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    (r,) = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert r["device_solver"] == "envelope" and r["failed_copies"] == 0 and r["scene_steps"] == 4
    # a factorisation a Newton iteration at least, but the last of a step that the simplified test ended
    assert r["factorizations_per_step"] >= r["newton_iters_mean"] - 1 >= 0
    # one solve each factorisation and each simplified test (no CG iterations): at most one test a Newton iteration
    assert r["factorizations_per_step"] <= r["linear_iterations_per_step"] <= (r["factorizations_per_step"]
                                                                                + r["newton_iters_mean"])


def test_bench_batch_rejects_bad_sizes_and_unknown_tasks(capsys):
    assert bench_main(["batch", "--arch", "numpy", "--sizes", "0"]) == 2
    assert "--sizes" in capsys.readouterr().err
    assert bench_main(["batch", "--arch", "numpy", "--scene", "juggling", "--sizes", "1"]) == 2
    assert "juggling" in capsys.readouterr().err


def test_bench_batch_auto_size_reports_the_probe(capsys):
    """--sizes auto: the largest B that fits (here bounded by --max-size), with the probe's figures;
    a reserve leaving nothing free is a usage error naming the memory."""
    assert bench_main(["batch", "--arch", "numpy", "--sizes", "auto", "--max-size", "2", "--steps", "1", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(rows) == 1 and rows[0]["B"] == rows[0]["auto_B"]
    r = rows[0]
    assert r["scene_steps"] == r["B"] and r["failed_copies"] == 0
    assert r["host_mib_per_copy_probe"] > 0 and r["host_mib_free"] > 0
    fits = int(0.8 * r["host_mib_free"] / r["host_mib_per_copy_probe"])
    assert r["B"] == min(2, fits) and r["auto_limit"] == ("cap" if fits > 2 else "host")
    assert bench_main(["batch", "--arch", "numpy", "--sizes", "auto", "--steps", "1", "--reserve", "0.9999999999"]) == 2
    assert "not even one copy fits in host memory" in capsys.readouterr().err
    assert bench_main(["batch", "--arch", "numpy", "--sizes", "auto", "4"]) == 2
    assert "auto alone" in capsys.readouterr().err


def test_bench_batch_task_population_steady_rate():
    """A task population in lockstep: the steady rate is the second step's scene-steps over its wall time,
    which is the sum of the members' shares of the batched step (``StepInfo.time_total``)."""
    from sim_core.bench.batch import bench_batch

    (r,) = bench_batch("folding_u", [2], 2, "numpy", lockstep=True)
    assert r["scene"] == "folding_u" and r["mode"] == "lockstep"
    assert r["scene_steps"] == 4 and r["failed_copies"] == 0
    second_wall = 2 / r["steady_scene_steps_per_s"]
    assert 0 < r["first_step_s"] and 0 < second_wall <= r["wall_s"] - r["first_step_s"] + 1e-9
