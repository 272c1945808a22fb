"""Marker detection in tactile images: synthetic round trips, the real GelSight Mini frame, tracking."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from sim_core.errors import CalibrationError
from sim_core.sensors.camera import PinholeCamera
from sim_core.sensors.image import render_marker_image
from sim_core.sensors.markers import marker_grid
from sim_core.transforms import quat_from_rotvec, transform_points
from sysid.markers_image import (
    CLIPPED,
    INTERPOLATED,
    MEASURED,
    MarkerTracker,
    detect_markers,
    find_marker_blobs,
    order_marker_grid,
)

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared"
REAL_FRAME = SHARED / "data" / "real" / "feats" / "gelsight_mini_cuboid_press.png"
GRID = (9, 7)
PITCH = 0.002
CAM = PinholeCamera(fx=300.0, fy=300.0, cx=160.0, cy=120.0, width=320, height=240, distance=0.025)
RADIUS_PX = 0.2 * PITCH * 300.0 / 0.025  # 4.8 px


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def test_rendered_grid_round_trip() -> None:
    uv = CAM.project(marker_grid(GRID, PITCH))
    image = render_marker_image(uv, CAM, marker_radius_px=RADIUS_PX, blur=0.8, shading=0.25)
    found = detect_markers(image, GRID)
    assert _rms(found, uv) < 0.1
    assert np.max(np.linalg.norm(found - uv, axis=1)) < 0.2


def test_rotated_tilted_distorted_grid_round_trip() -> None:
    camera = PinholeCamera(fx=300.0, fy=300.0, cx=158.3, cy=121.7, width=320, height=240, distance=0.025, k1=0.15)
    # the gel plane seen at an angle: 12 deg about z, 15 deg about x, -10 deg about y, shifted off-centre
    rot = np.concatenate([[0.0005, -0.0004, 0.001], quat_from_rotvec(np.deg2rad([15.0, -10.0, 12.0]))])
    points = transform_points(rot, marker_grid(GRID, PITCH))
    uv = camera.project(points)
    radius = 0.2 * PITCH * camera.fx / (points[:, 2] + camera.distance)
    bgr = cv2.cvtColor(render_marker_image(uv, camera, marker_radius_px=radius, blur=0.6), cv2.COLOR_GRAY2BGR)
    found = detect_markers(bgr, GRID)
    assert _rms(found, uv) < 0.1
    # the grid really is rotated and foreshortened, so ordering was not trivial
    row0 = uv[:9]
    assert abs(np.degrees(np.arctan2(row0[-1, 1] - row0[0, 1], row0[-1, 0] - row0[0, 0]))) > 8.0


def test_ordering_is_independent_of_input_order() -> None:
    uv = CAM.project(marker_grid(GRID, PITCH))
    shuffled = uv[np.random.default_rng(0).permutation(uv.shape[0])]
    np.testing.assert_array_equal(order_marker_grid(shuffled, GRID), uv)
    np.testing.assert_array_equal(order_marker_grid(uv[:3][::-1], (3, 1)), uv[:3])
    np.testing.assert_array_equal(order_marker_grid(uv[::9][::-1], (1, 7)), uv[::9])


def test_wrong_marker_count_is_reported() -> None:
    uv = CAM.project(marker_grid(GRID, PITCH))
    uv[20] = np.nan  # one marker not drawn
    image = render_marker_image(uv, CAM, marker_radius_px=RADIUS_PX)
    with pytest.raises(CalibrationError, match=r"found 62 markers, expected 9 x 7 = 63"):
        detect_markers(image, GRID)
    with pytest.raises(CalibrationError, match=r"found 0 markers"):
        detect_markers(np.full((240, 320), 180, dtype=np.uint8), GRID)
    with pytest.raises(CalibrationError, match=r"lattice, expected 7 x 9"):
        full = render_marker_image(CAM.project(marker_grid(GRID, PITCH)), CAM, marker_radius_px=RADIUS_PX)
        detect_markers(full, (7, 9))


def test_real_gelsight_mini_frame() -> None:
    if not REAL_FRAME.is_file():
        pytest.skip(f"real GelSight Mini frame not available at {REAL_FRAME}")
    image = cv2.imread(str(REAL_FRAME), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape[:2] == (240, 320)
    uv = detect_markers(image, GRID)
    assert uv.shape == (63, 2) and np.all(np.isfinite(uv))
    grid = uv.reshape(7, 9, 2)  # [iy, ix]
    assert np.all(np.diff(grid[:, :, 0], axis=1) > 0), "u must increase along every row"
    assert np.all(np.diff(grid[:, :, 1], axis=0) > 0), "v must increase down every column"
    du = np.diff(grid[:, :, 0], axis=1)
    dv = np.diff(grid[:, :, 1], axis=0)
    for steps in (du, dv):
        median = np.median(steps)
        assert 25.0 < median < 45.0
        assert np.all(np.abs(steps - median) < 0.25 * median), "marker spacing must be roughly uniform"
    # row and column lines are straight to within a few pixels despite the indentation
    assert np.max(np.ptp(grid[:, :, 1], axis=1)) < 8.0 and np.max(np.ptp(grid[:, :, 0], axis=0)) < 8.0
    # every detection sits on a dark blob
    gray = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    centre_levels = gray[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    assert np.all(centre_levels < np.median(gray))


def test_tracker_follows_a_sliding_sequence() -> None:
    uv0 = CAM.project(marker_grid(GRID, PITCH))
    velocity = np.array([6.0, 1.0])  # px per frame; 72 px in total, three marker pitches
    tracker = MarkerTracker(GRID, max_displacement_px=10.0)
    saw_lost = saw_clipped = False
    for t in range(13):
        truth = uv0 + t * velocity
        drawn = truth.copy()
        if t == 5:
            drawn[10] = np.nan  # marker 10 occluded for one frame
        image = render_marker_image(drawn, CAM, marker_radius_px=RADIUS_PX, blur=0.7)
        frame = tracker.update(image)
        tracked = frame.measured
        assert tracked.shape == (63, 2) and frame.status.shape == frame.weight.shape == (63,)
        inside = (truth[:, 0] > RADIUS_PX + 2) & (truth[:, 0] < CAM.width - RADIUS_PX - 3)
        outside = truth[:, 0] - RADIUS_PX > CAM.width
        visible = inside & ~np.isnan(drawn[:, 0])
        ok = ~np.isnan(tracked[:, 0])
        assert np.all(ok[visible]), f"frame {t}: visible markers lost"
        assert np.all(frame.status[visible] == MEASURED) and np.all(frame.weight[visible] == 1.0)
        assert np.max(np.linalg.norm(tracked[visible] - truth[visible], axis=1)) < 0.15, f"frame {t}: order lost"
        assert np.all(np.isnan(tracked[outside])), f"frame {t}: markers out of frame must be NaN"
        # ... yet followed: interpolated from their lattice neighbours (a rigid slide: exactly), weight 0
        assert np.all(frame.status[outside] == INTERPOLATED) and np.all(frame.weight[outside] == 0.0)
        cut = frame.status == CLIPPED  # partly out of the image: centre from the visible part
        err = np.linalg.norm(frame.uv - truth, axis=1)
        assert np.all(err[~cut] < 0.3) and np.all(err[cut] < 0.25 * RADIUS_PX), f"frame {t}: a marker not followed"
        assert np.all((frame.weight[cut] > 0.0) & (frame.weight[cut] < 1.0))
        assert np.all(~cut[inside])
        if t == 5:
            assert np.all(np.isnan(tracked[10])) and frame.status[10] == INTERPOLATED
        saw_lost |= bool(np.any(outside))
        saw_clipped |= bool(np.any(cut))
    assert saw_lost and saw_clipped  # the right column left the image
    first = render_marker_image(uv0, CAM, marker_radius_px=RADIUS_PX, blur=0.7)
    np.testing.assert_array_equal(tracker.reference, detect_markers(first, GRID))


def test_tracker_with_initial_points_and_gate() -> None:
    uv0 = CAM.project(marker_grid((3, 2), PITCH))
    tracker = MarkerTracker((3, 2), max_displacement_px=5.0, initial_uv=uv0)
    moved = uv0 + [2.0, -1.0]
    moved[4] += [0.0, 60.0]  # jumps farther than the gate, away from every other marker
    frame = tracker.update_points(moved[::-1])
    np.testing.assert_allclose(frame.uv[[0, 1, 2, 3, 5]], moved[[0, 1, 2, 3, 5]])
    assert np.all(np.isnan(frame.measured[4])) and frame.status[4] == INTERPOLATED
    np.testing.assert_allclose(frame.uv[4], uv0[4] + [2.0, -1.0], atol=1e-9)  # moved with its neighbours
    with pytest.raises(CalibrationError, match="max_displacement_px must be > 0"):
        MarkerTracker((3, 2), max_displacement_px=0.0)
    with pytest.raises(CalibrationError, match="no reference frame"):
        MarkerTracker((3, 2), max_displacement_px=5.0).update_points(uv0)
    with pytest.raises(CalibrationError, match=r"visible must have shape \(6,\)"):
        tracker.update_points(uv0, visible=np.ones(3))


def test_a_detection_that_disagrees_with_its_lattice_neighbours_is_not_taken() -> None:
    """A spurious dark spot nearer to a marker's last position than its own blob (inside the gate):
    the nearest-blob assignment takes it, the lattice check undoes it, and the marker's own blob,
    found where its neighbours' motion says, is taken instead."""
    uv0 = CAM.project(marker_grid(GRID, PITCH))
    tracker = MarkerTracker(GRID, max_displacement_px=10.0, initial_uv=uv0, marker_radius_px=RADIUS_PX)
    truth = uv0 + [7.0, 0.0]  # everything slides 7 px
    spurious = uv0[31] + [-2.0, 1.0]  # 2.2 px from marker 31's last position, 9 px from its blob
    frame = tracker.update_points(np.concatenate([truth, spurious[None]]))
    np.testing.assert_allclose(frame.uv, truth)
    assert np.all(frame.status == MEASURED)
    # without its own blob, the marker is interpolated, not put on the spot
    tracker = MarkerTracker(GRID, max_displacement_px=10.0, initial_uv=uv0, marker_radius_px=RADIUS_PX)
    frame = tracker.update_points(np.concatenate([np.delete(truth, 31, axis=0), spurious[None]]))
    assert frame.status[31] == INTERPOLATED
    np.testing.assert_allclose(frame.uv[31], truth[31], atol=1e-9)


