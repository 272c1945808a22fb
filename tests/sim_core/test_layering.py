"""One direction of dependency (ARCHITECTURE.md, STYLE.md rule 1): sim_core imports neither ROS, nor
the bag libraries, nor the packages built on top of it."""

from __future__ import annotations

import ast
from pathlib import Path

SIM_CORE = Path(__file__).resolve().parents[2] / "sim_core"
FORBIDDEN = ("rclpy", "rosbags", "mcap", "mcap_ros2", "rosidl_runtime_py", "builtin_interfaces", "geometry_msgs",
             "sensor_msgs", "std_msgs", "std_srvs", "rosgraph_msgs", "visualization_msgs", "sysid", "thinshell_ros")


def _imported_modules(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
    return out


def test_sim_core_imports_no_ros_bag_or_upper_layer_module():
    files = sorted(SIM_CORE.rglob("*.py"))
    assert len(files) > 50  # the whole package was walked
    offending = [f"{p.relative_to(SIM_CORE.parent)}:{line}: import {name}"
                 for p in files for line, name in _imported_modules(p)
                 if name.split(".")[0] in FORBIDDEN]
    assert not offending, "sim_core must not depend on ROS, bags or upper layers:\n" + "\n".join(offending)


def test_the_guard_sees_function_level_imports(tmp_path):
    """Imports inside functions count too (the guard walks the whole tree, not just the module top)."""
    src = tmp_path / "m.py"
    src.write_text("def f():\n    import rclpy.node\n    from sysid.evidence import load_evidence\n")
    assert [n for _, n in _imported_modules(src)] == ["rclpy.node", "sysid.evidence"]
