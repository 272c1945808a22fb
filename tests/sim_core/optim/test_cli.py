"""``thinshell optimise`` end to end on short tasks: outputs (trajectory.yaml by contract B, report,
checkpoint), refusal to overwrite, --force, --resume continuing a finished run, an inverse task."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.trajectory_file import read_trajectory
from sim_core.optim.cli import optimise_main
from thinshell_ros.cli import COMMANDS

ARGS = ["forming", "--horizon", "3", "--population", "4", "--control-points", "1", "--no-progress", "--seed", "2",
        "--backend", "numpy"]


def test_optimise_writes_trajectory_report_and_checkpoint_and_resumes(tmp_path):
    out = tmp_path / "run"
    assert COMMANDS["optimise"][:2] == ("sim_core.optim.cli", "optimise_main")
    assert optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(out)]) == 0
    for name in ("trajectory.yaml", "result.json", "report.html", "reward.png", "before_after.png", "checkpoint.pkl", "scene.yaml"):
        assert (out / name).is_file(), name
    doc = json.loads((out / "result.json").read_text())
    traj = read_trajectory(out / "trajectory.yaml")
    assert traj.waypoint_count == 4 and traj.effectors == ["dome"]
    np.testing.assert_allclose(np.diff(traj.t), 0.005)
    assert traj.prediction["reward"] == pytest.approx(doc["best_reward"])
    # the contact summary: one effector, so its peak is the episode's peak (recorded live while stepping)
    assert traj.prediction["wrench_peak_N.dome"] == pytest.approx(traj.prediction["wrench_peak_N"], rel=1e-12)
    assert len(traj.prediction["wrench_final.dome"]) == 6 and traj.prediction["torque_peak_Nm.dome"] >= 0.0
    assert doc["best_reward"] >= max(h["reward"] for h in doc["history"] if h["reward"] is not None)
    assert "reward.png" in (out / "report.html").read_text()
    # refuses to overwrite; --resume with a larger budget continues the same run
    with pytest.raises(ConfigError, match="exists"):
        optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(out)])
    assert optimise_main(ARGS + ["--method", "cma", "--episodes", "8", "--out", str(out), "--resume"]) == 0
    resumed = json.loads((out / "result.json").read_text())
    assert [h["score"] for h in resumed["history"][:4]] == [h["score"] for h in doc["history"]]
    assert len(resumed["history"]) == 8 and resumed["best_reward"] >= doc["best_reward"]
    # (that a resumed run equals an uninterrupted one: tests/sim_core/optim/test_search.py)
    with pytest.raises(ConfigError, match="another run"):
        optimise_main(ARGS + ["--method", "gd", "--episodes", "9", "--out", str(out), "--resume"])
    assert optimise_main(ARGS + ["--method", "gd", "--episodes", "1", "--out", str(out), "--force"]) == 0
    assert len(json.loads((out / "result.json").read_text())["history"]) == 1


def test_bad_arguments_are_named(tmp_path):
    with pytest.raises(ConfigError, match="unknown task"):
        optimise_main(["nosuchtask", "--episodes", "1", "--out", str(tmp_path / "a")])
    with pytest.raises(ConfigError, match="horizon"):
        optimise_main(["forming", "--horizon", "999", "--episodes", "1", "--out", str(tmp_path / "b")])
    with pytest.raises(ConfigError, match="inverse"):
        optimise_main(ARGS + ["--episodes", "1", "--start", "x=1", "--out", str(tmp_path / "c")])
    with pytest.raises(ConfigError, match="no checkpoint.pkl"):
        optimise_main(ARGS + ["--episodes", "1", "--resume", "--out", str(tmp_path / "d")])


def test_scene_argument_task_scene_or_sysid_fitted_values(tmp_path):
    import yaml

    from sim_core.optim.cli import load_target

    # a kind: task scene replaces the task's scene
    doc = yaml.safe_load(open(Path(__file__).resolve().parents[3] / "config/scenes/forming.yaml"))
    doc["friction"][0]["mu"] = 2.0
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(doc))
    task, params, path = load_target("forming", str(other), 3)
    assert task.scene["friction"][0]["mu"] == 2.0 and params == {} and path == str(other) and task.horizon == 3
    # a scene written by thinshell sysid: its fitted values of the task scene's parameters apply
    fitted = tmp_path / "fitted.yaml"
    fitted.write_text(yaml.safe_dump({"kind": "tactile", "fitted": {"params": {"friction.dome_sheet": 3.5,
                                                                               "gel.youngs_modulus": 2e5}}}))
    task, params, _ = load_target("forming", str(fitted), 3)
    assert params == {"friction.dome_sheet": 3.5}
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"kind": "tactile", "fitted": {"params": {"gel.youngs_modulus": 2e5}}}))
    with pytest.raises(ConfigError, match="none of the fitted parameters"):
        load_target("forming", str(bad), 3)
    doc["effectors"] = {"probe": doc["effectors"]["dome"]}  # renamed: the task moves "dome"
    doc["friction"] = [f for f in doc["friction"] if "dome" not in f["pair"]]
    other.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="lacks the effectors"):
        load_target("forming", str(other), 3)


def test_bench_optimise_appends_a_table(tmp_path):
    from thinshell_ros.bench import bench_main

    md = tmp_path / "bench.md"
    md.write_text("# benchmarks\n")
    assert bench_main(["optimise", "--tasks", "forming", "--methods", "cma", "--episodes", "3", "--horizon", "2",
                       "--population", "3", "--markdown", str(md), "--method-args", "--backend numpy"]) == 0
    text = md.read_text()
    assert text.startswith("# benchmarks\n") and "## Task optimisation" in text
    row = [line for line in text.splitlines() if line.startswith("| Forming | cma |")]
    assert len(row) == 1 and "| 1 | 3 |" in row[0]  # one seed, 3 episodes


def test_batched_flag_evaluates_populations_as_one_batch_with_the_serial_scores(tmp_path):
    serial, batched = tmp_path / "serial", tmp_path / "batched"
    assert optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(serial)]) == 0
    assert optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(batched), "--batched"]) == 0
    a = json.loads((serial / "result.json").read_text())
    b = json.loads((batched / "result.json").read_text())
    np.testing.assert_allclose([h["score"] for h in b["history"]], [h["score"] for h in a["history"]], rtol=1e-9)
    with pytest.raises(ConfigError, match="batched"):
        optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(tmp_path / "c"), "--batched",
                              "--workers", "2"])


def test_batched_hybrid_takes_gradients_at_its_best_cma_candidates_together(tmp_path):
    """``--method hybrid --batched``: the gradient phase's first batch evaluates the 4 (--gd-starts 4)
    best feasible CMA-ES candidates' episodes and their gradients together (sim_core.optim.batch_gradient):
    the same episodes, so the same rewards, as the CMA-ES generation gave them."""
    out = tmp_path / "hybrid"
    assert optimise_main(ARGS + ["--method", "hybrid", "--episodes", "8", "--out", str(out), "--batched",
                                 "--gd-starts", "4"]) == 0
    doc = json.loads((out / "result.json").read_text())
    assert doc["gd_starts"] == 4 and [h["phase"] for h in doc["history"]] == ["cma"] * 4 + ["gd"] * 4
    cma = sorted((h["reward"] for h in doc["history"][:4] if h["infeasible"] is None), reverse=True)
    gd = [h["reward"] for h in doc["history"][4:]]
    assert len(cma) >= 2 and gd[:len(cma)] == pytest.approx(cma, rel=1e-6)
    with pytest.raises(ConfigError, match="--gd-starts"):
        optimise_main(ARGS + ["--method", "hybrid", "--episodes", "8", "--out", str(tmp_path / "b"),
                              "--gd-starts", "2"])


def test_batched_gd_starts_on_an_inverse_task_follow_the_serial_run(tmp_path):
    """``bouncing --method gd --batched --gd-starts 2`` from twice the hidden bending stiffness: the two runs'
    gradients come from one batch a step (sim_core.optim.inverse_task.ParameterSpace.gd_gradients); the first run's
    episodes are those of the serial run from the same start (equal to 1e-3 relative: the default Newton
    tolerances, lockstep against alone; 7e-5 measured), and the runs climb."""
    from tests.sim_core.optim.task_support import short_task

    truth = short_task("bouncing", 2).true_parameters["sheet.bending_stiffness"]
    args = ["bouncing", "--horizon", "2", "--method", "gd", "--no-progress", "--backend", "numpy", "--start",
            f"sheet.bending_stiffness={2.0 * truth}"]
    serial, batched = tmp_path / "serial", tmp_path / "batched"
    assert optimise_main(args + ["--episodes", "4", "--batched", "--gd-starts", "2", "--out", str(batched)]) == 0
    assert optimise_main(args + ["--episodes", "2", "--out", str(serial)]) == 0
    b = json.loads((batched / "result.json").read_text())
    a = json.loads((serial / "result.json").read_text())
    assert b["gd_starts"] == 2 and [h["phase"] for h in b["history"]] == ["gd"] * 4
    first_run = [h["reward"] for h in b["history"][0::2]]
    assert first_run == pytest.approx([h["reward"] for h in a["history"]], rel=1e-3)
    assert b["best_reward"] > max(h["reward"] for h in b["history"][:2])  # the second step improves on the starts
    with pytest.raises(ConfigError, match="--gd-starts > 1 applies to --method gd or hybrid with --batched"):
        optimise_main(args + ["--episodes", "4", "--gd-starts", "2", "--out", str(tmp_path / "c")])


def test_batch_size_splits_each_population_into_chunks_with_the_serial_scores(tmp_path):
    serial, chunked = tmp_path / "serial", tmp_path / "chunked"
    assert optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(serial)]) == 0
    assert optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(chunked), "--batched",
                                 "--batch-size", "3"]) == 0  # the population of 4 as batches of 3 and 1
    a = json.loads((serial / "result.json").read_text())
    b = json.loads((chunked / "result.json").read_text())
    np.testing.assert_allclose([h["score"] for h in b["history"]], [h["score"] for h in a["history"]], rtol=1e-9)
    with pytest.raises(ConfigError, match="--batched"):
        optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(tmp_path / "c"), "--batch-size", "2"])
    with pytest.raises(SystemExit):
        optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(tmp_path / "d"), "--batched",
                              "--batch-size", "0"])


def test_cma_start_reference_evaluates_the_reference_first(tmp_path):
    out = tmp_path / "warm"
    args = ["forming", "--horizon", "2", "--population", "2", "--control-points", "1", "--no-progress",
            "--backend", "numpy"]
    assert optimise_main(args + ["--method", "cma", "--episodes", "2", "--cma-start", "reference", "--out", str(out)]) == 0
    doc = json.loads((out / "result.json").read_text())
    # Forming's target is the end of its reference trajectory: the reference scores exactly 0
    assert doc["history"][0]["reward"] == pytest.approx(0.0, abs=1e-15)  # the CMA-ES mean, evaluated first
    assert doc["start_reward"] == pytest.approx(0.0, abs=1e-15) and doc["history"][1]["reward"] < 0.0
    with pytest.raises(ConfigError, match="--cma-start applies to manipulation tasks"):
        optimise_main(["bouncing", "--horizon", "2", "--method", "cma", "--episodes", "2", "--cma-start", "zero",
                       "--out", str(tmp_path / "inv")])


def test_bench_optimise_starts_inverse_tasks_away_from_the_truth_and_reports_the_parameter_error(capsys):
    from sim_core.optim.bench import bench_optimise_main, parameter_error

    assert parameter_error({"a": 1.04, "b": 2.0}, {"a": 1.0, "b": 2.0}) == pytest.approx(0.04)
    with pytest.raises(ConfigError, match="'c' missing"):
        parameter_error({"a": 1.0}, {"c": 1.0})
    assert bench_optimise_main(["--tasks", "bouncing", "--methods", "cma", "--episodes", "2", "--horizon", "2",
                                "--population", "2", "--json", "--method-args", "--backend numpy"]) == 0
    row = json.loads([line for line in capsys.readouterr().out.splitlines() if line.startswith("{")][0])
    (name, true), = row["true_parameters"].items()
    found = row["parameters"][name]
    assert row["parameter_rel_error"] == pytest.approx(abs(found - true) / true)
    # two CMA-ES samples around the start (2 x the truth, sigma 0.2 in log space) are not within 5 %
    assert row["parameter_rel_error"] > 0.3 and row["success"] is False


def test_bench_optimise_first_seed_runs_the_seeds_from_there(monkeypatch, capsys):
    import sim_core.optim.bench as bench

    seen = []

    def fake_run(task, method, seed, args):
        seen.append((task, method, seed))
        return {"task": task, "method": method, "best_reward": 1.0, "start_reward": 0.0, "wall_time_s": 1.0,
                "rollouts_per_s": 1.0}

    monkeypatch.setattr(bench, "run_one", fake_run)
    assert bench.bench_optimise_main(["--tasks", "forming", "--methods", "cma,gd", "--seeds", "2",
                                      "--first-seed", "3"]) == 0
    assert seen == [("forming", "cma", 3), ("forming", "cma", 4), ("forming", "gd", 3), ("forming", "gd", 4)]
    with pytest.raises(ConfigError, match="--first-seed"):
        bench.bench_optimise_main(["--tasks", "forming", "--methods", "cma", "--first-seed", "-1"])