def test_blobs_cut_by_the_border_give_the_whole_marker_centre() -> None:
    """A marker cut by the image border: its centre from the visible part (circular segment) agrees
    with the drawn centre to a small part of the radius, also when less than half is visible."""
    radius = 5.5
    for centre in ([316.0, 120.0], [319.5, 120.0], [322.0, 120.0], [160.0, 2.0], [-1.5, 60.0], [318.0, 237.0]):
        uv = np.array([centre, [160.0, 120.0], [130.0, 120.0], [160.0, 90.0]])
        image = render_marker_image(uv, CAM, marker_radius_px=radius, blur=0.7)
        whole = find_marker_blobs(image, spacing_px=30.0)
        assert whole.uv.shape[0] == 3 and np.all(whole.visible == 1.0)
        blobs = find_marker_blobs(image, spacing_px=30.0, keep_clipped=True)
        cut = np.nonzero(blobs.clipped)[0]
        assert cut.size == 1, centre
        err = np.linalg.norm(blobs.uv[cut[0]] - uv[0])
        assert err < 0.25 * radius, f"marker at {centre}: centre off by {err:.2f} px"
        assert 0.0 < blobs.visible[cut[0]] < 1.0


def test_blobs_touching_the_border_are_dropped() -> None:
    uv = np.array([[1.0, 120.0], [160.0, 120.0]])
    blobs = find_marker_blobs(render_marker_image(uv, CAM, marker_radius_px=RADIUS_PX), spacing_px=24.0)
    np.testing.assert_allclose(blobs.uv, uv[1:], atol=0.02)


