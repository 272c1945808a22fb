"""The gel's tack in the nominal model of a lift recording: the card the gel carries up, let go at the recorded peel.

On a lift-and-fold the gel's tack carries the card (the reference world bonds the card to the gel at every
lift_fold, its nominal ones included: ``shared/data/reference_bags/README.md``); a replay without it leaves
the card on the table while the recording shows it 20 mm up. Measured on nominal_s109 at the engine's values
(labels.yaml; drive from the data; docs/benchmarks_log.md, session 52): the sheet points' whitened RMS is
0.98-1.0 in every window before the tack forms at 1.63 s and 8-182 after it (82 over the recording, the
"4 mm" of session 51), the replay's card staying flat while the recorded one rises with the gel. The gel's
markers and wrench hardly see it (2.56 / 3.62 / 2.09), so a fit of the materials cannot find it.

``thinshell sysid`` (:class:`sysid.fit_recording.FitOptions` ``tack``, ``--tack``; off by default)
gives the nominal model the tack wherever the recording shows the card carried, a data rule:

1. from the recording alone (:func:`carried_rows`, read on the scene's model without starting the replay backend:
   a recording with no carried row makes no replay, and the calibration's probe still forks before Taichi
   starts): rows where the gel's face (its footprint at the measured
   pose) stands more than the bond's release opening above where the card under it lay at the start, and the
   recorded card under it has risen by more than that opening and is within it of the face: the card rises
   with the gel. No row: no tack, no extra replay (seven of the nine reference recordings; the press-slides
   stiction_s105 and gel_creep_s108 have rows: their buckled card springs up under the lifting pad);
2. the diagnosis' tack (:func:`sysid.diagnose.peel.tack_with_peel`): bonds of strength
   :data:`~sysid.diagnose.candidates.ADHESION_PROBE_WEIGHTS` card weights a pair, released at the peel read
   from the recording, kept where its replay follows the recorded sheet points up to the peel better than
   the replay without it by more than the null allows (:func:`tack_margin`: the delta-BIC beyond
   :data:`sysid.gel_law.NULL_SIGMAS` of its spread under the null, as the gel law is chosen; a buckled card that
   springs up under a lifting pad rises on its own). Two replays. The bonds' strength is not fitted: above the card's weight the card follows the gel whatever
   the strength (:func:`sysid.diagnose.candidates.adhesion_weight_scale`).

3. the tack's compliant layer (:func:`fit_shear_layer`; ``nominal_tack(shear_layer=False)`` leaves it out):
   normal-only bonds let the card slide along the gel, where a real gel's adhesive layer holds it in shear with a
   finite stiffness; the layer's bonds are isotropic springs (:data:`LAYER_NORMAL_RATIO`), so the bonded patch also
   tilts under the card's bending moment instead of holding the card at the gel's slope. With the materials held at the start, the layer's ``k_t`` (N/m per bonded pair, bonds of
   :data:`LAYER_BOND_WEIGHTS` card weights held to the recorded peel) is searched in log on the sheet points
   before the peel (at most :data:`SHEAR_MAX_REPLAYS` replays), and kept where it follows the carried card better
   than the normal-only bonds. Its sigma counts one datum per correlation time of the card's residual
   (:func:`_rows_per_datum`).
4. ``k_t`` is then fitted jointly with the materials (:func:`sysid.fit_recording.fit_recording` adds it to the
   fitted parameters; its Jacobian column the tangent of
   :meth:`sim_core.candidates.adhesion.LaggedAdhesion.parameter_gradient`, with the bonds' lagged normals in the
   state tangents), so its robust sigma and its correlation with the bending stiffness are the fit's; the fit
   weighs each channel by its gap at its start (the carried card's sheet points, the layer's form error, would
   otherwise drive the materials). Held at the start's materials (session 53) or alternated with their fit
   (session 54), ``k_t`` stayed in the rough profile's pocket of the start's materials.

Every later replay (calibration and fit) takes the tack (:meth:`sysid.observation.ObservationModel.set_nominal`).
nominal_s109 at the engine's values, sheet points' whitened RMS over the recording: no tack 81.9, normal-only bonds
32.1, the compliant layer (k_t 2.64 N/m a pair, fitted) 7.59, markers 2.56 -> 1.44 (docs/benchmarks_log.md,
session 53). The rigid shear bonds of the coupled law (``adhesion.shear``) read 41: the fold needs the compliance.

What the fit with the tack gives on nominal_s109, measured (docs/benchmarks_log.md, sessions 53-57). Session 53: from +-30 % starts the materials did not come back (s109
-30 %: modulus -64 %, friction -50 %) and from the scene the friction landed at -27 %, with the force gain on its bound
(the reference records the bonds' force with the card's sign). Session 54 (docs/benchmarks_log.md, s54-49lift): with
that phase's wrench rows left out (:mod:`sysid.wrench_check`) the force gain is 1.01-1.14, inside its prior; with
``k_t`` refitted at each fit's materials the materials still followed the start (s109 from the scene / +30 % / -30 %:
bending -6.4 / +47.7 / -29.8 %, modulus -10.4 / +38.9 / -23.5 %). Session 55: the tangents of a carried card held
each bond's normal at ``x^n`` fixed, 26-40 % off the rollouts' differences after two steps of lift
(tests/sim_core/test_adhesion_tangents.py); with them exact, ``k_t`` is fitted jointly (docs/benchmarks_log.md,
s55-49lift). s109 from the scene / +30 % / -30 %: ``k_t`` 3.05 / 2.93 / 3.08 (started at 2.64 / 3.41 / 1.98: it no
longer follows the start), bending +12.6 / +27.0 / +12.1 %, modulus +7.7 / +21.6 / +7.0 %, friction -23.0 / -20.9 /
-30.3 %; 7 of 9 inside the robust 2-sigma (two frictions not), 2 of 9 within 10 %. The bending and ``k_t`` correlate
at 0.99 (the carried card's sag is set by both) and only the sheet points part them (markers 1.35 and pixels 1.61 at
every end); their layer form error (7.1-7.4) prefers the +30 % end, so the truth is not the layer model's minimum.
That form error was the layer's normal law: it held the bonded patch flat on the gel face, where the recorded card
pivots about its pinned edge as a straight ramp with the patch tilted under it. With the layer's bonds isotropic
springs (:data:`LAYER_NORMAL_RATIO`), at the engine's values (k_t 3): the lift's sheet points 0.74 -> 0.24 mm mean
error (own world nominal_s301: 0.39-0.70 -> 0.08-0.11 mm, the noise), s109 whitened RMS 9.4 -> 8.4, and the engine's
values now follow the card better than the +30 % end's (8.4 against 10.4). Half of what is left is the released
card's fall (the replay's card, undamped, lands in 30 ms where the recorded one takes 80; a sheet drag of 37 1/s takes
s109 to 6.6); docs/benchmarks_log.md, session 56. Both sides of that fall are time steps, not missing physics
(session 57): a card let go from 18 mm falls as the rigid rod pinned at its edge (49.9 ms), which this simulator
follows at 1 ms steps within 0.24 mm, while the replay's 10 ms backward Euler step runs ahead of it by its
first-order lead (tests/sim_core/test_known_answers_card_fall.py); the reference engine's 1 ms step with the flex's
Rayleigh damping (0.002 s) slows the same fall to 61 ms, 50.8 ms at 0.25 ms (benchmarks/mujoco_world/fall_answers.py).
A drag fitted to it would copy the engine's integrator into a parameter; none is added. With the tack, nominal_s109's
fits stop after 0-2 iterations from every start: at the peel the folded card is arched against the gel face and the
bonds let go at once, so friction on that contact holds the released card or not, a threshold (friction 0.6347 at the
-30 % start's first step) on whose far side the cost is 126x, and the friction lands +19 / +30 % off outside its
2-sigma interval from the scene / +30 % start (docs/benchmarks_log.md, session 57, s57-49lift): so the tack stays
opt-in. On the merged session-57 main (the drive replay's first iterate and evaluation starts changed under it; not
bisected) that cliff is not on the fit's path (session 58, s58-49peel): along the friction line at the -30 % start's
calibrated point the released card comes down on both sides of 0.6347 (sheet points' sum of squares 1.3246e7 /
1.3247e7), and the -30 % start's fit with the stop rules off steps through the release (friction 0.56 -> 0.87 -> 0.93 ->
0.71 -> 0.92, cost 2.07-2.21e5, no 126x step): bending +5.6 % and modulus -7.9 % come back covered, the gel-card
friction lands +25 % off outside its robust 2-sigma interval, as from the other starts in session 57. What keeps the
tack opt-in is that friction, not the release. At that end the sheet points prefer the high friction (in the hold,
3.0-3.84 s, and the fall), the markers the engine's; left out of the fit, the carried card's rows let the friction run
to 1.30 (+76 %, NOT IDENTIFIED): the friction's pull is not the carried rows alone (docs/benchmarks_log.md, session 58).

Where that pull comes from (docs/benchmarks_log.md, session 59, s59-49lift): with the tack, the gel-card friction acts on
a lift's card only on the bonded patch. The bonds form wherever the gel touches the card, so up to the peel every
gel-card friction row is a bonded vertex (tests/sysid/test_tack.py), and ``friction.gel_sheet`` holds the card in shear
side by side with the layer's spring ``k_t`` on the same vertices, its normal load the patch's press against the gel as
the fold arches the card (nominal_s109 at the engine's values, k_t 2.9: mu lam 0.18-0.21 N in the hold 3.0-3.84 s,
0.04 N in 2.2-3.0 s). The engine has both there too: its tack is adhesive point bonds (the reference set's README;
12 formed on nominal_s109, labels.yaml) beside its frictional gel-card contacts, as in the own MuJoCo world made after
it (benchmarks/mujoco_world/mjcf.py: ``connect`` equalities, contacts untouched), so the friction is not taken off the
patch: a bonded patch that presses is a frictional contact. With the friction zeroed on the bonded rows, friction 0.734 -> 0.92 changes the sheet
points' sum of squares by 2 % (the released card's fall): a lift sees the friction through the patch's one tangential
balance, beside ``k_t``, and which friction the sheet points prefer follows ``k_t`` (at the engine's materials, sheet
points' sum of squares at friction 0.734 / 0.92: 3.60e7 / 3.38e7 with k_t 2.0, 1.82e7 / 2.12e7 with k_t 2.9; the fits end
at k_t 2.4-3.5). The fitted friction then carries the layer law's form error (isotropic springs at the 48 bonded gel vertices
where the engine bonds 12 points), which no covariance of the fit shows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_core.candidates.hook import CandidateHook
from sim_core.errors import SimulationDivergedError
from sysid.diagnose.candidates import ADHESION_PROBE_WEIGHTS, adhesion_weight_scale
from sysid.diagnose.peel import ADHESION_PARAMETER, RELEASE_TIME_SETTING, face_gap, points_under, tack_with_peel
from sysid.diagnose.shear_layer import (LAYER_BOND_WEIGHTS, LAYER_NORMAL_RATIO, NORMAL_RATIO_SETTING,  # noqa: F401
                                        SHEAR_STIFFNESS_SETTING, ShearLayer, _rows_per_datum, fit_shear_layer,
                                        sheet_rms)
from sysid.evidence import resample_pose
from sim_core.transforms import quat_to_matrix

@dataclass(frozen=True)
class TackDecision:
    """Whether the nominal model of a recording has the gel's tack, and why.

    Attributes:
        on: the tack is part of the nominal model.
        why: the reason, in words.
        carried_rows: sheet-point rows where the recording shows the card carried by the gel.
        beta: bond strength per pair, N (nan when off).
        peel_s: the recorded peel, s from the recording's start (nan when off).
        params: the simulator parameters of the tack (empty when off).
        layer: the compliant shear layer's fit (None: not fitted).
        rounds: ``(k_t, sigma of ln k_t)`` of the layer's search.
        margin: the tack against no tack (:func:`tack_margin`; None where no replay compared them).
    """

    on: bool
    why: str
    carried_rows: int = 0
    beta: float = math.nan
    peel_s: float = math.nan
    params: dict[str, float] | None = None
    layer: "ShearLayer | None" = None
    rounds: tuple[tuple[float, float], ...] = ()
    margin: "TackMargin | None" = None

    def summary(self) -> dict[str, Any]:
        """fit.json's ``diagnostics.tack`` (``layer_rounds``: ``(k_t, sigma of ln k_t)`` of the layer's search at the
        start's materials; ``k_t`` then moves in the joint fit, fit.json's ``fit.parameters``)."""
        return {"layer_rounds": [[k, None if math.isnan(g) else g] for k, g in self.rounds], "on": self.on, "why": self.why, "carried_rows": self.carried_rows,
                "bond_strength_N": None if math.isnan(self.beta) else self.beta,
                "peel_s": None if math.isnan(self.peel_s) else self.peel_s,
                "shear_layer": None if self.layer is None else self.layer.summary(),
                "shear_layer_on": bool(self.params and SHEAR_STIFFNESS_SETTING in self.params),
                "margin": None if self.margin is None else self.margin.summary()}


def _face_corners(model) -> np.ndarray:
    """The gel's undeformed contact face in the sensor frame: a 5 x 5 grid over ``gel_size`` (x, y), ``(25, 3)`` m."""
    sx, sy = (float(v) for v in model.scene["sensors"][model.sensor]["gel_size"][:2])
    gx, gy = np.meshgrid(np.linspace(-sx / 2, sx / 2, 5), np.linspace(-sy / 2, sy / 2, 5))
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)


