"""Signature tests on the tracked sheet: bending plasticity and adhesion.

* **Bending plasticity** (SYSID.md: "a fold that remains after release ... persists after
  unloading, localised on the fold"): once the gel has let go of the sheet (the recorded gel's
  median marker back at rest, :func:`median_marker_displacement`), an elastic sheet returns to the shape the
  replay predicts for it; a plastic one keeps a set. Over the final free window the recorded
  sheet is compared with the replay (statistic: whitened SSE of the time-averaged difference, about
  chi-square(3p) without an effect) and with its own initial shape; the effect size is the smaller
  of the two largest point displacements (a set both unexplained by the replay and different from
  where the sheet started), and 0 where the replay itself leaves the sheet away from its start (a
  buckle held by friction: the difference is then the model's gap in that shape). A set is a rest
  shape: where the recorded sheet still moves over the final window (an elastic card flapping after
  the lift let it go), no set is read (:func:`final_motion`), unless the fold the gel gave it
  remains while it moves (:func:`remaining_fold`: the grid line that bent most under the gel's last
  contact keeps that bend's sign, by at least a resolvable set, over every released row after the
  contact, or any grid line keeps one bend in every 0.05 s block since the gel last touched the sheet,
  :func:`kept_bend`; an elastic card's lines bend by its motion only); nor where the sheet is back at its
  initial shape when the recording ends (:func:`_returned_by_the_end`).
* **Adhesion** (SYSID.md: "tensile force and the sheet following the gel on a lift"): where the
  replay has released the sheet but the recorded gel is still loaded (markers displaced), and the
  recorded sheet rises above the replay's, the sheet is being carried by the gel. The statistic is
  the whitened excess energy of the sheet residual over those rows; the effect size the largest
  height the recorded sheet has above the replay there, m.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2 as chi2_law

from sysid.diagnose.signatures.base import (Recording, SignatureResult, dilate, marker_displacement,
                                            not_applicable, predicted_contact, whitened_marker_offsets)
from sysid.diagnose.signatures.sensor import FREE_MARGIN_S, REST_DISPLACEMENT
from sysid.runs import segments

FINAL_WINDOW_S = 0.2
"""Length of the final free window of the permanent-set test, s."""

REPLAY_SET_FRACTION = 0.5
"""The permanent-set test reads a set only where the replay returns the sheet closer to its start
than this fraction of the recording's difference from the replay."""

RESOLVABLE_SET_SIGMAS = 10.0
"""A sheet height the tracking resolves, in sheet-point sigmas: a permanent set or a carried height
of at least this many (the size thresholds of the plasticity and adhesion decisions,
:func:`sysid.diagnose.signatures.null.default_thresholds`, and the stiction test's sheet-yield check)."""

MIN_CARRIED_S = 0.1
"""Shortest run of carried-sheet rows that counts, s (a tactile delay leaves shorter ones)."""

MIN_FOLLOW_CORRELATION = 0.8
"""Correlation of the sheet's highest point with the effector height over a carried run."""

KEPT_BLOCK_S = FINAL_WINDOW_S / 4.0
"""Blocks over which a kept bend must hold its sign (:func:`kept_bend`), s: a quarter of the final
window, so that a final window holds four."""

MEDIAN_MARKER_AT_REST = REST_DISPLACEMENT * float(np.sqrt(chi2_law.median(3) / 3.0))
"""Whitened displacement of the median marker below which the recorded gel counts as at rest:
:data:`REST_DISPLACEMENT` times what noise alone gives the median marker (a marker's whitened RMS
over its three axes is ``sqrt(chi2(3) / 3)``, median 0.888)."""


