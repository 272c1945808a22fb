"""The sim node under a flood of pose commands: its output rate before, during and after the burst.

    python benchmarks/flood_sim_node.py OUT.json [--rate 7300] [--seconds 15] [--bad-fraction 0.2]
                                                 [--fake] [--baseline-rate B] [--still] [--node-param NAME:=VALUE ...]
    python benchmarks/flood_sim_node.py publish --rate R --seconds S [--bad-fraction F] [--namespace NS] [--still]

The first form starts the sim node (``python -m thinshell_ros.sim_node``, realtime mode, ``rate 0``,
``mesh_rate 0``; ``--fake``: the kinematic stand-in of ``tests/thinshell_ros/fake_sim_process.py``)
on its own ROS domain, localhost only, waits for its outputs, counts its ``<effector>/pose`` messages
(one per step at ``rate 0``) for ``--seconds`` before the burst (with ``--baseline-rate B``: while a
client sends ``B`` valid pose commands/s, so that the pad moves before the burst as it does during
it: a moving pad costs the solver Newton iterations, a resting one repeats its fixed point), starts
the flood client (the second form, a process of its own) and counts them during the burst and for
``--seconds`` after it, then checks that the node follows the burst's last command (a valid pose,
1 mm above its start).

The flood client publishes ``R`` PoseStamped per second (paced every millisecond, reliable keep-last
:data:`~thinshell_ros.runtime.COMMAND_QOS`) for ``S`` s (bounded in count, ``R S``, and in time: the
final pose is published when ``S`` s have passed even if the count was not reached): ``F`` of them
bad, in turn NaN, inf, out of the workspace (1 m up), a zero quaternion and a frame other than
``world``; the valid ones circle 0.5 mm around the start pose (``--still``: hold it); the last one is
the valid "final" pose. It prints one JSON line:
``{"sent": N, "seconds": wall s, "bad": n, "t_start": s, "t_end": s, "final": pose}`` (the burst's
window in ``time.monotonic``, shared by the processes of one machine).

Writes ``OUT.json``: output rates (``before``, ``during``, ``after``, 1/s of wall time), their
ratios, the commands sent, the node's error lines in total and per kind (the first words after
``rejected:``), and whether the node reached the final pose.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FINAL_OFFSET = 1e-3
"""m above the node's start pose of the flood's last (valid) command."""
BAD_KINDS = ("nan", "inf", "workspace", "zero_quaternion", "frame")


def flood_messages(start: np.ndarray, count: int, bad_fraction: float, still: bool = False) -> list[Any]:
    """``count`` PoseStamped commands around ``start`` ``[x y z qx qy qz qw]``: every ``1/bad_fraction``-th
    one bad (:data:`BAD_KINDS` in turn), the others on a 0.5 mm circle (``still``: ``start`` itself,
    the pad at rest); the last one is the valid final pose ``start + FINAL_OFFSET`` along z."""
    from thinshell_ros import conversions as cv

    period = int(round(1.0 / bad_fraction)) if bad_fraction > 0 else 0
    msgs = []
    for k in range(count - 1):
        pose = start.copy()
        frame = "world"
        if period and k % period == period - 1:
            kind = BAD_KINDS[(k // period) % len(BAD_KINDS)]
            if kind == "nan":
                pose[0] = np.nan
            elif kind == "inf":
                pose[2] = np.inf
            elif kind == "workspace":
                pose[2] += 1.0
            elif kind == "zero_quaternion":
                pose[3:] = 0.0
            else:
                frame = "base_link"
        elif not still:
            a = 2 * np.pi * k / 400
            pose[:2] += 5e-4 * np.array([np.cos(a), np.sin(a)])
        msgs.append(cv.pose_to_msg(pose, 0, frame) if frame == "world" and np.all(np.isfinite(pose))
                    else _raw_pose_msg(pose, frame))
    final = start.copy()
    final[2] += FINAL_OFFSET
    msgs.append(cv.pose_to_msg(final, 0, "world"))
    return msgs


def _raw_pose_msg(pose: np.ndarray, frame: str) -> Any:
    """A PoseStamped of ``pose`` as given (no validation: NaN, zero quaternions pass)."""
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.header.frame_id = frame
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z, o.x, o.y, o.z, o.w = (float(v) for v in pose)
    return msg


def publish_main(args: argparse.Namespace) -> int:
    """The flood client: wait for the node's subscription, publish, print the JSON summary."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.node import Node

    from thinshell_ros import conversions as cv
    from thinshell_ros.runtime import COMMAND_QOS, SENSOR_QOS

    rclpy.init()
    node = Node("thinshell_flood_client")
    topic = f"{args.namespace}/{args.effector}/pose_cmd"
    pub = node.create_publisher(PoseStamped, topic, COMMAND_QOS)
    start: list[np.ndarray] = []
    node.create_subscription(PoseStamped, f"{args.namespace}/{args.effector}/pose",
                             lambda m: start.append(cv.pose_from_msg(m)[1]), SENSOR_QOS)
    deadline = time.monotonic() + 60.0
    while (pub.get_subscription_count() == 0 or not start) and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.01)
    if not start:
        print(f"flood client: no subscriber on {topic} within 60 s", file=sys.stderr)
        return 1
    count = max(2, int(round(args.rate * args.seconds)))
    msgs = flood_messages(start[0], count, args.bad_fraction, args.still)
    t0 = time.monotonic()
    sent = 0
    while sent < count - 1 and time.monotonic() - t0 < args.seconds:
        due = min(count - 1, int((time.monotonic() - t0) * args.rate) + 1)
        while sent < due:
            pub.publish(msgs[sent])
            sent += 1
        time.sleep(0.001)
    pub.publish(msgs[-1])  # the final valid pose, also when time ran out first
    sent += 1
    t_end = time.monotonic()
    seconds = t_end - t0
    time.sleep(0.5)  # the reliable writer's last samples out before the participant goes
    period = int(round(1.0 / args.bad_fraction)) if args.bad_fraction > 0 else 0
    bad = sum(1 for k in range(sent - 1) if period and k % period == period - 1)
    final = cv.pose_from_msg(msgs[-1])[1].tolist()
    print(json.dumps({"sent": sent, "seconds": seconds, "bad": bad, "t_start": t0, "t_end": t_end, "final": final}),
          flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def error_kinds(log: str) -> dict[str, int]:
    """Error lines of a node log per kind: the reason's first words after ``rejected:``
    (``pose has non-finite``, ``quaternion norm``, ...); other error lines under ``other``."""
    kinds: dict[str, int] = {}
    for line in log.splitlines():
        if "[ERROR]" not in line:
            continue
        m = re.search(r"rejected: (\S+ \S+)", line)
        key = m.group(1) if m else "other"
        kinds[key] = kinds.get(key, 0) + 1
    return kinds


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Start the node, count its outputs before, during and after a flood; see the module docstring."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from thinshell_ros import conversions as cv
    from thinshell_ros.runtime import SENSOR_QOS

    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("ROS_LOCALHOST_ONLY", None)
    module = "tests.thinshell_ros.fake_sim_process" if args.fake else "thinshell_ros.sim_node"
    node_args = [sys.executable, "-m", module, "--ros-args"]
    for p in ("mode:=realtime", "mesh_rate:=0.0", "rate:=0.0", *args.node_param):
        node_args += ["-p", p]
    log_path = Path(args.out).with_suffix(".node.log")
    with open(log_path, "w") as log:
        proc = subprocess.Popen(node_args, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=args.domain)
    client = Node("thinshell_flood_counter", context=ctx)
    poses: list[tuple[float, np.ndarray]] = []
    client.create_subscription(PoseStamped, f"/thinshell/{args.effector}/pose",
                               lambda m: poses.append((time.monotonic(), cv.pose_from_msg(m)[1])), SENSOR_QOS)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(client)

    def spin_for(seconds: float, until=lambda: False) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not until():
            ex.spin_once(timeout_sec=0.005)

    flood = None
    try:
        spin_for(args.start_timeout, lambda: len(poses) > 50 or proc.poll() is not None)
        if len(poses) <= 50:
            raise RuntimeError(f"the sim node published no poses within {args.start_timeout} s: "
                               f"{log_path.read_text()[-2000:]}")
        client_args = [sys.executable, str(Path(__file__).resolve()), "publish", "--seconds", str(args.seconds),
                       "--effector", args.effector]
        cpu = [_cpu_seconds(proc.pid)]
        if args.baseline_rate > 0:  # the "before" window: the pad moving under a gentle valid stream
            gentle = subprocess.Popen([*client_args, "--rate", str(args.baseline_rate), "--bad-fraction", "0"],
                                      cwd=REPO, env=env, stdout=subprocess.PIPE, text=True)
            spin_for(args.seconds + 120.0, lambda: gentle.poll() is not None)
            baseline = json.loads(gentle.stdout.read().strip().splitlines()[-1])
            t_before, t_baseline_end = baseline["t_start"], baseline["t_end"]
            spin_for(1.0)
        else:
            t_before = time.monotonic()
            spin_for(args.seconds)
            t_baseline_end = time.monotonic()
        start = poses[-1][1]
        flood = subprocess.Popen([*client_args, "--rate", str(args.rate), "--bad-fraction", str(args.bad_fraction),
                                  *(["--still"] if args.still else [])],
                                 cwd=REPO, env=env, stdout=subprocess.PIPE, text=True)
        if not args.still:  # the burst has begun when its first poses move the pad
            spin_for(60.0, lambda: flood.poll() is not None or _moved(poses, start))
        cpu.append(_cpu_seconds(proc.pid))
        spin_for(args.seconds + 60.0, lambda: flood.poll() is not None)
        cpu.append(_cpu_seconds(proc.pid))
        summary = json.loads(flood.stdout.read().strip().splitlines()[-1])
        t_during, t_after = summary["t_start"], summary["t_end"]  # the burst, as the client timed it
        spin_for(args.seconds)
        t_end = time.monotonic()
        cpu.append(_cpu_seconds(proc.pid))
        reached = bool(np.allclose(poses[-1][1][:3], summary["final"][:3], atol=1e-6))
    finally:
        if flood is not None and flood.poll() is None:
            flood.kill()
        ex.shutdown(timeout_sec=0)
        client.destroy_node()
        ctx.try_shutdown()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    stamps = np.array([t for t, _ in poses])

    def rate(a: float, b: float) -> float:
        return float(np.count_nonzero((stamps >= a) & (stamps < b)) / (b - a))

    before, during, after = rate(t_before, t_baseline_end), rate(t_during, t_after), rate(t_after, t_end)
    log = log_path.read_text()
    kinds = error_kinds(log)
    return {"node": module, "node_params": args.node_param, "baseline_rate": args.baseline_rate, "still": args.still,
            "commands": summary,
            "command_rate": summary["sent"] / summary["seconds"],
            "output_rate": {"before": before, "during": during, "after": after},
            "node_cpu_seconds": {"before_and_start": cpu[1] - cpu[0], "during": cpu[2] - cpu[1],
                                 "after": cpu[3] - cpu[2]},
            "during_over_before": during / before, "after_over_before": after / before,
            "error_lines": sum(kinds.values()), "error_lines_per_kind": kinds,
            "reached_final_pose": reached, "load_average": os.getloadavg(), "node_log": str(log_path)}


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (``/proc/<pid>/stat``; NaN where unreadable)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def _moved(poses: list[tuple[float, np.ndarray]], start: np.ndarray) -> bool:
    return bool(poses) and float(np.linalg.norm(poses[-1][1][:3] - start[:3])) > 1e-6


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "publish":
        p = argparse.ArgumentParser(prog="flood_sim_node.py publish")
        p.add_argument("--rate", type=float, required=True)
        p.add_argument("--seconds", type=float, required=True)
        p.add_argument("--bad-fraction", type=float, default=0.2)
        p.add_argument("--namespace", default="/thinshell")
        p.add_argument("--effector", default="ee")
        p.add_argument("--still", action="store_true", help="the valid commands hold the start pose")
        return publish_main(p.parse_args(argv[1:]))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out")
    p.add_argument("--rate", type=float, default=7300.0)
    p.add_argument("--seconds", type=float, default=15.0)
    p.add_argument("--bad-fraction", type=float, default=0.2)
    p.add_argument("--fake", action="store_true", help="the kinematic stand-in instead of the bundled scene")
    p.add_argument("--baseline-rate", type=float, default=0.0,
                   help="valid pose commands/s during the 'before' window (0: none, the scene at rest); the pad "
                        "then moves before the burst as during it, and the ratio compares like with like")
    p.add_argument("--node-param", action="append", default=[], help="NAME:=VALUE passed to the node")
    p.add_argument("--still", action="store_true",
                   help="the burst's valid commands hold the start pose (the pad at rest: the flood's cost alone)")
    p.add_argument("--effector", default="ee")
    p.add_argument("--domain", type=int, default=77)
    p.add_argument("--start-timeout", type=float, default=300.0)
    args = p.parse_args(argv)
    result = measure(args)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
