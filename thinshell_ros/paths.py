"""Locating bundled configuration (scenes, node parameter files) without hard-coded paths.

Installed as a ROS package (``colcon build`` / ``pip install``) the files live in the ament share
directory ``share/thinshell/config``; in a source checkout they are in ``<repo>/config``.
"""

from __future__ import annotations

from pathlib import Path

PACKAGE = "thinshell"
DEFAULT_SCENE = "press_slide"


def config_dir() -> Path:
    """``config`` directory of the installed package (ament index), else of the source tree.

    Raises:
        FileNotFoundError: neither exists.
    """
    try:
        # optional heavy dependency: ROS 2 (rclpy), for ROS commands only
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        try:
            share = Path(get_package_share_directory(PACKAGE)) / "config"
            if share.is_dir():
                return share
        except (PackageNotFoundError, OSError):  # OSError: AMENT_PREFIX_PATH unset
            pass
    except ImportError:
        pass
    source = Path(__file__).resolve().parents[1] / "config"
    if source.is_dir():
        return source
    raise FileNotFoundError(f"no thinshell config directory: package {PACKAGE!r} is not in the ament index "
                            f"(AMENT_PREFIX_PATH) and {source} does not exist")


def bundled_scene(name: str = DEFAULT_SCENE) -> Path:
    """Path of a bundled scene ``config/scenes/<name>.yaml``.

    Raises:
        FileNotFoundError: no such scene (the message lists the bundled ones).
    """
    scenes = config_dir() / "scenes"
    path = scenes / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in scenes.glob("*.yaml"))
        raise FileNotFoundError(f"no bundled scene {name!r} in {scenes} (bundled: {known})")
    return path