def scene_model(model):
    """The simulator model of ``model``'s scene, read without starting the replay backend (a scene file is parsed;
    a task scene's model is its simulation's): the tack's decision on a recording with no carried row makes no
    replay, so the calibration's probe can still fork before Taichi starts (:mod:`sysid.diagnose.probe_worker`)."""
    if model.task:
        return model.simulation().model
    from sim_core.scenes import load_scene

    return load_scene(model.scene)


def carried_rows(model, opening: float, sim_model=None) -> np.ndarray:
    """Sheet-point rows in which the recording shows the card carried by the gel (module docstring, step 1).

    Args:
        model: the :class:`~sysid.observation.ObservationModel` (``sheet_points`` and ``pose`` recorded).
        opening: the bonds' release opening, m (> 0).
        sim_model: the scene's simulator model (its sensor mount; None: :func:`scene_model`).

    Returns:
        bool ``(n,)`` over the recorded sheet-point rows (all False without sheet points or a sensor).
    """
    ev = model.evidence
    if model.sensor is None or "sheet_points" not in ev.channels_present:
        return np.zeros(0, bool)
    t = np.asarray(ev.t_ns["sheet_points"], dtype=np.int64)
    sheet = np.asarray(ev.values("sheet_points"), dtype=float)
    pose = resample_pose(ev.t_ns["pose"], ev.pose, t, outside="clamp")
    mount = (scene_model(model) if sim_model is None else sim_model).sensors[model.sensor].mount
    local = _face_corners(model)
    rest_z = sheet[0, :, 2]
    out = np.zeros(t.size, bool)
    for k in range(t.size):
        R = quat_to_matrix(pose[k, 3:7]) @ quat_to_matrix(mount[3:7])
        face = pose[k, :3] + (R @ (local + mount[:3]).T).T
        under = points_under(sheet[k], face)
        if not under.any():
            continue
        lifted = float(face[:, 2].min() - rest_z[under].max()) > opening  # the gel off where the card lay
        risen = float(np.max(sheet[k, under, 2] - rest_z[under])) > opening  # and the card off the table
        out[k] = lifted and risen and face_gap(sheet[k], face) < opening
    return out


