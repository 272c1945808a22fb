"""sysid.bagio: reading the reference bags, writer round trips, bare .mcap input, every error path."""

from __future__ import annotations

import os
import signal
import warnings

import numpy as np
import pytest
import yaml

from sim_core.errors import BagReadError, ConfigError, ThinShellError
from sim_core.scenes.scene_file import load_scene_file
from sysid.bagio import BagExistsError, BagWarning, BagWriteError, BagWriter, load_bag_config, open_bag
from sysid.bagio import codec, reader
from tests.sysid.conftest import NS, REFERENCE_BAGS, reference_bag, synthetic_streams, write_synthetic

# Bags written here often hold a few topics only; the missing-topic warnings are asserted where they
# matter (pytest.warns records them regardless of this filter).
pytestmark = pytest.mark.filterwarnings("ignore::sysid.bagio.errors.BagWarning")


def _metadata_counts(bag_dir):
    info = yaml.safe_load((bag_dir / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}, info


# ------------------------------------------------------------------------------ reference bags
@pytest.mark.parametrize("name", REFERENCE_BAGS)
def test_reference_bag_counts_fields_and_stamps(name):
    path = reference_bag(name)
    with warnings.catch_warnings():
        warnings.simplefilter("error", BagWarning)  # a clean recording reads without any repair
        bag = open_bag(path)
    counts, info = _metadata_counts(path)
    assert {t: i.message_count for t, i in bag.topics.items()} == counts
    assert bag.message_count == info["message_count"]
    for role, series in bag.series.items():
        assert len(series) == counts[series.topic], role
        assert np.all(np.diff(series.t_ns) > 0), f"{role} stamps not strictly increasing"
    assert bag.missing_roles == ("image",) and bag.notes == ()
    markers = bag.series["markers"]
    assert markers.field_names == ("x", "y", "z", "u", "v")
    assert markers.values.shape[1:] == (63, 5) and markers.frame_id == "tactile"
    assert bag.series["sheet_points"].values.shape[1:] == (273, 3)
    # Marker i = iy*9 + ix on a 2 mm grid centred on the origin: at t=0 (no contact) within noise.
    ix, iy = np.meshgrid(np.arange(9), np.arange(7))
    rest = np.stack([(ix.ravel() - 4) * 0.002, (iy.ravel() - 3) * 0.002], axis=1)
    assert np.abs(markers.values[0, :, :2] - rest).max() < 1e-4
    assert bag.series["clock"].values[-1] == pytest.approx(bag.series["clock"].t_ns[-1] * 1e-9)


@pytest.mark.parametrize("name", REFERENCE_BAGS)
def test_reference_markers_follow_the_pinhole_model(name):
    """u = fx x/(z+d) + cx, v = fy y/(z+d) + cy with independent noise on (x,y,z) and (u,v).

    The noiseless relation is checked by regressing u on x/(z+d) over all 22,743 samples: slope = fx
    to 2e-4 relative and intercept = cx to 8e-3 px (5 standard errors; measured 0.2-2e-3 px); the
    residual mean is 0 within 5 standard errors and its spread is what the documented noise
    predicts (0.15 px on u,v; 15/20 um on x,y/z).
    """
    bag = open_bag(reference_bag(name))
    cam = bag.scene.sensors["tactile"].camera
    x, y, z, u, v = np.moveaxis(bag.series["markers"].values, -1, 0)
    d = z + cam.distance
    for pix, coord, f, c in ((u, x, cam.fx, cam.cx), (v, y, cam.fy, cam.cy)):
        a = np.stack([(coord / d).ravel(), np.ones(pix.size)], axis=1)
        (slope, intercept), *_ = np.linalg.lstsq(a, pix.ravel(), rcond=None)
        assert slope == pytest.approx(f, rel=2e-4)
        assert intercept == pytest.approx(c, abs=8e-3)
        r = pix - (f * coord / d + c)
        predicted = np.sqrt(0.15 ** 2 + (f * 15e-6 / d) ** 2 + (f * coord / d ** 2 * 20e-6) ** 2)
        assert abs(r.mean()) < 5 * r.std() / np.sqrt(r.size)
        assert np.std(r / predicted) == pytest.approx(1.0, abs=0.08)


def test_bare_mcap_file_reads_like_the_directory():
    path = reference_bag("nominal_s101")
    as_dir = open_bag(path)
    bare = open_bag(path / "nominal_s101.mcap")
    assert bare.mcap_path == as_dir.mcap_path and bare.sha256 == as_dir.sha256
    assert bare.scene == as_dir.scene  # scene.yaml beside the file is found
    assert set(bare.series) == set(as_dir.series)
    for role in as_dir.series:
        np.testing.assert_array_equal(bare.series[role].t_ns, as_dir.series[role].t_ns)
        np.testing.assert_array_equal(bare.series[role].values, as_dir.series[role].values)


def test_bare_mcap_falls_back_to_the_mcap_library(monkeypatch):
    path = reference_bag("nominal_s101")
    expected = open_bag(path)

    def broken(*args, **kwargs):
        raise RuntimeError("rosbags disabled for this test")

    monkeypatch.setattr(reader, "_read_rosbags", broken)
    bare = open_bag(path / "nominal_s101.mcap")
    assert {t: i.message_count for t, i in bare.topics.items()} == _metadata_counts(path)[0]
    for role in expected.series:
        np.testing.assert_array_equal(bare.series[role].t_ns, expected.series[role].t_ns)
        np.testing.assert_array_equal(bare.series[role].values, expected.series[role].values)


# ---------------------------------------------------------------------------------- round trip
def test_writer_round_trip_rosbags_and_mcap_library(tmp_path, scene_dict):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.rosbag2 import Reader

    s = synthetic_streams(n=15)
    out = tmp_path / "run"
    write_synthetic(out, s, scene=scene_dict)
    image = (np.arange(12 * 16, dtype=np.uint8) * 7).reshape(12, 16)
    extra = tmp_path / "extra"
    with BagWriter(extra) as bag:
        bag.write_twist(f"{NS}/ee/twist_cmd", 5, [0.1, 0.2, 0.3, 0.0, 0.0, 1.5], "world")
        bag.write_float64(f"{NS}/ee/gripper_cmd", 6, 0.0125)
        bag.write_image(f"{NS}/tactile/image", 7, image, "tactile")
        bag.write_string(f"{NS}/note", 8, "hello")
    assert sorted(p.name for p in out.iterdir()) == ["metadata.yaml", "run.mcap", "scene.yaml"]
    assert load_scene_file(out / "scene.yaml").to_dict() == load_scene_file(scene_dict).to_dict()

    # 1) our reader (rosbags underneath)
    bag = open_bag(out)
    n = len(s["t_ns"])
    assert {t: i.message_count for t, i in bag.topics.items()} == {
        f"{NS}/ee/pose": n, f"{NS}/ee/pose_cmd": n, f"{NS}/tactile/wrench": n, f"{NS}/tactile/markers": n,
        f"{NS}/sheet/points": n, "/clock": n}
    np.testing.assert_array_equal(bag.series["pose"].t_ns, s["t_ns"])
    np.testing.assert_array_equal(bag.series["pose"].values, s["pose"])
    np.testing.assert_array_equal(bag.series["wrench"].values, s["wrench"])
    np.testing.assert_allclose(bag.series["markers"].values[..., :3], s["markers"], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(bag.series["markers"].values[..., 3:], s["uv"], rtol=1e-6)
    np.testing.assert_allclose(bag.series["sheet_points"].values, s["sheet"], rtol=1e-6)
    np.testing.assert_array_equal(bag.series["clock"].t_ns, s["t_ns"])

    # 2) independently: mcap + mcap_ros2 decoder, no rosbags involved
    seen: dict[str, list] = {}
    with open(out / "run.mcap", "rb") as fh:
        for schema, channel, message, msg in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            seen.setdefault(channel.topic, []).append((message.log_time, msg))
    assert {t: len(v) for t, v in seen.items()} == {t: i.message_count for t, i in bag.topics.items()}
    poses = seen[f"{NS}/ee/pose"]
    assert [lt for lt, _ in poses] == list(s["t_ns"])
    assert [codec.stamp_to_ns(m.header.stamp) for _, m in poses] == list(s["t_ns"])
    np.testing.assert_array_equal(np.array([codec.parse_pose_stamped(m)[1] for _, m in poses]), s["pose"])
    np.testing.assert_array_equal(np.array([codec.parse_wrench_stamped(m)[1] for _, m in seen[f"{NS}/tactile/wrench"]]),
                                  s["wrench"])
    clouds = np.array([codec.parse_point_cloud2(m, ("x", "y", "z", "u", "v"))[1] for _, m in seen[f"{NS}/tactile/markers"]])
    np.testing.assert_array_equal(clouds, bag.series["markers"].values)
    assert [codec.parse_clock(m) for _, m in seen["/clock"]] == list(s["t_ns"])

    # 3) the other message types, through rosbags directly and the mcap library
    with Reader(extra) as r:
        got = {c.topic: codec.deserialize(raw, c.msgtype) for c, _, raw in r.messages()}
    np.testing.assert_array_equal(codec.parse_twist_stamped(got[f"{NS}/ee/twist_cmd"])[1], [0.1, 0.2, 0.3, 0, 0, 1.5])
    assert codec.parse_float64(got[f"{NS}/ee/gripper_cmd"]) == 0.0125
    np.testing.assert_array_equal(codec.parse_image_mono8(got[f"{NS}/tactile/image"])[1], image)
    assert codec.parse_string(got[f"{NS}/note"]) == "hello"
    with open(extra / "extra.mcap", "rb") as fh:
        via_mcap = {c.topic: m for _, c, _, m in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()}
    np.testing.assert_array_equal(codec.parse_image_mono8(via_mcap[f"{NS}/tactile/image"])[1], image)
    assert codec.parse_twist_stamped(via_mcap[f"{NS}/ee/twist_cmd"])[0] == 5


def test_write_raw_accepts_serialised_cdr_and_short_type_names(tmp_path):
    msg = codec.wrench_stamped(42, [1, 2, 3, 4, 5, 6], "tactile")
    with BagWriter(tmp_path / "raw") as bag:
        bag.write_raw(f"{NS}/tactile/wrench", "geometry_msgs/WrenchStamped", 42, codec.serialize(msg, codec.WRENCH_STAMPED))
        bag.write_pose(f"{NS}/ee/pose", 42, [0, 0, 0, 0, 0, 0, 1], "world")
        with pytest.raises(BagWriteError, match="foo_msgs/msg/Bar is not a ROS 2 Jazzy standard type"):
            bag.write_raw(f"{NS}/x", "foo_msgs/msg/Bar", 1, b"\x00\x01\x00\x00")
        with pytest.raises(BagWriteError, match=f"topic {NS}/ee/pose was written as geometry_msgs/msg/PoseStamped"):
            bag.write_float64(f"{NS}/ee/pose", 43, 1.0)
    got = open_bag(tmp_path / "raw")
    np.testing.assert_array_equal(got.series["wrench"].values, [[1, 2, 3, 4, 5, 6]])
    assert got.series["wrench"].t_ns.tolist() == [42]


def test_codec_point_cloud_with_padding_and_big_endian():
    """Parsing honours offsets, point_step padding, float64 fields and big-endian data."""
    ts = codec.typestore().types
    pf = ts["sensor_msgs/msg/PointField"]
    xyz = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    rec = np.zeros(2, dtype=np.dtype({"names": ["x", "y", "z"], "formats": [">f8"] * 3, "offsets": [0, 8, 16],
                                      "itemsize": 32}))
    for i, n in enumerate("xyz"):
        rec[n] = xyz[:, i]
    msg = ts[codec.POINT_CLOUD2](
        header=codec.pose_stamped(3, np.r_[0, 0, 0, 0, 0, 0, 1], "w").header, height=1, width=2,
        fields=[pf(name=n, offset=8 * i, datatype=codec.POINTFIELD_FLOAT64, count=1) for i, n in enumerate("xyz")],
        is_bigendian=True, point_step=32, row_step=64, data=rec.view(np.uint8), is_dense=True)
    t, values, frame = codec.parse_point_cloud2(codec.deserialize(codec.serialize(msg, codec.POINT_CLOUD2),
                                                                  codec.POINT_CLOUD2), ("z", "x"))
    assert (t, frame) == (3, "w")
    np.testing.assert_array_equal(values, xyz[:, [2, 0]])
    with pytest.raises(KeyError, match=r"lacks field\(s\) \['u'\]"):
        codec.parse_point_cloud2(msg, ("x", "u"))
    with pytest.raises(ValueError, match="integer nanoseconds"):
        codec.ns_to_stamp(1.5)


# ---------------------------------------------------------------------------------- role topics
def test_role_topics_from_config_file_and_per_call(tmp_path, scene_dict):
    s = synthetic_streams(n=5)
    write_synthetic(tmp_path / "ns", s, scene=scene_dict, namespace="/robot1")
    cfg = tmp_path / "sysid.yaml"
    cfg.write_text("version: 1\nbag:\n  namespace: /robot1\n  topics: {markers: /gelsight/markers}\n")
    with pytest.warns(BagWarning, match="topic /gelsight/markers \\(role markers\\) is missing"):
        bag = open_bag(tmp_path / "ns", config=cfg)
    assert bag.roles["pose"] == "/robot1/ee/pose" and "markers" in bag.missing_roles
    bag = open_bag(tmp_path / "ns", config=cfg, roles={"markers": "tactile/markers"})
    assert bag.roles["markers"] == "/robot1/tactile/markers"
    assert bag.series["markers"].values.shape == (5, 6, 5)
    cfg.write_text("bag:\n  namespaces: /x\n")
    with pytest.raises(ConfigError, match=f"{cfg}: unknown key bag.namespaces"):
        load_bag_config(cfg)


def test_role_names_follow_the_scene_sensor(tmp_path, scene_dict):
    scene_dict["sensors"] = {"gs_left": dict(scene_dict["sensors"]["tactile"], effector="arm")}
    scene_dict["effectors"] = {"arm": scene_dict["effectors"]["ee"]}
    with BagWriter(tmp_path / "b", scene=scene_dict) as bag:
        bag.write_wrench(f"{NS}/gs_left/wrench", 1, np.ones(6), "gs_left")
        bag.write_pose(f"{NS}/arm/pose", 1, [0, 0, 0, 0, 0, 0, 1], "world")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BagWarning)
        got = open_bag(tmp_path / "b")
    assert got.roles["wrench"] == f"{NS}/gs_left/wrench" and got.roles["pose"] == f"{NS}/arm/pose"
    assert set(got.series) == {"wrench", "pose"}


# ------------------------------------------------------------------------------------ errors
def test_missing_path(tmp_path):
    with pytest.raises(BagReadError, match=f"{tmp_path / 'nope'}: bag path does not exist"):
        open_bag(tmp_path / "nope")


@pytest.mark.parametrize("bare", [False, True])
def test_truncated_mcap(writable_reference, bare):
    bag_dir = writable_reference()
    mcap = bag_dir / "nominal_s101.mcap"
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagReadError, match=f"{mcap}: corrupt or truncated MCAP file"):
        open_bag(mcap if bare else bag_dir)


