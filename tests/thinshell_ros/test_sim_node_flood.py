"""The sim node under a bounded flood of pose commands over real DDS (issue 50 item 7).

The node (realtime mode, the kinematic FakeSimulation, a process of its own) publishes its effector
pose after every step (200/s); an independent client (``benchmarks/flood_sim_node.py publish``, a
process of its own, loopback only) publishes 7.3k pose commands/s for a bounded time and count, a
fifth of them bad (NaN, inf, out of the workspace, zero quaternion, wrong frame), the last one a
valid pose. The node keeps at least half of its output rate during the burst, follows the last
valid command afterwards, logs at most one line per kind of rejection per ``error_log_period`` and
accounts for every rejection it counted in those lines and in its 1 Hz ``/diagnostics`` status.
"""

from __future__ import annotations

import json
import signal
import re
import subprocess
import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from benchmarks.flood_sim_node import FINAL_OFFSET, error_kinds
from tests.thinshell_ros.conftest import PYTHON, REPO, spin_until
from thinshell_ros import conversions as cv
from thinshell_ros.runtime import SENSOR_QOS
from thinshell_ros.sim_node import DIAGNOSTICS_TOPIC

pytestmark = pytest.mark.ros

RATE = 7300.0
"""Pose commands per second of the burst (the issue's measurement)."""
SECONDS = 3.0
"""Wall seconds the burst lasts at most (and the baseline window before it)."""
PERIOD = 1.0
"""The node's ``error_log_period``, s."""


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _counted(line: str) -> int:
    """Rejections one throttled error line stands for (``(N of this kind ...)``, else 1)."""
    m = re.search(r"\((\d+) of this kind", line)
    return int(m.group(1)) if m else 1


