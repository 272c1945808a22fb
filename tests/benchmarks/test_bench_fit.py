"""``python -m benchmarks.bench_fit`` (benchmarks.bench_fit): one JSON record of a real (tiny) fit on the bundled bag."""

from __future__ import annotations

import json

import pytest

from benchmarks.bench_fit import bench_sysid_main
from thinshell_ros.paths import bundled_bag


def test_bench_sysid_prints_one_json_record_of_the_fit(capsys, tmp_path):
    code = bench_sysid_main(["--bag", str(bundled_bag()), "--t-max", "0.05", "--params", "gel.youngs_modulus", "--json",
                             "--out", str(tmp_path / "fit"), "--", "--max-nfev", "1"])
    assert code == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1  # thinshell sysid's own lines go to stderr
    record = json.loads(lines[0])
    assert record["bag"] == str(bundled_bag()) and record["params"] == ["gel.youngs_modulus"]
    assert record["steps"] == 5 and record["dt"] == 0.01 and record["duration_s"] == 0.05
    assert record["sim_runs"] >= 1 and 0 < record["fit_wall_s"] <= record["wall_s"]
    assert set(record["values"]) == {"gel.youngs_modulus"} and record["values"]["gel.youngs_modulus"][0] == 3e5
    assert (tmp_path / "fit" / "fit.json").is_file()  # --out keeps the fit's files


def test_bench_sysid_reports_a_failing_fit_with_its_exit_code(tmp_path, capsys):
    assert bench_sysid_main(["--bag", str(tmp_path / "missing"), "--json"]) == 2
    assert "bag not found" in capsys.readouterr().err


def test_bench_sysid_needs_a_bag_when_the_caller_gives_no_default(capsys):
    with pytest.raises(SystemExit):
        bench_sysid_main(["--json"])
    assert "--bag" in capsys.readouterr().err