def test_shading_attached_to_a_marker_does_not_pull_its_centre() -> None:
    """A dark streak of gel shading (a contact edge) touching a marker merges with its blob; the
    centre is re-centred on a marker's disc and stays on the marker."""
    uv = CAM.project(marker_grid(GRID, PITCH))
    image = render_marker_image(uv, CAM, marker_radius_px=RADIUS_PX, blur=0.7)
    u, v = uv[31]
    streak = image.copy()
    cv2.line(streak, (int(u + 3), int(v + 3)), (int(u + 14), int(v + 14)), int(image.min()), thickness=4)
    clean = find_marker_blobs(image, spacing_px=24.0)
    blobs = find_marker_blobs(streak, spacing_px=24.0)
    i = int(np.argmin(np.linalg.norm(blobs.uv - uv[31], axis=1)))
    assert blobs.area[i] > 1.5 * np.median(clean.area)  # the streak is part of the blob
    # 6 px off without the re-centring; within a quarter of the marker radius with it
    pulled = float(np.linalg.norm(blobs.uv[i] - uv[31]))
    assert pulled < 0.25 * RADIUS_PX, f"centre pulled by {pulled:.2f} px"
    np.testing.assert_allclose(np.delete(blobs.uv, i, axis=0), np.delete(clean.uv, i, axis=0), atol=1e-9)
