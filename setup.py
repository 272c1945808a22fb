"""Packaging of thinshell: pip (``pip install -e .``) and ROS 2 ament_python (``colcon build``).

Installs the Python packages ``sim_core``, ``sysid`` and ``thinshell_ros`` with their package data
(``sysid/data``; ``config/`` as the package data of ``sim_core.bundled`` and ``bags/`` as that of
``thinshell_ros.bundled``, which :mod:`thinshell_ros.paths` reads with ``importlib.resources``), the ament resource-index marker,
``package.xml``, every file under ``config/`` (parameter files: ``config/nodes``) and the launch
files under ``launch/`` into ``share/thinshell`` (the ROS convention, for ``ros2 launch thinshell
sim.launch.py`` and ``--params-file``), and the console scripts (also under ``lib/thinshell`` for
``ros2 run``, see ``setup.cfg``).
"""

from __future__ import annotations

import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "thinshell"
HERE = os.path.dirname(os.path.abspath(__file__))


def tree_data_files(folder: str) -> list[tuple[str, list[str]]]:
    """``(install dir, [files])`` for every file under ``folder`` (``config``, ``launch``), keeping the
    folder layout under ``share/thinshell``."""
    groups: dict[str, list[str]] = {}
    for path in sorted(glob(os.path.join(folder, "**", "*"), recursive=True, root_dir=HERE)):
        if os.path.isfile(os.path.join(HERE, path)):
            groups.setdefault(os.path.join("share", PACKAGE, os.path.dirname(path)), []).append(path)
    return sorted(groups.items())


setup(
    name=PACKAGE,
    version="0.1.0",
    description="Differentiable thin-shell + tactile simulator with a ROS 2 bridge and system identification",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["sim_core", "sim_core.*", "sysid", "sysid.*", "thinshell_ros", "thinshell_ros.*"]),
    # sim_core/bundled/config and thinshell_ros/bundled/bags link to the top-level folders; installed as copies
    package_data={"sysid.data": ["*.yaml"], "sim_core.bundled": ["config/**/*"],
                  "thinshell_ros.bundled": ["bags/**/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        (os.path.join("share", PACKAGE), ["package.xml"]),
        *tree_data_files("config"),
        *tree_data_files("launch"),
    ],
    install_requires=["numpy", "scipy", "pyyaml"],
    zip_safe=False,
    entry_points={
        "console_scripts": [
            "thinshell = thinshell_ros.cli:main",
            "thinshell-sim-node = thinshell_ros.sim_node:main",
            "thinshell-sysid-node = thinshell_ros.sysid_node:main",
            "thinshell-deploy-node = thinshell_ros.deploy_node:main",
            "sim_node = thinshell_ros.sim_node:main",
        ],
    },
)
