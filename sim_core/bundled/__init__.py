"""The bundled configuration of thinshell (scenes, tasks, node parameter files), found with
:mod:`importlib.resources`.

``config/`` is the repository's top-level folder; in a source checkout this package reaches it
through the link ``config`` beside this file, and an installed package (pip, ``colcon build``)
carries a copy of it as its package data (``setup.py`` ``package_data``). It sits in ``sim_core``
because the simulator's own tools read it (the task files of :mod:`sim_core.tasks`, the benchmark
scenes); :mod:`thinshell_ros.paths` reads it through :func:`config_dir` too.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from sim_core.errors import ConfigError

BUNDLE = "sim_core.bundled"


def config_dir() -> Path:
    """The bundled ``config`` folder (``scenes/``, ``tasks/``, ``nodes/``).

    Raises:
        ConfigError: the package was installed without it (the message says to reinstall).
    """
    path = Path(str(resources.files(BUNDLE).joinpath("config"))).resolve()
    if not path.is_dir():
        raise ConfigError(f"the bundled 'config' folder is missing from the package {BUNDLE} ({path}): "
                          f"reinstall thinshell (pip install / colcon build) so that its package data is installed")
    return path