def test_metadata_count_mismatch_is_reported(tmp_path):
    out = write_synthetic(tmp_path / "b", synthetic_streams(n=6))
    meta = out / "metadata.yaml"
    meta.write_text(meta.read_text().replace("message_count: 6", "message_count: 9", 1))
    topic = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]["topics_with_message_count"][0]
    name = topic["topic_metadata"]["name"]
    with pytest.raises(BagReadError, match=f"metadata.yaml lists 9 messages on {name}, the file holds 6"):
        open_bag(out)


def test_empty_bag(tmp_path):
    with BagWriter(tmp_path / "empty"):
        pass
    with pytest.raises(BagReadError, match=f"{tmp_path / 'empty'}: bag is empty"):
        open_bag(tmp_path / "empty")


def test_role_topic_with_wrong_type(tmp_path):
    with BagWriter(tmp_path / "b") as bag:
        bag.write_float64(f"{NS}/ee/pose", 1, 2.0)
    with pytest.raises(BagReadError, match=f"topic {NS}/ee/pose \\(role pose\\) has type std_msgs/msg/Float64, "
                                           "expected geometry_msgs/msg/PoseStamped"):
        open_bag(tmp_path / "b")


def test_markers_without_xyz_fields(tmp_path):
    with BagWriter(tmp_path / "b") as bag:
        bag.write_message(f"{NS}/tactile/markers", codec.POINT_CLOUD2, 1,
                          codec.point_cloud2(1, {"u": np.ones(3), "v": np.ones(3)}, "tactile"))
    with pytest.raises(BagReadError, match=f"topic {NS}/tactile/markers: point cloud fields are \\('u', 'v'\\)"):
        open_bag(tmp_path / "b")


