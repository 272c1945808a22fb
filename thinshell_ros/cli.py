"""The ``thinshell`` command line: one entry point, subcommands per job.

``thinshell demo | sim | record | sysid | indent | diagnose | compare | deploy | optimise | compile | bench {forming,scale,node,diagnose,sysid,tasks,optimise,batch}``.
Each subcommand's implementation lives in the module that owns the job; this file only parses
arguments and dispatches (imports are lazy so ``thinshell bench forming`` never loads rclpy).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from sim_core.errors import ThinShellError

# subcommand -> (module, function, help). Functions take ``argv: list[str]`` and return an exit code.
COMMANDS: dict[str, tuple[str, str, str]] = {
    "demo": ("thinshell_ros.demo", "demo_main", "the main job: sim node + scripted commander + recording, then sysid on the bundled bag"),
    "sim": ("thinshell_ros.headless", "sim_main", "simulate a trajectory headless (no DDS) and write a bag"),
    "record": ("thinshell_ros.recorder", "record_main", "record the thinshell topics from a live ROS graph into a bag"),
    "sysid": ("sysid.cli", "sysid_main", "fit material parameters to a recorded bag"),
    "indent": ("sysid.indentation_cli", "indent_main", "fit the gel modulus to indentation depth/force measurements (FEATS)"),
    "diagnose": ("sysid.diagnose_cli", "diagnose_main", "find, name and model missing physics in recorded bags"),
    "compare": ("sysid.compare", "compare_main", "replay a recording's motion in scene(s): RMS per channel, overlay plots, report"),
    "deploy": ("thinshell_ros.deploy_node", "deploy_main", "play a trajectory.yaml (or a bag's pose_cmd stream) on the robot over DDS, with limits and an abort"),
    "compile": ("sim_core.kernel_compile", "compile_main", "compile the simulator's Taichi kernels into the offline cache ahead of the first run (make setup does)"),
    "bench": ("thinshell_ros.bench", "bench_main", "benchmarks: forming, scale, node, tasks, optimise, batch"),
    "optimise": ("sim_core.optim.cli", "optimise_main", "optimise a task's trajectory (CMA-ES, adjoint gradient, hybrid; Ray workers) or an inverse task's parameters"),
}


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``) and run the subcommand; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="thinshell", description="thinshell: thin-shell + tactile simulation, ROS 2 bridge, system identification")
    parser.add_argument("command", choices=sorted(COMMANDS), help="; ".join(f"{k}: {v[2]}" for k, v in sorted(COMMANDS.items())))
    parser.add_argument("args", nargs=argparse.REMAINDER, help="arguments of the subcommand (see thinshell COMMAND --help)")
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    ns = parser.parse_args(argv[:1])
    module, func, _ = COMMANDS[ns.command]
    try:
        entry = getattr(importlib.import_module(module), func)
    except (ImportError, AttributeError) as err:
        print(f"thinshell {ns.command}: not available in this installation ({err})", file=sys.stderr)
        return 2

    try:
        return int(entry(argv[1:]) or 0)
    except ThinShellError as err:
        print(f"thinshell {ns.command}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"thinshell {ns.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
