"""A task scene file (``kind: task``) read as data, for code that reads recordings (``sysid``).

A version-1 tactile scene is parsed into a :class:`~sim_core.scenes.scene_file.SceneFile`; a task
scene (:mod:`sim_core.scenes.task_scene`, ``task_scene_v2``) is validated by building its model, so
this module only keeps its mapping, its source and the directory its mesh files are relative to.
:func:`load_any_scene_file` returns whichever of the two a file (or mapping) is.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from sim_core.errors import ConfigError
from sim_core.scenes.scene_file import SceneFile, _read_yaml, load_scene_file


@dataclass(frozen=True)
class TaskSceneFile:
    """A ``kind: task`` scene as read from its file.

    Attributes:
        source: the file it was read from (``"<dict>"`` for a mapping).
        data: the scene mapping as written.
        base_dir: directory that relative mesh paths are resolved against, or None.
        sensors: always empty: task scenes carry no tactile sensor of the version-1 schema (the
            readers of recordings look up sensors by name here).
    """

    source: str
    data: dict
    base_dir: Path | None = None
    sensors: dict = field(default_factory=dict)

    @property
    def effector_names(self) -> list[str]:
        """Names of the scene's effectors, in file order."""
        return list((self.data.get("effectors") or {}).keys())

    def to_dict(self) -> dict[str, Any]:
        """A deep copy of the scene mapping."""
        return copy.deepcopy(self.data)


def is_task_scene(data: Any) -> bool:
    """True for a mapping with ``kind: task``."""
    return isinstance(data, Mapping) and data.get("kind") == "task"


def load_any_scene_file(scene: str | Path | Mapping[str, Any] | SceneFile | TaskSceneFile,
                        base_dir: Path | None = None) -> SceneFile | TaskSceneFile:
    """A version-1 :class:`SceneFile` or a :class:`TaskSceneFile`, whichever ``scene`` is.

    Args:
        scene: path, mapping, or an already loaded scene (returned unchanged).
        base_dir: mesh directory of a mapping (a path's own directory otherwise).

    Raises:
        ConfigError: missing file, invalid YAML, or an invalid version-1 scene (names file and key).
    """
    if isinstance(scene, (SceneFile, TaskSceneFile)):
        return scene
    if isinstance(scene, Mapping):
        data, source = scene, "<dict>"
    else:
        path = Path(scene)
        if not path.is_file():
            raise ConfigError(f"{path}: scene file not found")
        data, source, base_dir = _read_yaml(path), str(path), path.parent
    if is_task_scene(data):
        return TaskSceneFile(source=source, data=copy.deepcopy(dict(data)), base_dir=base_dir)
    return load_scene_file(scene)
