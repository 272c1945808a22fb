"""Marker detection and tracking in tactile images (real GelSight-type frames or rendered ones).

Pipeline of :func:`find_marker_blobs`:

1. grey image, lightly smoothed (Gaussian, sigma ~ spacing / 20) against the gel's speckle;
2. local background by a grey-level morphological closing with a disc wider than a marker
   (dark spots smaller than the disc are filled in), so uneven illumination cancels;
3. contrast ``d = background - image`` (markers positive), Otsu threshold, connected components;
4. specks and merged blobs (area far from the median) dropped, and components touching the image
   border unless ``keep_clipped`` (step 6);
5. sub-pixel centre of each blob: the ``d``-weighted centroid over the blob grown by two pixels; a
   blob larger than 1.5 times the median (a marker with dark gel shading attached, e.g. the edge of
   a contact) is re-centred on the part within one median marker radius of its centre until the
   centre stops moving (a symmetric window: a round marker's centre stays where it is);
6. with ``keep_clipped``, blobs cut by the image border too, the whole marker's centre estimated
   from the visible part (:func:`clipped_centre`).

:func:`detect_markers` then orders the blobs as the marker grid, ``i = iy * nx + ix`` (rows by image
``v``, columns by ``u``), by labelling the lattice: the grid direction comes from the four-fold
symmetric mean of nearest-neighbour directions, lattice vectors from the median neighbour steps, and
integer coordinates spread from the centre by breadth-first search along accepted unit steps, each
point carrying a local lattice basis so that mild rotation, perspective and indentation are tolerated.

:class:`MarkerTracker` and :func:`track_markers` follow the ordered markers through a stream: the
nearest blobs (Hungarian assignment within a gate), checked against the lattice neighbours' motion,
blobs cut by the border included, and every marker still not found interpolated from its lattice
neighbours. Each marker of each frame carries a status (:data:`MEASURED`, :data:`CLIPPED`,
:data:`INTERPOLATED`, :data:`LOST`) and a weight in ``[0, 1]`` for a fit (1 whole, the visible
fraction when cut by the border, 0 when not seen), so that interpolated positions can be
down-weighted or dropped; :func:`track_marker_stream` gives the measured positions alone (NaN
where a marker was not seen).

Pixel convention: OpenCV's (pixel (row i, column j) centred at ``(u, v) = (j, i)``).
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from sim_core.errors import CalibrationError

MIN_CONTRAST = 5.0
"""Grey levels: below this peak marker contrast the image is taken to hold no markers."""

TRIM_ITERATIONS = 20
"""Most re-centring passes on a disc of one marker radius for a blob with gel shading attached
(:func:`find_marker_blobs`, step 5); they stop when the centre moves less than 0.01 px."""

STEP_TOLERANCE = 0.3
"""Largest deviation (in lattice units) of a neighbour step from a unit lattice step."""


class MarkerBlobs(NamedTuple):
    """Unordered marker blobs found in one image.

    Attributes:
        uv: sub-pixel blob centres, shape ``(m, 2)``, px; for a blob cut by the image border, the
            centre of the whole marker estimated from its visible part (:func:`clipped_centre`),
            which may lie outside the image.
        area: blob areas above the threshold, shape ``(m,)``, px^2 (the visible part when clipped).
        visible: fraction of the marker's area inside the image, shape ``(m,)``, in ``[0, 1]``;
            1 for a blob clear of the border.
    """

    uv: np.ndarray
    area: np.ndarray
    visible: np.ndarray

    @property
    def clipped(self) -> np.ndarray:
        """Blobs cut by the image border, shape ``(m,)`` bool."""
        return self.visible < 1.0


def to_gray(image: np.ndarray) -> np.ndarray:
    """Grey image as float32 from mono8/mono16 ``(h, w)``, BGR ``(h, w, 3)`` or BGRA ``(h, w, 4)``.

    Raises:
        CalibrationError: any other shape.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 2:
        return img.astype(np.float32)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(img, code).astype(np.float32)
    raise CalibrationError(f"marker image must be mono (h, w) or BGR/BGRA (h, w, 3|4), got shape {img.shape}")


def _odd(n: float) -> int:
    k = max(3, int(round(n)))
    return k if k % 2 == 1 else k + 1