def nominal_tack(model, params: dict[str, float] | None = None, shear_layer: bool = True) -> TackDecision:
    """Decide the tack of ``model``'s recording and, where on, make it part of the model's nominal.

    Args:
        model: the :class:`~sysid.observation.ObservationModel` (its drive already set: the tack's replay takes it).
        params: simulator parameters of the tack's replay (None: the scene's).
        shear_layer: also fit the tack's compliant shear layer (:func:`fit_shear_layer`) and keep it where it
            follows the carried card better than the normal-only bonds (False: the normal-only bonds).

    Returns:
        the :class:`TackDecision`.

    Raises:
        SimulationDivergedError: the replay with the bonds diverged.
    """
    scene = scene_model(model)  # no replay backend started where the recording decides without a replay
    beta = ADHESION_PROBE_WEIGHTS * adhesion_weight_scale(scene)
    if not (math.isfinite(beta) and beta > 0.0):
        return TackDecision(False, "no card weight to carry (no sheet, gravity or gel face)")
    opening = CandidateHook({"adhesion": beta}).setting("adhesion.release")
    rows = carried_rows(model, opening, scene)
    if not rows.any():
        return TackDecision(False, "the recorded card is never carried by the gel (it stays within "
                                   f"{opening * 1e3:.2g} mm of where it lay wherever the gel is over it)")
    sim = model.simulation()
    ev = model.evidence
    t_sheet = (np.asarray(ev.t_ns["sheet_points"], dtype=np.int64) - int(ev.start_ns)) * 1e-9
    data = np.asarray(ev.values("sheet_points"), dtype=float)
    tack = tack_with_peel(model, dict(params or {}), t_sheet, data, beta, keep_carried=True)
    if tack is None:
        _drop_tack(sim.model)
        return TackDecision(False, "the card rises with the gel in the recording but no peel was found (the recorded "
                                   "card never leaves the gel)", int(rows.sum()))
    held = t_sheet <= tack["peel_s"]
    sigma = np.asarray(model.sigma["sheet_points"], dtype=float)
    pred_with = model.predict(tack["carried"])["sheet_points"]
    with_tack = sheet_rms(pred_with, data, sigma, held)
    plain = model.simulate({**dict(params or {}), ADHESION_PARAMETER: 0.0})
    pred_without = model.predict(plain)["sheet_points"]
    without = sheet_rms(pred_without, data, sigma, held)
    margin = tack_margin(model, pred_with, pred_without, data, sigma, held)
    if not margin.kept:
        _drop_tack(sim.model)
        return TackDecision(False, f"the card rises with the gel in the recording, but a replay with the tack follows "
                                   f"it no better up to the peel than the null allows (sheet points whitened RMS "
                                   f"{with_tack:.3g} against {without:.3g} without; {margin.words()}: the card springs "
                                   f"back on its own)", int(rows.sum()), margin=margin)
    release = float(tack["params"][RELEASE_TIME_SETTING])
    values = {ADHESION_PARAMETER: float(beta), RELEASE_TIME_SETTING: release}
    why = (f"the recording shows the card carried by the gel in {int(rows.sum())} rows: bonds of "
           f"{ADHESION_PROBE_WEIGHTS:g} card weights a pair, released at the recorded peel {tack['peel_s']:.3f} s "
           f"(sheet points whitened RMS up to the peel {without:.3g} -> {with_tack:.3g}; {margin.words()})")
    carried = t_sheet < tack["peel_s"]  # the peel's own row out: the replay lets go within a step of the recording
    layer = (fit_shear_layer(model, {**dict(params or {}), **values}, beta, data, sigma, carried,
                             normal_ratio=LAYER_NORMAL_RATIO)
             if shear_layer else None)
    if layer is not None and layer.rms < with_tack:
        values = {**values, **layer.settings()}
        why += (f"; a compliant layer of isotropic springs (k_n = {LAYER_NORMAL_RATIO:g} k_t) that holds the card in "
                f"shear and lets the bonded patch tilt, k_t {layer.stiffness:.3g} N/m a pair fitted from "
                f"the carried card (bonds of {LAYER_BOND_WEIGHTS:g} card weights, held to the peel): {layer.rms:.3g}")
    elif layer is not None:
        why += (f"; the compliant shear layer followed it no better ({layer.rms:.3g} at its best, "
                f"k_t {layer.stiffness:.3g})")
    for name, value in values.items():  # known to the simulator before the nominal takes them
        sim.set_parameter(name, value)
    model.set_nominal(values)
    on = SHEAR_STIFFNESS_SETTING in values
    return TackDecision(True, why, int(rows.sum()), float(values[ADHESION_PARAMETER]), float(tack["peel_s"]), values,
                        layer, ((layer.stiffness, layer.log_sigma),) if on else (), margin)


