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