def test_nan_samples_are_dropped_with_a_count(tmp_path):
    s = synthetic_streams(n=10)
    s["wrench"][[2, 7], 1] = np.nan
    s["markers"][4, 3, 0] = np.nan
    write_synthetic(tmp_path / "b", s)
    with pytest.warns(BagWarning) as record:
        bag = open_bag(tmp_path / "b")
    messages = [str(w.message) for w in record]
    assert f"topic {NS}/tactile/wrench: dropped 2 of 10 samples containing NaN/inf" in messages
    assert f"topic {NS}/tactile/markers: dropped 1 of 10 samples containing NaN/inf" in messages
    assert bag.series["wrench"].t_ns.tolist() == np.delete(s["t_ns"], [2, 7]).tolist()
    assert bag.series["wrench"].dropped_nonfinite == 2
    np.testing.assert_array_equal(bag.series["wrench"].values, np.delete(s["wrench"], [2, 7], axis=0))


def test_all_nan_topic_is_an_error(tmp_path):
    with BagWriter(tmp_path / "b") as bag:
        for t in range(5):
            bag.write_wrench(f"{NS}/tactile/wrench", t, np.full(6, np.nan), "tactile")
    with pytest.raises(BagReadError, match=f"topic {NS}/tactile/wrench: all 5 samples contain NaN"):
        open_bag(tmp_path / "b")