LAYER_RATIO_PRIOR = math.log(3.0)
"""Prior 1-sigma of the log of the tack layer's normal-to-shear stiffness ratio (:data:`LAYER_NORMAL_RATIO` its
nominal), a nuisance of every fit with the layer (:func:`sysid.fit_recording.nuisance_of`): a factor 3 a sigma. No
recording or data sheet gives it: an elastic layer bonded on both faces has ``k_n / k_t = 2 (1 - nu) / (1 - 2 nu)``
(2 at nu 0, 3.5 at nu 0.3, 13.5 at a silicone's 0.46), the model's isotropic springs 1, and the reference engine's
point bonds have none. Measured on this simulator's own lift-and-fold with the ratio concealed at 3
(docs/benchmarks_log.md, session 60, 49lift2): held at 1, the fit puts the layer's form error into the gel-card
friction (+106 %, 1.65 +- 0.30 robust: the interval misses the truth) and the bending stiffness (-55 %) while following
every channel at the noise (whitened RMS 0.93-0.98); the nuisance at ln 3 / 2 a sigma widened the friction to
+- 0.38, still missing it (the truth 2 of that prior's sigma away); at ln 3 a sigma the nuisance part doubles."""

TACK_PARAMETERS = 1
"""Parameters the tack adds to the nominal model in its information criterion: the peel time read from the recording
(the bonds' strength is set from the card's weight, :func:`sysid.diagnose.candidates.adhesion_weight_scale`)."""


