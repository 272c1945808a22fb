"""Process plumbing shared by the thinshell nodes: rclpy session, signals, spinning, QoS profiles.

SIGINT and SIGTERM only set a stop flag (Python-level handlers, rclpy's own handlers are not
installed), so a signal never raises inside a callback that is writing a bag; the spin loop returns
within ``poll`` seconds and the caller closes its recording in ``finally``.
"""

from __future__ import annotations

import gc
import math
import signal
import threading
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

import rclpy
from rclpy.callback_groups import CallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

DIAGNOSTICS_TOPIC = "/diagnostics"
"""Topic of the nodes' ``diagnostic_msgs/DiagnosticArray`` statuses (where ROS diagnostic tools listen)."""

STATUS_PERIOD = 1.0
"""s of wall time between two runtime statuses of a node on :data:`DIAGNOSTICS_TOPIC` (1 Hz, the
ROS diagnostics convention)."""

COMMAND_DEPTH = 10
"""Keep-last depth of the command topics: every command published while the receiving node is busy
(a solver step) stays queued until it is taken; the sim node takes all queued commands before each
step (:meth:`thinshell_ros.sim_node.SimNode.take_pending_commands`), so the newest one controls the
step and no lag builds up. With depth 1 a command that arrives before its predecessor was taken
replaces it unseen (docs/benchmarks_log.md, issue 27)."""

# INTERFACES.md "QoS" (commands reliable, keep-last COMMAND_DEPTH)
COMMAND_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=COMMAND_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
SENSOR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE)
# the profile rclpy's TimeSource subscribes /clock with (best-effort, keep-last 1)
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
# a camera's calibration, with each image: reliable, kept for subscribers that join later (transient
# local), the depth of SENSOR_QOS; a volatile or best-effort subscriber (image_transport's sensor-data
# profile) matches it too
CAMERA_INFO_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
# visualisation (RViz subscribes reliable by default)
MARKER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE)


class BurstGate(CallbackGroup):
    """A callback group whose entities can be held out of the executor's wait set for a while.

    rclpy's executors wait only on the entities whose group ``can_execute`` them
    (``Executor._wait_for_ready_callbacks``); while held, a subscription of this group does not wake
    the executor, its messages stay queued in its reader (keep-last: the newest ones), and the node
    takes them itself when it wants them (the sim node: at its next step). Otherwise the group is
    reentrant (no exclusion). The sim node holds its command subscriptions after a turn that found a
    burst (:meth:`thinshell_ros.sim_node.SimNode.take_pending_commands`), so that a flood of commands
    costs at most one executor turn per hold instead of one per message, and the steps go first.

    Args:
        clock: the clock of :meth:`hold`, s (default ``time.monotonic``).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self._clock = clock
        self._until = -math.inf
        self.holds = 0

    def hold(self, seconds: float) -> None:
        """Keep the group's entities out of the wait set for ``seconds`` from now."""
        self._until = self._clock() + seconds
        self.holds += 1

    def release(self) -> None:
        """End a hold now."""
        self._until = -math.inf

    @property
    def held(self) -> bool:
        """Whether a hold is in force."""
        return self._clock() < self._until

    def can_execute(self, entity: Any) -> bool:
        return not self.held

    def beginning_execution(self, entity: Any) -> bool:
        return True

    def ending_execution(self, entity: Any) -> None:
        """Nothing to release: the gate holds no per-entity state."""


@contextmanager
def ros_session(args: Sequence[str] | None = None) -> Iterator[threading.Event]:
    """Initialise rclpy with ``args`` (``--ros-args ...`` are parsed) and yield a stop event.

    SIGINT and SIGTERM set the event; the previous handlers are restored and the rclpy context is
    shut down on exit.
    """
    stop = threading.Event()
    rclpy.init(args=list(args) if args is not None else None, signal_handler_options=SignalHandlerOptions.NO)
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda signum, frame: stop.set())
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        rclpy.try_shutdown()


def spin_until_stopped(node: Node, stop: threading.Event, poll: float = 0.05, executor: Any | None = None) -> None:
    """Spin ``node`` until ``stop`` is set or the context is shut down (returns; never raises for that).

    Args:
        node: the node to spin.
        stop: event that ends the spin (set by the signal handlers of :func:`ros_session`).
        poll: s between checks of ``stop``.
        executor: executor to spin ``node`` in (an ``rclpy.executors.Executor`` or rclpy's
            ``EventsExecutor``; shut down on return); default a new ``SingleThreadedExecutor`` on the
            node's context.
    """
    executor = executor if executor is not None else SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    try:
        while not stop.is_set() and node.context.ok():
            executor.spin_once(timeout_sec=poll)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.remove_node(node)
        executor.shutdown(timeout_sec=0.0)


def freeze_start_up_objects() -> int:
    """Collect the garbage of a node's start-up, then move every object still alive to the cyclic
    collector's permanent generation (``gc.freeze``); returns the number of objects frozen.

    What a node builds before it spins (modules, compiled kernels, the scene, the solver's
    structures) lives as long as the process. Left in the collected generations, every full
    collection traverses it again, and a full collection stops the node mid-loop: about 60 ms of CPU
    for the sim node's 92,000 start-up objects (docs/benchmarks_log.md, session 36). Frozen, they are
    never traversed; objects made later are collected as before. The practice of CPython's
    ``gc.freeze`` documentation (freeze the long-lived state once it is built).
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def topic_namespace(node: Node, namespace_parameter: str) -> tuple[str, str]:
    """``(namespace, prefix)`` of a thinshell node's topics.

    A node given a ROS namespace (``--ros-args -r __ns:=/robot``, or the constructor's ``namespace``)
    creates its topics with relative names (``prefix`` ``""``): they resolve in that namespace and
    follow remapping rules written with relative or absolute names. A node in the root namespace keeps
    the thinshell default: absolute names under ``namespace_parameter`` (``/thinshell``), prefix
    ``"/thinshell/"``. ``namespace`` is where the topics end up, either way.
    """
    ns = node.get_namespace()
    if ns not in ("", "/"):
        return ns.rstrip("/"), ""
    ns = "/" + namespace_parameter.strip("/")
    return ns, ns.rstrip("/") + "/"