def test_out_of_order_stamps_are_sorted_with_a_warning(tmp_path):
    stamps = [0, 10, 30, 20, 40, 40]
    with BagWriter(tmp_path / "b") as bag:
        for i, t in enumerate(stamps):
            # header stamp out of order while the log time increases (a late-stamped sensor)
            msg = codec.wrench_stamped(t, np.full(6, float(i)), "tactile")
            bag.write_message(f"{NS}/tactile/wrench", codec.WRENCH_STAMPED, 100 + i, msg)
    with pytest.warns(BagWarning, match=f"topic {NS}/tactile/wrench: 1 stamps out of order; samples sorted"):
        bag = open_bag(tmp_path / "b")
    series = bag.series["wrench"]
    assert series.t_ns.tolist() == [0, 10, 20, 30, 40] and series.resorted
    assert series.values[:, 0].tolist() == [0, 1, 3, 2, 4]
    assert any("repeated stamp" in n for n in bag.notes)


def test_commands_taken_at_one_time_keep_the_last_one_the_robot_applied(tmp_path):
    # the sim node logs each command at the sim time it takes it; two queued during a step share that time
    log = [0, 5, 5, 10, 15, 15, 15]
    pose0 = np.array([0.06, 0.0, 0.004, 0.0, 0.0, 0.0, 1.0])
    with BagWriter(tmp_path / "b") as bag:
        for i, t in enumerate(log):
            msg = codec.pose_stamped(1000 + i, pose0 + np.r_[1e-4 * i, 0, 0, 0, 0, 0, 0], "world")
            bag.write_message(f"{NS}/ee/pose_cmd", codec.POSE_STAMPED, t, msg)
    with warnings.catch_warnings():
        warnings.simplefilter("error", BagWarning)  # normal for commands: no warning
        streams = reader.read_effector_streams(tmp_path / "b", ["ee"], NS)
    t_ns, values = streams["ee"]["pose_cmd"]
    assert t_ns.tolist() == [0, 5, 10, 15]
    np.testing.assert_allclose(values[:, 0] - pose0[0], [0.0, 2e-4, 3e-4, 6e-4], atol=1e-15)


