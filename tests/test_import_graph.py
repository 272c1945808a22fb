"""The import graph of thinshell's packages (module-level imports, read with ``ast``): no cycles, and
the layers of STYLE.md (sim_core <- sysid <- thinshell_ros): sim_core imports neither ROS, the bag
libraries nor the packages above it, sysid does not import thinshell_ros, only ``sysid.bagio`` opens
bags (rosbags / mcap), at any level of a module (function-level imports included).

Function-level imports close no cycle either, and neither do imports under ``if TYPE_CHECKING:``
(never executed, but a circle all the same for a reader: the annotation names a module that imports
this one; a ``Protocol`` of what is needed breaks it). ``tests/test_import_linter.py`` checks the same rules with import-linter
(``.importlinter``), which also forbids cycles between sibling packages.

A module-level import is one executed when the module is imported: in the module body, also inside
``if`` / ``try`` / ``with`` blocks and class bodies, but not inside functions and not under
``if TYPE_CHECKING:``. ``from package import name`` is an import of ``package.name`` when that is a
module of the tree, else of ``package``; a parent package is not counted as imported by its modules'
importers (as in grimp / import-linter).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("sim_core", "sysid", "thinshell_ros")

FORBIDDEN = {
    "sim_core": ("rclpy", "rosbags", "mcap", "mcap_ros2", "sysid", "thinshell_ros", "benchmarks"),
    "sysid": ("rclpy", "thinshell_ros", "benchmarks"),
    "thinshell_ros": ("benchmarks",),
}
"""Package -> top-level names its modules never import (at any level): the layers, and no product
package imports the checkout's benchmark and test-set tooling (``benchmarks/``, not installed)."""

BAG_LIBRARIES = ("rosbags", "mcap", "mcap_ros2")
BAG_READER_PACKAGE = "sysid.bagio"
"""The only part of sysid that imports a bag library."""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))}


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _import_nodes(tree: ast.Module, module_level: bool,
                  type_checking: bool = False) -> list[ast.Import | ast.ImportFrom]:
    """The import statements of a module: every one (``type_checking``), all of them but those under
    ``if TYPE_CHECKING:`` (never executed), or only those run at import time (``module_level``)."""
    if type_checking:
        return [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    if not module_level:
        typing_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If) and _is_type_checking(block.test)
                       for stmt in block.body for n in ast.walk(stmt)}
        return [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)) and id(n) not in typing_only]
    out: list[ast.Import | ast.ImportFrom] = []

    def visit(nodes: list[ast.stmt]) -> None:
        for node in nodes:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                out.append(node)
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            elif isinstance(node, ast.If):
                if not _is_type_checking(node.test):
                    visit(node.body)
                visit(node.orelse)
            elif isinstance(node, ast.Try):
                visit(node.body)
                for handler in node.handlers:
                    visit(handler.body)
                visit(node.orelse)
                visit(node.finalbody)
            elif isinstance(node, (ast.With, ast.ClassDef, ast.For, ast.While)):
                visit(node.body)

    visit(tree.body)
    return out


def _imported_names(module: str, path: Path, node: ast.Import | ast.ImportFrom, modules: dict[str, Path]) -> list[str]:
    """Absolute names ``node`` imports (a module of the tree where the name is one, else as written)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
        base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
    else:
        base = node.module or ""
    return [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]


def import_graph(module_level: bool = True, type_checking: bool = False) -> dict[str, set[str]]:
    """Module -> the names it imports (modules of the tree, or external names as written); the
    imports counted as in :func:`_import_nodes`."""
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for module, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        graph[module] = {name for node in _import_nodes(tree, module_level, type_checking)
                         for name in _imported_names(module, path, node, modules)}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (or a module importing itself) of
    the graph restricted to the tree's modules, each sorted; Tarjan's algorithm."""
    nodes = set(graph)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def connect(v: str) -> None:
        work = [(v, iter(sorted(graph[v] & nodes)))]
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        while work:
            node, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w] & nodes))))
                    break
                if w in on_stack:
                    low[node] = min(low[node], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        component.append(w)
                        if w == node:
                            break
                    if len(component) > 1 or node in graph[node]:
                        out.append(sorted(component))

    for v in sorted(nodes):
        if v not in index:
            connect(v)
    return sorted(out)


def _top(name: str) -> str:
    return name.split(".")[0]


def test_the_graph_sees_every_module_and_resolves_relative_and_submodule_imports():
    graph = import_graph()
    assert {"sim_core.solver", "sysid.observation", "thinshell_ros.sim_node"} <= set(graph)
    assert "sim_core.contact_set" in graph["sim_core.solver"]
    assert "numpy" in graph["sim_core.solver"]


def test_there_is_no_import_cycle():
    cycles = import_cycles(import_graph())
    assert not cycles, "import cycles (module-level imports):\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_no_cycle_through_function_level_imports():
    """Counting every executed import (function-level ones included, ``TYPE_CHECKING`` ones not),
    there is no cycle either."""
    cycles = import_cycles(import_graph(module_level=False))
    assert not cycles, "import cycles (all imports):\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_no_cycle_through_annotation_imports():
    """Counting every import statement, those under ``if TYPE_CHECKING:`` included, there is no cycle."""
    cycles = import_cycles(import_graph(type_checking=True))
    assert not cycles, "import cycles (every import statement):\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_annotation_imports_are_counted(tmp_path):
    """An import under ``if TYPE_CHECKING:`` is an edge of the full graph, not of the executed one."""
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import sysid.fit\n")
    assert [n.names[0].name for n in _import_nodes(tree, False, type_checking=True) if isinstance(n, ast.Import)] \
        == ["sysid.fit"]
    assert not [n for n in _import_nodes(tree, False) if isinstance(n, ast.Import)]


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_a_package_imports_nothing_above_its_layer(package):
    graph = import_graph(module_level=False)
    bad = sorted(f"{module} imports {name}" for module, names in graph.items() if _top(module) == package
                 for name in names if _top(name) in FORBIDDEN[package])
    assert not bad, "\n".join(bad)


def test_only_the_bag_reader_imports_a_bag_library():
    graph = import_graph(module_level=False)
    bad = sorted(f"{module} imports {name}" for module, names in graph.items()
                 if _top(module) != "thinshell_ros" and not (module + ".").startswith(BAG_READER_PACKAGE + ".")
                 for name in names if _top(name) in BAG_LIBRARIES)
    assert not bad, "\n".join(bad)


def test_cycles_are_found():
    graph = {"a": {"b"}, "b": {"c", "numpy"}, "c": {"a"}, "d": {"d"}, "e": {"a"}}
    assert import_cycles(graph) == [["a", "b", "c"], ["d"]]
