"""``load_any_scene_file``: a version-1 tactile scene parses to a SceneFile, a ``kind: task`` scene to a
TaskSceneFile that keeps its mapping and mesh directory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.scenes.scene_file import SceneFile
from sim_core.scenes.task_file import TaskSceneFile, load_any_scene_file
from sim_core.tasks.registry import load_task
from sim_core.tasks.rollout import build_task_simulation

SCENES = Path(__file__).resolve().parents[3] / "config" / "scenes"


def test_load_any_scene_file_tells_tactile_from_task_scenes(tmp_path):
    v1 = load_any_scene_file(SCENES / "press_slide.yaml")
    assert isinstance(v1, SceneFile) and v1.sensors
    task = load_any_scene_file(SCENES / "card.yaml")
    assert isinstance(task, TaskSceneFile) and task.sensors == {}
    assert task.effector_names == ["dome_left", "dome_right", "dome_top"] and task.base_dir == SCENES
    copy = task.to_dict()
    copy["sheets"]["card_0"]["size"][0] = 1.0
    assert task.data["sheets"]["card_0"]["size"][0] == 0.06        # to_dict is a deep copy
    assert load_any_scene_file(task) is task
    with pytest.raises(ConfigError, match="missing.yaml: scene file not found"):
        load_any_scene_file(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="unknown key"):
        load_any_scene_file({"version": 1, "name": "x", "bogus": 1})


def test_a_stack_of_cards_publishes_every_card_as_sheet_points():
    sim = build_task_simulation(load_task("card"))
    model = sim.model
    cards = [b for b in model.bodies.values() if b.kind == "sheet"]
    assert len(cards) == 3 and "sheet" not in model.bodies
    obs = sim.observe()
    assert obs.sheet_points.shape == (sum(b.vertex_stop - b.vertex_start for b in cards), 3)
    np.testing.assert_array_equal(obs.sheet_points, sim.state.x[model.tracked_sheet_vertices()])
    assert obs.sheet_triangles.shape[0] == sum(len(b.triangles) for b in cards)
    assert obs.sheet_triangles.max() == obs.sheet_points.shape[0] - 1