def median_marker_displacement(rec: Recording) -> np.ndarray | None:
    """Whitened displacement of the median marker from its rest position, per sample, on
    ``rec.t["markers_xyz"]`` (about 0.89 at rest: noise only).

    Each marker's displacement is its whitened RMS over the three axes from its rest position
    (:func:`~sysid.diagnose.signatures.base.whitened_marker_offsets`); the median over the markers is
    taken per sample. A load on the gel
    displaces a patch of markers (the elastic field spreads over the gel's thickness, more than the
    marker spacing); a few markers that stay displaced alone while the rest of the grid is at rest
    (a marker torn from its place, or a gel edge that does not spring back after a peel) move the
    grid's RMS but not its median marker.

    Returns:
        array ``(n,)``, or None without recorded markers.
    """
    offsets = whitened_marker_offsets(rec)
    return None if offsets is None else np.median(np.sqrt(np.mean(offsets ** 2, axis=2)), axis=1)


def _released_rows(rec: Recording, channel: str) -> np.ndarray | None:
    """Samples of ``channel`` where the recorded gel has let go of everything: its median marker at
    rest (:func:`median_marker_displacement` at most :data:`MEDIAN_MARKER_AT_REST`) at least
    :data:`FREE_MARGIN_S` from any loaded marker sample. The recording itself says whether the gel
    holds the sheet; the replay's contact is used only without recorded markers.

    Returns:
        boolean mask ``(n,)`` on ``rec.t[channel]``, or None when neither markers nor a replay tell.
    """
    t = rec.t[channel]
    disp = median_marker_displacement(rec)
    if disp is None:
        contact = predicted_contact(rec, channel)
        return None if contact is None else ~dilate(contact, t, FREE_MARGIN_S)
    moved = np.interp(t, rec.t["markers_xyz"], (disp > MEDIAN_MARKER_AT_REST).astype(float)) > 0.0
    return ~dilate(moved, t, FREE_MARGIN_S)


def final_motion(rec: Recording, final: np.ndarray) -> float:
    """How far the recorded sheet moves over the final window, m: the largest point displacement
    between the mean shapes of the window's first and second halves.

    A permanent set is the shape the sheet rests in once the gel has let it go (plasticity is rate
    independent: a set does not move); a sheet that still moves by more than the tracking resolves
    (:func:`resolvable_set`) holds no rest shape there (an elastic card flapping after the lift let
    it go), and :func:`plasticity_test` reads no set from it.

    Args:
        rec: the recording (sheet points).
        final: boolean mask ``(n,)`` of the final window on ``rec.t["sheet_points"]``.
    """
    x = np.asarray(rec.data["sheet_points"], dtype=float)[final]
    h = len(x) // 2
    return float(np.max(np.linalg.norm(x[h:].mean(axis=0) - x[:h].mean(axis=0), axis=1)))


