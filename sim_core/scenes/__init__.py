"""Scenes as data: YAML files in ``config/scenes`` loaded into a Model.

``load_scene(path_or_dict)`` validates a scene v1 file (INTERFACES.md) with
:mod:`sim_core.scenes.scene_file` and builds it with :mod:`sim_core.scenes.tactile_scene`.
"""

from __future__ import annotations

from pathlib import Path

from sim_core.model import Model


def load_scene(scene: str | Path | dict) -> Model:
    """Load a scene file (or an already-parsed dict) into a Model.

    Raises:
        ConfigError: missing file, YAML error, unknown key, wrong version (message names file and key).
    """
    from sim_core.scenes.scene_file import load_scene_file
    from sim_core.scenes.tactile_scene import build_tactile_scene

    parsed = load_scene_file(scene)
    return build_tactile_scene(parsed.to_dict())
