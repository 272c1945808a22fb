"""Fixtures for tests that start DDS participants: an isolated domain per test, localhost only."""

from __future__ import annotations

import itertools
import os
import sys
import time
from pathlib import Path
from typing import Callable

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


PYTHON = sys.executable