def find_marker_blobs(image: np.ndarray, spacing_px: float, keep_clipped: bool = False,
                      known_size: tuple[np.ndarray, np.ndarray] | None = None) -> MarkerBlobs:
    """Dark round marker blobs of a tactile image, unordered (module docstring, steps 1-5).

    Args:
        image: mono or BGR/BGRA image (:func:`to_gray`).
        spacing_px: approximate marker spacing, px; sets the smoothing, the background disc
            (0.9 spacing) and the smallest accepted blob.
        keep_clipped: also return blobs cut by the image border, their centres estimated from the
            visible part (:func:`clipped_centre`) and ``visible < 1``; by default they are dropped
            (a grid is ordered from whole markers only).
        known_size: optional ``(points (n, 2) px, relative area (n,))``: a cut marker's whole area is
            the median area of the four nearest whole blobs of this image times the relative area
            (:func:`relative_area`) of the nearest of these points (a tracker passes each marker's
            last position and its relative area when last seen whole, so that vignetting towards
            the border is followed marker by marker, and the image's own threshold by the
            neighbours); by default the relative area is 1.

    Returns:
        the blobs; empty when the image has no marker contrast.

    Raises:
        CalibrationError: bad image shape or non-positive spacing.
    """
    if not spacing_px > 0:
        raise CalibrationError(f"find_marker_blobs: spacing_px must be > 0, got {spacing_px!r}")
    gray = to_gray(image)
    H, W = gray.shape
    sigma = max(0.5, spacing_px / 20.0)
    smooth = cv2.GaussianBlur(gray, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
    k = _odd(0.9 * spacing_px)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    background = cv2.morphologyEx(smooth, cv2.MORPH_CLOSE, disc, borderType=cv2.BORDER_REFLECT)
    contrast = np.maximum(background - smooth, 0.0)
    peak = float(contrast.max()) if contrast.size else 0.0
    empty = MarkerBlobs(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    if peak < MIN_CONTRAST:
        return empty
    scaled = np.clip(contrast * (255.0 / peak), 0, 255).astype(np.uint8)
    _, binary = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    x0, y0, w, h, area = (stats[1:, j] for j in range(5))
    edges = np.stack([x0 == 0, y0 == 0, x0 + w >= W, y0 + h >= H], axis=1)  # left, top, right, bottom
    on_border = edges.any(axis=1)
    min_area = np.pi * (0.05 * spacing_px) ** 2
    candidates = np.nonzero(~on_border & (area >= min_area))[0]
    if candidates.size == 0:
        return empty
    median = float(np.median(area[candidates]))
    keep = candidates[(area[candidates] >= 0.25 * median) & (area[candidates] <= 4.0 * median)]
    grow = cv2.getStructuringElement(cv2.MORPH_RECT, (3, 3))
    trim_area = 1.5 * median  # px^2: blobs above this are trimmed to a marker's disc
    trim_radius = float(np.sqrt(median / np.pi))

    def centroid(c: int) -> tuple[float, float]:
        # contrast-weighted centre over the blob grown by two pixels (module docstring, step 5)
        label = c + 1
        ya, yb = max(y0[c] - 3, 0), min(y0[c] + h[c] + 3, H)
        xa, xb = max(x0[c] - 3, 0), min(x0[c] + w[c] + 3, W)
        region = labels[ya:yb, xa:xb]
        mask = cv2.dilate((region == label).astype(np.uint8), grow, iterations=2).astype(bool)
        mask &= (region == 0) | (region == label)
        weight = contrast[ya:yb, xa:xb] * mask
        vv, uu = np.arange(ya, yb, dtype=float)[:, None], np.arange(xa, xb, dtype=float)[None, :]
        total = float(weight.sum())
        u, v = float((weight * uu).sum()) / total, float((weight * vv).sum()) / total
        if area[c] <= trim_area:
            return u, v
        # a blob larger than a marker has dark gel shading (a contact edge, a ridge) attached: keep
        # re-centring on the part within a marker's radius of the centre (a symmetric window), which
        # leaves a round marker's centre where it is and drops what hangs off it
        for _ in range(TRIM_ITERATIONS):
            inside = weight * ((uu - u) ** 2 + (vv - v) ** 2 <= trim_radius**2)
            total = float(inside.sum())
            if total <= 0.0:
                break
            u_new, v_new = float((inside * uu).sum()) / total, float((inside * vv).sum()) / total
            moved = abs(u_new - u) + abs(v_new - v)
            u, v = u_new, v_new
            if moved < 0.01:
                break
        return u, v

    uv = np.array([centroid(c) for c in keep]).reshape(-1, 2)
    visible = np.ones(keep.size)
    areas = area[keep].astype(float)
    if keep_clipped and keep.size:
        cut = np.nonzero(on_border & (area >= min_area) & (area <= 4.0 * median))[0]
        if cut.size:
            boxes = np.column_stack([x0[cut] + 0.5 * w[cut], y0[cut] + 0.5 * h[cut]])
            near = cKDTree(uv).query(boxes, k=min(4, keep.size))[1].reshape(cut.size, -1)
            relative = np.ones(cut.size)
            if known_size is not None:
                points, sizes = (np.asarray(v, dtype=float) for v in known_size)
                relative = sizes.reshape(-1)[cKDTree(points.reshape(-1, 2)).query(boxes)[1]]
            radius = np.sqrt(relative * np.median(areas[near], axis=1) / np.pi)
            extra_uv, extra_vis = [], []
            for n, c in enumerate(cut):
                centre, fraction = clipped_centre(centroid(c), float(area[c]), float(radius[n]),
                                                  edges[c], (int(x0[c]), int(y0[c]), int(w[c]), int(h[c])), (H, W))
                extra_uv.append(centre)
                extra_vis.append(fraction)
            uv = np.concatenate([uv, np.array(extra_uv)])
            visible = np.concatenate([visible, np.array(extra_vis)])
            areas = np.concatenate([areas, area[cut].astype(float)])
    return MarkerBlobs(uv, areas, visible)


def relative_area(blobs: MarkerBlobs) -> np.ndarray:
    """Each whole blob's area over the median area of its (up to) four nearest other whole blobs,
    ``(m,)``; NaN for cut blobs, 1 when there is no other whole blob. Under one threshold this ratio
    is a property of the marker and its place in the image (vignetting), not of the threshold."""
    out = np.full(blobs.uv.shape[0], np.nan)
    whole = np.nonzero(~blobs.clipped)[0]
    if whole.size < 2:
        out[whole] = 1.0
        return out
    near = cKDTree(blobs.uv[whole]).query(blobs.uv[whole], k=min(5, whole.size))[1][:, 1:]
    out[whole] = blobs.area[whole] / np.median(blobs.area[whole][near], axis=1)
    return out


_CHORD_X = np.linspace(-1.0, 1.0, 401)
_CHORD_FRACTION = (np.pi - np.arccos(_CHORD_X) + _CHORD_X * np.sqrt(1.0 - _CHORD_X**2)) / np.pi
"""Visible fraction of a disc whose centre lies ``x`` radii inside a straight cut (circular segment)."""


def clipped_centre(centroid: tuple[float, float], area: float, radius: float, edges: np.ndarray,
                   box: tuple[int, int, int, int], shape: tuple[int, int]) -> tuple[tuple[float, float], float]:
    """Centre of a round marker cut by the image border, from its visible part.

    Along the border the visible part is symmetric about the centre, so its (contrast-weighted)
    centroid is kept. Across one cutting edge, the visible area ``A`` of a disc of radius ``r``
    whose centre lies ``h`` inside the edge line is the circular-segment area
    ``A = r^2 (pi - acos(h/r)) + h sqrt(r^2 - h^2)``, inverted for ``h``. At a corner (two cutting
    edges) each coordinate comes from the visible extent ``d`` across its edge, ``h = d - r``.
    The edge lines are the outer pixel boundaries, ``u = -0.5`` and ``u = W - 0.5`` (likewise v).

    Args:
        centroid: ``(u, v)`` px, weighted centroid of the visible part.
        area: visible area above the threshold, px^2.
        radius: the marker's radius at that threshold, px (> 0).
        edges: ``(4,)`` bool, the blob touches the left, top, right, bottom border.
        box: the visible part's bounding box ``(x0, y0, w, h)`` px.
        shape: image ``(H, W)``.

    Returns:
        ``((u, v), visible)``: the estimated centre, px (it may lie outside the image), and the
        visible fraction ``A / (pi r^2)`` clipped to ``[0, 1]``.
    """
    H, W = shape
    x0, y0, w, h = box
    fraction = float(np.clip(area / (np.pi * radius**2), 0.0, 1.0))
    centre = [float(centroid[0]), float(centroid[1])]
    single = int(np.count_nonzero(edges)) == 1
    # (axis, inward sign, edge line, visible extent across the edge)
    cuts = ((0, 1.0, -0.5, x0 + w), (1, 1.0, -0.5, y0 + h), (0, -1.0, W - 0.5, W - x0), (1, -1.0, H - 0.5, H - y0))
    for touched, (axis, inward, line, extent) in zip(edges, cuts):
        if not touched:
            continue
        if single:
            depth = radius * float(np.interp(fraction, _CHORD_FRACTION, _CHORD_X))
        else:
            depth = float(np.clip(extent - radius, -radius, radius))
        centre[axis] = line + inward * depth
    return (centre[0], centre[1]), fraction


def _lattice_basis(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lattice vectors ``a`` (towards +u) and ``b`` (towards +v) from nearest-neighbour steps."""
    tree = cKDTree(points)
    dist, idx = tree.query(points, k=min(5, points.shape[0]))
    steps, ok = [], []
    for j in range(1, dist.shape[1]):
        steps.append(points[idx[:, j]] - points)
        ok.append(dist[:, j] < 1.25 * dist[:, 1])
    steps_arr = np.concatenate(steps)[np.concatenate(ok)]
    phi = np.arctan2(steps_arr[:, 1], steps_arr[:, 0])
    theta0 = 0.25 * float(np.angle(np.sum(np.exp(4j * phi))))  # in (-pi/4, pi/4]
    basis = []
    for theta in (theta0, theta0 + 0.5 * np.pi):
        e = np.array([np.cos(theta), np.sin(theta)])
        along = steps_arr @ e
        cos_angle = np.abs(along) / np.maximum(np.linalg.norm(steps_arr, axis=1), 1e-300)
        sel = cos_angle > np.cos(np.deg2rad(30.0))
        if not np.any(sel):
            raise CalibrationError("detect_markers: cannot find the marker lattice directions")
        oriented = steps_arr[sel] * np.sign(along[sel])[:, None]
        basis.append(np.median(oriented, axis=0))
    return basis[0], basis[1]


def order_marker_grid(points: np.ndarray, expected_grid: tuple[int, int]) -> np.ndarray:
    """Order unordered marker centres as the grid ``i = iy * nx + ix`` (module docstring).

    Args:
        points: marker centres, shape ``(nx * ny, 2)``, px.
        expected_grid: ``(nx, ny)`` markers along image u (columns) and v (rows).

    Returns:
        the same points reordered, shape ``(nx * ny, 2)``.

    Raises:
        CalibrationError: wrong count, or the points do not form an ``nx`` x ``ny`` lattice.
    """
    nx, ny = (int(v) for v in expected_grid)
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if pts.shape[0] != nx * ny:
        raise CalibrationError(f"detect_markers: found {pts.shape[0]} markers, expected {nx} x {ny} = {nx * ny}")
    if nx * ny == 1:
        return pts.copy()
    if min(nx, ny) == 1:  # a single row or column: sort along the principal axis
        centred = pts - pts.mean(axis=0)
        axis = np.linalg.svd(centred, full_matrices=False)[2][0]
        towards = 0 if nx > 1 else 1  # a row runs towards +u, a column towards +v
        axis = -axis if axis[towards] < 0 else axis
        return pts[np.argsort(centred @ axis)]
    a, b = _lattice_basis(pts)
    tree = cKDTree(pts)
    _, neighbours = tree.query(pts, k=min(9, pts.shape[0]))
    coords = np.full((pts.shape[0], 2), np.iinfo(np.int64).min, dtype=np.int64)
    local = np.zeros((pts.shape[0], 2, 2))
    start = int(np.argmin(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))
    coords[start] = (0, 0)
    local[start] = (a, b)
    queue = deque([start])
    assigned = 1
    while queue:
        p = queue.popleft()
        basis = local[p].T  # columns a_p, b_p
        for q in neighbours[p, 1:]:
            step = pts[q] - pts[p]
            alpha_beta = np.linalg.solve(basis, step)
            rounded = np.rint(alpha_beta)
            if np.max(np.abs(alpha_beta - rounded)) > STEP_TOLERANCE or np.abs(rounded).sum() != 1:
                continue
            target = coords[p] + rounded.astype(np.int64)
            if coords[q, 0] == np.iinfo(np.int64).min:
                coords[q] = target
                la, lb = local[p]
                if rounded[0] != 0:
                    la = 0.5 * (la + rounded[0] * step)
                else:
                    lb = 0.5 * (lb + rounded[1] * step)
                local[q] = (la, lb)
                queue.append(q)
                assigned += 1
            elif np.any(coords[q] != target):
                raise CalibrationError(
                    f"detect_markers: marker at ({pts[q, 0]:.1f}, {pts[q, 1]:.1f}) px is reached at lattice "
                    f"positions {coords[q].tolist()} and {target.tolist()}: the markers do not form a grid"
                )
    if assigned != pts.shape[0]:
        raise CalibrationError(
            f"detect_markers: only {assigned} of {pts.shape[0]} markers connect to the grid by unit steps"
        )
    coords -= coords.min(axis=0)
    extent = tuple(int(v) + 1 for v in coords.max(axis=0))
    if extent != (nx, ny):
        raise CalibrationError(
            f"detect_markers: the markers form a {extent[0]} x {extent[1]} (columns x rows) lattice, "
            f"expected {nx} x {ny}"
        )
    index = coords[:, 1] * nx + coords[:, 0]
    if np.unique(index).size != index.size:
        raise CalibrationError("detect_markers: two markers share one grid position")
    ordered = np.empty_like(pts)
    ordered[index] = pts
    return ordered


def default_spacing(image_shape: tuple[int, ...], expected_grid: tuple[int, int]) -> float:
    """Marker spacing guess for a grid that fills the image: ``min(width / nx, height / ny)``, px."""
    nx, ny = (int(v) for v in expected_grid)
    return min(image_shape[1] / nx, image_shape[0] / ny)


def detect_markers(
    image: np.ndarray, expected_grid: tuple[int, int], spacing_px: float | None = None
) -> np.ndarray:
    """Find the markers of a tactile image and return them in grid order.

    Args:
        image: mono8/mono16, BGR or BGRA image.
        expected_grid: ``(nx, ny)`` markers along image u (columns) and v (rows).
        spacing_px: approximate marker spacing, px; default :func:`default_spacing`.

    Returns:
        marker centres ``(u, v)``, shape ``(nx * ny, 2)``, px, ordered ``i = iy * nx + ix``.

    Raises:
        CalibrationError: not exactly ``nx * ny`` markers found (the count is named), or they do not
            form the expected grid.
    """
    nx, ny = (int(v) for v in expected_grid)
    if nx < 1 or ny < 1:
        raise CalibrationError(f"detect_markers: expected_grid must be positive, got {expected_grid!r}")
    gray = to_gray(image)
    spacing = float(spacing_px) if spacing_px is not None else default_spacing(gray.shape, (nx, ny))
    blobs = find_marker_blobs(gray, spacing)
    return order_marker_grid(blobs.uv, (nx, ny))


def marker_spacing(uv: np.ndarray, image_shape: tuple[int, ...] | None, expected_grid: tuple[int, int]) -> float:
    """Marker spacing, px: the median nearest-neighbour distance of ``uv (k, 2)``; for a single marker,
    :func:`default_spacing` of ``image_shape``."""
    if uv.shape[0] > 1:
        dist, _ = cKDTree(uv).query(uv, k=2)
        return float(np.median(dist[:, 1]))
    return default_spacing(image_shape, expected_grid)


MEASURED = 0
"""Marker status: its blob was found whole in this frame (weight 1)."""

CLIPPED = 1
"""Marker status: its blob is cut by the image border; the centre is estimated from the visible part
(weight = the visible fraction of the blob)."""

INTERPOLATED = 2
"""Marker status: not seen in this frame (out of the image, occluded, merged, or its detection
disagrees with its lattice neighbours); the position is interpolated from the lattice neighbours'
displacements (weight 0)."""

LOST = 3
"""Marker status: not seen and too few markers seen to interpolate it; position NaN (weight 0)."""


class MarkerFrame(NamedTuple):
    """Every marker of one frame in the fixed order ``i = iy * nx + ix``.

    Attributes:
        uv: positions ``(k, 2)`` px: measured, or interpolated where ``status == INTERPOLATED``;
            NaN only where ``status == LOST``.
        status: ``(k,)`` int8, :data:`MEASURED`, :data:`CLIPPED`, :data:`INTERPOLATED` or :data:`LOST`.
        weight: ``(k,)`` in ``[0, 1]``, a per-marker factor on the inverse variance of the pixel
            residual: 1 measured, the visible fraction when clipped, 0 interpolated or lost.
    """

    uv: np.ndarray
    status: np.ndarray
    weight: np.ndarray

    @property
    def measured(self) -> np.ndarray:
        """``uv`` with NaN rows where the marker was not seen (interpolated or lost), ``(k, 2)`` px."""
        return np.where((self.status <= CLIPPED)[:, None], self.uv, np.nan)


class MarkerTracks(NamedTuple):
    """Every marker of every frame of a stream (:func:`track_markers`); fields as
    :class:`MarkerFrame` with a leading frame axis: ``uv (F, k, 2)`` px, ``status (F, k)`` int8,
    ``weight (F, k)``."""

    uv: np.ndarray
    status: np.ndarray
    weight: np.ndarray

    @property
    def measured(self) -> np.ndarray:
        """``uv`` with NaN where the marker was not seen (interpolated or lost), ``(F, k, 2)`` px."""
        return np.where((self.status <= CLIPPED)[..., None], self.uv, np.nan)


def lattice_neighbours(expected_grid: tuple[int, int], reach: int) -> list[np.ndarray]:
    """For each marker ``i = iy * nx + ix``, the indices of the other markers within ``reach``
    lattice steps (Chebyshev distance: ``reach = 1`` is the 8-neighbourhood)."""
    nx, ny = (int(v) for v in expected_grid)
    out = []
    for iy in range(ny):
        for ix in range(nx):
            ys = range(max(iy - reach, 0), min(iy + reach + 1, ny))
            xs = range(max(ix - reach, 0), min(ix + reach + 1, nx))
            out.append(np.array([y * nx + x for y in ys for x in xs if (y, x) != (iy, ix)], dtype=np.int64))
    return out


class MarkerTracker:
    """Frame-to-frame marker tracking with a fixed marker order, constrained by the marker lattice.

    The first frame is read with :func:`detect_markers` (or the order is given as ``initial_uv``).
    Each later frame's blobs, those cut by the image border included (:func:`find_marker_blobs` with
    ``keep_clipped``), are matched to the markers in three steps:

    1. one-to-one minimum total distance assignment (Hungarian) from the markers' previous positions,
       within a gate of ``max_displacement_px``;
    2. a lattice check: the gel's displacement field is smooth at the scale of the marker pitch, so a
       marker's motion since the previous frame must agree with the median motion of its matched
       lattice neighbours (8-neighbourhood) to within ``marker_radius_px``. A wrong blob (a neighbour's,
       or a spurious dark spot) lies at least a marker diameter from the right one, so a match that
       fails the check is undone;
    3. every marker still unmatched is predicted from its lattice neighbours (below) and matched to
       the remaining blobs within ``marker_radius_px`` of that prediction.

    A marker found in none of these steps (out of the image, occluded, merged with another under
    contact) gets the position interpolated from its lattice neighbours: its displacement from the
    reference frame is the least-squares affine function of reference position fitted to the
    displacements of the seen markers within two lattice steps (their mean displacement when they
    are too few or collinear), and it is flagged :data:`INTERPOLATED` with weight 0. It is searched
    for again from there in the next frames.

    Args:
        expected_grid: ``(nx, ny)``.
        max_displacement_px: largest accepted motion of a marker between two frames, px (> 0).
        initial_uv: optional ordered marker positions of the reference frame, shape ``(nx * ny, 2)``.
        spacing_px: marker spacing for blob detection; default from the first frame.
        marker_radius_px: tolerance of the lattice check, px; default the radius of the median blob
            of the first frame (``sqrt(area / pi)``) when read from an image, else ``spacing / 6``.
        initial_size: optional :func:`relative_area` of each marker's blob in the reference frame,
            ``(nx * ny,)`` (for the centres of blobs cut by the border, :func:`clipped_centre`);
            default from the first image, else 1. Updated whenever a marker is seen whole.

    Raises:
        CalibrationError: invalid gate or radius, or initial positions of the wrong shape.
    """

    def __init__(
        self,
        expected_grid: tuple[int, int],
        max_displacement_px: float,
        initial_uv: np.ndarray | None = None,
        spacing_px: float | None = None,
        marker_radius_px: float | None = None,
        initial_size: np.ndarray | None = None,
    ) -> None:
        self.expected_grid = (int(expected_grid[0]), int(expected_grid[1]))
        if not max_displacement_px > 0:
            raise CalibrationError(f"MarkerTracker: max_displacement_px must be > 0, got {max_displacement_px!r}")
        if marker_radius_px is not None and not marker_radius_px > 0:
            raise CalibrationError(f"MarkerTracker: marker_radius_px must be > 0, got {marker_radius_px!r}")
        self.max_displacement_px = float(max_displacement_px)
        self.spacing_px = spacing_px
        self.marker_radius_px = None if marker_radius_px is None else float(marker_radius_px)
        self.reference: np.ndarray | None = None
        self.last_known: np.ndarray | None = None
        self.size: np.ndarray | None = None
        if initial_size is not None:
            self.size = np.asarray(initial_size, dtype=float).reshape(-1).copy()
            if self.size.shape != (self.marker_count,) or not np.all(self.size > 0):
                raise CalibrationError(f"MarkerTracker: initial_size must be positive with shape "
                                       f"({self.marker_count},), got {self.size.shape}")
        near = lattice_neighbours(self.expected_grid, 1)
        self._near_padded = np.full((len(near), 8), len(near), dtype=np.int64)  # index k: no neighbour
        for i, n in enumerate(near):
            self._near_padded[i, : n.size] = n
        self._around = lattice_neighbours(self.expected_grid, 2)
        if initial_uv is not None:
            uv = np.asarray(initial_uv, dtype=float)
            k = self.expected_grid[0] * self.expected_grid[1]
            if uv.shape != (k, 2) or not np.all(np.isfinite(uv)):
                raise CalibrationError(f"MarkerTracker: initial_uv must be finite with shape ({k}, 2), got {uv.shape}")
            self._start(uv)

    @property
    def marker_count(self) -> int:
        """Number of tracked markers ``nx * ny``."""
        return self.expected_grid[0] * self.expected_grid[1]

    def _start(self, uv: np.ndarray, image_shape: tuple[int, ...] | None = None) -> None:
        self.reference = uv.copy()
        self.last_known = uv.copy()
        if self.size is None:
            self.size = np.ones(uv.shape[0])
        if self.spacing_px is None:
            if uv.shape[0] <= 1 and image_shape is None:
                raise CalibrationError("MarkerTracker: a single marker given by initial_uv needs spacing_px")
            self.spacing_px = marker_spacing(uv, image_shape, self.expected_grid)
        if self.marker_radius_px is None:
            self.marker_radius_px = float(self.spacing_px) / 6.0

    def update(self, image: np.ndarray) -> MarkerFrame:
        """Track the markers in the next image (see the class docstring).

        Returns:
            every marker's position, status and weight in the fixed order.

        Raises:
            CalibrationError: on the first frame, when :func:`detect_markers` fails.
        """
        if self.last_known is None:
            gray = to_gray(image)
            nx, ny = self.expected_grid
            spacing = float(self.spacing_px) if self.spacing_px is not None else default_spacing(gray.shape, (nx, ny))
            blobs = find_marker_blobs(gray, spacing)
            uv = order_marker_grid(blobs.uv, self.expected_grid)
            if self.marker_radius_px is None and blobs.area.size:
                self.marker_radius_px = float(np.sqrt(np.median(blobs.area) / np.pi))
            self.size = relative_area(blobs)[cKDTree(blobs.uv).query(uv)[1]]
            self._start(uv, gray.shape)
            k = self.marker_count
            return MarkerFrame(uv.copy(), np.full(k, MEASURED, np.int8), np.ones(k))
        blobs = find_marker_blobs(image, float(self.spacing_px), keep_clipped=True,
                                  known_size=(self.last_known, self.size))
        frame = self.update_points(blobs.uv, blobs.visible)
        whole = frame.status == MEASURED
        if np.any(whole):  # each marker's relative size when last seen whole, for its cut blobs later
            index = cKDTree(blobs.uv).query(frame.uv[whole])[1]
            self.size[whole] = relative_area(blobs)[index]
        return frame

    def update_points(self, detections: np.ndarray, visible: np.ndarray | None = None) -> MarkerFrame:
        """Match unordered detections ``(m, 2)`` px to the tracked markers (see the class docstring).

        Args:
            detections: blob centres, ``(m, 2)`` px.
            visible: the blobs' visible fractions ``(m,)`` (:class:`MarkerBlobs`); default all 1.

        Returns:
            every marker's position, status and weight in the fixed order.

        Raises:
            CalibrationError: called before the reference order is known, or ``visible`` of the
                wrong shape.
        """
        if self.last_known is None or self.reference is None:
            raise CalibrationError("MarkerTracker: no reference frame yet (call update(image) or pass initial_uv)")
        det = np.asarray(detections, dtype=float).reshape(-1, 2)
        vis = np.ones(det.shape[0]) if visible is None else np.asarray(visible, dtype=float).reshape(-1)
        if vis.shape != (det.shape[0],):
            raise CalibrationError(f"MarkerTracker: visible must have shape ({det.shape[0]},), got {vis.shape}")
        k = self.marker_count
        radius = float(self.marker_radius_px)
        match = np.full(k, -1, dtype=np.int64)  # marker -> detection
        # 1. nearest blobs from the previous positions
        rows, cols = self._match(self.last_known, det, self.max_displacement_px)
        match[rows] = cols
        # 2. lattice check against the neighbours' motion
        step = np.full((k, 2), np.nan)
        step[rows] = det[cols] - self.last_known[rows]
        near_step = np.concatenate([step, np.full((1, 2), np.nan)])[self._near_padded]  # (k, 8, 2)
        has_near = np.any(np.isfinite(near_step[:, :, 0]), axis=1)
        near_median = np.full((k, 2), np.nan)
        near_median[has_near] = np.nanmedian(near_step[has_near], axis=1)
        disagrees = has_near & (np.linalg.norm(step - near_median, axis=1) > radius)  # NaN compares False
        match[disagrees] = -1
        # 3. markers left over: predicted from their lattice neighbours, matched near the prediction
        seen = match >= 0
        left = np.nonzero(~seen)[0]
        predicted = self._interpolate(left, det[match[seen]], seen) if left.size else np.zeros((0, 2))
        free = np.setdiff1d(np.arange(det.shape[0]), match[seen])
        if left.size and free.size and np.all(np.isfinite(predicted)):
            r2, c2 = self._match(predicted, det[free], radius)
            match[left[r2]] = free[c2]
        seen = match >= 0
        uv = np.full((k, 2), np.nan)
        uv[seen] = det[match[seen]]
        status = np.full(k, LOST, dtype=np.int8)
        weight = np.zeros(k)
        status[seen] = np.where(vis[match[seen]] < 1.0, CLIPPED, MEASURED)
        weight[seen] = vis[match[seen]]
        left = np.nonzero(~seen)[0]
        if left.size and seen.any():
            uv[left] = self._interpolate(left, uv[seen], seen)
            status[left] = INTERPOLATED
        known = np.all(np.isfinite(uv), axis=1)
        self.last_known[known] = uv[known]
        return MarkerFrame(uv, status, weight)

    def _interpolate(self, markers: np.ndarray, seen_uv: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """Positions ``(len(markers), 2)`` px of unseen markers from the displacements (from the
        reference frame) of the seen ones ``seen_uv`` (``seen`` is the ``(k,)`` mask they come from):
        a local affine fit over the seen markers within two lattice steps, their mean when fewer
        than three or collinear, the median displacement of all seen markers when none is near."""
        ref = self.reference
        disp = np.full((self.marker_count, 2), np.nan)
        disp[seen] = seen_uv - ref[seen]
        everywhere = np.median(disp[seen], axis=0) if seen.any() else np.full(2, np.nan)
        out = np.empty((markers.size, 2))
        for n, i in enumerate(markers):
            near = self._around[i][seen[self._around[i]]]
            if near.size == 0:
                out[n] = ref[i] + everywhere
                continue
            if near.size >= 3:
                design = np.column_stack([np.ones(near.size), ref[near] - ref[i]])
                coef, _, rank, _ = np.linalg.lstsq(design, disp[near], rcond=None)
                if rank == 3:
                    out[n] = ref[i] + coef[0]
                    continue
            out[n] = ref[i] + disp[near].mean(axis=0)
        return out

    @staticmethod
    def _match(known: np.ndarray, det: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
        """One-to-one minimum-distance assignment within ``gate``; returns (marker, detection) indices."""
        if known.shape[0] == 0 or det.shape[0] == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        dist = np.linalg.norm(known[:, None, :] - det[None, :, :], axis=2)
        gated = np.where(dist <= gate, dist, 1e6 * (1.0 + gate))
        rows, cols = linear_sum_assignment(gated)
        good = dist[rows, cols] <= gate
        return rows[good], cols[good]


def track_markers(images: np.ndarray, expected_grid: tuple[int, int], gate_fraction: float = 0.4) -> MarkerTracks:
    """Every marker of every frame of an image stream, in the fixed grid order, with its status.

    The first frame is read with :func:`detect_markers` (every marker must be whole there); the
    others are followed with a :class:`MarkerTracker` whose gate is ``gate_fraction`` times the
    median marker spacing of the first frame (a marker moving farther than that between two frames
    cannot be told from its neighbour) and whose lattice tolerance is the radius of the first
    frame's median marker blob.

    Args:
        images: frames ``(F, h, w)`` (or ``(F, h, w, 3|4)``), uint8/uint16.
        expected_grid: ``(nx, ny)`` markers along image u (columns) and v (rows).
        gate_fraction: tracking gate as a fraction of the marker spacing, in (0, 0.5].

    Returns:
        ``uv (F, nx * ny, 2)`` px, ``i = iy * nx + ix``, with each marker's status and weight per
        frame (:class:`MarkerTracks`).

    Raises:
        CalibrationError: no frames, a bad ``gate_fraction``, or the first frame does not show the
            expected grid (the count found is named).
    """
    frames = np.asarray(images)
    if frames.ndim < 3 or frames.shape[0] == 0:
        raise CalibrationError(f"track_marker_stream: need frames (F, h, w), got shape {frames.shape}")
    if not 0.0 < gate_fraction <= 0.5:
        raise CalibrationError(f"track_marker_stream: gate_fraction must be in (0, 0.5], got {gate_fraction!r}")
    nx, ny = (int(v) for v in expected_grid)
    first = find_marker_blobs(to_gray(frames[0]), default_spacing(frames[0].shape, (nx, ny)))
    uv0 = order_marker_grid(first.uv, (nx, ny))
    spacing = marker_spacing(uv0, frames[0].shape, expected_grid)
    tracker = MarkerTracker(expected_grid, gate_fraction * spacing, initial_uv=uv0, spacing_px=spacing,
                            marker_radius_px=float(np.sqrt(np.median(first.area) / np.pi)),
                            initial_size=relative_area(first)[cKDTree(first.uv).query(uv0)[1]])
    k = uv0.shape[0]
    uv = np.empty((frames.shape[0], k, 2))
    status = np.empty((frames.shape[0], k), dtype=np.int8)
    weight = np.empty((frames.shape[0], k))
    uv[0], status[0], weight[0] = uv0, MEASURED, 1.0
    for f in range(1, frames.shape[0]):
        uv[f], status[f], weight[f] = tracker.update(frames[f])
    return MarkerTracks(uv, status, weight)


def track_marker_stream(images: np.ndarray, expected_grid: tuple[int, int],
                        gate_fraction: float = 0.4) -> np.ndarray:
    """The measured marker pixels of :func:`track_markers`: ``(F, nx * ny, 2)`` px,
    ``i = iy * nx + ix``, NaN rows where a marker was not seen in a frame (interpolated or lost).

    Raises:
        CalibrationError: as :func:`track_markers`.
    """
    return track_markers(images, expected_grid, gate_fraction).measured
