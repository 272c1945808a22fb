"""Refit of bending plasticity with its physics term: the hinge bending's yield angle.

The hinge bending energy moves a hinge's rest angle where ``|theta - theta_bar|`` exceeds the
yield angle (:func:`sim_core.energies.hinge_bending.reference.plastic_update`; ThinShellLab, Wang
et al. 2024), so a replay with a finite ``sheet.yield_angle`` keeps a set after the gel lets go of
the sheet. The refit searches that one angle by bounded scalar minimisation (Brent's method on
``log(yield / theta_max)``, :func:`scipy.optimize.minimize_scalar`), each evaluation one replay of
the recording with the calibrated parameters, within a replay count and a wall-time budget.

Training and held-out data: the sheet points split in a checkerboard of the sheet grid (points
``(i + j) % 2 == 0`` train, the others are held out), both halves over the same rows. A split in
time is not honest here: the set exists only after the release, and the rows before it carry no
information on the yield angle (fitting there and testing after it would test an unidentified
parameter); the checkerboard keeps both halves on the fold while their noise is independent, and
with one fitted scalar the held-out half tests whether the replay with the term predicts the
sheet's shape where it was not fitted. The cost and the held-out figure are read on the effect's
windows (after the release, where the set lives); the held-out RMS over the whole recording is
reported as well, so a term that helps after the release but harms the loading shows it.

On a lift the set comes from a fold made by the gel's tack, which a calibrated replay without
adhesion never makes; where adhesion is named too, the search starts from the replay in which the
tack carries the card and lets go at the peel read from the recording (:func:`tack_base`,
:mod:`sysid.diagnose.peel`), and the figures before / after are that replay without / with the term.
The tack's bonds hold the card in shear as well (the compliant layer, :func:`with_shear_layer`) where
that follows the carried card better: with normal-only bonds the card slides along the gel, stays a
straight ramp from the clamp and never folds (plastic_s102: largest dihedral angle 0.004 rad against
the recording's 0.28-0.33 rad), so the yield search was flat and the refit explained 0.11 of the
held-out excess (docs/benchmarks_log.md, session 56).
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable, Mapping

import numpy as np
from scipy.optimize import minimize_scalar

from sim_core.errors import ConfigError, SimulationDivergedError
from sysid.diagnose.resume import YIELD_PARAMETER, YieldReplays, resume_before_time

LOWEST_FRACTION = 0.02
"""Smallest yield angle searched, as a fraction of the largest hinge angle of the calibrated replay."""

FALLBACK_THETA_MAX = 0.5
"""Largest yield angle searched (rad) when the replay's hinge angles cannot be computed from its sheet points."""

SMALL_REDUCTION = 0.05
"""A refit that lowers the held-out whitened RMS by less than this fraction gets a note that the term
does not reproduce the set (the replay does not bend the sheet where the recording folds it)."""

XATOL = 0.05
"""Tolerance of the search on ``log(yield / theta_max)``."""

LAYER_REPLAYS = 6
"""Most replays of the tack's shear-layer search in the refit's base (:func:`with_shear_layer`: the layer
search's four grid points and two of Brent's steps)."""


