"""The launch files (``launch/*.launch.py``) and per-node parameter files (``config/nodes/*.yaml``),
checked without the ``launch`` package (the wheels here have none; a ROS 2 install runs them).

Each launch file is read as Python source (``ast``): every ``launch_ros`` ``Node`` it starts must name
this package, an executable that ``setup.py`` installs (``console_scripts``), a parameter file that
exists under ``config/nodes`` and is installed, whose node key is the launched node's name, and only
parameters the node declares (read from the node itself, built here on a stand-in simulation);
every ``LaunchConfiguration`` it reads must be declared by a ``DeclareLaunchArgument``; a CLI
subcommand's options must be the subcommand's. ``setup.py`` is run with ``setuptools.setup``
captured, so what it would install is what is checked.
"""

from __future__ import annotations

import ast
import re
import runpy
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any, Callable

import pytest
import setuptools
import yaml

from tests.thinshell_ros.conftest import REPO

pytestmark = pytest.mark.ros

LAUNCH_FILES = sorted((REPO / "launch").glob("*.launch.py"))
BUILTIN_PARAMETERS = {"use_sim_time"}
"""Parameters every rclpy node declares."""


def _setup_kwargs(monkeypatch) -> dict[str, Any]:
    captured: dict[str, Any] = {}
    monkeypatch.setattr(setuptools, "setup", lambda **kw: captured.update(kw))
    monkeypatch.chdir(REPO)
    runpy.run_path(str(REPO / "setup.py"), run_name="__main__")
    return captured


def _console_scripts(kwargs: dict[str, Any]) -> dict[str, str]:
    """executable -> ``module:function``."""
    return dict(re.fullmatch(r"\s*(\S+)\s*=\s*(\S+)\s*", s).groups() for s in kwargs["entry_points"]["console_scripts"])


def _installed(kwargs: dict[str, Any]) -> set[str]:
    """Repository paths installed by ``data_files``, as ``install dir/file name``."""
    return {f"{folder}/{Path(f).name}" for folder, files in kwargs["data_files"] for f in files}


def _name(node: ast.AST) -> str:
    return node.func.id if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) else ""


def _const(node: ast.AST) -> Any:
    if not isinstance(node, ast.Constant):
        raise AssertionError(f"expected a literal, got {ast.unparse(node)}")
    return node.value


def _launch_nodes(path: Path) -> tuple[list[dict[str, Any]], set[str], set[str]]:
    """``(nodes, declared arguments, read configurations)`` of a launch file; each node ``{package,
    executable, name, params_files: [[parts]], params: {key}, arguments: [str | None]}`` (None: a
    substitution)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    assert any(isinstance(f, ast.FunctionDef) and f.name == "generate_launch_description" for f in tree.body), path
    declared, read, nodes = set(), set(), []
    for call in (n for n in ast.walk(tree) if isinstance(n, ast.Call)):
        if _name(call) == "DeclareLaunchArgument":
            declared.add(_const(call.args[0]))
        elif _name(call) == "LaunchConfiguration":
            read.add(_const(call.args[0]))
        elif _name(call) == "Node":
            kw = {k.arg: k.value for k in call.keywords}
            node = {"package": _const(kw["package"]), "executable": _const(kw["executable"]),
                    "name": _const(kw["name"]) if "name" in kw else None, "params_files": [], "params": set(),
                    "arguments": []}
            for item in getattr(kw.get("parameters"), "elts", []):
                if isinstance(item, ast.Dict):
                    node["params"] |= {_const(k) for k in item.keys}
                else:  # a name bound to PathJoinSubstitution([FindPackageShare(pkg), parts...])
                    node["params_files"].append(_params_file(tree, item))
            node["arguments"] = [a.value if isinstance(a, ast.Constant) else None
                                 for a in getattr(kw.get("arguments"), "elts", [])]
            nodes.append(node)
    return nodes, declared, read


def _params_file(tree: ast.AST, item: ast.AST) -> list[str]:
    """The path parts of a parameter file given as ``PathJoinSubstitution([FindPackageShare("thinshell"), ...])``,
    inline, through a local name, or as the default of a launch argument (``LaunchConfiguration``)."""
    if _name(item) == "LaunchConfiguration":
        name = _const(item.args[0])
        declare = next(c for c in ast.walk(tree) if _name(c) == "DeclareLaunchArgument" and _const(c.args[0]) == name)
        item = next(k.value for k in declare.keywords if k.arg == "default_value")
    if isinstance(item, ast.Name):
        item = next(a.value for a in ast.walk(tree) if isinstance(a, ast.Assign)
                    and any(isinstance(t, ast.Name) and t.id == item.id for t in a.targets))
    assert _name(item) == "PathJoinSubstitution", ast.unparse(item)
    share, *parts = item.args[0].elts
    assert _name(share) == "FindPackageShare" and _const(share.args[0]) == "thinshell", ast.unparse(share)
    return [_const(p) for p in parts]


def _declared_parameters(ros_context) -> dict[str, Callable[[], set[str]]]:
    """Entry point module -> the parameters its node declares (the node built on a stand-in)."""
    from tests.thinshell_ros.fake_sim import FakeSimulation
    from tests.thinshell_ros.test_deploy_node import _line

    def built(factory) -> set[str]:
        node = factory()
        try:
            return set(node.list_parameters([], 0).names)
        finally:
            node.destroy_node()

    def sim() -> set[str]:
        from thinshell_ros.sim_node import SimNode
        return built(lambda: SimNode(sim=FakeSimulation(), context=ros_context)) - set(FakeSimulation().parameter_names)

    def sysid() -> set[str]:
        from thinshell_ros.sysid_node import SysidNode
        return built(lambda: SysidNode(context=ros_context))

    def deploy() -> set[str]:
        from thinshell_ros.deploy_node import DeployNode
        return built(lambda: DeployNode(trajectory=_line(), context=ros_context))

    return {"thinshell_ros.sim_node": sim, "thinshell_ros.sysid_node": sysid, "thinshell_ros.deploy_node": deploy}


def _cli_options(module: str, function: str) -> set[str]:
    """The ``--options`` a CLI function's ``argparse`` parser adds (read from its source)."""
    tree = ast.parse((REPO / (module.replace(".", "/") + ".py")).read_text())
    fn = next(f for f in ast.walk(tree) if isinstance(f, ast.FunctionDef) and f.name == function)
    return {a.value for c in ast.walk(fn) if isinstance(c, ast.Call) and getattr(c.func, "attr", "") == "add_argument"
            for a in c.args if isinstance(a, ast.Constant) and str(a.value).startswith("--")}


