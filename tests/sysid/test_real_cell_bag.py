"""A real cell's recording read through a recording map gives the evidence and answers of the contract bag.

The bundled recording is rewritten as a real cell records it (tests/support/real_cell.py: TF chain
with non-identity mounts, the world at a non-identity pose in base_link, an F/T sensor in its own
rotated and offset frame with a tool weight and an offset, compressed zero-stamped colour images,
other topic names, two .mcap files) and compared with the same recording under today's contract
(plus the same frames as mono8 images).
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import yaml

from sim_core.errors import BagReadError, ConfigError
from sysid.bagio import BagWriter, open_bag
from sysid.bagio.recording_map import load_recording_map, parse_recording_map
from sysid.cli import sysid_main
from sysid.diagnose.cli import diagnose_main
from sysid.evidence import load_evidence
from sysid.markers_image import track_marker_stream
from tests.support import real_cell
from tests.sysid.conftest import reference_bag

TOL = 1e-9
CHEAP = ["--t-max", "0.3", "--dt", "0.05", "--gel-resolution"]


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("cell")
    src = reference_bag("nominal_s101")
    real_cell.write_plain_bag_with_images(src, root / "plain")
    real_cell.write_real_cell_bag(src, root / "cell")
    (root / "window.yaml").write_text(yaml.safe_dump(real_cell.recording_map(tare="window")))
    return root


def _evidence(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_evidence(path, include_image=True, **kw)


def _assert_same_channel(a, b, ch):
    np.testing.assert_array_equal(a.t_ns[ch], b.t_ns[ch], err_msg=ch)
    va, vb = a.values(ch).astype(float), b.values(ch).astype(float)
    assert va.shape == vb.shape, ch
    if ch in ("pose", "pose_cmd"):  # q and -q are one rotation
        vb = vb.copy()
        vb[:, 3:] *= np.sign(np.sum(va[:, 3:] * vb[:, 3:], axis=1))[:, None]
    np.testing.assert_allclose(vb, va, rtol=0, atol=TOL, err_msg=ch)


def test_real_cell_bag_gives_the_contract_evidence(bags):
    plain, cell = _evidence(bags / "plain"), _evidence(bags / "cell")
    assert cell.source.mcap_path.name == "cell_0.mcap"  # a split bag, read through metadata.yaml
    assert plain.channels_present == cell.channels_present
    assert set(cell.channels_present) >= {"pose", "pose_cmd", "markers_xyz", "markers_uv", "wrench", "sheet_points",
                                          "image"}
    for ch in plain.channels_present:
        _assert_same_channel(plain, cell, ch)
    for ch in plain.noise:
        np.testing.assert_allclose(cell.noise[ch], plain.noise[ch], rtol=1e-6, atol=1e-15, err_msg=ch)
    np.testing.assert_array_equal(plain.clock_t_ns, cell.clock_t_ns)
    assert cell.scene == plain.scene  # the recorded camera_info states the scene's intrinsics
    # the zero-stamped compressed frames take their log times (stamp: auto): one sample per frame
    assert cell.t_ns["image"].shape[0] == plain.t_ns["image"].shape[0] > 30
    grid = tuple(plain.scene.sensors["tactile"].marker_grid)
    tracks_plain, tracks_cell = track_marker_stream(plain.image, grid), track_marker_stream(cell.image, grid)
    assert np.all(np.isfinite(tracks_plain))
    np.testing.assert_array_equal(tracks_cell, tracks_plain)


def test_tare_over_a_pre_contact_window_removes_the_window_mean(bags):
    plain = _evidence(bags / "plain")
    cell = _evidence(bags / "cell", recording_map=bags / "window.yaml")
    t = plain.t_ns["wrench"]
    window = (t >= t[0]) & (t <= t[0] + 50_000_000)
    expected = plain.wrench - plain.wrench[window].mean(axis=0)
    np.testing.assert_allclose(cell.wrench, expected, rtol=0, atol=TOL)
    _assert_same_channel(plain, cell, "pose")


def test_time_window_keeps_the_samples_inside(bags):
    full = _evidence(bags / "cell")
    cut = _evidence(bags / "cell", t_start=0.5, t_end=1.25)
    start = full.start_ns
    for ch in cut.channels_present:
        t = full.t_ns[ch]
        keep = (t >= start + 500_000_000) & (t <= start + 1_250_000_000)
        np.testing.assert_array_equal(cut.t_ns[ch], t[keep], err_msg=ch)
        np.testing.assert_array_equal(cut.values(ch), full.values(ch)[keep], err_msg=ch)
    with pytest.raises(ConfigError, match="t_start < t_end"):
        _evidence(bags / "cell", t_start=1.0, t_end=0.5)


def test_a_frame_that_contradicts_the_map_is_one_error_naming_topic_and_frames(bags, tmp_path):
    rmap = real_cell.recording_map()
    rmap["wrench"]["frame"] = "ft_link"
    (tmp_path / "wrong.yaml").write_text(yaml.safe_dump(rmap))
    with pytest.raises(BagReadError, match=r"topic /ft_sensor/wrench: header frame_id is 'ft_sensor' but the "
                                           r"recording map says the wrench is in 'ft_link'"):
        _evidence(bags / "cell", recording_map=tmp_path / "wrong.yaml")
    rmap = real_cell.recording_map()
    rmap["frames"]["effector"] = "gripper"
    (tmp_path / "noframe.yaml").write_text(yaml.safe_dump(rmap))
    with pytest.raises(BagReadError, match="frame gripper is not in /tf or /tf_static"):
        _evidence(bags / "cell", recording_map=tmp_path / "noframe.yaml")


def test_a_pose_outside_world_without_a_map_is_an_error(tmp_path):
    with BagWriter(tmp_path / "bag") as w:
        for k in range(3):
            w.write_pose("/thinshell/ee/pose", k * 1_000_000, np.array([0.0, 0, 0.1 * k, 0, 0, 0, 1]), "base_link")
    with pytest.raises(BagReadError, match=r"topic /thinshell/ee/pose: header frame_id is 'base_link' .* "
                                           r"expected 'world'"):
        open_bag(tmp_path / "bag")


def test_map_schema_rejects_unknown_keys_and_needs_a_version(tmp_path):
    good = real_cell.recording_map()
    assert parse_recording_map(good).wrench.tare_offset == tuple(real_cell.FT_OFFSET)
    with pytest.raises(ConfigError, match=r"unknown key wrench.tare.mean \(allowed: window, offset\)"):
        parse_recording_map({**good, "wrench": {**good["wrench"], "tare": {"mean": [0, 1]}}}, "m.yaml")
    with pytest.raises(ConfigError, match="m.yaml: version must be 1"):
        parse_recording_map({**good, "version": 2}, "m.yaml")
    with pytest.raises(ConfigError, match="image.stamp must be one of header, log, auto"):
        parse_recording_map({**good, "image": {"topic": "/x", "stamp": "zero"}}, "m.yaml")
    (tmp_path / "r.yaml").write_text("version: 1\nframes: {base: b, sensor: s}\n")
    with pytest.raises(ConfigError, match=r"r.yaml: frames.world_in_base is required"):
        load_recording_map(tmp_path / "r.yaml")


def _fit(path):
    doc = json.loads((path / "fit.json").read_text())
    return {"fit": doc["fit"], "metrics": doc["metrics"]}


def _assert_close(a, b, where=""):
    """Same JSON structure; numbers equal to a relative 1e-7 (strings and flags exactly)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _assert_close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_close(x, y, f"{where}[{i}]")
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=1e-7, abs=1e-12), where
    else:
        assert a == b, where


