"""Recording ROS 2 traffic into thinshell bags (INTERFACES.md "Recordings").

- :class:`BagRecorder`: rclpy messages (or their CDR bytes) -> :class:`sysid.bagio.BagWriter`
  (rosbag2 MCAP + ``scene.yaml``). The simulator node records its inputs and outputs through it.
- :class:`RecorderNode`: a standalone node that subscribes to the thinshell topics of a live graph
  (discovered by name and type under a namespace, or an explicit list) and records every message as
  received (serialised bytes, no decoding), with the node clock's receive time as log time (wall
  time, or sim time with ``use_sim_time``). QoS of each subscription follows the publishers: reliable
  only when every publisher is reliable, so best-effort sensor streams are matched too.
- :func:`record_main`: ``thinshell record --out DIR [--topics ...]``; SIGINT/SIGTERM close the bag.
"""

from __future__ import annotations

import argparse
import importlib
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message

from sim_core.errors import ConfigError
from sysid.bagio import BagWriter
from thinshell_ros.runtime import ros_session, spin_until_stopped

# topic suffix (relative to the namespace) -> ROS type, INTERFACES.md "Topics"
EFFECTOR_TOPICS = {
    "pose_cmd": "geometry_msgs/msg/PoseStamped",
    "twist_cmd": "geometry_msgs/msg/TwistStamped",
    "gripper_cmd": "std_msgs/msg/Float64",
    "pose": "geometry_msgs/msg/PoseStamped",
}
SENSOR_TOPICS = {
    "markers": "sensor_msgs/msg/PointCloud2",
    "wrench": "geometry_msgs/msg/WrenchStamped",
    "image": "sensor_msgs/msg/Image",
}
SHEET_TOPICS = {"sheet/points": "sensor_msgs/msg/PointCloud2", "sheet/mesh": "visualization_msgs/msg/Marker"}
CLOCK_TOPIC = ("/clock", "rosgraph_msgs/msg/Clock")


def msgtype_of(msg: Any) -> str:
    """``pkg/msg/Type`` of an rclpy message instance or class (from its generated module path)."""
    cls = msg if isinstance(msg, type) else type(msg)
    package = cls.__module__.split(".")[0]
    return f"{package}/msg/{cls.__name__}"


def message_class(msgtype: str) -> type:
    """The rclpy message class of ``pkg/msg/Type`` (or ``pkg/Type``).

    Raises:
        ConfigError: the package or type is not installed.
    """
    parts = msgtype.strip("/").split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    try:
        return getattr(importlib.import_module(f"{parts[0]}.{parts[1]}"), parts[2])
    except (ImportError, AttributeError, IndexError) as err:
        raise ConfigError(f"message type {msgtype!r} is not available in this ROS installation") from err


def interface_type(topic: str, namespace: str) -> str | None:
    """The INTERFACES.md type of ``topic`` if it is a thinshell topic under ``namespace``, else None."""
    if topic == CLOCK_TOPIC[0]:
        return CLOCK_TOPIC[1]
    prefix = namespace.rstrip("/") + "/"
    if not topic.startswith(prefix):
        return None
    rel = topic[len(prefix):]
    if rel in SHEET_TOPICS:
        return SHEET_TOPICS[rel]
    parts = rel.split("/")
    if len(parts) == 2 and parts[0] and parts[0] != "sheet":
        return EFFECTOR_TOPICS.get(parts[1]) or SENSOR_TOPICS.get(parts[1])
    return None


class BagRecorder:
    """Write rclpy messages into a thinshell bag.

    Args:
        out_dir: bag directory (must not exist or be empty unless ``force``).
        scene: scene path or mapping written as ``scene.yaml`` (None: no scene file).
        force: replace an existing bag directory.

    Raises:
        BagExistsError: ``out_dir`` is not empty and ``force`` is False.
        ConfigError: invalid scene.
    """

    def __init__(self, out_dir: str | Path, scene: str | Path | Mapping[str, Any] | None = None,
                 force: bool = False) -> None:
        self.out_dir = Path(out_dir)
        self._writer = BagWriter(out_dir, scene=scene, force=force)

    @property
    def closed(self) -> bool:
        """True once closed."""
        return self._writer.closed

    @property
    def message_counts(self) -> dict[str, int]:
        """Messages written per topic."""
        return self._writer.message_counts

    def write(self, topic: str, msg: Any, t_ns: int) -> None:
        """Serialise an rclpy message (CDR, ``rclpy.serialization``) and write it at log time ``t_ns``.

        Raises:
            BagWriteError: closed bag, type clash on the topic, negative stamp.
        """
        self._writer.write_raw(topic, msgtype_of(msg), t_ns, serialize_message(msg))

    def write_serialized(self, topic: str, msgtype: str, t_ns: int, cdr: bytes) -> None:
        """Write already serialised CDR bytes of type ``msgtype`` at log time ``t_ns``."""
        self._writer.write_raw(topic, msgtype, t_ns, cdr)

    def close(self) -> None:
        """Finish the bag (idempotent; safe to call from a signal handler)."""
        self._writer.close()