def sheet_grid(x0: np.ndarray) -> tuple[int, int] | None:
    """``(nx, ny)`` of sheet points laid out as a row-major grid (point ``iy * nx + ix``,
    :func:`sim_core.mesh.sheet.grid_sheet`), read from their initial shape: ``nx`` points share point 0's
    y (within half the spacing of points 0 and 1) before the next row starts.

    Args:
        x0: initial sheet points ``(p, 3)`` m.

    Returns:
        ``(nx, ny)`` with ``nx, ny >= 3``, or None when the points are not such a grid.
    """
    p = len(x0)
    if p < 9:
        return None
    spacing = float(np.linalg.norm(x0[1] - x0[0]))
    if not spacing > 0.0:
        return None
    off_row = np.nonzero(np.abs(x0[:, 1] - x0[0, 1]) > 0.5 * spacing)[0]
    nx = int(off_row[0]) if off_row.size else p
    if nx < 3 or p % nx or p // nx < 3:
        return None
    g = x0.reshape(p // nx, nx, 3)
    if np.ptp(g[:, :, 1], axis=1).max() > 0.5 * spacing or np.ptp(g[:, :, 0], axis=0).max() > 0.5 * spacing:
        return None
    return nx, p // nx


def line_curvatures(x: np.ndarray, grid: tuple[int, int], spacing: float) -> np.ndarray:
    """Mean height curvature of the sheet's grid lines, 1/m: the second difference of the points'
    heights along each grid direction over ``spacing**2`` (the z component of a material line's
    curvature vector), averaged over the parallel lines; interior lines along x first (``nx - 2``),
    then along y (``ny - 2``). Linear in the data: white point noise ``sigma_z`` gives each value a
    standard error ``sqrt(6) sigma_z / (spacing**2 sqrt(lines averaged))``.

    Args:
        x: sheet points ``(n, p, 3)`` m.
        grid: ``(nx, ny)`` (:func:`sheet_grid`).
        spacing: grid spacing, m.

    Returns:
        ``(n, nx - 2 + ny - 2)``.
    """
    nx, ny = grid
    z = np.asarray(x, dtype=float)[:, :, 2].reshape(len(x), ny, nx)
    along_x = (z[:, :, 2:] - 2.0 * z[:, :, 1:-1] + z[:, :, :-2]).mean(axis=1)
    along_y = (z[:, 2:, :] - 2.0 * z[:, 1:-1, :] + z[:, :-2, :]).mean(axis=2)
    return np.concatenate([along_x, along_y], axis=1) / spacing ** 2


def line_resolvable_curvatures(rec: Recording, grid: tuple[int, int], spacing: float) -> np.ndarray:
    """Per grid line (the order of :func:`line_curvatures`), the curvature whose turning angle over one
    spacing tilts the shorter side of the sheet beyond the line by a resolvable set
    (:func:`resolvable_set`), 1/m: at least 6.7 standard errors of a final window's mean
    (:func:`line_curvatures`) on a 21 x 13 grid of 5 mm sampled 21 times, the most for the middle line.

    Returns:
        ``(nx - 2 + ny - 2,)``.
    """
    nx, ny = grid
    index = np.r_[np.arange(1, nx - 1), np.arange(1, ny - 1)]
    count = np.r_[np.full(nx - 2, nx), np.full(ny - 2, ny)]
    return resolvable_set(rec) / (spacing ** 2 * np.minimum(index, count - 1 - index))


def kept_bend(t: np.ndarray, k: np.ndarray, released: np.ndarray, resolvable: np.ndarray) -> np.ndarray | None:
    """Per grid line, how far it keeps one bend over every :data:`KEPT_BLOCK_S` block of ``released``:
    the smallest block mean of its curvature, signed as its mean over all those rows, over its
    resolvable curvature. A plastic hinge keeps its rest angle whatever the sheet's motion (at least 1
    in every block); an elastic sheet freed from the gel bends only by its motion, through flat and
    beyond (a free or hinged card carries no static bend a grid spacing resolves: its own weight bends
    a 100 mm card of the reference's stiffness about 1 1/m at most), so some block of every line falls
    below 1. A block holds about five sheet samples: its mean's standard error is below a third of the
    middle line's resolvable curvature, and every block must pass.

    Args:
        t: sample times ``(n,)`` s.
        k: line curvatures ``(n, lines)`` 1/m less their initial values (:func:`line_curvatures`).
        released: boolean mask ``(n,)`` of rows where the gel has let go of the sheet.
        resolvable: ``(lines,)`` (:func:`line_resolvable_curvatures`).

    Returns:
        ``(lines,)``, or None when the released rows span fewer than ``FINAL_WINDOW_S / KEPT_BLOCK_S``
        blocks of at least two samples.
    """
    tr, kr = t[released], k[released]
    block = np.floor((tr - tr[0]) / KEPT_BLOCK_S).astype(int)
    ids, counts = np.unique(block, return_counts=True)
    ids = ids[counts >= 2]
    if len(ids) < round(FINAL_WINDOW_S / KEPT_BLOCK_S):
        return None
    sign = np.sign(kr.mean(axis=0))
    means = np.stack([kr[block == i].mean(axis=0) for i in ids])
    return (sign * means).min(axis=0) / resolvable


def remaining_fold(rec: Recording, hold: np.ndarray, released: np.ndarray, final: np.ndarray,
                   initial: np.ndarray, untouched: np.ndarray) -> dict | None:
    """Whether a fold the gel gave the sheet remains after the gel let it go, while the sheet moves.

    The fold line is the grid line whose mean height curvature over the gel's contact (``hold``),
    less its initial one, is largest in size (:func:`line_curvatures`). A plastic hinge keeps a rest
    angle of that sign, so the line keeps its bend whatever the card's motion; an elastic card's lines
    bend by its motion only, through flat and beyond. The fold remains when that line's mean
    curvature, signed as under the gel, over every ``released`` row and over the ``final`` window is
    at least its resolvable curvature (:func:`line_resolvable_curvatures`), or when any grid line keeps
    one bend of at least its resolvable curvature in every block of the ``untouched`` rows
    (:func:`kept_bend`): a kink the card kept where it yielded, which need not be the line it bent most
    under the gel (a tent's kink settles beside the hold's fold line or across it) nor where it was
    before a later touch of the gel (a strike of the lifted pad bends a yielded card again).

    Args:
        rec: the recording (sheet points).
        hold, released, final, initial, untouched: boolean masks ``(n,)`` on ``rec.t["sheet_points"]``:
            the gel's last contact, the released rows after it, the final window, the free rows before
            the first contact, the released run that holds the final window (no touch of the gel since).

    Returns:
        ``{"remains", "line", "along", "hold_curvature", "released_curvature", "final_curvature",
        "resolvable_curvature", "kept_line", "kept_along", "kept_curvature", "kept_ratio"}`` (curvatures
        1/m, signed; the kept line is the one with the largest :func:`kept_bend`, None where the
        released rows are too short), or None when the points are no grid or a mask is empty.
    """
    x = np.asarray(rec.data["sheet_points"], dtype=float)
    if not (hold.any() and released.any() and final.any() and initial.any()):
        return None
    x0 = x[initial].mean(axis=0)
    grid = sheet_grid(x0)
    if grid is None:
        return None
    nx, ny = grid
    spacing = float(np.linalg.norm(x0[1] - x0[0]))
    k = line_curvatures(x, grid, spacing)
    k = k - k[initial].mean(axis=0)
    resolvable = line_resolvable_curvatures(rec, grid, spacing)

    def named_line(j: int) -> tuple[int, str]:
        return (j + 1, "x") if j < nx - 2 else (j - (nx - 2) + 1, "y")

    k_hold = k[hold].mean(axis=0)
    j = int(np.argmax(np.abs(k_hold)))
    sign = float(np.sign(k_hold[j]))
    kept, kept_final = sign * float(k[released, j].mean()), sign * float(k[final, j].mean())
    held = bool(min(kept, kept_final) >= resolvable[j])
    ratio = kept_bend(rec.t["sheet_points"], k, untouched, resolvable)
    jk = None if ratio is None else int(np.argmax(ratio))
    index, along = named_line(j)
    kept_line, kept_along = (None, None) if jk is None else named_line(jk)
    return {"remains": held or bool(jk is not None and ratio[jk] >= 1.0), "line": index, "along": along,
            "hold_curvature": float(k_hold[j]), "released_curvature": sign * kept,
            "final_curvature": sign * kept_final, "resolvable_curvature": float(resolvable[j]),
            "kept_line": kept_line, "kept_along": kept_along,
            "kept_curvature": None if jk is None else float(k[untouched, jk].mean()),
            "kept_ratio": None if jk is None else float(ratio[jk])}


def _fold_words(fold: dict) -> str:
    """The figures of a :func:`remaining_fold` result, in words."""
    words = (f"the fold the gel gave it, {fold['along']} line {fold['line']}: {fold['hold_curvature']:.3g} 1/m under "
             f"the gel, {fold['released_curvature']:.3g} 1/m after the release, {fold['resolvable_curvature']:.3g} "
             "1/m resolvable")
    if fold["kept_line"] is None:
        return words + "; the run since the gel last touched it is too short to tell a kept bend"
    return words + (f"; the line that keeps one bend best, {fold['kept_along']} line {fold['kept_line']}: "
                    f"{fold['kept_curvature']:.3g} 1/m since the gel last touched it, its smallest block mean "
                    f"{fold['kept_ratio']:.2g} times its resolvable curvature")


def _returned_by_the_end(rec: Recording, final: np.ndarray, initial: np.ndarray,
                         released_runs: list[tuple[int, int]]) -> str:
    """Why a set in the final window did not remain, or "" when it may have: a permanent set is still
    there when the recording ends. Where a later released run reaches the recording's end (too short
    to be the final window: a touch of the gel came between, at least three samples), the sheet's mean
    shape there is compared with its initial shape; back within :func:`resolvable_set` of it while the
    final window is not, the fold sprang back (an elastic sheet caught in mid-motion by the window).

    Args:
        rec: the recording (sheet points).
        final: boolean mask ``(n,)`` of the final window.
        initial: boolean mask ``(n,)`` of the free rows before the first contact.
        released_runs: the released runs after the gel's main contact, ``[(i0, i1), ...]``.
    """
    t = rec.t["sheet_points"]
    tail = [(i0, i1) for i0, i1 in released_runs if i1 == len(t) and i1 - i0 >= 3 and not final[i0:i1].any()]
    if not tail or initial.sum() < 3:
        return ""
    x = np.asarray(rec.data["sheet_points"], dtype=float)
    x0 = x[initial].mean(axis=0)
    i0, i1 = tail[0]
    held_set = float(np.max(np.linalg.norm(x[final].mean(axis=0) - x0, axis=1)))
    end_set = float(np.max(np.linalg.norm(x[i0:i1].mean(axis=0) - x0, axis=1)))
    floor = resolvable_set(rec)
    if held_set < floor or end_set >= floor:
        return ""
    return (f"the sheet stands {1e3 * held_set:.2g} mm from its initial shape in the final window but is back "
            f"within {1e3 * end_set:.2g} mm of it at the recording's end ({t[i0]:.2f}-{t[i1 - 1]:.2f} s): "
            "the fold did not remain")


def _resting_on_the_gel(rec: Recording, final: np.ndarray, t_first_contact: float) -> str:
    """Why a sheet the gel never lets go of still holds a rest shape, or "": over the recording's last
    :data:`FINAL_WINDOW_S` (``final``) the sheet is at rest (:func:`final_motion` within
    :func:`resolvable_set`) and the recorded wrench is at its free level (its whitened RMS about its mean
    before the first contact at most :data:`REST_DISPLACEMENT`, as a gel at rest), while some markers stay
    displaced: a kept fold standing up against the lifted gel. Lifted, the gel is above the card: a
    card held up against it without a measurable force rests on its own kept shape (an elastic card
    falls flat under its weight), so its shape there is read as in a free final window.

    Args:
        rec: the recording (sheet points, wrench).
        final: boolean mask ``(n,)`` of the recording's last :data:`FINAL_WINDOW_S` on ``rec.t["sheet_points"]``.
        t_first_contact: time of the gel's first contact, s.
    """
    if final.sum() < 3 or not rec.has("wrench") or final_motion(rec, final) > resolvable_set(rec):
        return ""
    t = rec.t["sheet_points"]
    tw = rec.t["wrench"]
    w = np.asarray(rec.data["wrench"], dtype=float) / np.asarray(rec.sigma["wrench"], dtype=float)
    before, last = tw < t_first_contact, tw >= t[final][0]
    if before.sum() < 3 or last.sum() < 3:
        return ""
    rms = float(np.sqrt(np.mean((w[last] - w[before].mean(axis=0)) ** 2)))
    if rms > REST_DISPLACEMENT:
        return ""
    return (f"the gel's markers stay displaced to the end, but over the last {FINAL_WINDOW_S} s the sheet rests "
            f"and the wrench is at its free level (whitened RMS {rms:.2g} about it): a kept fold standing against "
            "the lifted gel, read as a rest shape")


def plasticity_test(rec: Recording) -> SignatureResult:
    """Permanent set of the sheet after the gel released it (module docstring).

    The final window is the last :data:`FINAL_WINDOW_S` (at least three samples) of the last run of
    released rows (:func:`_released_rows`) after the recorded gel's last contact (its last loaded run
    lasting :data:`FINAL_WINDOW_S` beyond the :data:`FREE_MARGIN_S` margins, else its longest) that
    lasts :data:`FINAL_WINDOW_S`, else of the free tail that reaches the recording's end: a
    touch later (a kept fold brushing the lifted pad) neither hides the set nor enters the window;
    without one it is the recording's last :data:`FINAL_WINDOW_S`, read only where the sheet rests there
    against a gel that carries no measurable load (:func:`_resting_on_the_gel`). Where the replay has released the sheet
    there too, the recorded sheet is compared with the replay's and with its own initial shape (the
    smaller of the two sets is the size). Where the replay still presses the gel on the sheet in that
    window (its contact outlasts the recorded one, e.g. an elastic fold of the replay leaning on the
    pad), the replay's sheet is not a released shape: the set is read against the sheet's initial
    shape alone, the statistic being the whitened SSE of the difference of the two windows' means
    (about chi-square(3p) without a set).
    """
    effect = "bending_plasticity"
    if not rec.predicted("sheet_points"):
        return not_applicable(effect, "needs the tracked sheet points and their replay")
    t = rec.t["sheet_points"]
    free = _released_rows(rec, "sheet_points")
    contact = predicted_contact(rec, "sheet_points")
    if free is None or contact is None or not contact.any():
        return not_applicable(effect, "the replay predicts no contact with the sheet")
    held = np.nonzero(~free)[0]
    if not len(held):
        return not_applicable(effect, "the recorded gel is never loaded")
    # the gel's last contact: the last loaded run that lasts a final window beyond its margins (a
    # touch is shorter); without one, the longest loaded run
    loaded = segments(~free)
    contacts = [seg for seg in loaded if t[seg[1] - 1] - t[seg[0]] - 2.0 * FREE_MARGIN_S >= FINAL_WINDOW_S]
    main_end = contacts[-1][1] if contacts else max(loaded, key=lambda seg: t[seg[1] - 1] - t[seg[0]])[1]
    after = [(i0, i1) for i0, i1 in segments(free) if i0 >= main_end]
    runs = [(i0, i1) for i0, i1 in after if t[i1 - 1] - t[i0] >= FINAL_WINDOW_S] or [r for r in after if r[1] == len(t)]
    final = np.zeros(len(t), bool)
    if runs:
        i0, i1 = runs[-1]
        final[i0:i1] = t[i0:i1] >= t[i1 - 1] - FINAL_WINDOW_S
        last_held = i0 - 1
    first_contact = min(int(np.nonzero(contact)[0][0]), int(held[0]))
    initial = free & (np.arange(len(t)) < first_contact)
    leaning = ""
    if final.sum() < 3:
        final = t >= t[-1] - FINAL_WINDOW_S
        leaning = _resting_on_the_gel(rec, final, float(t[first_contact]))
        if not leaning:
            return not_applicable(effect, "the gel does not release the sheet before the recording ends "
                                          f"(no free final window of {FINAL_WINDOW_S} s)")
        last_held = int(np.nonzero(final)[0][0]) - 1
    motion = final_motion(rec, final)
    fold = None
    if motion > resolvable_set(rec):
        rows = np.arange(len(t))
        main_start = contacts[-1][0] if contacts else max(loaded, key=lambda seg: t[seg[1] - 1] - t[seg[0]])[0]
        fold = remaining_fold(rec, (rows >= main_start) & (rows < main_end), free & (rows >= main_end), final, initial,
                              (rows >= i0) & (rows < i1))
        if fold is None or not fold["remains"]:
            kept = "" if fold is None else f", and no fold remains ({_fold_words(fold)})"
            return not_applicable(effect, f"the sheet still moves {1e3 * motion:.2g} mm over the final window "
                                          f"({t[final][0]:.2f}-{t[final][-1]:.2f} s){kept}: no rest shape to read "
                                          "a set from")
    returned = _returned_by_the_end(rec, final, initial, after)
    if returned:
        return not_applicable(effect, returned)
    replay_released = not bool(contact[final].any())
    x = np.asarray(rec.data["sheet_points"], dtype=float)
    xp = np.asarray(rec.prediction["sheet_points"], dtype=float)
    sig = rec.sigma["sheet_points"]
    n, n0 = int(final.sum()), int(initial.sum())
    d_pred = (x[final] - xp[final]).mean(axis=0)                       # (p, 3)
    set_vs_pred = float(np.max(np.linalg.norm(d_pred, axis=1)))
    replay_set, set_vs_initial, d_init = 0.0, set_vs_pred, None
    if n0 >= 3:
        d_init = x[final].mean(axis=0) - x[initial].mean(axis=0)
        set_vs_initial = float(np.max(np.linalg.norm(d_init, axis=1)))
        # where the replay itself ends far from its start (a buckle held by friction), the
        # difference of the two final shapes is the model's gap in that shape, not a set
        replay_set = float(np.max(np.linalg.norm(xp[final].mean(axis=0) - xp[initial].mean(axis=0), axis=1)))
    reason = ""
    if replay_released:
        stat = float(np.sum((d_pred / sig) ** 2) * n - d_pred.size)
        per_point = np.linalg.norm(d_pred, axis=1)
        size = min(set_vs_pred, set_vs_initial)
        if replay_set > REPLAY_SET_FRACTION * set_vs_pred:
            size, reason = 0.0, (f"the replay itself keeps the sheet {1e3 * replay_set:.2g} mm from its start after "
                                 "release: the final shapes' difference is not read as a set")
    elif d_init is not None:
        stat = float(np.sum((d_init / sig) ** 2) / (1.0 / n + 1.0 / n0) - d_init.size)
        per_point = np.linalg.norm(d_init, axis=1)
        size = set_vs_initial
        reason = ("the replay still presses the gel on the sheet after the recorded gel let go: the set is read "
                  "against the sheet's initial shape")
    else:
        return not_applicable(effect, "the replay holds the sheet after the recorded release and the sheet has "
                                      "no free initial window to compare with")
    if leaning:
        reason = (f"{reason}; " if reason else "") + leaning
    if fold is not None:
        reason = (f"{reason}; " if reason else "") + (
            f"the sheet still moves {1e3 * motion:.2g} mm over the final window, but a fold remains "
            f"({_fold_words(fold)}): the set is read from the moving sheet")
    top = np.argsort(per_point)[::-1][: max(3, len(per_point) // 20)]
    t_release, t_end = float(t[last_held]), float(t[final][-1])
    return SignatureResult(
        effect=effect, statistic=max(stat, 0.0), effect_size=size, effect_unit="m", reason=reason,
        estimate={"permanent_set_m": set_vs_pred if replay_released else size}, windows_s=[[t_release, t_end]],
        channels=["sheet_points"], markers=[],
        detail={"final_samples": n, "set_vs_replay_m": set_vs_pred, "set_vs_initial_m": set_vs_initial,
                "replay_set_m": replay_set, "replay_released": replay_released, "final_motion_m": motion,
                "final_window_s": [float(t[final][0]), t_end],
                "points": sorted(top.tolist()), "release_s": t_release, "remaining_fold": fold})


def resolvable_set(rec: Recording) -> float:
    """Smallest permanent set the sheet tracking resolves, m: :data:`RESOLVABLE_SET_SIGMAS` times the
    largest sheet-point noise sigma."""
    return RESOLVABLE_SET_SIGMAS * float(np.max(rec.sigma["sheet_points"]))


def set_rise(rec: Recording, result: SignatureResult, t0: float, t1: float) -> float:
    """How far the points carrying a permanent set rose between ``t0`` and ``t1``, m.

    Args:
        rec: the recording.
        result: a :func:`plasticity_test` result (its ``detail["points"]``: the points with the
            largest set).
        t0, t1: the interval, s.

    Returns:
        the mean height of those points at ``t1`` minus that at ``t0`` (each the mean of the sheet
        samples within one sheet period of the instant); 0 for a result without points.
    """
    points = result.detail.get("points") if result.applicable else None
    if not points:
        return 0.0
    t = rec.t["sheet_points"]
    z = np.asarray(rec.data["sheet_points"], dtype=float)[:, points, 2].mean(axis=1)
    half = rec.sample_period("sheet_points")

    def height(at: float) -> float:
        rows = np.abs(t - at) <= half
        return float(z[rows].mean()) if rows.any() else float(np.interp(at, t, z))

    return height(t1) - height(t0)


def adhesion_test(rec: Recording) -> SignatureResult:
    """The sheet carried by the gel after the replay has let it go."""
    effect = "adhesion"
    if not (rec.predicted("sheet_points") and rec.has("markers_xyz")):
        return not_applicable(effect, "needs the tracked sheet points, their replay and the marker positions")
    t = rec.t["sheet_points"]
    contact = predicted_contact(rec, "sheet_points")
    disp = marker_displacement(rec)
    if contact is None or disp is None or not contact.any():
        return not_applicable(effect, "the replay predicts no contact with the sheet")
    loaded = np.interp(t, rec.t["markers_xyz"], (disp > REST_DISPLACEMENT).astype(float)) > 0.5
    after_first = np.arange(len(t)) > int(np.nonzero(contact)[0][0])
    carried = after_first & ~contact & loaded
    x = np.asarray(rec.data["sheet_points"], dtype=float)
    xp = np.asarray(rec.prediction["sheet_points"], dtype=float)
    sig = rec.sigma["sheet_points"]
    if carried.sum() < 3:
        return SignatureResult(effect=effect, statistic=0.0, effect_size=0.0, effect_unit="m",
                               reason="the recorded gel is never loaded where the replay has released the sheet")
    # the carried sheet follows the effector: its highest point rises and falls with it
    ee_z = np.interp(t, rec.t["pose"], np.asarray(rec.data["pose"], dtype=float)[:, 2]) if rec.has("pose") else None
    runs = [(i0, i1) for i0, i1 in segments(carried) if t[i1 - 1] - t[i0] >= MIN_CARRIED_S]
    top = x[:, :, 2].max(axis=1)
    follows = []
    for i0, i1 in runs:
        if ee_z is None or i1 - i0 < 3 or np.std(ee_z[i0:i1]) == 0.0:
            continue
        follows.append(float(np.corrcoef(top[i0:i1], ee_z[i0:i1])[0, 1]))
    keep = np.zeros(len(t), bool)
    for (i0, i1), c in zip(runs, follows):
        if c >= MIN_FOLLOW_CORRELATION:
            keep[i0:i1] = True
    if not keep.any():
        return SignatureResult(effect=effect, statistic=0.0, effect_size=0.0, effect_unit="m",
                               detail={"carried_samples": int(carried.sum()), "follow_correlation": follows},
                               reason="the recorded sheet does not follow the effector where the replay released it")
    carried = keep
    r = (x[carried] - xp[carried]) / sig
    stat = float(np.sum(r ** 2) - r.size)
    lift = float(np.max(x[carried][:, :, 2].max(axis=1) - xp[carried][:, :, 2].max(axis=1)))
    windows = [[float(t[i0]), float(t[i1 - 1])] for i0, i1 in segments(carried)]
    return SignatureResult(effect=effect, statistic=max(stat, 0.0), effect_size=max(lift, 0.0), effect_unit="m",
                           estimate={"carried_height_m": max(lift, 0.0)}, windows_s=windows,
                           channels=["sheet_points", "wrench"],
                           detail={"carried_samples": int(carried.sum()), "follow_correlation": follows})
