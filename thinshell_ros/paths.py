"""Locating the bundled configuration (scenes, node parameter files) and recordings.

The configuration is package data of :mod:`sim_core.bundled` (the simulator's tools read it too), the
recordings of :mod:`thinshell_ros.bundled`, both read with :mod:`importlib.resources`: the same code
finds them in a source checkout and in an installed package (``pip install``,
``colcon build``), with no search of the ament index or of the source tree.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from sim_core import bundled as sim_core_bundled
from sim_core.errors import ConfigError

BUNDLE = "thinshell_ros.bundled"
DEFAULT_SCENE = "press_slide"
DEFAULT_BAG = "nominal_s101"


def _bundled_dir(name: str) -> Path:
    """The folder ``name`` (``bags``) of this package's bundled data.

    Raises:
        ConfigError: the package was installed without it.
    """
    path = Path(str(resources.files(BUNDLE).joinpath(name))).resolve()
    if not path.is_dir():
        raise ConfigError(f"the bundled {name!r} folder is missing from the package {BUNDLE} ({path}): "
                          f"reinstall thinshell (pip install / colcon build) so that its package data is installed")
    return path


def config_dir() -> Path:
    """The bundled ``config`` folder (``scenes/``, ``tasks/``, ``nodes/``).

    Raises:
        ConfigError: it is not installed.
    """
    return sim_core_bundled.config_dir()


def bags_dir() -> Path:
    """The bundled ``bags`` folder (one rosbag2 directory per recording).

    Raises:
        ConfigError: it is not installed.
    """
    return _bundled_dir("bags")


def bundled_scene(name: str = DEFAULT_SCENE) -> Path:
    """Path of a bundled scene ``config/scenes/<name>.yaml``.

    Raises:
        ConfigError: no such scene (the message lists the bundled ones), or no bundled config.
    """
    scenes = config_dir() / "scenes"
    path = scenes / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in scenes.glob("*.yaml"))
        raise ConfigError(f"no bundled scene {name!r} in {scenes} (bundled: {known})")
    return path


def bundled_bag(name: str = DEFAULT_BAG) -> Path:
    """Path of a bundled recording ``bags/<name>`` (a rosbag2 directory with ``metadata.yaml``).

    Raises:
        ConfigError: no such recording (the message lists the bundled ones), or no bundled bags.
    """
    bags = bags_dir()
    path = bags / name
    if not (path / "metadata.yaml").is_file():
        known = sorted(p.name for p in bags.iterdir() if (p / "metadata.yaml").is_file())
        raise ConfigError(f"no bundled recording {name!r} in {bags} (expected metadata.yaml, .mcap and "
                          f"scene.yaml; bundled: {known})")
    return path
