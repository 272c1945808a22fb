"""benchmarks/mujoco_world/plan_jobs.py: one device job a plan line (generate, then diagnose, report copied to $OUT)."""

import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.mujoco_world.plan_jobs import job_lines

REPO = Path(__file__).resolve().parents[3]
PLAN = REPO / "benchmarks" / "mujoco_world" / "plans" / "session51_power.txt"


def test_every_plan_line_becomes_one_generate_and_diagnose_job(tmp_path):
    lines = job_lines(PLAN)
    plan = [x.split() for x in PLAN.read_text().splitlines() if x.strip() and not x.startswith("#")]
    assert len(lines) == len(plan) == 32
    by_name = {p[1]: line for p, line in zip(plan, lines)}
    creep = by_name["gel_creep_s631"]
    assert "--variant gel_creep" in creep and "--magnitude 0.03" in creep and "--direction=+x" in creep
    assert "diagnose /tmp/gen/gel_creep_s631 " in creep and "$OUT/reports/" in creep
    assert "--stiction-switch=load" in by_name["stiction_s611"] and "--stiction-switch" not in by_name["stiction_s661"]
    short = by_name["nominal_s600"]
    assert "--short" in short and "--magnitude" not in short and "--direction" not in short
    assert len(job_lines(PLAN, "none")) == 0
    bad = tmp_path / "bad.txt"
    bad.write_text("power x nominal - press_slide 1 +x long\n")
    with pytest.raises(ValueError, match="bad.txt:1"):
        job_lines(bad)


def test_the_script_prints_the_jobs():
    out = subprocess.run([sys.executable, "benchmarks/mujoco_world/plan_jobs.py", str(PLAN), "power"], cwd=REPO,
                         capture_output=True, text=True, timeout=120, check=True).stdout
    assert len(out.strip().splitlines()) == 32