CLI_SUBCOMMANDS = {"record": ("thinshell_ros.recorder", "record_main")}
"""``thinshell <subcommand>`` a launch file may run -> the function that parses its options."""


def test_the_launch_files_exist_and_are_installed(monkeypatch):
    kwargs = _setup_kwargs(monkeypatch)
    names = {p.name for p in LAUNCH_FILES}
    assert {"sim.launch.py", "sysid.launch.py", "record.launch.py", "deploy.launch.py"} <= names, names
    installed = _installed(kwargs)
    assert {f"share/thinshell/launch/{n}" for n in names} <= installed
    params_files = {p.name for p in (REPO / "config" / "nodes").glob("*.yaml")}
    assert {"sim_node.yaml", "sysid_node.yaml", "deploy_node.yaml"} <= params_files
    assert {f"share/thinshell/config/nodes/{n}" for n in params_files} <= installed
    package = ET.parse(REPO / "package.xml").getroot()
    assert {d.text for d in package.iter("exec_depend")} >= {"launch", "launch_ros", "diagnostic_msgs"}


def test_every_node_executable_parameter_and_argument_the_launch_files_name_exists(monkeypatch, ros_context):
    kwargs = _setup_kwargs(monkeypatch)
    scripts = _console_scripts(kwargs)
    installed = _installed(kwargs)
    package = ET.parse(REPO / "package.xml").getroot().findtext("name")
    declared_of = _declared_parameters(ros_context)
    cache: dict[str, set[str]] = {}
    checked = 0
    for path in LAUNCH_FILES:
        nodes, declared_args, read_args = _launch_nodes(path)
        assert read_args <= declared_args, \
            f"{path.name}: undeclared launch arguments {sorted(read_args - declared_args)}"
        assert nodes, f"{path.name}: starts no node"
        for node in nodes:
            where = f"{path.name}: {node['executable']}"
            assert node["package"] == package, where
            assert node["executable"] in scripts, f"{where}: not a console script of setup.py ({sorted(scripts)})"
            module, function = scripts[node["executable"]].split(":")
            if node["arguments"]:  # a CLI subcommand: its options must be the subcommand's
                sub = node["arguments"][0]
                assert module == "thinshell_ros.cli" and sub in CLI_SUBCOMMANDS, f"{where}: subcommand {sub!r}"
                options = _cli_options(*CLI_SUBCOMMANDS[sub])
                flags = {a for a in node["arguments"][1:] if isinstance(a, str) and a.startswith("--")}
                assert flags <= options, f"{where} {sub}: unknown options {sorted(flags - options)}"
                known = BUILTIN_PARAMETERS
            else:
                assert module in declared_of, f"{where}: add its node to _declared_parameters"
                known = cache.setdefault(module, declared_of[module]()) | BUILTIN_PARAMETERS
            assert node["params"] <= known, f"{where}: undeclared parameters {sorted(node['params'] - known)}"
            for parts in node["params_files"]:
                file = REPO.joinpath(*parts)
                assert file.is_file(), f"{where}: no {'/'.join(parts)}"
                assert f"share/thinshell/{'/'.join(parts)}" in installed, f"{where}: {file} not installed"
                doc = yaml.safe_load(file.read_text())
                # the node's key: its name, or its name in any namespace (ROS 2 wildcards)
                assert len(doc) == 1 and next(iter(doc)) in (node["name"], f"/**/{node['name']}"), \
                    f"{file.name}: node key {list(doc)} is not {node['name']!r}"
                keys = set(next(iter(doc.values()))["ros__parameters"])
                assert keys <= known, f"{file.name}: undeclared parameters {sorted(keys - known)}"
            checked += 1
    assert checked >= 4


def test_the_checks_catch_a_wrong_name(monkeypatch, ros_context, tmp_path):
    """A launch file naming an executable, a parameter or an argument that does not exist fails the check."""
    source = (REPO / "launch" / "sim.launch.py").read_text()
    declared = _declared_parameters(ros_context)["thinshell_ros.sim_node"]()
    assert {"scene", "mode", "step_count", "error_log_period", "workspace_margin"} <= declared
    for old, new, expect in (('"thinshell-sim-node"', '"thinshell-simulator"', "executable"),
                             ('"publish_image": ', '"publish_images": ', "parameter"),
                             ('LaunchConfiguration("backend")', 'LaunchConfiguration("solver")', "argument")):
        broken = tmp_path / "broken.launch.py"
        broken.write_text(source.replace(old, new))
        nodes, declared_args, read_args = _launch_nodes(broken)
        scripts = _console_scripts(_setup_kwargs(monkeypatch))
        problems = {"executable": nodes[0]["executable"] not in scripts,
                    "parameter": not nodes[0]["params"] <= declared | BUILTIN_PARAMETERS,
                    "argument": not read_args <= declared_args}
        assert [k for k, bad in problems.items() if bad] == [expect]
