"""The gel's constitutive law chosen by the data: each law fitted to the recording, compared by an information
criterion, a change of law accepted only beyond the comparison's spread under the null.

The laws (:data:`GEL_LAWS`, ``simulation.gel_element``) share the small-strain response (``E``, ``nu``) and part at
second order in the strain: Stable Neo-Hookean (the default) keeps a sheared layer's thickness, the Green-strain
law (Saint Venant-Kirchhoff, :mod:`sim_core.energies.green_strain`) thins it and softens in compression, so a pressed
gel sinks further once it slides (docs/known_answers.md, "The slide's depth gap is the gel's law").

**Each law near its own fitted values, after one step.** The laws' difference trades against the gel modulus (a softer
law looks like a softer gel at small strain), so a comparison at one shared modulus, the start's, follows the start where
the recording barely parts the laws: this simulator's shallow press made with the default law chose the Green-strain
law from a start x1.3 / x2 its modulus (delta-BIC 21 / 64, docs/benchmarks_log.md, session 53 "49law"). Each law's
modulus, friction and stick speed (:data:`PROFILED`) are therefore moved towards that law's own values first, by one
Levenberg-Marquardt step (:func:`law_step`, :func:`damped_step`, at most :data:`STEP_RADIUS` in each search
coordinate) on the tangents of one cold replay at the start (:class:`sysid.jacobians.TangentReplay`). The step's end
is not replayed: the raw prediction is moved along its tangents (first order in the step) and the sensor gains are
refitted to it in closed form, which gives the end's residual and the gains it asks (the force gain a start off its
modulus asks, the step takes back). So a law costs one replay with tangents; ``thinshell sysid --gel-element auto``
(:func:`choose_at_start`) compares at the fit's start, after the scene's law was calibrated, where the scene's law's
replay is the one the calibration made for the fit (:mod:`sysid.calibration_secant`, ``last``) and the other law's is
the one its fit takes as its first: one replay with tangents over a fit at the scene's law (32-35 CPU s on nominal_s101
against ~100 for two replayed steps a law; docs/benchmarks_log.md, session 56 "49auto"). Where the other law's predicted
cost is the smaller, each law takes a second step from its first step's end, replayed there (:func:`restep`): one
predicted step leaves a law far from a far start short of its own minimum, and the comparison would then reward the
law whose step got further (this simulator's card press-slide with the quick demo's concealed viscoelasticity and
hidden materials). Every replay goes through the effector's drive fitted
from the recording (:func:`sysid.drive_calibration.fit_drive`), with the sensor gains (force gain, marker scales,
camera) refitted in closed form within their prior (:class:`sysid.gain_profile.GainProfile`); the tactile channels
are compared. The laws have the same number of parameters, so the difference of their Bayesian information criteria
is the difference of their whitened sums of squares (``-2 log L`` up to a constant shared by both).

**The margin from the null.** Let ``R`` be the reference law (the scene's) and ``A`` the other, ``e`` the whitened
residual of ``R`` and ``g = r_R - r_A`` the whitened difference of the two laws' stepped predictions. Where ``R`` made
the recording (``e`` its noise), ``delta = |r_R|^2 - |r_A|^2 = 2 e.g - |g|^2``: mean ``-|g|^2``, standard deviation
``2 sqrt(Var(e.g))``, with ``Var(e.g)`` the long-run variance of the products ``e_i g_i`` binned in time
(Newey-West with Andrews' window, :mod:`sysid.covariance`: the residuals' time correlation counts, a white-noise
count of the samples would overstate the evidence), ``e`` estimated by the better law's residual. ``A`` replaces ``R``
only where ``delta`` exceeds :data:`NULL_SIGMAS` times that spread (a one-sided test at about 2.3 % under the null; the
residual of a model that does not follow the recording inflates ``e`` and so the margin: conservative). Otherwise
the reference law is kept, and :attr:`GelLawChoice.decided` says so.

**A law the sensor must bend to follow.** Each law's replay asks the sensor gains (force gain, marker scales) that
follow the recording best; the prior bounds them (:mod:`sysid.gain_prior`, +-15 % by default). ``A`` also replaces
``R`` only where it asks its gains no further outside their prior than ``R`` does (:func:`beyond_prior`): a law
that fits only through a sensor gain a real cell's data sheet rules out (e.g. markers that move twice as deep as
recorded) is not evidence for the law. (Session 53 measured the calibration's depth scale 0.39 / 0.40 under the
Green-strain law on the deep presses stiction_s105 and gel_creep_s108 of the reference set.)

**Where no comparison is made.** ``auto`` is ``thinshell sysid``'s default (``--gel-element scene``: the scene's
law without a comparison). It keeps the scene's law, saying why (:func:`auto_not_applicable`), without a tactile
sensor, with the tack's layer, where the scene names a law outside :data:`GEL_LAWS`, and where the replays' gel mesh
is coarser than the one the scene states (:func:`gel_mesh`): the laws part at second order in the strain, a coarse
mesh's locking at first (the quick demo's one-layer ``3,3,2`` replay of a four-layer recording chose the Green-strain
law for it).

**Why ``thinshell diagnose`` keeps the scene's law by default** (docs/benchmarks_log.md, session 58 "49law"). Its
calibration under the Green-strain law takes the recordings of the reference engine (StVK) whose card stays flat
towards the null (latency_s103 markers / pixels / wrench 8.51 / 12.14 / 5.85 -> 5.62 / 7.82 / 3.05, its depth followed
row by row; nominal_s101 2.19 / 2.91 -> 1.78 / 2.35), but not the deep press-slides whose card buckles under the pad
(stiction_s105 markers 10.07 -> 11.81, gel_creep_s108 11.26 -> 13.27, depth scale asked 0.4): there the pad's leading
edge collapses (StVK past the stretch ``1/sqrt(3)``) and stays collapsed after the load is gone. The recorded edge is
StVK on the engine's own tet mesh (on two layers with each cell cut along the Kuhn split's mirror, as MuJoCo's grid
cuts it in its own frame, the calibrated depth follows at whitened RMS 3.4-3.7; the split's handedness moved the
Green-strain calibration by a fifth, the default law's by 4 %), a discretisation no law should copy; the gel's
cut ``simulation.gel_cut: mirrored`` has no handedness. And :func:`choose_gel_law`
before the calibration compares the laws at the scene's stick speed, where latency_s103's Green-strain replay leaves
the recording (whitened RMS 28 after its step), so ``--gel-element auto`` keeps the default law on the one deep press
the data's law follows. A choice worth its price there has to compare the laws at the calibrated stick speed.

This module reads a recording only through :mod:`sysid.evidence` and replays it through
:class:`sysid.observation.ObservationModel`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from sim_core.errors import CalibrationError, ConfigError, SimulationDivergedError
from sim_core.scenes.tactile_scene import SIMULATION_KEYS, default_gel_resolution
from sysid.covariance import andrews_bandwidth, bin_scores, hac_meat, residual_bin_s, residual_times_s, time_bins
from sysid.drive_calibration import fit_drive
from sysid.fit import FitProblem, parameter_spec
from sysid.gain_prior import PRIOR_OF, GainPrior
from sysid.gain_profile import GainProfile
from sysid.jacobians import TangentReplay, load_sensitivity, make_jacobian, tangent_columns
from sysid.observation import SENSOR_PARAMETERS, ObservationModel, scene_dict_for

GEL_LAWS: tuple[str, ...] = ("stable_neohookean", "green_strain")
"""The gel laws compared by default (:data:`sim_core.elastic.SOLID_ELEMENTS` names)."""

AUTO_LAW = "auto"
"""``simulation.gel_element`` (``thinshell diagnose`` / ``thinshell sysid --gel-element``) that asks for the law the
recording chooses (:func:`choose_gel_law`) instead of a named one."""
SCENE_LAW = "scene"
"""``--gel-element`` value that replays the scene's law (else the simulator's default) without a comparison."""

TACTILE = ("markers_xyz", "markers_uv", "wrench")
"""Channels whose whitened sums of squares are compared."""

PROFILED: tuple[str, ...] = ("gel.youngs_modulus", "friction.gel_sheet", "contact.eps_v")
"""Parameters fitted for each law before the comparison (every column from the replay's tangents): the modulus,
which the laws' difference trades against; the gel-sheet friction, which sets the slide's shear (from a start with
both x0.7 this simulator's Green-strain press-slide fitted with the modulus alone took the modulus to 0.56-0.61 x the
truth and could not part the laws); the lagged friction's stick speed, which the calibration fits too (on
nominal_s101 at the scene's 10 mm/s both laws stay at whitened RMS 4.4-6.6, fitted to 3.4-3.5 mm/s 1.9-2.5)."""

STEP_RADIUS = 1.5
"""Largest change of each :data:`PROFILED` search coordinate (log units: a factor 4.5) in a law's step
(:func:`damped_step`): wide enough that the scene's stick speed (10 mm/s) reaches nominal_s101's 2.8 mm/s (ln 3.5 =
1.27) and a start x2 its values in one Gauss-Newton step, narrow enough that a step the tangents mispredict stays near
where they hold."""

CHECKED_GAINS = ("force_gain", "marker_scale_xy", "marker_scale_z")
"""Sensor gains whose excursion outside their prior keeps the reference law (:func:`beyond_prior`)."""

NULL_SIGMAS = 2.0
"""The other law replaces the reference law only where its delta-BIC exceeds this many standard deviations of the
delta-BIC under the null (module docstring)."""


@dataclass(frozen=True)
class GelLawChoice:
    """What :func:`choose_gel_law` / :func:`choose_at_start` found.

    Attributes:
        chosen: the law the recording is replayed with: the other law where it is better by more than the margin,
            else the reference law.
        cost: law -> whitened sum of squares over :attr:`channels` at the law's stepped values as its tangents
            predict it (:func:`law_step`; noise units squared, summed over samples).
        rms: law -> channel -> whitened RMS at the law's stepped values (predicted).
        margin: the runner-up's cost minus the best law's (the delta-BIC in the best law's favour; equal parameter
            counts).
        channels: the compared channels.
        reference: the law kept unless the data reject it (the scene's).
        fitted: law -> its :data:`PROFILED` values after its step (empty where nothing was stepped).
        gains: law -> the sensor gains its step's end asked for before their prior bounded them (``force_gain``,
            ``marker_scale_xy``, ``marker_scale_z``, ...; empty without ``gain_prior``).
        steps: law -> whitened sums of squares of the compared rows at the start and, predicted, at its step's end
            (:func:`law_step`).
        beyond_prior: law -> how far its asked force gain or marker scales lie outside their prior
            (:func:`beyond_prior`; filled where the other law is the best).
        null_sd: standard deviation of the reference's delta-BIC under the null (module docstring); NaN where the
            reference law is the best (no change to test).
        decided: False where the best law is not the reference but its delta-BIC is within ``NULL_SIGMAS * null_sd``
            (the reference is kept: the recording does not part the laws), or it asks its sensor gains further
            outside their prior than the reference does (:attr:`beyond_prior`; module docstring).
        restepped: each law took a second step from its first step's end, replayed there (:func:`restep`: the
            reference's one step left it costlier than the other law's); :attr:`steps` then holds each law's four
            costs (start, first end predicted, first end replayed, second end predicted; the first two where the first
            step's end did not replay).
    """

    chosen: str
    cost: dict[str, float]
    rms: dict[str, dict[str, float]]
    margin: float
    channels: tuple[str, ...]
    reference: str = GEL_LAWS[0]
    fitted: dict[str, dict[str, float]] | None = None
    null_sd: float = math.nan
    decided: bool = True
    gains: dict[str, dict[str, float]] | None = None
    steps: dict[str, list[float]] | None = None
    beyond_prior: dict[str, float] | None = None
    restepped: bool = False

    def summary(self) -> dict[str, Any]:
        """JSON-ready: the chosen law, the margin and its null spread, each law's cost, fitted values and whitened
        RMS per channel."""
        return {"chosen": self.chosen, "delta_bic": self.margin, "reference": self.reference,
                "null_sd": None if math.isnan(self.null_sd) else self.null_sd, "decided": self.decided,
                "cost": dict(self.cost), "fitted": {law: dict(v) for law, v in (self.fitted or {}).items()},
                "gains_asked": {law: dict(v) for law, v in (self.gains or {}).items()},
                "step_costs": {law: list(v) for law, v in (self.steps or {}).items()},
                "beyond_prior": dict(self.beyond_prior or {}), "restepped": self.restepped,
                "whitened_rms": {law: dict(r) for law, r in self.rms.items()}, "channels": list(self.channels)}


class _GainsFromRest(GainProfile):
    """:class:`sysid.gain_profile.GainProfile` that first takes the markers' rest positions from the first raw
    prediction it sees (its first stamp), as :func:`sysid.calibration.calibrate` does, so that the marker scales are
    profiled too (without rest positions only the force gain and the camera are)."""

    def __call__(self, raw: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        if self.model.marker_rest is None and "markers_xyz" in raw:
            self.model.marker_rest = np.asarray(raw["markers_xyz"][0], dtype=float)
        return super().__call__(raw)


def beyond_prior(asked: Mapping[str, float], prior: GainPrior) -> float:
    """How far the gains ``asked`` (:data:`CHECKED_GAINS`, relative to the scene's: 1 = the data sheet) lie outside
    ``prior``: the largest distance of one past its bound (-), 0 where all lie inside."""
    out = 0.0
    for key in CHECKED_GAINS:
        if key in asked:
            lo, hi = prior.bounds(PRIOR_OF[key])
            out = max(out, lo - float(asked[key]), float(asked[key]) - hi)
    return out


def _whitened(model: ObservationModel, prediction: Mapping[str, np.ndarray], channels: Sequence[str]) -> np.ndarray:
    """``(data - prediction) / sigma`` of ``channels``, concatenated as :func:`sysid.covariance.residual_times_s`
    places them (each channel time first, row-major), ``(m,)``."""
    return np.concatenate([((model.data(ch) - prediction[ch]).reshape(-1, model.sigma[ch].shape[0])
                            / model.sigma[ch]).ravel() for ch in channels])


def null_spread(e: np.ndarray, g: np.ndarray, times_s: np.ndarray, bin_s: float) -> float:
    """Standard deviation of ``2 e.g`` for noise ``e`` with the time correlation ``e`` itself shows: ``2 sqrt(S)``,
    ``S`` the Newey-West long-run variance (Bartlett weights, Andrews' window: :mod:`sysid.covariance`) of the
    products ``e_i g_i`` summed per time bin. For white ``e`` of unit variance it is ``2 |g|``; a positive
    correlation of neighbouring samples raises it.

    Args:
        e: whitened residual ``(m,)`` standing for the noise (the better law's).
        g: whitened difference of the two laws' predictions ``(m,)``.
        times_s: time of each element ``(m,)``, s.
        bin_s: time bin width, s (> 0).
    """
    scores = bin_scores(np.asarray(g, dtype=float)[:, None], np.asarray(e, dtype=float), time_bins(times_s, bin_s))
    return float(2.0 * math.sqrt(max(float(hac_meat(scores, andrews_bandwidth(scores))[0, 0]), 0.0)))


def _residual_times(model: ObservationModel, channels: Sequence[str]) -> np.ndarray:
    """Time (s) of each element of :func:`_whitened`'s vector of ``channels``, ``(m,)``."""
    stamps = {ch: np.asarray(model.evidence.t_ns[ch]) for ch in channels}
    return residual_times_s(stamps, {ch: int(np.asarray(model.data(ch)).size) for ch in channels}, channels)


def damped_step(J: np.ndarray, r: np.ndarray, radius: float, lb: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Levenberg-Marquardt step of the whitened residual ``r`` ``(m,)`` with Jacobian ``J`` ``(m, p)``: the
    Gauss-Newton step ``-(J^T J)^-1 J^T r`` where no coordinate moves more than ``radius``, else
    ``-(J^T J + lam D)^-1 J^T r`` (``D`` the diagonal of ``J^T J``, Marquardt's scaling) with the smallest ``lam`` that
    keeps every coordinate within ``radius`` (bisected in ``log lam``); then clipped to the bounds ``lb <= step <=
    ub`` ``(p,)`` (the start at ``u = 0``). A column that is not finite (a parameter without tangents) stays at zero.

    Returns:
        the step ``(p,)``, search-coordinate units.
    """
    J = np.asarray(J, dtype=float)
    r = np.asarray(r, dtype=float)
    step = np.zeros(J.shape[1])
    seen = np.all(np.isfinite(J), axis=0) & np.any(J != 0.0, axis=0)
    if not seen.any():
        return step
    A, g = J[:, seen].T @ J[:, seen], J[:, seen].T @ r
    D = np.diag(np.maximum(np.diag(A), 1e-12 * float(np.max(np.diag(A)))))

    def solve(lam: float) -> np.ndarray:
        return np.linalg.lstsq(A + lam * D, -g, rcond=None)[0]

    s = solve(0.0)
    if float(np.max(np.abs(s))) > radius:
        lo, hi = -12.0, 12.0  # log10 lam: at 1e12 the step is the gradient's, 1e-12 of it
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if float(np.max(np.abs(solve(10.0 ** mid)))) > radius else (lo, mid)
        s = solve(10.0 ** hi)
    step[seen] = s
    return np.clip(step, lb, ub)


@dataclass
class LawStep:
    """One law's replay with tangents at the start and its Levenberg-Marquardt step, predicted on those tangents
    (:func:`law_step`).

    Attributes:
        values: the stepped parameters' values at the step's end, SI.
        start_cost: whitened sum of squares of the compared rows at the start (the replay's own).
        residual: the compared rows' whitened residual at the step's end as the tangents predict it, ``r + J s``
            ``(m,)``.
        gains: the sensor gains the start's replay asked for before their prior bounded them (empty without a gain
            profile).
        made: the start's replay with the tangents of every name (:class:`sysid.jacobians.TangentReplay`), for a fit
            at the same start to take as its first joint evaluation; None where the replay could not carry tangents.
    """

    values: dict[str, float]
    start_cost: float
    residual: np.ndarray
    gains: dict[str, float]
    made: TangentReplay | None


def law_step(model: ObservationModel, names: Sequence[str], start: Mapping[str, float], rows: np.ndarray, *,
             stepped: Sequence[str] = PROFILED, extra: Sequence[str] = (), made: TangentReplay | None = None,
             radius: float = STEP_RADIUS) -> LawStep:
    """One Levenberg-Marquardt step (:func:`damped_step`) of ``model``'s parameters ``stepped`` (those of ``names``),
    on the whitened rows ``rows`` of its residual, from one cold replay with the tangents of ``names`` (then
    ``extra``, held at their nominal, as :func:`sysid.fit.joint_tangent_names` orders a fit's) at ``start`` (a
    missing name: the model's value). The end is not replayed: its residual is the tangents' prediction ``r + J s``.
    ``made`` is taken for that replay where it is the same one (:meth:`sysid.jacobians.TangentReplay.matches`), else
    one is made.

    Raises:
        CalibrationError: the replay diverged at the start.
    """
    problem, provider, tangent_names = _step_problem(model, names, start, extra)
    u = np.zeros(len(names))
    try:
        made = problem.made = _start_made(model, problem, tangent_names, made)
        r = problem.residual(u, phase="initial")
        if r is None:
            raise CalibrationError(f"the replay diverged at the start values {problem.values(u)}: "
                                   f"{problem.last_failure} (try a smaller --dt)")
        J = problem.cached_jacobian(u)
        if J is None:  # no joint replay (finite differences' provider): its columns, a replay each
            J = provider(problem, u)
        found = None if model.gain_profile is None else model.gain_profile.calibration_of(problem.best_prediction())
    finally:
        problem.close()
    cols = [i for i, n in enumerate(names) if n in stepped]
    Js = np.asarray(J, dtype=float)[rows][:, cols]
    lb, ub = problem.bounds
    step = damped_step(Js, r[rows], radius, lb[cols], ub[cols])
    start_values = problem.values(u)
    u[cols] = step
    residual = r[rows] + np.where(np.isfinite(Js), Js, 0.0) @ step
    if model.gain_profile is not None and made is not None and np.any(step != 0.0):
        # the raw prediction stepped on its tangents and the gains refitted to it in closed form: the gains the step's
        # end asks (a law's start off its modulus asks a force gain that its step takes back) and its residual
        moved = _stepped_raw(model, made, start_values, {names[i]: float(step[k]) for k, i in enumerate(cols)})
        residual = model.residuals(model.gain_profile(moved))[rows]
        found = model.gain_profile.last
    return LawStep(values={names[i]: problem.values(u)[names[i]] for i in cols}, start_cost=float(r[rows] @ r[rows]),
                   residual=residual, gains={} if found is None else {k: float(v) for k, v in found[1].items()},
                   made=made)


def _step_problem(model: ObservationModel, names: Sequence[str], start: Mapping[str, float], extra: Sequence[str]
                  ) -> tuple[FitProblem, Any, list[str]]:
    """``(problem, provider, tangent names)`` of :func:`law_step` of ``model``'s ``names`` from ``start`` (a missing
    name: the model's value) with ``extra`` held at their nominal: its :class:`sysid.fit.FitProblem` (close it), its
    Jacobian provider and the columns its joint replay asks (:func:`sysid.jacobians.tangent_columns`)."""
    specs = [parameter_spec(n, float(start[n]) if n in start else model.parameter_value(n)) for n in names]
    extra_specs = [parameter_spec(n, model.parameter_value(n)) for n in extra]
    provider = make_jacobian("auto")
    own, kept = tangent_columns(names, extra)
    return FitProblem(model, specs, joint=getattr(provider, "joint", None), extra=extra_specs), provider, [*own, *kept]


def _start_made(model: ObservationModel, problem: FitProblem, tangent_names: Sequence[str],
                made: TangentReplay | None) -> TangentReplay | None:
    """The cold replay with the tangents ``tangent_names`` at ``problem``'s start: ``made`` where it is that replay
    (:meth:`sysid.jacobians.TangentReplay.matches`), else one made here; ``made`` as given where the problem has no
    joint replay, None where the replay cannot carry tangents (a step with dt halved: the provider's own columns).

    Raises:
        CalibrationError: the replay diverged at the start.
    """
    values = problem.values(np.zeros(len(problem.specs)))
    if problem.joint is None or (made is not None and made.matches(model, values, tangent_names)):
        return made
    try:
        return TangentReplay.make(model, values, tangent_names)[0]
    except ConfigError:  # not differentiable (a step with dt halved): the provider's own columns
        return None
    except SimulationDivergedError as err:
        raise CalibrationError(f"the replay diverged at the start values {values}: {err} (try a smaller --dt)") from err


@dataclass(frozen=True)
class BesideReplay:
    """A law's :func:`law_step` start replay with tangents made in the calibration's probe process
    (:func:`replay_beside`), with what it was made of.

    Attributes:
        law: the gel law replayed (``simulation.gel_element``).
        parameters: every parameter's nominal value of the model that replayed it (:func:`model_parameters`), SI.
        drive: that model's ``(drive_stiffness, drive_damping)``.
        made: the replay, or None where it could not carry tangents.
    """

    law: str
    parameters: dict[str, float]
    drive: tuple[float, float]
    made: TangentReplay | None

    def taken(self, law: str, model: ObservationModel) -> TangentReplay | None:
        """:attr:`made` where it is ``model``'s replay of ``law``: the same law, drive and every nominal value bitwise
        (:meth:`sysid.jacobians.TangentReplay.matches` then checks the replayed values and columns), else None."""
        same = (self.law == law and self.drive == (float(model.drive_stiffness), float(model.drive_damping))
                and self.parameters == model_parameters(model))
        return self.made if same else None


def model_parameters(model: ObservationModel) -> dict[str, float]:
    """Every simulation parameter's nominal value of ``model`` and its sensor offsets, name -> SI value."""
    return {**{n: float(model.parameter_value(n)) for n in model.simulation().parameter_names},
            **dict.fromkeys(SENSOR_PARAMETERS, float(model.nominal_normal_offset))}


def replay_beside(model: ObservationModel, cache: dict, law: str, parameters: Mapping[str, float],
                  drive: tuple[float, float], names: Sequence[str], start: Mapping[str, float],
                  extra: Sequence[str]) -> BesideReplay:
    """In the calibration's probe process (:meth:`sysid.diagnose.probe_worker.ProbeWorker.call`; ``model`` its copy
    of the scene's law's model, ``cache`` its dict): the start replay with tangents that :func:`law_step` of ``names``
    from ``start`` with ``extra`` makes on a model of ``law`` with the nominal values ``parameters`` and ``drive``
    (:func:`_with_law`, built once per law and kept in ``cache``).

    Raises:
        CalibrationError: the replay diverged (the parent then replays it and meets the same).
    """
    other = cache.get(("gel_law", law))
    if other is None:
        other = cache[("gel_law", law)] = _with_law(model, law)
    other.reset_nominal()
    other.set_nominal({n: v for n, v in parameters.items() if v != other.parameter_value(n)})
    other.set_drive_stiffness(*drive)
    problem, _, tangent_names = _step_problem(other, names, start, extra)
    try:
        made = _start_made(other, problem, tangent_names, None)
    finally:
        problem.close()
    return BesideReplay(law, model_parameters(other), (float(other.drive_stiffness), float(other.drive_damping)), made)


def ask_beside(worker: Any, law: str, model: ObservationModel, names: Sequence[str], start: Mapping[str, float],
               extra: Sequence[str], parameters: Mapping[str, float] | None = None) -> bool:
    """Ask the probe process ``worker`` (:class:`sysid.diagnose.probe_worker.ProbeWorker`, or None) for
    :func:`replay_beside` of ``law`` with ``model``'s drive and nominal values (``parameters``: those instead, e.g.
    the ones the model will have); the reply is ``worker.collect()``. False where nothing was asked."""
    if worker is None:
        return False
    return worker.call(replay_beside, law, dict(model_parameters(model) if parameters is None else parameters),
                       (float(model.drive_stiffness), float(model.drive_damping)), list(names), dict(start), list(extra))


def collected(worker: Any, law: str, model: ObservationModel) -> TangentReplay | None:
    """The replay :func:`ask_beside` asked of ``worker`` where it is ``model``'s of ``law``
    (:meth:`BesideReplay.taken`), else None (the caller replays)."""
    got = worker.collect() if worker is not None else None
    return got.taken(law, model) if isinstance(got, BesideReplay) else None


def _stepped_raw(model: ObservationModel, made: TangentReplay, values: Mapping[str, float],
                 step: Mapping[str, float]) -> dict[str, np.ndarray]:
    """The raw aligned prediction (:meth:`sysid.observation.ObservationModel.predict_raw`) of ``made``'s replay at
    ``values`` moved along its tangents by ``step`` (parameter -> search-coordinate change, log for a positive scale
    parameter: :func:`sysid.fit.parameter_spec`): ``y + sum_k dy/du_k step_k``, channel -> array."""
    sim = model.prepare(values)
    traj, dX, dF, dQ = made.rollout
    raw = model.predict_raw(model.trace_of(sim, traj.states))
    obs = load_sensitivity().observation_sensitivities(sim.model, traj, dX, dF, sensor=model.sensor,
                                                       effector_position=dQ)
    du = np.zeros(len(made.names))
    for k, name in enumerate(made.names):
        if name in step:
            spec = parameter_spec(name, float(values[name]))
            du[k] = float(step[name]) * (abs(float(values[name])) if spec.log else spec.scale)
    return {ch: y + model.align(ch, obs[ch]) @ du if ch in obs else y for ch, y in raw.items()}


def compared_rows(model: ObservationModel, channels: Sequence[str]) -> tuple[tuple[str, ...], np.ndarray]:
    """``(channels, rows)``: the compared ``channels`` the model replays, in its order, and their rows of its
    whitened residual (:meth:`sysid.observation.ObservationModel.channel_slices`)."""
    slices = model.channel_slices()
    present = tuple(ch for ch in model.channels if ch in channels)
    return present, np.concatenate([np.arange(slices[ch].start, slices[ch].stop) for ch in present])


def decide(steps: Mapping[str, LawStep], reference: str, model: ObservationModel, channels: Sequence[str],
           gain_prior: GainPrior | None, null_sigmas: float = NULL_SIGMAS) -> GelLawChoice:
    """The law the compared rows of ``steps`` (law -> its :func:`law_step` on ``channels`` of ``model``, the same
    rows for every law) choose: the other law only where its predicted whitened sum of squares is smaller than the
    ``reference``'s beyond ``null_sigmas`` times the spread under the null and it asks its sensor gains no further
    outside ``gain_prior`` than the reference does (module docstring)."""
    cost = {law: float(s.residual @ s.residual) for law, s in steps.items()}
    slices = model.channel_slices()
    sizes = {ch: slices[ch].stop - slices[ch].start for ch in channels}
    bounds = np.cumsum([0, *sizes.values()])
    rms = {law: {ch: float(np.sqrt(np.mean(s.residual[a:b] ** 2))) for ch, a, b in zip(channels, bounds, bounds[1:])}
           for law, s in steps.items()}
    other = next(law for law in steps if law != reference)
    ranked = sorted(cost, key=cost.get)
    margin = cost[ranked[1]] - cost[ranked[0]]
    null_sd, decided, beyond = math.nan, True, {}
    if ranked[0] == other:
        null_sd = null_spread(steps[other].residual, steps[reference].residual - steps[other].residual,
                              _residual_times(model, channels), residual_bin_s(model))
        beyond = {law: beyond_prior(s.gains, gain_prior) for law, s in steps.items()} if gain_prior else {}
        decided = margin > null_sigmas * null_sd and beyond.get(other, 0.0) <= beyond.get(reference, 0.0)
    return GelLawChoice(chosen=other if ranked[0] == other and decided else reference, cost=cost, rms=rms,
                        margin=margin, channels=tuple(channels), reference=reference,
                        fitted={law: dict(s.values) for law, s in steps.items()}, null_sd=null_sd, decided=decided,
                        gains={law: dict(s.gains) for law, s in steps.items()},
                        steps={law: [s.start_cost, cost[law]] for law, s in steps.items()}, beyond_prior=beyond)


def restep(choice: GelLawChoice, steps: dict[str, LawStep], models: Mapping[str, ObservationModel],
           names: Sequence[str], rows: np.ndarray, gain_prior: GainPrior | None, *,
           stepped: Sequence[str] = PROFILED, extra: Sequence[str] = (), radius: float = STEP_RADIUS,
           null_sigmas: float = NULL_SIGMAS, beside: Any = None) -> GelLawChoice:
    """``choice`` made again where the other law's cost is the smaller: each law (its model in ``models``, its
    :func:`law_step` in ``steps``) takes a second step from its first step's end, replayed there with tangents, and
    keeps the smaller of its two predicted ends (its start's replay stays its ``made``, a fit's first).

    One predicted step leaves a law short of its own minimum where its start is far off (the first order of a step
    that lowers the cost tenfold), and the comparison then rewards the law whose step happened to get further: on this
    simulator's card press-slide made with the default law, a concealed gel viscoelasticity and the quick demo's
    hidden materials (modulus x1.5 and friction x0.75 of the start's) the default law's one step ended at 10,423 and
    the Green-strain law's at 7,133; stepped twice, the default law reaches 2,317 (modulus 4.42e5 of the hidden 4.5e5)
    and is chosen (docs/benchmarks_log.md, session 57 "49default"). Both laws are stepped again, so that neither is
    compared at a step the other was given beyond it (the gains a law asks, :func:`beyond_prior`, fall as it nears its
    minimum). A law whose replay at its first step's end diverges keeps its first step. Costs a replay with tangents a
    law where the other law leads; the two replays do not depend on each other, and with ``beside`` (the calibration's
    probe process, :class:`sysid.diagnose.probe_worker.ProbeWorker`) the other law's is made there while this process
    makes the reference law's (:func:`replay_beside`: the same replay). Modifies ``steps`` in place."""
    reference = choice.reference
    other = next(law for law in steps if law != reference)
    if choice.cost[other] >= choice.cost[reference]:
        return choice
    asked = ask_beside(beside, other, models[other], names, steps[other].values, extra)
    trail = {}
    for law in sorted(models, key=lambda name: name == other):  # the reference law's replay here first
        model, first = models[law], steps[law]
        end = float(first.residual @ first.residual)
        made = collected(beside, law, model) if asked and law == other else None
        try:
            again = law_step(model, names, first.values, rows, stepped=stepped, extra=extra, radius=radius, made=made)
        except CalibrationError:  # the first step's end does not replay: that step stands
            trail[law] = [first.start_cost, end]
            continue
        if float(again.residual @ again.residual) < end:
            steps[law] = LawStep(values=again.values, start_cost=first.start_cost, residual=again.residual,
                                 gains=again.gains, made=first.made)
        trail[law] = [first.start_cost, end, again.start_cost, float(again.residual @ again.residual)]
    out = decide(steps, reference, models[reference], choice.channels, gain_prior, null_sigmas)
    return dataclasses.replace(out, restepped=True, steps=trail)


def choose_gel_law(evidence, laws: Sequence[str] = GEL_LAWS, *, dt: float = 0.01, t_max: float | None = None,
                   values: Mapping[str, float] | None = None, channels: Sequence[str] = TACTILE,
                   arch: str = "cpu", simulation: Mapping[str, Any] | None = None,
                   profile: Sequence[str] = PROFILED, step_radius: float = STEP_RADIUS,
                   null_sigmas: float = NULL_SIGMAS, gain_prior: GainPrior | None = GainPrior()) -> GelLawChoice:
    """Step each gel law's :data:`PROFILED` values towards ``evidence`` and choose the law (module docstring): one
    replay with tangents a law.

    Args:
        evidence: a loaded recording (:func:`sysid.evidence.load_evidence`) of a tactile scene.
        laws: ``simulation.gel_element`` names to compare (exactly two); the scene's law (``simulation.gel_element``,
            else the default) is the reference where it is among them, else the first.
        dt, t_max, arch: the replays' step (s), end (s; None: the recording's) and elastic backend.
        values: parameter values of every replay, and the start of each law's step (None: the scene's).
        channels: the compared channels; those the recording lacks are skipped.
        simulation: other overrides of the scene's ``simulation:`` block for every replay (e.g. ``gel_resolution``).
        profile: parameters stepped per law before the comparison, those the scene has (empty: each law compared at
            ``values``).
        step_radius: largest change of each search coordinate in a law's step (:data:`STEP_RADIUS`).
        null_sigmas: the margin in standard deviations of the delta-BIC under the null (0: the smaller cost wins).
        gain_prior: the sensor gains refitted in closed form to every replay within this prior
            (:class:`sysid.gain_profile.GainProfile`); None: the scene's sensor calibration.

    Returns:
        :class:`GelLawChoice`.

    Raises:
        ValueError: not two laws, or none of ``channels`` in the recording.
        ConfigError: an unknown law (the scene's check names it) or parameter.
        CalibrationError: a law's replay that diverged at ``values``.
    """
    if len(laws) != 2:
        raise ValueError(f"choose_gel_law: compare two gel laws, got {list(laws)}")
    values = dict(values or {})
    present = [ch for ch in channels if ch in evidence.channels_present]
    if not present:
        raise ValueError(f"choose_gel_law: the recording has none of the channels {list(channels)}")
    scene_law = (scene_dict_for(evidence, None, simulation).get("simulation") or {}).get(
        "gel_element", SIMULATION_KEYS["gel_element"])
    reference = scene_law if scene_law in laws else laws[0]
    steps: dict[str, LawStep] = {}
    models: dict[str, ObservationModel] = {}
    for law in laws:
        model = ObservationModel(evidence, dt=dt, t_max=t_max, arch=arch, channels=present,
                                 simulation={**dict(simulation or {}), "gel_element": law})
        drive = fit_drive(model)
        model.set_drive_stiffness(drive.replay_stiffness, drive.replay_damping)
        if gain_prior is not None:
            model.gain_profile = _GainsFromRest(model, gain_prior)
        held = {n: v for n, v in values.items() if n not in profile}
        if held:
            model.set_nominal(held)
        names = [n for n in profile if n in model.simulation().parameter_names] or [
            n for n in PROFILED if n in model.simulation().parameter_names][:1]
        compared, rows = compared_rows(model, present)
        steps[law] = law_step(model, names, {n: values[n] for n in names if n in values}, rows,
                              stepped=profile, radius=step_radius)
        models[law] = model
    choice = decide(steps, reference, models[reference], compared, gain_prior, null_sigmas)
    return restep(choice, steps, models, names, rows, gain_prior, stepped=profile, radius=step_radius,
                  null_sigmas=null_sigmas)


def _with_law(model: ObservationModel, law: str) -> ObservationModel:
    """A copy of the tactile ``model`` (its scene, recording, step, channels, backend) whose gel follows ``law``,
    with ``model``'s nominal values, drive, sensor calibration and its profile, marker rest positions, rows left out
    and channel scales."""
    out = ObservationModel(model.evidence, scene=model.scene, dt=model.dt, t_max=model.t_max,
                           channels=list(model.channels), simulation={"gel_element": law}, arch=model.arch)
    changed = {n: v for n in model.simulation().parameter_names
               if (v := model.parameter_value(n)) != out.parameter_value(n)}
    out.set_nominal({**changed, **dict.fromkeys(SENSOR_PARAMETERS, model.nominal_normal_offset)})
    out.set_drive_stiffness(model.drive_stiffness, model.drive_damping)
    out.sensor_calibration, out.marker_rest = model.sensor_calibration, model.marker_rest
    out.row_mask = None if model.row_mask is None else dict(model.row_mask)
    out.sigma_scale = None if model.sigma_scale is None else dict(model.sigma_scale)
    if model.gain_profile is not None:
        out.gain_profile = type(model.gain_profile)(out, model.gain_profile.prior)
    return out


def gel_mesh(scene: Mapping[str, Any]) -> list[int] | None:
    """The gel's tet-box vertices ``[NX, NY, NZ]`` of the first tactile sensor of the plain scene dict ``scene``: its
    ``simulation.gel_resolution``, else :func:`sim_core.scenes.tactile_scene.default_gel_resolution`; None where the
    scene has no tactile sensor."""
    sensors = list((scene.get("sensors") or {}).values())
    if not sensors:
        return None
    stated = (scene.get("simulation") or {}).get("gel_resolution")
    if stated:
        return [int(n) for n in stated]
    return default_gel_resolution(tuple(float(v) for v in sensors[0]["gel_size"]), float(sensors[0]["marker_pitch"]))


def auto_not_applicable(tactile: bool, tack: bool, scene_law: str | None, laws: Sequence[str] = GEL_LAWS, *,
                        mesh: Sequence[int] | None = None, scene_mesh: Sequence[int] | None = None) -> str | None:
    """Why ``--gel-element auto`` keeps the scene's gel law for a recording, or None where it compares ``laws``.

    The comparison needs a tactile sensor's replays (its channels carry the laws' difference), is made without the
    tack's layer (whose stiffness :mod:`sysid.diagnose.tack` fits with the scene's law) and takes the scene's law as its
    reference, so a scene that names a law outside ``laws`` keeps it. It is made on the gel mesh the scene states
    (:func:`gel_mesh`) or a finer one: the laws part at second order in the strain, less than a coarser mesh's own
    error. On the quick demo's recording (this simulator's default law, a concealed gel viscoelasticity, the modulus
    x1.5 off the start) replayed on a ``3,3,2`` mesh (the scene's ``8,6,5``), the default law's start cost is 22x its
    cost on the scene's mesh (4.8e6 against 2.2e5) and the Green-strain law's 1.4x, so the comparison chose the
    Green-strain law by 1.5e6 (23 null sd); on the scene's mesh it keeps the default law (costs 67,311 against
    88,275; docs/benchmarks_log.md, session 57 "49default").

    Args:
        tactile: the recording's scene has a tactile sensor.
        tack: the recording's nominal model has the gel's tack (:func:`sysid.diagnose.tack.nominal_tack` kept it).
        scene_law: the scene's ``simulation.gel_element``, None where it names none.
        laws: the laws compared.
        mesh: the replays' gel mesh ``[NX, NY, NZ]`` (None: the scene's).
        scene_mesh: the mesh the scene states (:func:`gel_mesh` of the scene without the replays' overrides).

    Returns:
        The reason in words, or None.
    """
    if not tactile:
        return "the scene has no tactile sensor"
    if tack:
        return "the recording's nominal model has the gel's tack, whose layer is fitted with the scene's law"
    if scene_law is not None and scene_law not in laws:
        return f"the scene names {scene_law}, which auto does not compare"
    if mesh is not None and scene_mesh is not None and any(int(a) < int(b) for a, b in zip(mesh, scene_mesh)):
        return (f"the replays' gel mesh {list(mesh)} is coarser than the scene's {list(scene_mesh)}: its own error "
                "would outweigh the laws' difference")
    return None


def _reference_law(model: ObservationModel, laws: Sequence[str] = GEL_LAWS) -> str:
    """The law of ``laws`` a comparison at ``model``'s fit start takes as its reference: the scene's law (else the
    simulator's default) where it is among them, else the first."""
    scene_law = (model.scene.get("simulation") or {}).get("gel_element", SIMULATION_KEYS["gel_element"])
    return scene_law if scene_law in laws else laws[0]


def other_law(model: ObservationModel, laws: Sequence[str] = GEL_LAWS) -> str:
    """The law of ``laws`` that :func:`choose_at_start` compares with ``model``'s reference law (:func:`_reference_law`)."""
    reference = _reference_law(model, laws)
    return next(law for law in laws if law != reference)


def choose_at_start(model: ObservationModel, names: Sequence[str], extra: Sequence[str] = (),
                    made: TangentReplay | None = None, *, laws: Sequence[str] = GEL_LAWS,
                    channels: Sequence[str] = TACTILE, gain_prior: GainPrior = GainPrior(),
                    step_radius: float = STEP_RADIUS, null_sigmas: float = NULL_SIGMAS, beside: Any = None
                    ) -> tuple[GelLawChoice, ObservationModel, TangentReplay | None]:
    """The gel law chosen at a fit's start (``thinshell sysid --gel-element auto``): ``model`` replays the scene's law
    (the reference), calibrated (its nominal values, drive, sensor gains and their profile, rows left out); its
    start replay with the tangents of the fit's ``names`` and ``extra`` (:func:`sysid.fit.joint_tangent_names`) is
    ``made`` where the calibration made it (else one is made). The other law's model is ``model``'s with that law
    and the same nominal values, drive, sensor and rows; it makes the same replay with tangents. Each law takes one
    :func:`law_step` of :data:`PROFILED` on its tangents, and :func:`decide` chooses. Added cost over a fit at the
    scene's law: the other law's replay with tangents (which a fit with that law takes as its first evaluation).

    With ``beside`` (the calibration's probe process, :class:`sysid.diagnose.probe_worker.ProbeWorker`) the other
    law's start replay is the one asked of it before (:func:`ask_beside`, ``thinshell sysid`` while this process makes
    the calibration's last replay) where it is this replay (:meth:`BesideReplay.taken`), else asked of it now, beside
    the reference law's (made here where ``made`` is not it: a calibration that kept the scene's stick speed); so is
    the other law's second replay in :func:`restep`. The same replays either way: the choice and values are the same.

    Returns:
        ``(choice, model, made)``: the choice, the chosen law's model and its start replay with tangents (to hand to
        :func:`sysid.fit.fit`; None: none made).

    Raises:
        ValueError: not two laws, or none of ``channels`` among the model's.
        CalibrationError: a law's start replay diverged.
    """
    if len(laws) != 2:
        raise ValueError(f"choose_at_start: compare two gel laws, got {list(laws)}")
    compared, rows = compared_rows(model, channels)
    if not compared:
        raise ValueError(f"choose_at_start: the model replays none of the channels {list(channels)}")
    reference, other = _reference_law(model, laws), other_law(model, laws)
    models = {reference: model, other: _with_law(model, other)}
    first = collected(beside, other, models[other])  # asked while the calibration made its last replay
    asked = first is None and ask_beside(beside, other, models[other], names, {}, extra)  # beside the reference's
    steps = {reference: law_step(model, names, {}, rows, extra=extra, made=made, radius=step_radius)}
    steps[other] = law_step(models[other], names, {}, rows, extra=extra, radius=step_radius,
                            made=collected(beside, other, models[other]) if asked else first)
    choice = decide(steps, reference, model, compared, gain_prior, null_sigmas)
    choice = restep(choice, steps, models, names, rows, gain_prior, extra=extra, radius=step_radius,
                    null_sigmas=null_sigmas, beside=beside)
    return choice, models[choice.chosen], steps[choice.chosen].made
