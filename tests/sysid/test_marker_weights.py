"""Marker weights from the image tracker in the fit: an interpolated marker does not count, a clipped one
counts by its visible fraction, and weights of 1 leave the fit exactly as without weights."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from sim_core.sensors.camera import PinholeCamera
from sim_core.sensors.image import render_marker_image
from sysid.bagio import BagWriter
from sysid.diagnose.residuals import residual as diagnosis_residual, whiten
from sysid.evidence import load_evidence
from sysid.fit import fit
from sysid.observation import ObservationModel
from tests.sysid.simbag import DT, NS, PRESS_ONLY, TRUE_PARAMS, add_noise, scene_with, simulate_streams, \
    targets_from_segments

HIDDEN = (2, 5)
"""(frame, marker) drawn nowhere in the press recording's images: the tracker interpolates it."""


@pytest.fixture(scope="module")
def image_bag(tmp_path_factory):
    """The fitting tests' short card press with the tactile images rendered from its marker pixels and
    no markers topic; marker :data:`HIDDEN` is left out of its frame."""
    scene = scene_with(TRUE_PARAMS)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), PRESS_ONLY)
    streams = add_noise(simulate_streams(scene, TRUE_PARAMS, targets), seed=3)
    camera = PinholeCamera(**scene["sensors"]["tactile"]["camera"])
    out = tmp_path_factory.mktemp("images") / "bag"
    with BagWriter(out, scene=scene) as bag:
        for i, t in enumerate(streams["t_ns"]):
            t = int(t)
            bag.write_pose(f"{NS}/ee/pose", t, streams["pose"][i], "world")
            bag.write_pose(f"{NS}/ee/pose_cmd", t, streams["pose_cmd"][i], "world")
            bag.write_wrench(f"{NS}/tactile/wrench", t, streams["wrench"][i], "tactile")
            bag.write_points(f"{NS}/sheet/points", t, streams["sheet_points"][i], "world")
            uv = streams["markers_uv"][i].copy()
            if i == HIDDEN[0]:
                uv[HIDDEN[1]] = np.nan
            bag.write_image(f"{NS}/tactile/image", t, render_marker_image(uv, camera, marker_radius_px=5.0), "tactile")
            bag.write_clock(t)
    return out, streams


def _model(evidence, channels=("markers_uv", "wrench")) -> ObservationModel:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObservationModel(evidence, dt=DT, channels=channels)


def _evidence(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_evidence(path, include_image="auto")


def test_a_frame_with_an_interpolated_marker_is_kept_and_its_residual_has_zero_weight(image_bag):
    path, streams = image_bag
    ev = _evidence(path)
    frame, marker = HIDDEN
    assert ev.markers_uv.shape == streams["markers_uv"].shape  # no frame dropped
    assert ev.markers_uv_weight[frame, marker] == 0.0
    seen = np.ones(ev.markers_uv_weight.shape, dtype=bool)
    seen[frame, marker] = False
    np.testing.assert_array_equal(ev.markers_uv_weight[seen], 1.0)  # every other marker whole
    # the interpolated position is a position (near the truth), not a hole
    assert np.linalg.norm(ev.markers_uv[frame, marker] - streams["markers_uv"][frame, marker]) < 2.0

    model = _model(ev)
    rows = model.residual_slices()["markers_uv"]
    off = {"markers_uv": np.asarray(ev.markers_uv) + 1.0, "wrench": np.asarray(ev.wrench)}  # 1 px on every marker
    r = model.residuals(off)[rows].reshape(ev.markers_uv.shape)
    np.testing.assert_array_equal(r[frame, marker], 0.0)
    np.testing.assert_allclose(r[seen], np.broadcast_to(-1.0 / model.sigma["markers_uv"], r[seen].shape),
                               rtol=1e-12)
    # the Jacobian rows of that marker are zero too: it cannot pull a parameter
    d = np.ones(ev.markers_uv.shape + (2,))
    J = model.whiten_derivative("markers_uv", d).reshape(ev.markers_uv.shape + (2,))
    np.testing.assert_array_equal(J[frame, marker], 0.0)
    assert np.all(J[seen] != 0.0)
    # the diagnosis whitens the same way (its residuals and candidate signatures)
    np.testing.assert_array_equal(diagnosis_residual(model, "markers_uv", off["markers_uv"]), r)
    np.testing.assert_array_equal(whiten(model, "markers_uv", -d).reshape(J.shape), J)


def test_a_clipped_marker_counts_by_its_visible_fraction(image_bag):
    ev = _evidence(image_bag[0])
    weight = np.array(ev.markers_uv_weight)
    weight[1, 0] = 0.25  # a quarter of the blob visible
    model = _model(dataclasses.replace(ev, markers_uv_weight=weight))
    plain = _model(dataclasses.replace(ev, markers_uv_weight=None))
    rng = np.random.default_rng(0)
    pred = {"markers_uv": np.asarray(ev.markers_uv) + rng.normal(size=ev.markers_uv.shape),
            "wrench": np.asarray(ev.wrench)}
    rows = model.residual_slices()["markers_uv"]
    r = model.residuals(pred)[rows].reshape(ev.markers_uv.shape)
    r0 = plain.residuals(pred)[rows].reshape(ev.markers_uv.shape)
    np.testing.assert_allclose(r[1, 0], 0.5 * r0[1, 0], rtol=1e-14)  # sqrt(0.25): its cost counts a quarter
    np.testing.assert_array_equal(r[0], r0[0])


def test_weights_of_one_leave_the_fit_on_rendered_images_bit_for_bit(image_bag):
    ev = _evidence(image_bag[0])
    frame, marker = HIDDEN
    ones = dataclasses.replace(ev, markers_uv_weight=np.ones_like(ev.markers_uv_weight))
    none = dataclasses.replace(ev, markers_uv_weight=None)  # a markers topic's evidence: weight 1 everywhere
    start = {"gel.youngs_modulus": 2.0 * TRUE_PARAMS["gel.youngs_modulus"]}
    a = fit(_model(ones), ["gel.youngs_modulus"], initial=start, jacobian="fd", max_replays=4)
    b = fit(_model(none), ["gel.youngs_modulus"], initial=start, jacobian="fd", max_replays=4)
    assert a.cost_final < a.cost_initial  # the fit moved
    assert a.values == b.values and a.cost_final == b.cost_final and a.cost_initial == b.cost_initial
    # the tracker's weights (one marker interpolated) move the fit: the weights reach it
    c = fit(_model(ev), ["gel.youngs_modulus"], initial=start, jacobian="fd", max_replays=4)
    assert c.cost_initial != a.cost_initial
    assert ev.markers_uv_weight[frame, marker] == 0.0
