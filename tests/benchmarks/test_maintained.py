"""benchmarks/ keeps maintained benchmarks only: each script has a line in benchmarks/README.md and starts
(``--help``, a tiny input, or for the GPU machine's shell scripts a syntax check); ``sync_gpu_src.sh`` copies
a real tree. The heavier benchmarks (diagnose_bench, bench_fit, synthetic_effects, single_rounds,
node_latency_trace, roofline, mujoco_world) have test modules of their own beside this one."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BENCHMARKS = REPO / "benchmarks"
SCRIPTS = ("bench_band_factor", "bench_cg_precision", "bench_copy_bands", "bench_envelope", "bench_projection",
           "roofline", "count_single_syncs",
           "iterations_lockstep", "parts_lockstep", "pipeline_lockstep", "profile_lockstep", "profile_single",
           "single_rounds", "synthetic_diagnose", "time_batched_gradients", "time_candidate_lists", "time_generation",
           "time_kernel_prep", "time_envelope_phases",
           "node_latency_trace", "flood_sim_node",
           "sysid_coverage")
"""Scripts run as ``python benchmarks/NAME.py``."""
MODULES = ("diagnose_bench", "bench_fit", "synthetic_effects", "profile_replay")
"""Benchmarks run as ``python -m benchmarks.NAME``."""
SHELL = ("device_cpu.sh", "device_cuda.sh", "compare_cuda.sh", "sync_gpu_src.sh")


def _run(args: list[str], **kwargs) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=300, check=False, **kwargs)


def test_every_benchmark_has_a_line_in_the_readme():
    readme = (BENCHMARKS / "README.md").read_text(encoding="utf-8")
    entries = sorted(p.name for p in BENCHMARKS.iterdir() if p.suffix in (".py", ".sh") and p.name != "__init__.py")
    entries.append("mujoco_world/")
    missing = [name for name in entries if f"`{name}" not in readme and f"benchmarks.{name[:-3]}`" not in readme]
    assert not missing, f"benchmarks/README.md has no line for {missing}"
    assert set(SCRIPTS + MODULES) | {"diagnose_summary", "emulated_cuda", "bench_effects", "reference_bench",
                                     "diagnose_scoring"} == {n[:-3] for n in entries if n.endswith(".py")}, \
        "a benchmark script without a smoke test here (or a listed one that is gone)"


@pytest.mark.parametrize("name", SCRIPTS)
def test_script_starts(name):
    run = _run([sys.executable, f"benchmarks/{name}.py", "--help"])
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.startswith(f"usage: {name}.py")


@pytest.mark.parametrize("name", MODULES)
def test_module_starts(name):
    run = _run([sys.executable, "-m", f"benchmarks.{name}", "--help"])
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.startswith(f"usage: python -m benchmarks.{name}")


def test_the_cuda_emulation_imports_without_a_gpu():
    run = _run([sys.executable, "-c", "import benchmarks.emulated_cuda as e; print(callable(e.answer_cuda), "
                "callable(e.gpu_sum_cells))"])
    assert run.returncode == 0 and run.stdout.split() == ["True", "True"], run.stderr[-2000:]


def test_diagnose_summary_of_a_tiny_report(tmp_path):
    report = {"explained_by": ["latency"], "baseline": {"calibration": {"whitened_rms_after": {"wrench": 1.234}}},
              "extra": {"wall_time_s": 12.5, "signatures": {"latency": {"statistic": 9.87, "effect_size": 0.002,
                                                                        "detected": True}}},
              "refit": {"effects": {"latency": {"heldout_rms_before": 3.0, "heldout_rms_after": 1.0}}}}
    path = tmp_path / "report.json"
    path.write_text(json.dumps(report), encoding="utf-8")
    run = _run([sys.executable, "benchmarks/diagnose_summary.py", "s101", "alone", str(path)])
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout) == {"bag": "s101", "mode": "alone", "explained_by": ["latency"], "wall_s": 12.5,
                                      "rms_after": {"wrench": 1.23}, "sig": {"latency": [9.9, 0.002, True]},
                                      "refit": {"latency": [3.0, 1.0]}}


@pytest.mark.parametrize("name", SHELL)
def test_shell_script_parses(name):
    run = _run(["bash", "-n", f"benchmarks/{name}"])
    assert run.returncode == 0, run.stderr


def test_sync_gpu_src_copies_the_code_and_the_kernel_tests_only(tmp_path):
    dest = tmp_path / "gpu_src"
    run = _run(["bash", "benchmarks/sync_gpu_src.sh", str(dest)])
    assert run.returncode == 0, run.stderr
    assert (dest / "sim_core" / "solver.py").is_file() and (dest / "tests" / "sim_core" / "ti_kernels").is_dir()
    assert not (dest / "docs").exists() and not (dest / "bags").exists() and not (dest / "tests" / "sysid").exists()


@pytest.mark.parametrize(("old", "module"), [("diagnose", "benchmarks.diagnose_bench"), ("sysid", "benchmarks.bench_fit")])
def test_the_former_bench_subcommands_name_their_checkout_module(old, module, capsys):
    from thinshell_ros.bench import bench_main

    assert bench_main([old, "--quick"]) == 2
    err = capsys.readouterr().err
    assert f"thinshell bench {old}: moved out of the installed package; run `python -m {module}`" in err