@dataclass(frozen=True)
class TackMargin:
    """The tack against no tack on the carried card's sheet points up to the peel (:func:`tack_margin`).

    Attributes:
        delta_bic: ``|r_without|^2 - |r_with|^2 - TACK_PARAMETERS ln m`` (whitened, ``m`` residuals): > 0 favours the tack.
        null_sd: standard deviation of the sum-of-squares difference under the null (no tack made the recording;
            :func:`sysid.gel_law.null_spread`, the residual's time correlation counted).
        kept: ``delta_bic > NULL_SIGMAS null_sd`` (:data:`sysid.gel_law.NULL_SIGMAS`).
    """

    delta_bic: float
    null_sd: float
    kept: bool

    def words(self) -> str:
        """The margin in words."""
        return f"delta-BIC {self.delta_bic:.4g}, {self.delta_bic / self.null_sd:.3g} null sd" if self.null_sd > 0 else \
            f"delta-BIC {self.delta_bic:.4g}"

    def summary(self) -> dict[str, Any]:
        """fit.json's ``diagnostics.tack.margin``."""
        return {"delta_bic": self.delta_bic, "null_sd": self.null_sd, "kept": self.kept}


def tack_margin(model, pred_with: np.ndarray, pred_without: np.ndarray, data: np.ndarray, sigma: np.ndarray,
                rows: np.ndarray) -> TackMargin:
    """Whether the tack follows the recorded card beyond what the null allows: the gel law's rule
    (:mod:`sysid.gel_law`, the margin from the null) on the sheet points of ``rows``, the tack's
    :data:`TACK_PARAMETERS` charged at ``ln m`` each (Bayesian information criterion).

    Args:
        model: the :class:`~sysid.observation.ObservationModel` (its residual time bins).
        pred_with, pred_without: predicted sheet points ``(n, p, 3)`` m with and without the tack.
        data: recorded sheet points ``(n, p, 3)`` m; sigma: their noise, broadcastable; rows: bool ``(n,)``.
    """
    from sysid.covariance import residual_bin_s
    from sysid.gel_law import NULL_SIGMAS, null_spread

    r_with = ((np.asarray(pred_with)[rows] - data[rows]) / sigma).ravel()
    r_without = ((np.asarray(pred_without)[rows] - data[rows]) / sigma).ravel()
    t = np.asarray(model.evidence.t_ns["sheet_points"], dtype=np.int64)[rows]
    times = np.repeat((t - int(model.evidence.start_ns)) * 1e-9, r_with.size // max(int(rows.sum()), 1))
    delta = float(r_without @ r_without - r_with @ r_with) - TACK_PARAMETERS * math.log(max(r_with.size, 1))
    null_sd = null_spread(r_with, r_without - r_with, times, residual_bin_s(model))
    return TackMargin(delta, null_sd, bool(delta > NULL_SIGMAS * null_sd))


def _drop_tack(sim_model) -> None:
    """Take the trial's tack out of the simulator's candidates (a candidate at 0 would still make every step
    search for its pairs, and keep replays out of lockstep batches)."""
    kept = {k: v for k, v in sim_model.candidates.items() if not k.startswith("adhesion")}
    if kept != sim_model.candidates:
        sim_model.candidates = kept
        sim_model.revision += 1
