"""Fixtures for tests that start DDS participants: an isolated domain per test, localhost only."""

from __future__ import annotations

import contextlib
import itertools
import os
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

import pytest

REPO = Path(__file__).resolve().parents[2]
_counter = itertools.count()


def _domain_id(worker: str, worker_count: str, k: int) -> int:
    """ROS_DOMAIN_ID ``1 + w + n * (k mod (101 // n))`` of xdist worker ``worker`` ("gw<w>") of ``worker_count`` = n.

    Distinct workers get disjoint sets of ids, all in 1..101.

    Raises:
        ValueError: a worker name that is not ``gw<int>``, or more than 101 workers.
    """
    if not worker.startswith("gw") or not worker[2:].isdigit():
        raise ValueError(f"ros_env: PYTEST_XDIST_WORKER={worker!r} is not gw<int>")
    w, n = int(worker[2:]), max(1, int(worker_count))
    if n > 101:
        raise ValueError(f"ros_env: {n} xdist workers; at most 101 get distinct ROS domain ids")
    return 1 + w + n * (k % (101 // n))


@pytest.fixture
def ros_env(monkeypatch) -> dict[str, str]:
    """Environment with a ROS_DOMAIN_ID unique to this test, discovery on localhost only.

    Under pytest-xdist the ids are split between the workers (worker ``w`` of ``n`` takes the ids
    ``1 + w + n * k``), so two tests that run at once in two workers never share a domain; within a
    worker each test takes the next ``k``, starting from an offset drawn from the process id (two
    pytest runs on one machine mostly differ). All ids stay in 1..101, the range that ROS 2 documents
    as safe on Linux (higher ids map DDS ports into the ephemeral port range).
    """
    domain = _domain_id(os.environ.get("PYTEST_XDIST_WORKER", "gw0"),
                        os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"), os.getpid() * 7 + next(_counter))
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    monkeypatch.setenv("PYTHONPATH", str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return dict(os.environ)


@pytest.fixture
def ros_context(ros_env):
    """An initialised rclpy Context on the test's domain (shut down afterwards)."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env["ROS_DOMAIN_ID"]))
    yield ctx
    ctx.try_shutdown()


def spin_until(executor, condition: Callable[[], bool], timeout: float, step: float = 0.02) -> bool:
    """Spin ``executor`` until ``condition()`` holds or ``timeout`` s pass; returns the condition."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        executor.spin_once(timeout_sec=step)
    return condition()


def call_trigger_collecting_diagnostics(context, node, service: str, client_name: str,
                                        timeout: float = 10.0) -> tuple[object, list]:
    """Call the ``std_srvs/Trigger`` service ``service`` of ``node`` from a new client node while
    collecting the ``diagnostic_msgs/DiagnosticStatus`` entries ``node`` publishes on its diagnostics
    topic (all but its 1 Hz runtime status); the client and its executor are gone on return.

    Returns:
        the service's response and the statuses received (at least one).

    Raises:
        AssertionError: no diagnostics publisher, no service, or no response and status within ``timeout`` s.
    """
    from diagnostic_msgs.msg import DiagnosticArray  # ROS messages only where a test calls a node
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    from thinshell_ros.sim_node import DIAGNOSTICS_TOPIC

    client = Node(client_name, context=context)
    got: list = []
    # the node's 1 Hz runtime status ("<name>: status") is not what a service call publishes
    sub = client.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                     lambda m: got.extend(s for s in m.status if not s.name.endswith(": status")), 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(client)
    try:
        assert spin_until(executor, lambda: sub.get_publisher_count() > 0, timeout)
        cli = client.create_client(Trigger, service)
        assert cli.wait_for_service(timeout_sec=5.0)
        fut = cli.call_async(Trigger.Request())
        assert spin_until(executor, lambda: fut.done() and got, timeout)
        return fut.result(), got
    finally:
        executor.shutdown(timeout_sec=0)
        client.destroy_node()


@contextlib.contextmanager
def spinning(context, *nodes, period: float = 0.005) -> Iterator[object]:
    """Spin ``nodes`` on a single-threaded executor in a background thread for the ``with`` block.

    ``period`` is each ``spin_once`` timeout, s. On exit the thread is stopped and the executor shut
    down; the nodes are left to the caller. Yields the executor."""
    from rclpy.executors import SingleThreadedExecutor  # rclpy only where a test spins nodes

    executor = SingleThreadedExecutor(context=context)
    for node in nodes:
        executor.add_node(node)
    stop = threading.Event()
    thread = threading.Thread(target=lambda: [executor.spin_once(timeout_sec=period) for _ in iter(stop.is_set, True)])
    thread.start()
    try:
        yield executor
    finally:
        stop.set()
        thread.join(timeout=5)
        executor.shutdown(timeout_sec=0)


PYTHON = sys.executable