def test_missing_markers_topic_warns_and_names_it(tmp_path):
    write_synthetic(tmp_path / "b", synthetic_streams(n=5), skip=("markers",))
    with pytest.warns(BagWarning, match=f"topic {NS}/tactile/markers \\(role markers\\) is missing"):
        bag = open_bag(tmp_path / "b")
    assert "markers" in bag.missing_roles and "markers" not in bag.series
    assert any("tactile/markers" in n for n in bag.notes)


# ------------------------------------------------------------------------------------ writer
def test_refuses_to_overwrite_without_force(tmp_path):
    out = write_synthetic(tmp_path / "b", synthetic_streams(n=3))
    with pytest.raises(BagExistsError, match=f"{out}: output bag directory exists and is not empty"):
        BagWriter(out)
    assert issubclass(BagExistsError, FileExistsError) and issubclass(BagExistsError, ThinShellError)
    assert open_bag(out).series["pose"].values.shape == (3, 7)  # untouched
    write_synthetic_force = BagWriter(out, force=True)
    write_synthetic_force.write_pose(f"{NS}/ee/pose", 5, [1, 2, 3, 0, 0, 0, 1], "world")
    write_synthetic_force.close()
    assert open_bag(out).series["pose"].values.tolist() == [[1, 2, 3, 0, 0, 0, 1]]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]  # no staging or old copies left
    (tmp_path / "empty").mkdir()
    with BagWriter(tmp_path / "empty") as bag:  # an existing empty directory is fine
        bag.write_clock(1)
    assert (tmp_path / "empty" / "metadata.yaml").is_file()


