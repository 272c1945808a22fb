"""``thinshell bench``: dispatch to the benchmarks, each of which lives with what it measures.

* ``bench forming``, ``bench scale``: the simulator's speed (:mod:`sim_core.bench`, no ROS needed);
  ``forming`` runs the bundled ``forming.yaml`` unless ``--scene`` is given.
* ``bench node``: the sim node's stepping rate and latency through DDS (:mod:`thinshell_ros.bench_node`).
* ``bench tasks``: the ten ThinShellLab tasks' reference trajectories, rewards vs Table A
  (:mod:`sim_core.tasks.bench`).
* ``bench optimise``: the optimisers on the ThinShellLab tasks vs Table A (:mod:`sim_core.optim.bench`).
* ``bench batch``: B copies of a scene stepped together, scene-steps/s against B (:mod:`sim_core.bench.batch`).

The diagnosis benchmark and the fit-time benchmark are tooling of a source checkout, not of the installed
package: ``python -m benchmarks.diagnose_bench`` and ``python -m benchmarks.bench_fit`` (:data:`MOVED`).
"""

from __future__ import annotations

import argparse
import sys

from sim_core.bench.cli import bench_forming_main, bench_scale_main
from sim_core.tasks.bench import bench_tasks_main
from thinshell_ros.paths import bundled_scene

BENCHMARKS = {
    "forming": "ThinShellLab Forming scene, 1698 DoF, benchmark trajectory (sim_core.bench)",
    "scale": "flat sheets of ~1k, 10k, 100k DoF under gravity (sim_core.bench)",
    "node": "the sim node through DDS: real-time factor and command-to-output latency",
    "tasks": "the ten ThinShellLab tasks: reference trajectories' rewards vs Table A",
    "optimise": "the optimisers (CMA-ES, adjoint gradient, hybrid) on the ThinShellLab tasks vs Table A",
    "batch": "B copies of a scene stepped together: scene-steps/s and memory per copy against B",
}
MOVED = {"diagnose": "benchmarks.diagnose_bench", "sysid": "benchmarks.bench_fit"}
"""Former ``thinshell bench`` subcommands -> the checkout module that runs them (``python -m MODULE``)."""


def bench_main(argv: list[str] | None = None) -> int:
    """Entry point of ``thinshell bench {forming,scale,node,tasks,optimise,batch} [ARGS]``; returns the exit
    code of the benchmark (see each one's ``--help``; 2 for an unknown benchmark or one of :data:`MOVED`)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in MOVED:
        print(f"thinshell bench {argv[0]}: moved out of the installed package; run `python -m {MOVED[argv[0]]}` "
              "from the root of a thinshell checkout (benchmarks/)", file=sys.stderr)
        return 2
    parser = argparse.ArgumentParser(prog="thinshell bench", description="benchmarks")
    parser.add_argument("which", choices=sorted(BENCHMARKS),
                        help="; ".join(f"{k}: {v}" for k, v in sorted(BENCHMARKS.items())))
    parser.add_argument("args", nargs=argparse.REMAINDER, help="arguments of the benchmark (thinshell bench WHICH --help)")
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    which, rest = parser.parse_args(argv[:1]).which, argv[1:]
    if which == "forming":
        return bench_forming_main(rest, default_scene=lambda: bundled_scene("forming"))
    if which == "scale":
        return bench_scale_main(rest)
    if which == "tasks":
        return bench_tasks_main(rest)
    if which == "node":
        # optional heavy dependency: ROS 2 (rclpy), for the node benchmark only
        from thinshell_ros.bench_node import bench_node_main

        return int(bench_node_main(rest) or 0)
    # kept lazy: bench forming's cold start counts this process's imports
    if which == "batch":
        from sim_core.bench.batch import bench_batch_main

        return int(bench_batch_main(rest) or 0)
    from sim_core.optim.bench import bench_optimise_main

    return int(bench_optimise_main(rest) or 0)


if __name__ == "__main__":
    sys.exit(bench_main())
