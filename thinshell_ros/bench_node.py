"""``thinshell bench node``: real-time factor and command-to-output latency of the sim node over DDS.

The node runs in a subprocess (``python -m thinshell_ros.sim_node``); a client node in this process
measures

- real-time factor: simulated time advanced (``/clock``) / wall time, over a window;
- latency: wall time from publishing a pose command (a small step of the effector, within the
  per-step limit so one step reaches it) to receiving the first ``<effector>/pose`` that shows it;
  it includes DDS transport both ways, the wait for the next step, the step and the publication.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import Any, Sequence

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from sim_core.backend import BACKEND_CHOICES
from thinshell_ros import conversions as cv
from thinshell_ros.runtime import CLOCK_QOS, COMMAND_QOS, SENSOR_QOS
from thinshell_ros.sim_node import EXECUTORS


def measure_node(context: Context, namespace: str = "/thinshell", effector: str = "ee", window: float = 3.0,
                 commands: int = 20, step: float = 2e-4, timeout: float = 60.0, warmup: int = 20,
                 keep_probes: bool = False) -> dict[str, Any]:
    """Measure a running sim node from a client node in ``context``.

    Args:
        context: initialised rclpy context on the node's domain.
        namespace, effector: topics of the node.
        window: wall seconds of the real-time-factor window.
        commands: number of latency probes (alternately +step and -step along world z).
        step: probe displacement in m (must be within the node's per-step limit).
        timeout: wall seconds to wait for the node's first output, for its warm-up and for each probe.
        warmup: node steps (advances of ``/clock``) to wait for before the window starts: the first
            steps of a Taichi backend compile its kernels (seconds), which is start-up, not stepping.
        keep_probes: also return each probe (``probes_sent``).

    Returns:
        dict with ``real_time_factor``, ``steps_per_second`` (simulated time over the step dt, the
        smallest /clock increment: robust to dropped best-effort /clock messages), ``latency_ms``
        (``median``, ``p95``, ``max``), ``probes``, ``lost``; with ``keep_probes`` also
        ``probes_sent``: per probe ``[sent, received, z]``, the client's ``time.monotonic()`` (s) when
        the command was published and when its pose arrived (None: lost) and the commanded z (m).

    Raises:
        TimeoutError: the node published nothing, or did not finish its warm-up, within ``timeout``.
    """
    node = Node("thinshell_bench_client", context=context)
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    clock: list[tuple[float, int]] = []
    poses: list[tuple[float, np.ndarray]] = []
    node.create_subscription(Clock, "/clock", lambda m: clock.append((time.monotonic(), cv.clock_from_msg(m))), CLOCK_QOS)
    node.create_subscription(PoseStamped, f"{namespace}/{effector}/pose",
                             lambda m: poses.append((time.monotonic(), cv.pose_from_msg(m)[1])), SENSOR_QOS)
    pub = node.create_publisher(PoseStamped, f"{namespace}/{effector}/pose_cmd", COMMAND_QOS)

    def spin_for(cond, limit: float) -> bool:
        end = time.monotonic() + limit
        while time.monotonic() < end and not cond():
            ex.spin_once(timeout_sec=0.005)
        return cond()

    try:
        if not spin_for(lambda: bool(clock) and bool(poses) and pub.get_subscription_count() > 0, timeout):
            raise TimeoutError(f"no /clock and {namespace}/{effector}/pose from the sim node within {timeout} s")
        def clock_advances() -> int:
            return sum(1 for a, b in zip(clock, clock[1:]) if b[1] > a[1])

        if not spin_for(lambda: clock_advances() >= warmup, timeout):
            raise TimeoutError(f"the sim node did not take {warmup} steps (/clock) within {timeout} s")
        n0 = len(clock)
        spin_for(lambda: False, window)
        win = clock[n0:]
        rtf = steps_per_s = float("nan")
        if len(win) >= 2 and win[-1][0] > win[0][0]:
            rtf = (win[-1][1] - win[0][1]) * 1e-9 / (win[-1][0] - win[0][0])
            # /clock is best effort, keep-last 1: a busy client drops some, so count steps by sim
            # time over the step dt (the smallest clock increment seen) rather than by messages
            increments = np.diff([c[1] for c in win])
            increments = increments[increments > 0]
            if increments.size:
                steps_per_s = rtf / (float(increments.min()) * 1e-9)
        base = poses[-1][1].copy()
        latencies, lost, sent = [], 0, []
        for k in range(commands):
            target = base.copy()
            target[2] += step if k % 2 == 0 else 0.0
            n_before = len(poses)
            t0 = time.monotonic()
            pub.publish(cv.pose_to_msg(target, 0))
            reached = spin_for(lambda: any(abs(p[2] - target[2]) < 1e-7 for _, p in poses[n_before:]), timeout)
            if not reached:
                lost += 1
                sent.append([t0, None, float(target[2])])
                continue
            t1 = next(t for t, p in poses[n_before:] if abs(p[2] - target[2]) < 1e-7)
            latencies.append(t1 - t0)
            sent.append([t0, t1, float(target[2])])
        lat = np.array(latencies) * 1e3
        result = {
            "real_time_factor": rtf,
            "steps_per_second": steps_per_s,
            "latency_ms": {"median": float(np.median(lat)) if lat.size else float("nan"),
                           "p95": float(np.percentile(lat, 95)) if lat.size else float("nan"),
                           "max": float(lat.max()) if lat.size else float("nan")},
            "probes": commands,
            "lost": lost,
        }
        if keep_probes:
            result["probes_sent"] = sent
        return result
    finally:
        ex.shutdown(timeout_sec=0)
        node.destroy_node()


def bench_node_main(argv: Sequence[str]) -> int:
    """``thinshell bench node [--scene S] [--mode realtime|fast] [--backend B] [--executor E] [--window s] [--commands N] [--json]``.

    Starts the sim node in a subprocess on ``ROS_DOMAIN_ID`` (default: derived from the pid, so as not
    to disturb a live graph), measures it and prints a summary (one JSON line with ``--json``).
    """
    import rclpy  # optional heavy dependency: ROS 2 (rclpy), for ROS commands only

    parser = argparse.ArgumentParser(prog="thinshell bench node", description=bench_node_main.__doc__.split("\n")[0])
    parser.add_argument("--scene", default="", help="scene file (default: the bundled press_slide scene)")
    parser.add_argument("--mode", choices=("realtime", "fast"), default="realtime")
    parser.add_argument("--backend", choices=BACKEND_CHOICES, default="auto",
                        help="the node's solver backend (its 'backend' parameter; default auto, as the node's)")
    parser.add_argument("--executor", choices=tuple(EXECUTORS), default="single",
                        help="the node's executor (its 'executor' parameter; default single, as the node's)")
    parser.add_argument("--window", type=float, default=3.0, help="wall seconds for the real-time factor")
    parser.add_argument("--commands", type=int, default=20, help="latency probes")
    parser.add_argument("--timeout", type=float, default=120.0, help="wall seconds to wait for the node")
    parser.add_argument("--json", action="store_true", help="print one JSON line")
    args = parser.parse_args(list(argv))
    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    cmd = [sys.executable, "-m", "thinshell_ros.sim_node", "--ros-args", "-p", f"mode:={args.mode}",
           "-p", "rate:=0.0", "-p", "mesh_rate:=0.0", "-p", f"backend:={args.backend}", "-p", f"executor:={args.executor}"]
    if args.scene:
        cmd += ["-p", f"scene:={args.scene}"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(env["ROS_DOMAIN_ID"]))
    try:
        result = measure_node(ctx, window=args.window, commands=args.commands, timeout=args.timeout)
    finally:
        ctx.try_shutdown()
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
    result = {"bench": "node", "mode": args.mode, "backend": args.backend, "executor": args.executor, **result}
    if args.json:
        print(json.dumps(result))
    else:
        lat = result["latency_ms"]
        print(f"sim node ({args.mode}, {args.executor} executor): real-time factor {result['real_time_factor']:.3g}, "
              f"{result['steps_per_second']:.1f} steps/s, command->output latency median {lat['median']:.1f} ms, "
              f"p95 {lat['p95']:.1f} ms, max {lat['max']:.1f} ms ({result['lost']} of {result['probes']} probes lost)")
    return 0


if __name__ == "__main__":
    sys.exit(bench_node_main(sys.argv[1:]))
