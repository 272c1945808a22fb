"""Where the sim node's command-to-output latency goes, probe by probe (``thinshell bench node``'s probes).

    python benchmarks/node_latency_trace.py OUT.json [--commands N] [--executor single|events]

Starts the sim node as ``thinshell bench node`` does (bundled scene, realtime mode, ``rate 0``,
``mesh_rate 0``; a subprocess on its own ROS domain, localhost only), with :class:`TracedSimNode`
recording when each command was handled, each step (``advance``) started and ended, its outputs
started and each effector pose was published (``time.monotonic``, shared by the two processes on
one machine). The client is :func:`thinshell_ros.bench_node.measure_node`. Per probe:

- ``wait``: from the probe's publication to the start of the step that applied it (DDS in, the step
  in progress when it arrived and the executor's turn);
- ``step``: that step's solve (its start to the start of its outputs: commands taken, controls, the
  Newton solve);
- ``publish``: the start of the outputs to the pose's publication;
- ``back``: the pose's publication to its arrival in the client (DDS out, the client's turn);
- ``busy_at_send``: wall ms of the step in progress when the probe was published (0: none);
- ``step_cpu``: CPU ms of the node's thread in the probe's whole ``advance`` (commands, solve, every
  output), ``time.thread_time``: what the step costs, apart from the machine's load;
- ``busy_cpu``: CPU ms of the step in progress when the probe was published (0: none).

Writes ``OUT.json`` (the bench result, the rows, the node's events) and prints the rows.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from thinshell_ros.sim_node import EXECUTORS, SimNode


class TracedSimNode(SimNode):
    """The sim node with a trace: ``events`` of ``[name, monotonic s, value]``, names ``command``
    (value: handled inside a step), ``advance`` / ``advanced`` (a step's start and end; value: the
    node thread's CPU time, ``time.thread_time`` s), ``outputs`` (its outputs start) and ``pose``
    (value: the published z, m)."""

    def __init__(self, **kwargs: Any) -> None:
        self.events: list[list[Any]] = []
        super().__init__(**kwargs)

    def _step_for_command(self) -> None:
        self.events.append(["command", time.monotonic(), self._advancing])
        super()._step_for_command()

    def advance(self) -> bool:
        self.events.append(["advance", time.monotonic(), time.thread_time()])
        try:
            return super().advance()
        finally:
            self.events.append(["advanced", time.monotonic(), time.thread_time()])

    def publish_outputs(self, force: bool = False) -> None:
        self.events.append(["outputs", time.monotonic(), None])
        super().publish_outputs(force)

    def _publish(self, pub: Any, msg: Any, t_ns: int) -> None:
        super()._publish(pub, msg, t_ns)
        if pub in self._pub_pose.values():
            self.events.append(["pose", time.monotonic(), float(msg.pose.position.z)])


def run_node(events_path: Path, ros_args: Sequence[str]) -> int:
    """Spin a :class:`TracedSimNode` (as ``thinshell_ros.sim_node.main``) until SIGTERM, then write its events."""
    from thinshell_ros.runtime import freeze_start_up_objects, ros_session, spin_until_stopped

    with ros_session(["node_latency_trace", "--ros-args", *ros_args]) as stop:
        node = TracedSimNode()
        freeze_start_up_objects()
        try:
            spin_until_stopped(node, stop, executor=node.make_executor())
        finally:
            events_path.write_text(json.dumps(node.events))
            node.destroy_node()
    return 0


def probe_rows(probes: list[list[Any]], events: list[list[Any]]) -> list[dict[str, float]]:
    """Per probe ``[sent, received, z]`` (client), the node's events -> the latency split (ms)."""
    steps = []  # (start, outputs, end, CPU s) of each advance
    start = outputs = cpu = None
    for name, t, value in events:
        if name == "advance":
            start, outputs, cpu = t, None, value
        elif name == "outputs" and start is not None:
            outputs = t
        elif name == "advanced" and start is not None:
            steps.append((start, outputs if outputs is not None else t, t,
                          value - cpu if value is not None and cpu is not None else float("nan")))
            start = None
    rows = []
    for sent, received, z in probes:
        if received is None:
            continue
        pose_t = next((t for name, t, v in events if name == "pose" and t >= sent - 1e-3 and abs(v - z) < 1e-7), None)
        if pose_t is None:
            continue
        own = [s for s in steps if s[1] <= pose_t <= s[2]]
        if not own:
            continue
        s0, s1, _, cpu = own[-1]
        busy = [s for s in steps if s[0] <= sent < s[2]]
        rows.append({"latency": 1e3 * (received - sent), "wait": 1e3 * (s0 - sent), "step": 1e3 * (s1 - s0),
                     "publish": 1e3 * (pose_t - s1), "back": 1e3 * (received - pose_t),
                     "busy_at_send": 1e3 * (busy[0][2] - busy[0][0]) if busy else 0.0,
                     "step_cpu": 1e3 * cpu, "busy_cpu": 1e3 * busy[0][3] if busy else 0.0})
    return rows


def main(argv: Sequence[str]) -> int:
    """Trace ``thinshell bench node``'s probes (module docstring)."""
    if argv and argv[0] == "--node":
        return run_node(Path(argv[1]), argv[2:])
    import rclpy
    from rclpy.context import Context

    from thinshell_ros.bench_node import measure_node

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path, help="JSON file to write (refused if it exists)")
    parser.add_argument("--commands", type=int, default=20, help="latency probes")
    parser.add_argument("--executor", choices=tuple(EXECUTORS), default="single")
    args = parser.parse_args(list(argv))
    if args.out.exists():
        raise SystemExit(f"{args.out} exists; not overwritten")
    events_path = args.out.with_suffix(".events.json")
    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    cmd = [sys.executable, __file__, "--node", str(events_path), "-p", "mode:=realtime", "-p", "rate:=0.0",
           "-p", "mesh_rate:=0.0", "-p", f"executor:={args.executor}"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(env["ROS_DOMAIN_ID"]))
    try:
        result = measure_node(ctx, commands=args.commands, timeout=120.0, keep_probes=True)
    finally:
        ctx.try_shutdown()
        proc.terminate()
        proc.wait(timeout=30)
    events = json.loads(events_path.read_text())
    events_path.unlink()
    rows = probe_rows(result["probes_sent"], events)
    args.out.write_text(json.dumps({"result": result, "load": os.getloadavg()[0], "rows": rows, "events": events}))
    columns = ("latency", "wait", "step", "publish", "back", "busy_at_send", "step_cpu", "busy_cpu")
    print(" ".join(f"{k:>12}" for k in columns))
    for row in rows:
        print(" ".join(f"{row[k]:12.2f}" for k in columns))
    lat = np.array([r["latency"] for r in rows])
    cpu = np.array([r["step_cpu"] for r in rows])
    print(f"median {np.median(lat):.1f} ms, p95 {np.percentile(lat, 95):.1f} ms; the probes' advance CPU median "
          f"{np.median(cpu):.2f} ms, p95 {np.percentile(cpu, 95):.2f} ms; load {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
