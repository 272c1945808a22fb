"""Scenes as data: YAML files in ``config/scenes`` loaded into a Model.

``load_scene(path_or_dict)`` validates a scene v1 file (INTERFACES.md) with
:mod:`sim_core.scenes.scene_file` and builds it with :mod:`sim_core.scenes.tactile_scene`; a file
with ``kind: task`` (ThinShellLab-style task scenes: Forming, Folding, Card) is built by
:mod:`sim_core.scenes.task_scene`.
"""

from __future__ import annotations

from pathlib import Path

from sim_core.errors import ConfigError
from sim_core.model import Model


def load_scene(scene: str | Path | dict) -> Model:
    """Load a scene file (or an already-parsed dict) into a Model.

    Raises:
        ConfigError: missing file, YAML error, unknown key, wrong version (message names file and key).
    """
    from sim_core.scenes.scene_file import load_scene_file, load_yaml
    from sim_core.scenes.tactile_scene import build_tactile_scene

    raw = scene
    base_dir = None
    if not isinstance(scene, dict):
        path = Path(scene)
        if not path.is_file():
            raise ConfigError(f"{path}: scene file not found")
        raw = load_yaml(path.read_text())
        base_dir = path.parent
    if isinstance(raw, dict) and raw.get("kind") == "task":
        from sim_core.scenes.task_scene import build_task_scene

        return build_task_scene(raw, base_dir)
    parsed = load_scene_file(scene)
    return build_tactile_scene(parsed.to_dict())
