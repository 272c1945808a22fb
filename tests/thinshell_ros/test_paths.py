"""The bundled scenes and recordings are package data of sim_core.bundled and thinshell_ros.bundled
(importlib.resources):
found in a source checkout (the installed case: tests/thinshell_ros/test_colcon_build.py), with a
clear error naming the missing folder, scene or recording."""

from __future__ import annotations

from importlib import resources

import pytest

from sim_core.errors import ConfigError
from sim_core.scenes.scene_file import load_scene_file
from thinshell_ros import paths
from tests.thinshell_ros.conftest import REPO


def test_the_checkout_finds_the_repository_config_and_bags():
    assert paths.config_dir() == REPO / "config" and paths.bags_dir() == REPO / "bags"
    scene = paths.bundled_scene()
    assert scene == REPO / "config" / "scenes" / "press_slide.yaml"
    assert load_scene_file(scene) is not None
    bag = paths.bundled_bag()
    assert bag == REPO / "bags" / "nominal_s101" and (bag / "nominal_s101.mcap").is_file()


def test_unknown_names_are_refused_with_the_bundled_ones_listed():
    with pytest.raises(ConfigError, match=r"no bundled scene 'nope'.*'press_slide'"):
        paths.bundled_scene("nope")
    with pytest.raises(ConfigError, match=r"no bundled recording 'nope'.*'nominal_s101'"):
        paths.bundled_bag("nope")


def test_a_package_installed_without_its_data_says_so(tmp_path, monkeypatch):
    """A package whose bundled folders were not installed (no package data): the error names the
    folder and the package and says to reinstall."""
    real = resources.files
    fake = lambda name: tmp_path if name in (paths.BUNDLE, "sim_core.bundled") else real(name)  # noqa: E731
    monkeypatch.setattr(resources, "files", fake)
    for call, folder, package in ((paths.bundled_scene, "config", "sim_core.bundled"),
                                  (paths.bundled_bag, "bags", "thinshell_ros.bundled")):
        with pytest.raises(ConfigError, match=rf"bundled '{folder}' folder is missing from the package "
                                              rf"{package} .*reinstall"):
            call()


def test_the_task_files_are_found_as_package_data():
    """The simulator's own tools (task registry) read the same bundled configuration."""
    from sim_core.tasks.registry import default_tasks_dir

    assert default_tasks_dir() == REPO / "config" / "tasks" and (default_tasks_dir() / "forming.yaml").is_file()
