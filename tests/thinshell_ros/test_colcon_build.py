"""``colcon build`` of the package in a temporary workspace (ament_python) and what it installs."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

from tests.thinshell_ros.conftest import PYTHON, REPO

PACKAGE_FILES = ("package.xml", "setup.py", "setup.cfg", "resource", "config", "bags", "sim_core", "sysid", "thinshell_ros")


def test_colcon_build_installs_package(tmp_path):
    src = tmp_path / "src" / "thinshell"
    src.mkdir(parents=True)
    for name in PACKAGE_FILES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(path, src / name)
    colcon = Path(PYTHON).parent / "colcon"
    env = {k: v for k, v in os.environ.items() if k not in ("AMENT_PREFIX_PATH", "COLCON_PREFIX_PATH")}
    proc = subprocess.run([str(colcon), "build", "--base-paths", "src"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    prefix = tmp_path / "install" / "thinshell"
    share = prefix / "share" / "thinshell"
    assert (share / "package.xml").read_text() == (REPO / "package.xml").read_text()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "thinshell").is_file()
    assert (share / "config" / "scenes" / "press_slide.yaml").is_file()
    for script in ("thinshell", "thinshell-sim-node", "thinshell-sysid-node", "thinshell-deploy-node", "sim_node"):
        path = prefix / "lib" / "thinshell" / script
        assert path.is_file() and os.access(path, os.X_OK), script
    (site,) = prefix.glob("lib/python3*/site-packages")
    assert (site / "thinshell_ros" / "sim_node.py").is_file() and (site / "sim_core" / "simulation.py").is_file()
    # the installed code finds its bundled scene and recording as its package data (importlib.resources),
    # not through the ament index or the source tree
    run_env = dict(env, AMENT_PREFIX_PATH=str(prefix), PYTHONPATH=str(site))
    out = subprocess.run([PYTHON, "-c", "from thinshell_ros.paths import bundled_bag, bundled_scene; "
                          "print(bundled_scene()); print(bundled_bag())"],
                         cwd=tmp_path, env=run_env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    scene, bag = out.stdout.split()
    assert Path(scene) == site / "sim_core" / "bundled" / "config" / "scenes" / "press_slide.yaml"
    bag_dir = site / "thinshell_ros" / "bundled" / "bags" / "nominal_s101"
    assert Path(bag) == bag_dir and (Path(bag) / "nominal_s101.mcap").is_file()
    # sysid's packaged data comes with the installed package (importlib.resources)
    out = subprocess.run([PYTHON, "-c", "from sysid.data import data_file; print(data_file('default.yaml'))"],
                         cwd=tmp_path, env=run_env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert Path(out.stdout.strip()) == site / "sysid" / "data" / "default.yaml"
    out = subprocess.run([str(prefix / "lib" / "thinshell" / "thinshell"), "--help"], env=run_env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "usage: thinshell" in out.stdout, out.stderr