class RecorderNode(Node):
    """Subscribe to thinshell topics and record them into a bag.

    Args:
        recorder: where messages go.
        namespace: topic namespace to discover thinshell topics in (default ``/thinshell``).
        topics: explicit absolute topic names; when given only these are recorded (any type).
        discovery_period: s between graph scans for new topics.
        **kwargs: passed to ``rclpy.node.Node`` (e.g. ``context``, ``parameter_overrides``).
    """

    def __init__(self, recorder: BagRecorder, namespace: str = "/thinshell", topics: Sequence[str] | None = None,
                 discovery_period: float = 0.2, **kwargs: Any) -> None:
        super().__init__("thinshell_recorder", **kwargs)
        self.recorder = recorder
        self.namespace = "/" + namespace.strip("/")
        self.topics = [t if t.startswith("/") else f"{self.namespace}/{t}" for t in (topics or [])]
        self._subs: dict[str, Any] = {}
        self._write_errors = 0
        self.create_timer(discovery_period, self.discover)
        self.discover()

    @property
    def subscribed_topics(self) -> dict[str, str]:
        """Topic -> type of the subscriptions made so far."""
        return {t: s[1] for t, s in self._subs.items()}

    def discover(self) -> None:
        """Subscribe to wanted topics that appeared in the graph since the last scan."""
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs or not types:
                continue
            msgtype = types[0]
            if self.topics:
                if topic not in self.topics:
                    continue
            else:
                expected = interface_type(topic, self.namespace)
                if expected is None:
                    continue
                if msgtype != expected:
                    self.get_logger().warning(f"{topic}: type {msgtype} is not the INTERFACES.md type {expected}; not recorded")
                    self._subs[topic] = (None, msgtype)
                    continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                             reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
            try:
                cls = message_class(msgtype)
            except ConfigError as err:
                self.get_logger().warning(f"{topic}: {err}; not recorded")
                self._subs[topic] = (None, msgtype)
                continue
            sub = self.create_subscription(cls, topic, self._callback(topic, msgtype), qos, raw=True)
            self._subs[topic] = (sub, msgtype)
            self.get_logger().info(f"recording {topic} [{msgtype}] ({'reliable' if reliable else 'best-effort'})")

    def _callback(self, topic: str, msgtype: str):
        def on_message(raw: bytes) -> None:
            if self.recorder.closed:
                return
            try:
                self.recorder.write_serialized(topic, msgtype, self.get_clock().now().nanoseconds, raw)
            except Exception as err:  # noqa: BLE001 - a recorder keeps recording the other topics
                self._write_errors += 1
                if self._write_errors <= 5:
                    self.get_logger().error(f"{topic}: cannot record message: {err}")
        return on_message


def record_main(argv: Sequence[str]) -> int:
    """``thinshell record --out DIR [--topics T ...] [--namespace NS] [--scene S] [--force] [--duration S]``.

    Arguments after ``--ros-args`` go to rclpy (e.g. ``-p use_sim_time:=true``). Records until
    SIGINT/SIGTERM (or ``--duration`` seconds), then closes the bag. Returns the exit code.
    """
    from rclpy.utilities import remove_ros_args  # optional heavy dependency: ROS 2 (rclpy), for ROS commands only

    argv = list(argv)
    parser = argparse.ArgumentParser(prog="thinshell record", description=record_main.__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="bag directory to create")
    parser.add_argument("--topics", nargs="+", default=None, help="absolute (or namespace-relative) topics; default: "
                        "every INTERFACES.md topic found under the namespace, and /clock")
    parser.add_argument("--namespace", default="/thinshell")
    parser.add_argument("--scene", default=None, help="scene file copied into the bag as scene.yaml (empty: none, "
                        "as a launch file's default passes it)")
    parser.add_argument("--force", action="store_true", help="replace an existing bag directory")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    args = parser.parse_args(remove_ros_args(args=["thinshell-record", *argv])[1:])
    args.scene = args.scene or None
    recorder = BagRecorder(args.out, scene=args.scene, force=args.force)
    try:
        with ros_session(["thinshell-record", *argv]) as stop:
            node = RecorderNode(recorder, namespace=args.namespace, topics=args.topics)
            if args.scene is None:
                node.get_logger().warning("no --scene given: the bag will have no scene.yaml")
            if args.duration is not None:
                deadline = time.monotonic() + args.duration
                node.create_timer(0.05, lambda: stop.set() if time.monotonic() >= deadline else None)
            try:
                spin_until_stopped(node, stop)
            finally:
                counts = recorder.message_counts
                recorder.close()
                node.get_logger().info(f"bag {args.out} closed: {sum(counts.values())} messages on {len(counts)} topics")
                node.destroy_node()
    finally:
        recorder.close()
    return 0
