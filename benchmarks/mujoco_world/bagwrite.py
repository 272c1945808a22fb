"""Write :class:`benchmarks.mujoco_world.observe.Streams` as a rosbag2 bag (mcap, CDR, Jazzy types).

Topics in namespace ``/thinshell`` plus ``/clock`` (reference README): ``ee/pose``,
``ee/pose_cmd`` (PoseStamped, ``world``), ``tactile/wrench`` (WrenchStamped, ``tactile``),
``tactile/markers`` (PointCloud2 x y z u v float32, ``tactile``), ``sheet/points`` (PointCloud2
x y z float32, ``world``), ``/clock``. Log time = header stamp. Offered QoS as the reference bags:
commands reliable keep-last 1, ``/clock`` best-effort keep-last 1, the rest reliable keep-last 5.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

NS = "/thinshell"


def _qos(depth: int, reliable: bool) -> Qos:
    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.VOLATILE, zero, zero, QosLiveliness.AUTOMATIC, zero, False)


def write_bag(out_dir: str | Path, streams, quat_xyzw) -> dict[str, int]:
    """Write the bag directory ``out_dir`` (must not exist). Returns message counts per topic.

    Raises:
        FileExistsError: ``out_dir`` exists.
    """
    out_dir = Path(out_dir)
    if out_dir.exists():
        raise FileExistsError(f"{out_dir} exists; refusing to overwrite")
    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    PoseStamped, Pose, Point, Quat = (T["geometry_msgs/msg/PoseStamped"], T["geometry_msgs/msg/Pose"],
                                      T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"])
    WrenchStamped, Wrench, Vec3 = T["geometry_msgs/msg/WrenchStamped"], T["geometry_msgs/msg/Wrench"], T["geometry_msgs/msg/Vector3"]
    PointCloud2, PointField = T["sensor_msgs/msg/PointCloud2"], T["sensor_msgs/msg/PointField"]
    Clock = T["rosgraph_msgs/msg/Clock"]
    counts: dict[str, int] = {}

    def stamp(ns: int):
        return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))

    def cloud(ns, frame, pts: np.ndarray, names):
        pts = np.ascontiguousarray(pts, dtype="<f4")
        fields = [PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate(names)]
        return PointCloud2(header=Header(stamp=stamp(ns), frame_id=frame), height=1, width=pts.shape[0],
                           fields=fields, is_bigendian=False, point_step=4 * len(names),
                           row_step=4 * len(names) * pts.shape[0], data=np.frombuffer(pts.tobytes(), dtype=np.uint8),
                           is_dense=True)

    q = Quat(x=float(quat_xyzw[0]), y=float(quat_xyzw[1]), z=float(quat_xyzw[2]), w=float(quat_xyzw[3]))

    def pose(ns, p):
        return PoseStamped(header=Header(stamp=stamp(ns), frame_id="world"),
                           pose=Pose(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])), orientation=q))

    with Writer(out_dir, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {
            "pose": w.add_connection(f"{NS}/ee/pose", "geometry_msgs/msg/PoseStamped", typestore=ts, offered_qos_profiles=[_qos(5, True)]),
            "cmd": w.add_connection(f"{NS}/ee/pose_cmd", "geometry_msgs/msg/PoseStamped", typestore=ts, offered_qos_profiles=[_qos(1, True)]),
            "markers": w.add_connection(f"{NS}/tactile/markers", "sensor_msgs/msg/PointCloud2", typestore=ts, offered_qos_profiles=[_qos(5, True)]),
            "wrench": w.add_connection(f"{NS}/tactile/wrench", "geometry_msgs/msg/WrenchStamped", typestore=ts, offered_qos_profiles=[_qos(5, True)]),
            "sheet": w.add_connection(f"{NS}/sheet/points", "sensor_msgs/msg/PointCloud2", typestore=ts, offered_qos_profiles=[_qos(5, True)]),
            "clock": w.add_connection("/clock", "rosgraph_msgs/msg/Clock", typestore=ts, offered_qos_profiles=[_qos(1, False)]),
        }
        slow = {int(n): i for i, n in enumerate(streams.t_slow_ns)}

        def put(key, ns, msg, typ):
            w.write(conns[key], int(ns), ts.serialize_cdr(msg, typ))
            counts[conns[key].topic] = counts.get(conns[key].topic, 0) + 1

        for i, ns in enumerate(streams.t_fast_ns):
            put("pose", ns, pose(ns, streams.pose[i]), "geometry_msgs/msg/PoseStamped")
            put("cmd", ns, pose(ns, streams.pose_cmd[i]), "geometry_msgs/msg/PoseStamped")
            f = streams.wrench[i]
            put("wrench", ns, WrenchStamped(header=Header(stamp=stamp(ns), frame_id="tactile"),
                                            wrench=Wrench(force=Vec3(x=float(f[0]), y=float(f[1]), z=float(f[2])),
                                                          torque=Vec3(x=float(f[3]), y=float(f[4]), z=float(f[5])))),
                "geometry_msgs/msg/WrenchStamped")
            put("clock", ns, Clock(clock=stamp(ns)), "rosgraph_msgs/msg/Clock")
            j = slow.get(int(ns))
            if j is not None:
                put("markers", ns, cloud(ns, "tactile", streams.markers[j], "xyzuv"), "sensor_msgs/msg/PointCloud2")
                put("sheet", ns, cloud(ns, "world", streams.sheet[j], "xyz"), "sensor_msgs/msg/PointCloud2")
    return counts