def test_flood_keeps_half_the_output_rate_follows_the_last_command_and_throttles_errors(ros_env, tmp_path):
    log_path = tmp_path / "node.log"
    with open(log_path, "w") as log:
        node_proc = subprocess.Popen([PYTHON, "-m", "tests.thinshell_ros.fake_sim_process", "--ros-args",
                                      "-p", "mode:=realtime", "-p", "mesh_rate:=0.0",
                                      "-p", f"error_log_period:={PERIOD}"],
                                     cwd=REPO, env=ros_env, stdout=log, stderr=subprocess.STDOUT)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env["ROS_DOMAIN_ID"]))
    client = Node("flood_counter", context=ctx)
    poses: list[tuple[float, np.ndarray]] = []
    statuses: list = []
    client.create_subscription(PoseStamped, "/thinshell/ee/pose",
                               lambda m: poses.append((time.monotonic(), cv.pose_from_msg(m)[1])), SENSOR_QOS)
    client.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC,
                               lambda m: statuses.extend(s for s in m.status if s.name.endswith(": status")), 10)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(client)
    flood = None
    try:
        assert spin_until(ex, lambda: len(poses) > 100 or node_proc.poll() is not None, 60.0), log_path.read_text()
        assert node_proc.poll() is None, log_path.read_text()
        start = poses[-1][1]
        t_before = time.monotonic()
        spin_until(ex, lambda: False, SECONDS)
        flood = subprocess.Popen([PYTHON, str(REPO / "benchmarks" / "flood_sim_node.py"), "publish", "--rate",
                                  str(RATE), "--seconds", str(SECONDS), "--bad-fraction", "0.2"],
                                 cwd=REPO, env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert spin_until(ex, lambda: flood.poll() is not None, SECONDS + 60.0)
        out = flood.stdout.read()
        assert flood.returncode == 0, out
        burst = json.loads(out.strip().splitlines()[-1])
        # a flood it was: thousands of commands per second, a fifth of them bad
        assert burst["sent"] / burst["seconds"] > 0.25 * RATE and burst["bad"] > 0.15 * burst["sent"], burst

        final = start.copy()
        final[2] += FINAL_OFFSET
        assert spin_until(ex, lambda: bool(np.allclose(poses[-1][1], final, atol=1e-9)), 10.0), \
            (poses[-1][1], final, log_path.read_text()[-3000:])
        # the next statuses: the held-back error lines are flushed and the counts of the burst published
        n_status = len(statuses)
        assert spin_until(ex, lambda: len(statuses) >= n_status + 2, 10.0)
        assert node_proc.poll() is None, log_path.read_text()[-3000:]
    finally:
        if flood is not None and flood.poll() is None:
            flood.kill()
        ex.shutdown(timeout_sec=0)
        client.destroy_node()
        ctx.try_shutdown()
        _stop(node_proc)

    stamps = np.array([t for t, _ in poses])
    before = np.count_nonzero((stamps >= t_before) & (stamps < burst["t_start"])) / (burst["t_start"] - t_before)
    during = np.count_nonzero((stamps >= burst["t_start"]) & (stamps < burst["t_end"])) / burst["seconds"]
    print(f"flood: {burst['sent'] / burst['seconds']:.0f} commands/s for {burst['seconds']:.2f} s; node outputs "
          f"{before:.1f}/s before, {during:.1f}/s during ({during / before:.2f})")
    assert before > 100.0, before  # the node kept up before the burst (200 steps/s of 5 ms)
    assert during >= 0.5 * before, (during, before)

    lines = [line for line in log_path.read_text().splitlines() if "[ERROR]" in line]
    kinds = error_kinds("\n".join(lines))
    # the four reasons of a bad pose, each reported, none more than once per period (and its flush)
    assert set(kinds) == {"pose has", "frame_id 'base_link'", "quaternion norm", "position [0.06,"}, kinds
    per_kind_bound = 2 * int(np.ceil((burst["seconds"] + 3.0) / PERIOD)) + 2
    assert all(n <= per_kind_bound for n in kinds.values()), (kinds, per_kind_bound)
    # every rejection the node counted stands behind a logged line, and its status says how many
    rejected = {key.removeprefix("rejected "): 0 for s in statuses for key in (kv.key for kv in s.values)
                if key.startswith("rejected ee/")}
    for s in statuses:
        for kv in s.values:
            if kv.key.startswith("rejected ee/"):
                rejected[kv.key.removeprefix("rejected ")] += int(kv.value)
    total = int({kv.key: kv.value for kv in statuses[-1].values}["rejected_commands"])
    assert sum(rejected.values()) == total == sum(_counted(line) for line in lines) > 0, (rejected, total)
    assert set(rejected) == {f"ee/pose_cmd {k}" for k in ("non_finite", "frame", "quaternion", "workspace")}


def test_a_held_burst_gate_keeps_its_subscription_out_of_the_executor(ros_context):
    """While held, a message queued on the gated subscription does not run its callback (the executor
    does not wait on it); it stays queued, the newest ones of a keep-last queue, until released."""
    from std_msgs.msg import Float64

    from thinshell_ros.runtime import COMMAND_DEPTH, COMMAND_QOS, BurstGate

    now = [0.0]
    gate = BurstGate(clock=lambda: now[0])
    node = Node("gated", context=ros_context)
    got: list[float] = []
    sub = node.create_subscription(Float64, "gated", lambda m: got.append(m.data), COMMAND_QOS, callback_group=gate)
    pub = node.create_publisher(Float64, "gated", COMMAND_QOS)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    try:
        assert spin_until(ex, lambda: pub.get_subscription_count() > 0, 5.0)
        gate.hold(1.0)
        assert gate.held and gate.holds == 1
        for k in range(3 * COMMAND_DEPTH):
            pub.publish(Float64(data=float(k)))
        spin_until(ex, lambda: bool(got), 0.5)
        assert got == []  # held: the executor never took them
        now[0] += 1.0  # the hold has passed
        assert not gate.held
        assert spin_until(ex, lambda: len(got) == COMMAND_DEPTH, 5.0), got
        assert got == [float(k) for k in range(2 * COMMAND_DEPTH, 3 * COMMAND_DEPTH)]  # the newest, in order
        gate.hold(1.0)
        gate.release()
        pub.publish(Float64(data=-1.0))
        assert spin_until(ex, lambda: got[-1] == -1.0, 5.0)
        assert sub.callback_group is gate
    finally:
        ex.shutdown(timeout_sec=0)
        node.destroy_node()
