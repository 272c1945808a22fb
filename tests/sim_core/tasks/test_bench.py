"""``thinshell bench tasks --reference``."""

from __future__ import annotations

import json

from sim_core.tasks.bench import bench_tasks_main
from thinshell_ros.cli import main


def test_bench_tasks_reference_reports_reward_score_and_time(capsys):
    assert bench_tasks_main(["--reference", "--tasks", "bouncing", "--json"]) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["task"] == "Bouncing" and row["steps"] == row["horizon"] == 30 and row["infeasible"] is None
    assert row["reward"] == 0.0 and row["units"] == "m^2" and row["sim_s"] > 0 and row["vertices"] == 418


def test_bench_tasks_is_a_bench_subcommand_and_rejects_unknown_tasks(capsys):
    assert main(["bench", "tasks", "--reference", "--tasks", "juggling"]) == 2
    assert "unknown task" in capsys.readouterr().err
