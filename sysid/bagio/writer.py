"""Write thinshell recordings as rosbag2 MCAP directories (INTERFACES.md, "Recordings").

A bag is written into a hidden staging directory beside ``out_dir`` and renamed to ``out_dir`` only
when :meth:`BagWriter.close` has finished it (``metadata.yaml``, ``<name>.mcap`` with its summary and
index, and ``scene.yaml``), so ``out_dir`` never holds a half-written bag: an exception inside the
``with`` block, or :meth:`BagWriter.abort`, removes the staging directory and leaves nothing behind.

Messages are CDR-serialised with the ROS 2 Jazzy type store of ``rosbags``; the log time of every
message is its stamp. Offered QoS recorded in ``metadata.yaml`` follows INTERFACES.md: commands
reliable keep-last 1, sensor outputs reliable keep-last 5 (as recorded), ``/clock`` best-effort
keep-last 1.
"""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from sim_core.scenes.scene_file import SceneFile, load_scene_file
from sysid.bagio import codec
from sysid.bagio.errors import BagExistsError, BagWriteError

SCENE_FILENAME = "scene.yaml"


def _qos(depth: int, reliable: bool) -> Any:
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.VOLATILE, zero, zero, QosLiveliness.AUTOMATIC, zero, False)


def default_qos(topic: str, msgtype: str) -> list[Any]:
    """Offered QoS recorded for a topic (INTERFACES.md "QoS", as recorded).

    Commands (``*_cmd``) reliable keep-last 1, ``/clock`` best-effort keep-last 1, everything else
    reliable keep-last 5.
    """
    if msgtype == codec.CLOCK or topic == "/clock":
        return [_qos(1, reliable=False)]
    if topic.rstrip("/").endswith("_cmd"):
        return [_qos(1, reliable=True)]
    return [_qos(5, reliable=True)]


def _is_nonempty(path: Path) -> bool:
    if not path.exists() and not path.is_symlink():
        return False
    return not path.is_dir() or any(path.iterdir())


def _is_task_scene(path: str | Path) -> bool:
    """Whether a scene file is a ``kind: task`` scene (False when unreadable: the scene-file loader
    then reports the problem)."""
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(doc, dict) and doc.get("kind") == "task"