def test_sysid_and_diagnose_answer_the_same_on_both(bags, tmp_path, capsys):
    # --fixed-gains: with the gains refitted at every replay (the default), six steps of 50 ms leave the gel modulus
    # to the marker scales (robust sigma ~3e12 Pa, so its digits past the sixth are round-off of a near-singular
    # covariance); held, the two bags' fits agree to 1e-7 as the evidence does
    fast = [*CHEAP, "5,4,2", "--params", "gel.youngs_modulus", "--max-nfev", "3", "--quiet", "--fixed-gains"]
    assert sysid_main([str(bags / "plain"), "--out", str(tmp_path / "fp"), *fast]) == 0
    assert sysid_main([str(bags / "cell"), "--out", str(tmp_path / "fc"), *fast]) == 0
    prov = json.loads((tmp_path / "fc" / "fit.json").read_text())["provenance"]
    assert prov["recording_map"] == str(bags / "cell" / "recording.yaml")
    fp, fc = _fit(tmp_path / "fp"), _fit(tmp_path / "fc")
    assert "gel.youngs_modulus" in fp["fit"]["parameters"]
    _assert_close(fp, fc)
    assert sysid_main([str(bags / "cell"), "--out", str(tmp_path / "fx"), "--recording-map", "nowhere.yaml"]) == 2
    assert "recording map not found: nowhere.yaml" in capsys.readouterr().err
    diag = [*CHEAP, "5", "4", "2", "--no-calibrate"]
    docs = []
    for name in ("plain", "cell"):
        out = tmp_path / f"d_{name}.json"
        assert diagnose_main([str(bags / name), *diag, "--json", str(out)]) == 0, capsys.readouterr().err
        docs.append(json.loads(out.read_text()))
    assert docs[0]["explained_by"] == docs[1]["explained_by"]


