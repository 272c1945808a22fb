"""``thinshell optimise`` end to end on short tasks: outputs (trajectory.yaml by contract B, report,
checkpoint), refusal to overwrite, --force, --resume continuing a finished run, an inverse task."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.trajectory_file import read_trajectory
from sysid.optimise_cli import optimise_main
from thinshell_ros.cli import COMMANDS

ARGS = ["forming", "--horizon", "3", "--population", "4", "--control-points", "1", "--no-progress", "--seed", "2"]


def test_optimise_writes_trajectory_report_and_checkpoint_and_resumes(tmp_path):
    out = tmp_path / "run"
    assert COMMANDS["optimise"][:2] == ("sysid.optimise_cli", "optimise_main")
    assert optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(out)]) == 0
    for name in ("trajectory.yaml", "result.json", "report.html", "reward.png", "before_after.png", "checkpoint.pkl", "scene.yaml"):
        assert (out / name).is_file(), name
    doc = json.loads((out / "result.json").read_text())
    traj = read_trajectory(out / "trajectory.yaml")
    assert traj.waypoint_count == 4 and traj.effectors == ["dome"]
    np.testing.assert_allclose(np.diff(traj.t), 0.005)
    assert traj.prediction["reward"] == pytest.approx(doc["best_reward"])
    assert doc["best_reward"] >= max(h["reward"] for h in doc["history"] if h["reward"] is not None)
    assert "reward.png" in (out / "report.html").read_text()
    # refuses to overwrite; --resume with a larger budget continues the same run
    with pytest.raises(ConfigError, match="exists"):
        optimise_main(ARGS + ["--method", "cma", "--episodes", "4", "--out", str(out)])
    assert optimise_main(ARGS + ["--method", "cma", "--episodes", "8", "--out", str(out), "--resume"]) == 0
    resumed = json.loads((out / "result.json").read_text())
    assert [h["score"] for h in resumed["history"][:4]] == [h["score"] for h in doc["history"]]
    assert len(resumed["history"]) == 8 and resumed["best_reward"] >= doc["best_reward"]
    # a fresh run of the 8 episodes gives the resumed one's history
    fresh = tmp_path / "fresh"
    assert optimise_main(ARGS + ["--method", "cma", "--episodes", "8", "--out", str(fresh)]) == 0
    assert [h["score"] for h in json.loads((fresh / "result.json").read_text())["history"]] == \
        [h["score"] for h in resumed["history"]]
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
