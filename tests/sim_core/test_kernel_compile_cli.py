"""``thinshell compile``: the simulator's kernels compiled ahead of the first run, one line a scene."""

from __future__ import annotations

import pytest

from sim_core.bundled import config_dir
from sim_core.kernel_compile import COMPILE_SCENES, compile_main


def test_the_default_scenes_are_bundled():
    for name in COMPILE_SCENES:
        assert (config_dir() / name).is_file(), name


def test_compile_a_scene_and_step_it(capsys):
    assert compile_main(["--scene", str(config_dir() / "scenes" / "press_slide.yaml"), "--steps", "2"]) == 0
    out = capsys.readouterr().out
    assert "press_slide.yaml:" in out and "for 2 steps" in out and "done in" in out


def test_negative_steps_are_refused(capsys):
    with pytest.raises(SystemExit):
        compile_main(["--steps", "-1"])
    assert "--steps must be >= 0" in capsys.readouterr().err


def test_compile_a_task_runs_its_batched_optimiser(capsys):
    assert compile_main(["--task", "folding_u"]) == 0
    out = capsys.readouterr().out
    assert "0 scene(s) and 1 task(s)" in out and "task Folding-U (batched optimiser):" in out and "done in" in out
    assert "elastic worker kernels" not in out  # a task alone: not the bundled scenes' kernels


def test_compile_task_refuses_a_population_too_small_or_too_long():
    from sim_core.errors import ConfigError
    from sim_core.kernel_compile import compile_task

    with pytest.raises(ConfigError, match="1 copies; a lockstep batch needs at least 2"):
        compile_task("folding_u", copies=1)
    with pytest.raises(ConfigError, match=r"0 steps; task Folding-U takes 1 \.\. \d+"):
        compile_task("folding_u", steps=0)