def checkerboard(n_points: int, resolution: tuple[int, int] | None) -> np.ndarray:
    """Training points of the sheet: ``(i + j) % 2 == 0`` on the ``nx x ny`` grid (vertex ``k`` at
    ``i = k % nx, j = k // nx``, :func:`sim_core.mesh.sheet.grid_sheet`), alternate points when the
    points are not that grid.

    Returns:
        boolean mask ``(n_points,)``: True for a training point.
    """
    k = np.arange(int(n_points))
    if resolution is not None and int(resolution[0]) * int(resolution[1]) == n_points:
        nx = int(resolution[0])
        return (k % nx + k // nx) % 2 == 0
    return k % 2 == 0


def _sse(x: np.ndarray, xp: np.ndarray, sigma: np.ndarray) -> float:
    return float(np.sum(((x - xp) / sigma) ** 2))


def _rms(x: np.ndarray, xp: np.ndarray, sigma: np.ndarray) -> float:
    return math.sqrt(_sse(x, xp, sigma) / max(x.size, 1)) if x.size else float("nan")


def brent_first_points(lower: float, upper: float, xatol: float) -> tuple[float, float]:
    """The first two points that bounded Brent minimisation (:func:`scipy.optimize.minimize_scalar`,
    ``method="bounded"``; Brent 1973, "Algorithms for Minimization without Derivatives", ch. 5) evaluates on
    ``[lower, upper]``: the golden section point, then a golden section step from it (no parabola can be
    fitted through one point), computed as SciPy computes them (the same floating-point operations), so
    neither depends on a function value and both can be replayed at once.

    Returns:
        ``(x1, x2)``.
    """
    golden_mean = 0.5 * (3.0 - math.sqrt(5.0))
    a, b = float(lower), float(upper)
    xf = a + golden_mean * (b - a)
    xm = 0.5 * (a + b)
    tol1 = math.sqrt(2.2e-16) * abs(xf) + xatol / 3.0
    e = a - xf if xf >= xm else b - xf
    rat = golden_mean * e
    si = np.sign(rat) + (rat == 0)
    return xf, float(xf + si * np.maximum(np.abs(rat), tol1))


def fit_yield_angle(replay: Callable[[float], np.ndarray], data: np.ndarray, nominal: np.ndarray,
                    sigma: np.ndarray, rows: np.ndarray, train: np.ndarray, theta_max: float,
                    max_replays: int = 5, max_time: float | None = None,
                    prefetch: Callable[[float], None] | None = None) -> dict[str, Any]:
    """Yield angle of the hinge bending that best fits the training sheet points.

    Args:
        replay: yield angle (rad) -> predicted sheet points ``(n, p, 3)`` m aligned to ``data``
            (may raise :class:`~sim_core.errors.SimulationDivergedError`).
        data: recorded sheet points ``(n, p, 3)`` m.
        nominal: the calibrated replay without plasticity ``(n, p, 3)`` m.
        sigma: noise per axis ``(3,)`` m.
        rows: rows ``(n,)`` of the cost and of the held-out figure (the effect's windows).
        train: training points ``(p,)`` (the others are held out).
        theta_max: largest hinge angle of the nominal replay, rad (> 0): the search spans
            ``[LOWEST_FRACTION * theta_max, theta_max]`` on a log scale; at ``theta_max`` nothing yields.
        max_replays: most replays of the search.
        max_time: wall-time budget of the search, s (None: none); a replay started before it ends
            is finished.
        prefetch: called with the search's second yield angle (rad) before its first replay, so that
            ``replay`` may make both at once (:meth:`sysid.diagnose.resume.YieldReplays.prefetch`); None: none.

    Returns:
        dict with ``yield_angle`` (rad; None when no evaluated angle beats the nominal replay on the
        training points), ``evaluations`` (``[[yield_angle, training whitened RMS or None where the
        replay diverged], ...]``),
        ``prediction`` (the replay at the fitted angle, or ``nominal``), the training and held-out
        whitened RMS in ``rows`` before and after, the held-out RMS over all rows before and after,
        ``heldout_reduction`` (1 - after / before of the held-out RMS in ``rows``),
        ``heldout_points`` (indices) and ``notes``.

    Raises:
        ValueError: ``theta_max`` not > 0, no training or no held-out point, no row.
    """
    if not theta_max > 0.0:
        raise ValueError(f"fit_yield_angle: theta_max must be > 0 rad, got {theta_max}")
    if train.all() or not train.any():
        raise ValueError("fit_yield_angle: needs both training and held-out sheet points")
    if not rows.any():
        raise ValueError("fit_yield_angle: no row to fit")
    held = ~train
    x_tr, x_he = data[rows][:, train], data[rows][:, held]
    nominal_cost = _sse(x_tr, nominal[rows][:, train], sigma)
    t0 = time.monotonic()
    evals: list[tuple[float, float, np.ndarray | None]] = []  # (u, sse, prediction)
    notes: list[str] = []

    class _Budget(Exception):
        """Raised inside the scalar search when the replay or time budget is spent (ends the search)."""

    def cost(u: float) -> float:
        if len(evals) >= max_replays or (max_time is not None and time.monotonic() - t0 > max_time):
            raise _Budget
        y = theta_max * math.exp(u)
        try:
            pred = replay(y)
        except SimulationDivergedError as err:
            notes.append(f"yield angle {y:.4g} rad: replay diverged ({err})")
            evals.append((u, math.inf, None))
            return 10.0 * nominal_cost + 1.0
        c = _sse(x_tr, pred[rows][:, train], sigma)
        evals.append((u, c, pred))
        return c

    lo = math.log(LOWEST_FRACTION)
    if prefetch is not None and max_replays >= 2:
        prefetch(theta_max * math.exp(brent_first_points(lo, 0.0, XATOL)[1]))
    try:
        minimize_scalar(cost, bounds=(lo, 0.0), method="bounded", options={"xatol": XATOL, "maxiter": max_replays})
    except _Budget:
        notes.append(f"search stopped by its budget ({max_replays} replays, {max_time} s) after {len(evals)} replays")
    finite = [e for e in evals if math.isfinite(e[1])]
    best = min(finite, key=lambda e: e[1]) if finite else None
    improved = best is not None and best[1] < nominal_cost
    pred = best[2] if improved else nominal
    yield_angle = theta_max * math.exp(best[0]) if improved else None
    if not improved:
        notes.append("no yield angle searched fits the training points better than the replay without plasticity")
    n_tr = max(x_tr.size, 1)
    before, after = _rms(x_he, nominal[rows][:, held], sigma), _rms(x_he, pred[rows][:, held], sigma)
    reduction = 1.0 - after / before if before > 0.0 else 0.0
    if improved and reduction < SMALL_REDUCTION:
        notes.append(f"the term lowers the held-out sheet residual by {100 * reduction:.2g} % only: the replay's sheet "
                     f"bends at most {theta_max:.3g} rad, so no yield angle makes the fold the recorded set comes from")
    return {"heldout_reduction": reduction, "yield_angle": yield_angle, "theta_max": theta_max,
            "evaluations": [[theta_max * math.exp(u), math.sqrt(c / n_tr) if math.isfinite(c) else None]
                            for u, c, _ in evals],
            "prediction": pred, "notes": notes, "wall_s": time.monotonic() - t0,
            "train_rms_before": math.sqrt(nominal_cost / n_tr),
            "train_rms_after": math.sqrt(_sse(x_tr, pred[rows][:, train], sigma) / n_tr),
            "heldout_rms_before": before, "heldout_rms_after": after,
            "heldout_rms_all_rows_before": _rms(data[:, held], nominal[:, held], sigma),
            "heldout_rms_all_rows_after": _rms(data[:, held], pred[:, held], sigma),
            "heldout_points": np.nonzero(held)[0].tolist()}


def sheet_resolution(model: Any) -> tuple[int, int] | None:
    """``(nx, ny)`` of the scene's grid sheet of an :class:`~sysid.observation.ObservationModel`, or None."""
    from sim_core.scenes.scene_file import load_scene_file

    try:
        sheet = getattr(load_scene_file(model.scene), "sheet", None)
    except ConfigError:
        return None
    return None if sheet is None else tuple(int(v) for v in sheet.resolution)


def with_shear_layer(model: Any, tack: dict[str, Any], t: np.ndarray, data: np.ndarray,
                     sigma: np.ndarray) -> dict[str, Any]:
    """The tack of :func:`sysid.diagnose.peel.tack_with_peel` with the gel's compliant shear layer, where the layer
    follows the carried card better than the normal-only bonds.

    Normal-only bonds let the card slide along the gel face: on a lift-and-fold the carried card stays a straight
    ramp from the clamp (plastic_s102: largest dihedral angle 0.004 rad, the recording's fold 0.28-0.33 rad), so no
    yield angle gives it the recorded set. The layer holds the bonded points in shear (``k_t`` searched on the sheet
    points of the rows before the peel, :func:`sysid.diagnose.shear_layer.fit_shear_layer`, at most
    :data:`LAYER_REPLAYS` replays, bonds of :data:`~sysid.diagnose.shear_layer.LAYER_BOND_WEIGHTS` card weights), so
    the card arches and folds as the gel carries it back. Those rows are not the refit's (the effect's windows
    follow the release). No more replay: the search's own replay at the fitted ``k_t`` (kept with its states,
    ``keep_best``) is the layer's replay of ``params`` with the release, and it is also the layer's carried replay
    up to the release, the only steps read from it (:func:`tack_base`'s and the yield search's resumes take the steps
    before the release, :func:`~sysid.diagnose.resume.steps_before`; the release acts on none of them,
    :meth:`sim_core.candidates.hook.CandidateHook.released`: its states there are the carried replay's to the bit,
    tests/sysid/diagnose/test_plasticity_lift.py); as the released replay it is made from the start, where a resume
    from the carried replay gives the same to round-off. Where the search kept no replay at its best (a cost that is
    not a number), the carried replay is made as before: one replay more.

    Args:
        model: the calibrated observation model.
        tack: :func:`~sysid.diagnose.peel.tack_with_peel`'s result with ``carried`` (``keep_carried=True``).
        t: recorded sheet rows' times ``(n,)`` s; data: recorded sheet points ``(n, p, 3)`` m; sigma: their noise ``(3,)`` m.

    Returns:
        ``tack`` itself, or with the layer: ``params`` with its bond strength and ``k_t``, ``beta``,
        ``shear_stiffness`` (N/m a pair), ``shear_layer`` (the search's
        :meth:`~sysid.diagnose.shear_layer.ShearLayer.summary`: its profile and the sigma of ``ln k_t``), ``carried``
        replaced (a replay with its states, the same as the carried one before the release) and ``replay``: the
        replay of ``params`` itself (with the release; None where the carried replay was made without it).
    """
    from sysid.diagnose.peel import RELEASE_TIME_SETTING
    from sysid.diagnose.shear_layer import fit_shear_layer, sheet_rms

    carried = t < tack["peel_s"]  # the peel's own row out: the replay lets go within a step of the recording
    layer = fit_shear_layer(model, tack["params"], tack["beta"], data, sigma, carried, max_replays=LAYER_REPLAYS,
                            keep_best=True)
    normal_only = sheet_rms(model.predict(tack["carried"])["sheet_points"], data, sigma, carried)
    if layer is None or not layer.rms < normal_only:
        return tack
    params = {**tack["params"], **layer.settings()}
    fitted = {**tack, "params": params, "beta": layer.beta, "shear_stiffness": layer.stiffness,
              "shear_layer": layer.summary()}
    if layer.replay is not None:
        return {**fitted, "carried": layer.replay, "replay": layer.replay}
    held = {k: v for k, v in params.items() if k != RELEASE_TIME_SETTING}
    return {**fitted, "carried": model.simulate(held, keep_states=True), "replay": None}


def tack_base(model: Any, params: Mapping[str, float], recording: Any, nominal: np.ndarray,
              train: np.ndarray, shear_layer: bool = True) -> dict[str, Any] | None:
    """The replay in which the gel's tack carries the card and lets go at the recorded peel, when it
    fits the training sheet points (all rows) better than the calibrated replay.

    A set is made by a fold, and on a lift the fold is made by the tack that carries the card
    (candidate adhesion); a calibrated replay without it never lifts the card, so no yield angle can
    give it the recorded set. The bonds' strength is :data:`~sysid.diagnose.candidates.
    ADHESION_PROBE_WEIGHTS` times :func:`~sysid.diagnose.candidates.adhesion_weight_scale` (bonds
    that together bear four card weights: the card follows the gel, and far above that only the pull
    on the gel grows); their release time is the peel read from the recording
    (:func:`sysid.diagnose.peel.tack_with_peel`). Two replays (the released one resumed from the carried one
    before the peel). With ``shear_layer`` the bonds hold the card in shear too where that follows the carried card
    better (:func:`with_shear_layer`: up to :data:`LAYER_REPLAYS` replays more, whose best is the released replay
    itself, so that the released replay is not made again): a card that slides along the gel never folds.

    Returns:
        ``{"params", "peel_s", "beta", "prediction" (n, p, 3) m, "train_rms", "nominal_train_rms"}`` (and
        ``shear_stiffness`` with the layer), or None (no adhesion candidate, no peel in the recording, or no
        better fit).
    """
    from sysid.diagnose.candidates import ADHESION_PROBE_WEIGHTS, adhesion_weight_scale
    from sysid.diagnose.peel import RELEASE_TIME_SETTING, tack_with_peel

    t = np.asarray(recording.t["sheet_points"], dtype=float)
    data = np.asarray(recording.data["sheet_points"], dtype=float)
    sigma = np.asarray(recording.sigma["sheet_points"], dtype=float)
    w = adhesion_weight_scale(model.simulation().model)
    if not (math.isfinite(w) and w > 0.0):
        return None
    tack = tack_with_peel(model, params, t, data, ADHESION_PROBE_WEIGHTS * w, keep_carried=True)
    if tack is None:
        return None
    if shear_layer:
        tack = with_shear_layer(model, tack, t, data, sigma)
    trace = tack.pop("replay", None)
    if trace is None:
        resume = resume_before_time(tack["carried"], tack["params"][RELEASE_TIME_SETTING])
        trace = model.simulate(tack["params"], resume=resume)
    pred = np.asarray(model.predict(trace)["sheet_points"], dtype=float)
    n_tr = max(data[:, train].size, 1)
    c_tack, c_nom = _sse(data[:, train], pred[:, train], sigma), _sse(data[:, train], nominal[:, train], sigma)
    if not c_tack < c_nom:
        return None
    return {**tack, "prediction": pred, "train_rms": math.sqrt(c_tack / n_tr), "nominal_train_rms": math.sqrt(c_nom / n_tr)}


def refit_plasticity(model: Any, params: Mapping[str, float], recording: Any, nominal: np.ndarray,
                     windows_s: list[list[float]], max_replays: int = 5,
                     max_time: float | None = None, carried_by_tack: bool = False,
                     worker: Any = None, shear_layer: bool = True) -> dict[str, Any]:
    """Bending plasticity refitted with its term (``sheet.yield_angle``) on a calibrated recording.

    Args:
        model: the calibrated :class:`~sysid.observation.ObservationModel` of the recording.
        params: its calibrated simulator parameters (every replay starts from them).
        recording: the :class:`~sysid.diagnose.signatures.Recording` (``sheet_points`` recorded).
        nominal: the calibrated replay's ``sheet_points`` ``(n, p, 3)`` m.
        windows_s: the effect's windows ``[[t0, t1], ...]`` s (the rows of the cost).
        max_replays, max_time: budget of the search (:func:`fit_yield_angle`).
        carried_by_tack: (the diagnosis also names adhesion) try the replay in which the gel's tack
            carries the card up to the recorded peel (:func:`tack_base`, two replays) as the base of the search; it is kept
            when it fits the training points better than the calibrated replay. The held-out figures
            before / after are then those of that base without / with the term
            (``detail.heldout_rms_calibrated``: the calibrated replay's).
        shear_layer: with ``carried_by_tack``, the tack's bonds may hold the card in shear
            (:func:`with_shear_layer`; False: normal-only bonds).
        worker: a process that makes replays beside this one (the calibration's probe process,
            :class:`~sysid.diagnose.probe_worker.ProbeWorker`), or None: the search's second replay is made
            there while this process makes its first (:class:`~sysid.diagnose.resume.YieldReplays`).

    Returns:
        the refit block of the report (``params``, ``observable``, ``heldout``, ``rms``,
        ``heldout_rms_before`` / ``_after``, ``detail``) and ``prediction``: channel -> the replay
        with the fitted term (popped by the caller before the report is written).
    """
    from sysid.diagnose.candidates import hinge_angle_history
    from sysid.diagnose.peel import RELEASE_TIME_SETTING

    t = recording.t["sheet_points"]
    data = np.asarray(recording.data["sheet_points"], dtype=float)
    sigma = np.asarray(recording.sigma["sheet_points"], dtype=float)
    rows = np.zeros(len(t), bool)
    for a, b in windows_s:
        rows |= (t >= a) & (t <= b)
    train = checkerboard(data.shape[1], sheet_resolution(model))
    held = ~train
    calibrated = nominal
    base_params = dict(params)
    tack = tack_base(model, params, recording, nominal, train, shear_layer) if carried_by_tack else None
    carried = None
    if tack is not None:
        base_params, nominal, carried = dict(tack.pop("params")), tack.pop("prediction"), tack.pop("carried")
    angles = hinge_angle_history(model, nominal)
    theta_max = float(np.max(angles)) if angles is not None and angles.size else FALLBACK_THETA_MAX
    theta_max = theta_max if theta_max > 1e-6 else FALLBACK_THETA_MAX

    replay = YieldReplays(model, base_params, carried, RELEASE_TIME_SETTING if carried is not None else None,
                          worker=worker, nominal=params)
    f = fit_yield_angle(replay, data, nominal, sigma, rows, train, theta_max, max_replays, max_time,
                        prefetch=replay.prefetch)
    f["shared_steps"] = list(replay.shared_steps)
    f["prefetched"] = list(replay.prefetched)
    pred = f.pop("prediction")
    f["tack"] = tack
    f["heldout_rms_calibrated"] = _rms(data[rows][:, held], calibrated[rows][:, held], sigma)
    fitted = {} if f["yield_angle"] is None else {"yield_angle_rad": f["yield_angle"]}
    if tack is not None:
        fitted = {**fitted, "adhesion_N_per_pair": tack["beta"], "peel_s": tack["peel_s"]}
        if "shear_stiffness" in tack:
            fitted["shear_stiffness_N_per_m"] = tack["shear_stiffness"]
    return {"params": fitted,
            "base": ("calibrated replay" if tack is None else
                     f"calibrated replay with the gel's tack ({tack['beta']:.3g} N per bond"
                     + (f", held in shear by a layer of {tack['shear_stiffness']:.3g} N/m per bond"
                        if "shear_stiffness" in tack else "")
                     + f", bonds broken at the recorded peel, {tack['peel_s']:.3f} s)"),
            "observable": "sheet_points in the effect's windows (after the release)",
            "heldout": "checkerboard of the sheet grid (half the points fitted, the other half held out)",
            "rms": {"sheet_points": f["train_rms_after"]},
            "heldout_rms_before": f["heldout_rms_before"], "heldout_rms_after": f["heldout_rms_after"],
            "detail": f, "prediction": {"sheet_points": pred}}
