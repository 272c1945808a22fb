"""rosbag2 MCAP input/output: the only place in thinshell that opens bag files (ARCHITECTURE.md).

- :mod:`sysid.bagio.codec`: NumPy <-> ROS 2 messages (PoseStamped, TwistStamped, WrenchStamped,
  Float64, String, PointCloud2, Image mono8, Clock), CDR via the ``rosbags`` Jazzy type store.
- :mod:`sysid.bagio.writer`: :class:`BagWriter`, atomic rosbag2 MCAP directories plus ``scene.yaml``.
- :mod:`sysid.bagio.reader`: :func:`open_bag` -> :class:`BagContents` of per-role :class:`Series`.
- :mod:`sysid.bagio.recording_map`: :class:`RecordingMap`, where each role of a real cell's bag comes from
  (``recording.yaml``; docs/recording_map.md), read by :mod:`sysid.bagio.cell` with the TF buffer of
  :mod:`sysid.bagio.tf_buffer` and the frames of :mod:`sysid.bagio.images`.
- :mod:`sysid.bagio.errors`: :class:`BagExistsError`, :class:`BagWriteError`, :class:`BagWarning`
  (reading errors are :class:`sim_core.errors.BagReadError`).
"""

from __future__ import annotations

from sysid.bagio.errors import BagExistsError, BagReadError, BagWarning, BagWriteError
from sysid.bagio.reader import (
    ROLES,
    BagConfig,
    BagContents,
    Series,
    TopicInfo,
    load_bag_config,
    open_bag,
    resolve_roles,
)
from sysid.bagio.recording_map import RecordingMap, load_recording_map
from sysid.bagio.writer import BagWriter

__all__ = [
    "ROLES", "BagConfig", "BagContents", "BagExistsError", "BagReadError", "BagWarning", "BagWriteError",
    "BagWriter", "RecordingMap", "Series", "TopicInfo", "load_bag_config", "load_recording_map", "open_bag",
    "resolve_roles",
]
