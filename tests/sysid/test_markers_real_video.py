"""Marker tracking on a real GelSight Mini press: every marker followed on every frame.

Input: ``shared/data/real/gsmini_press/mini_example.avi`` (219 real frames, 320 x 240, a fingertip
pressed, sheared, twisted and released; a 10 x 7 marker grid whose right column and bottom row are
cut by the image border during the press; see ``shared/data/real/README.md``: GPL-3 test input only).
No ground-truth tracks come with it, so the checks are physical: every marker is seen on every
frame, the lattice keeps its order and orientation (no identity swap), the tracks are continuous
within bounds set by the marker size and pitch, and the press shows as a displacement field that
rises from the sensor noise and relaxes after the release; a marker painted out under the contact is
interpolated from its lattice neighbours, flagged, and found again. The video is decoded and tracked once
per module.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from sysid.markers_image import (
    CLIPPED,
    INTERPOLATED,
    MEASURED,
    MarkerTracks,
    find_marker_blobs,
    lattice_neighbours,
    marker_spacing,
    track_marker_stream,
    track_markers,
)

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared"
VIDEO = SHARED / "data" / "real" / "gsmini_press" / "mini_example.avi"
GRID = (10, 7)  # markers along u (columns) and v (rows) on the first frame


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    if not VIDEO.is_file():
        pytest.skip(f"real GelSight Mini video not available at {VIDEO}")
    capture = cv2.VideoCapture(str(VIDEO))
    out = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        out.append(frame)
    capture.release()
    assert len(out) == 219 and out[0].shape == (240, 320, 3), "the README's 219 BGR frames of 320 x 240"
    return np.array(out)


@pytest.fixture(scope="module")
def tracks(frames: np.ndarray) -> MarkerTracks:
    return track_markers(frames, GRID)


@pytest.fixture(scope="module")
def scale(frames: np.ndarray, tracks: MarkerTracks) -> tuple[float, float]:
    """(marker pitch, marker radius) px of the first frame: the scales every bound below is set from."""
    blobs = find_marker_blobs(frames[0], marker_spacing(tracks.uv[0], frames[0].shape, GRID))
    return marker_spacing(tracks.uv[0], frames[0].shape, GRID), float(np.sqrt(np.median(blobs.area) / np.pi))


def test_every_marker_is_seen_on_every_frame(frames, tracks) -> None:
    F, k = frames.shape[0], GRID[0] * GRID[1]
    assert tracks.uv.shape == (F, k, 2) and tracks.status.shape == tracks.weight.shape == (F, k)
    assert np.all(np.isfinite(tracks.uv))
    # none lost, none interpolated: each marker is measured, whole or cut by the image border
    assert np.all(tracks.status <= CLIPPED), f"{int(np.sum(tracks.status > CLIPPED))} marker positions not seen"
    cut = tracks.status == CLIPPED
    # the press pushes the right column and the bottom row across the border (the old tracker lost
    # those: 329 positions in 68 frames); their centres come from the visible part, down-weighted
    assert cut.any(axis=1).sum() > 30
    cut_markers = np.unique(np.nonzero(cut)[1])
    assert set(cut_markers) <= set(range(GRID[0] - 1, 70, GRID[0])) | set(range(60, 70))
    assert np.all((tracks.weight[cut] > 0.0) & (tracks.weight[cut] < 1.0))
    assert np.all(tracks.weight[tracks.status == MEASURED] == 1.0)
    # the stream the evidence reads (measured positions only) has no gap either
    assert np.all(np.isfinite(track_marker_stream(frames[:3], GRID)))
    np.testing.assert_array_equal(tracks.measured, tracks.uv)


def test_lattice_order_and_orientation_are_kept(tracks) -> None:
    """Marker i stays marker i: along every row u increases, down every column v increases, and
    every lattice cell keeps its orientation and roughly its area (two neighbours swapping identity
    would fold the cells between them, a negative area)."""
    F = tracks.uv.shape[0]
    grid = tracks.uv.reshape(F, GRID[1], GRID[0], 2)  # [frame, iy, ix]
    assert np.all(np.diff(grid[..., 0], axis=2) > 0), "u must increase along every row of every frame"
    assert np.all(np.diff(grid[..., 1], axis=1) > 0), "v must increase down every column of every frame"
    corners = (grid[:, :-1, :-1], grid[:, :-1, 1:], grid[:, 1:, 1:], grid[:, 1:, :-1])
    area = 0.5 * sum(p[..., 0] * q[..., 1] - q[..., 0] * p[..., 1]
                     for p, q in zip(corners, corners[1:] + corners[:1]))
    ratio = area / area[0]
    assert np.all((ratio > 0.5) & (ratio < 2.0)), f"cell area ratio in [{ratio.min():.2f}, {ratio.max():.2f}]"


def test_tracks_are_continuous(tracks, scale) -> None:
    """Between two frames (40 ms) no marker moves half a pitch (beyond that the nearest blob could be
    a neighbour's: an identity swap), and no marker moves away from its lattice neighbours' motion
    by a marker diameter (another marker's blob lies at least that far from its own)."""
    pitch, radius = scale
    step = np.diff(tracks.uv, axis=0)  # (F - 1, k, 2)
    assert np.max(np.linalg.norm(step, axis=2)) < 0.5 * pitch
    near = lattice_neighbours(GRID, 1)
    relative = np.array([np.linalg.norm(step[:, i] - np.median(step[:, n], axis=1), axis=1)
                         for i, n in enumerate(near)])
    assert np.max(relative) < 2.0 * radius, f"a marker left its neighbours' motion by {np.max(relative):.1f} px"
    # and most of the time the field is far smoother than that
    assert np.percentile(relative, 99) < 0.5 * radius


def test_the_press_shows_as_a_displacement_field(tracks, scale) -> None:
    """Before the finger touches, markers stay within the tracking noise; at the press they move by
    a good part of a pitch, unevenly (a contact patch, not a rigid shift of the image); after the
    release the elastic gel brings them back."""
    pitch, _ = scale
    disp = np.linalg.norm(tracks.uv - tracks.uv[0], axis=2)  # (F, k) px
    noise = float(np.sqrt(np.mean(disp[1:30] ** 2)))
    assert np.max(disp[:30]) < 0.5, "no contact in the first 30 frames: markers must stay put"
    peak = int(np.argmax(np.median(disp, axis=1)))
    assert np.median(disp[peak]) > 0.1 * pitch and np.median(disp[peak]) > 20.0 * noise
    assert np.max(disp[peak]) > 3.0 * np.min(disp[peak]), "the press moves the markers unevenly"
    assert np.max(disp[-1]) < 0.1 * pitch, "after the release the markers return near their rest"


def test_a_marker_hidden_under_contact_is_interpolated_then_found_again(frames, tracks, scale) -> None:
    """Marker 34 (in the contact patch) painted over with the gel's colour around it for 31 frames of
    the press, as a marker merged into contact shading would vanish: it is followed through the gap
    by interpolation from its lattice neighbours (flagged, weight 0), within a marker radius of where
    it really was, and taken up again from its own blob afterwards."""
    _, radius = scale
    hidden, gap = 34, slice(85, 116)
    painted = frames.copy()
    for f in range(gap.start, gap.stop):
        centre = tuple(int(round(c)) for c in tracks.uv[f, hidden])
        ring = np.zeros(frames.shape[1:3], np.uint8)
        cv2.circle(ring, centre, int(2.5 * radius), 1, -1)
        cv2.circle(ring, centre, int(1.8 * radius), 0, -1)
        colour = np.median(frames[f][ring.astype(bool)], axis=0)
        cv2.circle(painted[f], centre, int(1.8 * radius), tuple(int(c) for c in colour), -1)
    out = track_markers(painted, GRID)
    assert np.all(out.status[gap, hidden] == INTERPOLATED) and np.all(out.weight[gap, hidden] == 0.0)
    assert np.all(np.isnan(out.measured[gap, hidden]))
    others = np.delete(np.arange(GRID[0] * GRID[1]), hidden)
    assert np.all(out.status[:, others] <= CLIPPED)
    assert np.all(out.status[: gap.start, hidden] == MEASURED) and np.all(out.status[gap.stop :, hidden] == MEASURED)
    err = np.linalg.norm(out.uv[:, hidden] - tracks.uv[:, hidden], axis=1)
    assert np.max(err[gap]) < radius, f"interpolated marker off by up to {np.max(err[gap]):.2f} px"
    assert np.max(err[gap.stop :]) < 0.1, "the marker must be found again on its own blob"