def test_a_pose_topic_in_base_link_of_another_link_is_carried_to_the_effector_in_world(bags, tmp_path):
    rmap = real_cell.recording_map()
    rmap["pose"] = {"topic": real_cell.TOPICS["pose_cmd"], "link": "tool0", "stamp": "log"}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(rmap))
    plain, cell = _evidence(bags / "plain"), _evidence(bags / "cell", recording_map=tmp_path / "m.yaml")
    a, b = plain.pose_cmd, cell.pose.copy()
    b[:, 3:] *= np.sign(np.sum(a[:, 3:] * b[:, 3:], axis=1))[:, None]
    np.testing.assert_allclose(b, a, rtol=0, atol=TOL)


def test_deploy_replays_the_same_command_stream_from_the_real_cell_bag(bags):
    from thinshell_ros.deploy_plan import trajectory_from_bag

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain, cell = trajectory_from_bag(bags / "plain"), trajectory_from_bag(bags / "cell")
    np.testing.assert_array_equal(cell.t, plain.t)
    a, b = plain.poses["ee"], cell.poses["ee"].copy()
    b[:, 3:] *= np.sign(np.sum(a[:, 3:] * b[:, 3:], axis=1))[:, None]
    np.testing.assert_allclose(b, a, rtol=0, atol=TOL)


def test_the_example_map_is_valid():
    from thinshell_ros.paths import config_dir

    rmap = load_recording_map(config_dir() / "recording_maps" / "ur5e_gsmini_ft.yaml")
    assert rmap.pose == "tf" and rmap.wrench.tare_window == (0.0, 0.5) and rmap.image.stamp == "auto"


def test_split_files_must_be_those_metadata_lists(bags, tmp_path):
    import shutil

    bag = tmp_path / "cell"
    shutil.copytree(bags / "cell", bag)
    (bag / "cell_1.mcap").rename(bag / "other.mcap")
    with pytest.raises(BagReadError, match=r"2 .mcap files in the bag directory but metadata.yaml lists "
                                           r"\['cell_0.mcap', 'cell_1.mcap'\]"):
        open_bag(bag)


def test_commands_in_another_frame_among_world_ones_are_dropped_with_a_warning(tmp_path):
    with BagWriter(tmp_path / "bag") as w:
        for k in range(4):
            pose = np.array([0.0, 0, 0.1 * k, 0, 0, 0, 1])
            w.write_pose("/thinshell/ee/pose", k * 1_000_000, pose)
            w.write_pose("/thinshell/ee/pose_cmd", k * 1_000_000, pose, "map" if k == 2 else "world")
    with pytest.warns(UserWarning, match=r"topic /thinshell/ee/pose_cmd: dropped 1 of 4 commands in frame\(s\) "
                                         r"\['map'\] instead of 'world'"):
        bag = open_bag(tmp_path / "bag")
    np.testing.assert_array_equal(bag.series["pose_cmd"].t_ns, [0, 1_000_000, 3_000_000])