class BagWriter:
    """A rosbag2 MCAP writer for thinshell topics; use as a context manager.

    Args:
        out_dir: bag directory to create (its ``.mcap`` is named ``<out_dir name>.mcap``).
        scene: scene written as ``scene.yaml`` beside the bag: a path (validated, copied verbatim),
            a mapping or :class:`SceneFile` (validated, dumped), or ``None`` for no scene file.
        force: replace an existing non-empty ``out_dir`` (the old one is removed only after the new
            bag is complete).

    Raises:
        BagExistsError: ``out_dir`` exists and is not empty and ``force`` is False.
        ConfigError: the scene is invalid (message names the file and key).

    Example::

        with BagWriter("out/run1", scene="config/scenes/press_slide.yaml") as bag:
            bag.write_pose("/thinshell/ee/pose", t_ns, pose7, "world")

    ``close()`` may be called from a signal handler: it is idempotent, and if it interrupts a
    ``write_*`` call it only marks the bag for closing, which that call completes before returning.
    Writes after closing raise :class:`BagWriteError`.
    """

    def __init__(self, out_dir: str | Path, scene: str | Path | Mapping[str, Any] | SceneFile | None = None,
                 force: bool = False) -> None:
        self.out_dir = Path(out_dir).absolute()
        self.force = bool(force)
        if _is_nonempty(self.out_dir) and not self.force:
            raise BagExistsError(f"{self.out_dir}: output bag directory exists and is not empty (use force=True "
                                 "to replace it)")
        self._scene_text = self._scene_yaml(scene)
        self._staging = self.out_dir.parent / f".{self.out_dir.name}.partial-{uuid.uuid4().hex[:8]}"
        self._bag_dir = self._staging / self.out_dir.name
        self._connections: dict[str, Any] = {}
        self._counts: dict[str, int] = {}
        self._busy = False
        self._close_requested = False
        self._state = "open"
        from rosbags.rosbag2 import StoragePlugin, Writer

        self._staging.mkdir(parents=True)
        try:
            self._writer = Writer(self._bag_dir, version=9, storage_plugin=StoragePlugin.MCAP)
            self._writer.open()
        except BaseException:
            shutil.rmtree(self._staging, ignore_errors=True)
            raise

    # ------------------------------------------------------------------------------ lifecycle
    @staticmethod
    def _scene_yaml(scene: str | Path | Mapping[str, Any] | SceneFile | None) -> str | None:
        if scene is None:
            return None
        if isinstance(scene, (str, Path)) and _is_task_scene(scene):
            from sim_core.scenes import load_scene

            load_scene(scene)  # a task scene (docs/scene_schema.md): validated by building it
            return Path(scene).read_text(encoding="utf-8")
        if isinstance(scene, (str, Path)):
            load_scene_file(scene)
            return Path(scene).read_text(encoding="utf-8")
        if isinstance(scene, Mapping) and scene.get("kind") == "task":
            from sim_core.scenes import load_scene

            load_scene(dict(scene))
            return yaml.safe_dump(dict(scene), sort_keys=False)
        parsed = load_scene_file(scene)
        return yaml.safe_dump(parsed.to_dict(), sort_keys=False)

    @property
    def closed(self) -> bool:
        """True once the bag was closed or aborted."""
        return self._state != "open"

    @property
    def message_counts(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        return dict(self._counts)

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def close(self) -> None:
        """Finish the bag (MCAP summary, ``metadata.yaml``, ``scene.yaml``) and move it to ``out_dir``.

        Idempotent. Called during a write (e.g. from a signal handler), it defers to the end of
        that write.

        Raises:
            BagExistsError: ``out_dir`` became non-empty meanwhile and ``force`` is False (the
                finished bag is left in the staging directory named in the message).
        """
        if self._state != "open":
            return
        if self._busy:
            self._close_requested = True
            return
        self._state = "closing"
        try:
            self._writer.close()
            if self._scene_text is not None:
                (self._bag_dir / SCENE_FILENAME).write_text(self._scene_text, encoding="utf-8")
            self._fsync_tree(self._bag_dir)
        except BaseException:
            self._state = "open"
            self.abort()
            raise
        self._publish()
        self._state = "closed"

    def abort(self) -> None:
        """Discard the bag being written: nothing is left at ``out_dir`` or in the staging area. Idempotent."""
        if self._state in ("closed", "aborted"):
            return
        self._state = "aborted"
        try:
            self._writer.abort()
        except Exception:  # noqa: BLE001 - the storage is discarded anyway
            pass
        shutil.rmtree(self._staging, ignore_errors=True)

    @staticmethod
    def _fsync_tree(path: Path) -> None:
        for f in path.iterdir():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())

    def _publish(self) -> None:
        out = self.out_dir
        trash = None
        if _is_nonempty(out):
            if not self.force:
                self._state = "closed"
                raise BagExistsError(f"{out}: output bag directory appeared while writing; the finished bag is "
                                     f"in {self._bag_dir}")
            trash = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(out, trash)
        elif out.is_dir():
            out.rmdir()
        elif out.is_symlink() or out.exists():
            out.unlink()
        os.replace(self._bag_dir, out)
        shutil.rmtree(self._staging, ignore_errors=True)
        if trash is not None:
            shutil.rmtree(trash, ignore_errors=True) if trash.is_dir() else trash.unlink()

    # ---------------------------------------------------------------------------------- writing
    def _connection(self, topic: str, msgtype: str, qos: Sequence[Any] | Any | None) -> Any:
        conn = self._connections.get(topic)
        if conn is not None:
            if conn.msgtype != msgtype:
                raise BagWriteError(f"{self.out_dir}: topic {topic} was written as {conn.msgtype}, now {msgtype}")
            return conn
        if not topic.startswith("/"):
            raise BagWriteError(f"{self.out_dir}: topic {topic!r} must be absolute (start with '/')")
        if qos is None:
            qos = default_qos(topic, msgtype)
        elif hasattr(qos, "reliability"):
            qos = [qos]
        try:
            conn = self._writer.add_connection(topic, msgtype, typestore=codec.typestore(),
                                               offered_qos_profiles=list(qos))
        except Exception as err:  # noqa: BLE001 - rosbags raises KeyError or TypesysError here
            raise BagWriteError(f"{self.out_dir}: topic {topic}: message type {msgtype} is not a ROS 2 Jazzy "
                                "standard type") from err
        self._connections[topic] = conn
        self._counts[topic] = 0
        return conn

    def write_raw(self, topic: str, msgtype: str, t_ns: int, cdr_bytes: bytes | memoryview,
                  qos: Sequence[Any] | Any | None = None) -> None:
        """Write an already CDR-serialised message (e.g. from ``rclpy.serialization.serialize_message``).

        Args:
            topic: absolute topic name.
            msgtype: ``pkg/msg/Type`` or ``pkg/Type`` (ROS 2 Jazzy standard type).
            t_ns: log time, integer ns (>= 0).
            cdr_bytes: CDR payload including the 4-byte encapsulation header.
            qos: ``rosbags.interfaces.Qos`` (or a list of them) recorded as offered QoS; default
                :func:`default_qos`.

        Raises:
            BagWriteError: bag closed, type clash on the topic, unknown type, negative stamp.
        """
        if self._state != "open" or self._close_requested:
            raise BagWriteError(f"{self.out_dir}: bag is closed; cannot write to {topic}")
        t_ns = int(t_ns)
        if t_ns < 0:
            raise BagWriteError(f"{self.out_dir}: topic {topic}: negative stamp {t_ns} ns")
        msgtype = codec.normalize_msgtype(msgtype)
        self._busy = True
        try:
            conn = self._connection(topic, msgtype, qos)
            self._writer.write(conn, t_ns, bytes(cdr_bytes))
            self._counts[topic] += 1
        finally:
            self._busy = False
            if self._close_requested:
                self._close_requested = False
                self.close()

    def write_message(self, topic: str, msgtype: str, t_ns: int, msg: Any) -> None:
        """Serialise a ``rosbags`` message object and write it (see :meth:`write_raw`)."""
        self.write_raw(topic, msgtype, t_ns, codec.serialize(msg, codec.normalize_msgtype(msgtype)))

    def write_pose(self, topic: str, t_ns: int, pose7: np.ndarray, frame_id: str = "world") -> None:
        """PoseStamped ``[x y z qx qy qz qw]`` (m, unit quaternion) at ``t_ns``."""
        self.write_message(topic, codec.POSE_STAMPED, t_ns, codec.pose_stamped(t_ns, pose7, frame_id))

    def write_twist(self, topic: str, t_ns: int, twist6: np.ndarray, frame_id: str = "world") -> None:
        """TwistStamped ``[vx vy vz wx wy wz]`` (m/s, rad/s) at ``t_ns``."""
        self.write_message(topic, codec.TWIST_STAMPED, t_ns, codec.twist_stamped(t_ns, twist6, frame_id))

    def write_float64(self, topic: str, t_ns: int, value: float) -> None:
        """std_msgs/Float64 logged at ``t_ns`` (the message has no header)."""
        self.write_message(topic, codec.FLOAT64, t_ns, codec.float64(value))

    def write_string(self, topic: str, t_ns: int, text: str) -> None:
        """std_msgs/String logged at ``t_ns``."""
        self.write_message(topic, codec.STRING, t_ns, codec.string(text))

    def write_wrench(self, topic: str, t_ns: int, wrench6: np.ndarray, frame_id: str) -> None:
        """WrenchStamped ``[Fx Fy Fz Tx Ty Tz]`` (N, N m) at ``t_ns``."""
        self.write_message(topic, codec.WRENCH_STAMPED, t_ns, codec.wrench_stamped(t_ns, wrench6, frame_id))

    def write_points(self, topic: str, t_ns: int, xyz: np.ndarray, frame_id: str,
                     extra_fields: Mapping[str, np.ndarray] | None = None) -> None:
        """PointCloud2 with float32 fields ``x y z`` from ``xyz (p, 3)`` (m) plus ``extra_fields`` (each ``(p,)``).

        For tactile markers pass ``extra_fields={"u": u, "v": v}`` (px).
        """
        self.write_message(topic, codec.POINT_CLOUD2, t_ns, codec.xyz_cloud(t_ns, xyz, frame_id, extra_fields))

    def write_image(self, topic: str, t_ns: int, image: np.ndarray, frame_id: str) -> None:
        """sensor_msgs/Image ``mono8`` from a ``(height, width)`` uint8 array."""
        self.write_message(topic, codec.IMAGE, t_ns, codec.image_mono8(t_ns, image, frame_id))

    def write_clock(self, t_ns: int, topic: str = "/clock") -> None:
        """rosgraph_msgs/Clock carrying ``t_ns``, logged at ``t_ns``."""
        self.write_message(topic, codec.CLOCK, t_ns, codec.clock(t_ns))
