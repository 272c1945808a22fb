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


@pytest.fixture
def ros_env(monkeypatch) -> dict[str, str]:
    """Environment with a ROS_DOMAIN_ID unique to this process and test, discovery on localhost only."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:] or "0"
    domain = 1 + (os.getpid() * 7 + int(worker) * 13 + next(_counter)) % 200
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