def test_exception_inside_with_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        with BagWriter(tmp_path / "b", scene=None) as bag:
            bag.write_clock(1)
            assert any(p.name.startswith(".b.partial-") for p in tmp_path.iterdir())
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    bag.abort()  # idempotent after the abort of __exit__
    with pytest.raises(BagWriteError, match="bag is closed; cannot write to /clock"):
        bag.write_clock(2)


def test_invalid_scene_is_rejected_before_writing(tmp_path, scene_dict):
    scene_dict["sheet"]["thicknes"] = 1.0
    with pytest.raises(ConfigError, match="unknown key sheet.thicknes"):
        BagWriter(tmp_path / "b", scene=scene_dict)
    assert list(tmp_path.iterdir()) == []


def test_close_is_idempotent_and_safe_from_a_signal_handler(tmp_path):
    """A SIGALRM handler calls close() in the middle of write(): the write completes and the bag is readable."""
    bag = BagWriter(tmp_path / "b")
    inner = bag._writer.write
    fired = []

    def write_then_signal(conn, t, data):
        inner(conn, t, data)
        if t == 3 and not fired:
            fired.append(t)
            os.kill(os.getpid(), signal.SIGALRM)  # handler runs before this frame returns

    previous = signal.signal(signal.SIGALRM, lambda *_: bag.close())
    try:
        bag._writer.write = write_then_signal
        for t in range(1, 6):
            try:
                bag.write_clock(t)
            except BagWriteError:
                break
    finally:
        signal.signal(signal.SIGALRM, previous)
    assert fired == [3] and bag.closed
    bag.close()
    got = open_bag(tmp_path / "b")
    assert got.series["clock"].t_ns.tolist() == [1, 2, 3]
