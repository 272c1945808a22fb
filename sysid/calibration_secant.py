"""The calibration's stage for parameters without tangents: the stick regularisation of the
lagged friction, fitted on secants with the sensor calibration projected out.

``contact.eps_v`` (m/s) is the slip speed below which the lagged friction of the simulator's contact
(IPC's smoothed Coulomb friction, Li et al. 2020, "Incremental Potential Contact", sec. 5) treats a
contact as stuck: a sheared gel held by static friction creeps back at about that speed. It is a
regularisation whose physical limit is exact Coulomb stick (``eps_v -> 0``), so a real cell's value is
not on any data sheet, and on a press-and-slide it decides how much shear the gel keeps once the slide
stops. It has no forward sensitivity (its column is a difference), so instead of a fresh difference
column at every step it is fitted by Gauss-Newton on a secant column with Broyden updates
(:func:`sysid.secant.secant_least_squares`): a first probe a factor :data:`SECANT_FIRST_FACTOR` towards
exact stick, then one replay per step. Each replay's residual is taken after the closed-form sensor
calibration fitted to that replay (variable projection, Golub & Pereyra 1973, "The differentiation of
pseudo-inverses and nonlinear least squares problems whose variables separate", SIAM J. Numer. Anal.
10), so a gain or a marker scale does not stand in for the shear the friction keeps.

The stick regularisation acts only on contacts that carry a load and slip. Before the gel's first
contact force the card rests on the table (slip zero) and nothing else touches, so every replay of the
stage takes the same steps up to then (equal to round-off: the stick stiffness enters the Newton
matrix of the resting card's table contacts, not its solution). The stage's first replay keeps its
states, and each later replay starts from its state :data:`CONTACT_MARGIN_STEPS` steps before the
gel's first force (:func:`resume_before_contact`, :class:`~sysid.observation.Resume`). The first
replay's parameters are known before the calibration's start replay ends (the scene values when the
parameter fit takes no step), so it can run beside that replay in another process (``first``,
:mod:`sysid.diagnose.probe_worker`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sim_core.errors import SimulationDivergedError
from sysid.observation import Resume, SimTrace
from sysid.secant import SecantResult, secant_least_squares

SECANT_PARAMETERS = ("contact.eps_v",)
"""Calibration parameters fitted on secants by default (no tangents: a difference column each)."""

SECANT_FIRST_FACTOR = 1.0 / 3.0
"""Factor of the first probe on a secant parameter's scene value, and the largest factor of one
Gauss-Newton step: towards exact stick for ``contact.eps_v`` (its physical limit is 0), one third of
the factor-of-10 range a regularisation is known to (``CALIBRATION_BOUNDS``: 1 % to 10x)."""

SECANT_MIN_GAIN = 5.0e-4
"""Fraction by which the stage's best replay must lower the whitened RMS of its cost for its values to
be taken (:attr:`SecantStage.accepted`): the scale of the replays' numerical noise, as
:data:`sysid.fit.STOP_RMS` (Newton tolerance, contact set changes). A smaller gain is a flat cost,
where the values would follow the noise."""

CONTACT_ONSET_PARAMETERS = ("contact.eps_v",)
"""Secant parameters that change a replay only from the gel's first contact force on (the friction's
stick regularisation: no slipping loaded contact before it), so that the stage's later replays start
from its first replay's state before that force (:func:`resume_before_contact`)."""

CONTACT_MARGIN_STEPS = 2
"""A resumed replay starts this many steps before the last step without gel force (the lagged friction
of a step reads the contacts at its start, so one step would do; two keep a step of margin)."""

SECANT_REPLAYS = 2
"""Default replay budget of the secant stage: the probe and one Gauss-Newton step on its secant. A
count, so that the calibration is the same on any machine; each replay is a plain one (no tangents)."""


@dataclass
class SecantStage:
    """What :func:`secant_calibration` fitted.

    Attributes:
        names: the parameters fitted.
        values: name -> the best value replayed (SI); the start's values when no replay was better.
        start: name -> the start value (SI).
        raw: channel -> the uncalibrated prediction at ``values``.
        result: the :class:`sysid.secant.SecantResult` (search coordinates ``log(value / start)``).
        channel_scale: channel -> the factor on its noise level in the stage's cost: its whitened
            RMS at the start times ``sqrt(n / mean n)`` (``n`` its sample count), so that every
            channel enters the start's cost with the same weight (:func:`secant_calibration`).
        wall_time_s: the stage's wall time, s.
    """

    names: tuple[str, ...]
    values: dict[str, float]
    start: dict[str, float]
    raw: dict[str, np.ndarray]
    result: SecantResult
    channel_scale: dict[str, float]
    wall_time_s: float

    @property
    def accepted(self) -> bool:
        """Whether the best replay lowered the stage's whitened RMS by :data:`SECANT_MIN_GAIN` or more."""
        r = self.result
        return r.cost_initial > 0.0 and 1.0 - math.sqrt(r.cost / r.cost_initial) >= SECANT_MIN_GAIN

    def summary(self) -> dict[str, Any]:
        """JSON-ready: parameters, start values, replays, status, whether the values were taken, cost
        before and after (in the stage's reweighted units) and the channel factors."""
        return {"fitted": list(self.names), "values": dict(self.values), "start": dict(self.start),
                "accepted": self.accepted,
                "replays": int(self.result.evaluations), "status": self.result.status,
                "cost_initial": float(self.result.cost_initial), "cost_final": float(self.result.cost),
                "channel_scale": dict(self.channel_scale), "wall_time_s": float(self.wall_time_s)}


def secant_calibration(model, base: Mapping[str, float], raw0: Mapping[str, np.ndarray],
                       calibrated: Callable[[Mapping[str, np.ndarray]], Mapping[str, np.ndarray]],
                       names: Sequence[str], bounds: Mapping[str, tuple[float, float]],
                       max_replays: int, first: Callable[[], "FirstReplay | None"] | None = None,
                       before: Callable[[Mapping[str, float]], None] | None = None,
                       last: Callable[[Mapping[str, float]], SimTrace] | None = None) -> SecantStage:
    """Fit the positive parameters ``names`` of ``model`` on secants (module docstring).

    Args:
        model: the :class:`~sysid.observation.ObservationModel` (its nominal values are the start).
        base: parameter values every replay of the stage sets (the calibration's other parameters).
        raw0: channel -> the uncalibrated prediction at the start (already replayed).
        calibrated: raw prediction -> calibrated prediction (the sensor calibration fitted to it).
        names: the parameters (positive; searched in ``log(value / start)``).
        bounds: name -> ``(lower, upper)`` SI, containing the start.
        max_replays: replays allowed (the probes included; fewer than ``len(names)``: none made).
        first: called once, at the stage's first replay: that replay made elsewhere (:class:`FirstReplay`,
            e.g. :meth:`sysid.diagnose.probe_worker.ProbeWorker.result`), taken when its parameters are
            bitwise the stage's first ones; None (or a None result): replayed here.
        before: called with each replay's parameters (all of them, SI) before the replay is made (or taken from
            ``first``): a caller may start work that needs them beside it (:func:`sysid.diagnose.signature_engine.prepare`
            starts the kinematic reference at the step's values in its probe process).
        last: makes the stage's last replay of its budget (the ``max_replays``-th, a Gauss-Newton step; not a lone
            probe) from its parameters instead of the stage, from t = 0: ``thinshell sysid`` makes it with the
            tangents its fit's first joint replay needs (:class:`sysid.jacobians.TangentReplay`), since the fit starts
            at that step's values where it is the stage's best (:mod:`sysid.fit_recording`). None: a plain replay
            (resumed where the stage resumes).

    The cost gives every fitted channel one vote: each channel's whitened residual is divided by its
    RMS at the start and by ``sqrt`` of its sample count relative to the mean count. The model's gap,
    not the sensor noise, sets a channel's residual here, and its samples are far from independent
    (the card's points move as one body, the markers with the gel), so neither the noise level nor
    the sample count measures how much a channel tells: weighted by counts, the card's 273 points per
    frame would outvote the 63 markers and the wrench on nominal_s101 (80 % of the cost).

    Returns:
        the :class:`SecantStage`.

    Raises:
        ValueError: a start or bound that is not positive.
    """
    t0 = time.perf_counter()
    names = tuple(names)
    start = {n: float(model.parameter_value(n)) for n in names}
    if any(v <= 0.0 for v in start.values()) or any(bounds[n][0] <= 0.0 for n in names):
        raise ValueError("secant parameters are searched in log space: positive starts and bounds needed "
                         f"({start}, {bounds})")
    lower = np.array([math.log(bounds[n][0] / start[n]) for n in names])
    upper = np.array([math.log(bounds[n][1] / start[n]) for n in names])
    channels = tuple(model.channels)
    data = {ch: model.data(ch) for ch in channels}

    def whitened(raw: Mapping[str, np.ndarray], scale: Mapping[str, float]) -> np.ndarray:
        pred = calibrated(raw)
        return np.concatenate([((data[ch] - pred[ch]) / (model.sigma[ch] * scale[ch]) * model.residual_weight_root(ch))
                               .reshape(-1) for ch in channels])

    unit = {ch: 1.0 for ch in channels}
    r_unit = whitened(raw0, unit)
    scale, offset = {}, 0
    sizes = [data[ch].size for ch in channels if data[ch].size]
    reference = float(np.mean(sizes)) if sizes else 1.0
    for ch in channels:
        n = data[ch].size
        rms = float(np.sqrt(np.mean(r_unit[offset:offset + n] ** 2))) if n else 1.0
        scale[ch] = max(rms, 1e-12) * math.sqrt(n / reference) if n else 1.0
        offset += n
    r0 = whitened(raw0, scale)
    raws: dict[bytes, dict[str, np.ndarray]] = {np.zeros(len(names)).tobytes(): dict(raw0)}
    # a later replay resumes from the first one's states: none left to resume where the only later one is ``last``'s
    shared = set(names) <= set(CONTACT_ONSET_PARAMETERS) and max_replays > (2 if last is not None else 1)
    count = [0]  # replays made so far
    kept: list[Resume | None] = []  # the later replays' start, from the first replay (None: none)

    def residual(u: np.ndarray) -> np.ndarray | None:
        values = {**dict(base), **{n: start[n] * math.exp(float(x)) for n, x in zip(names, u)}}
        if before is not None:
            before(values)
        count[0] += 1
        try:
            trace = (last(values) if last is not None and count[0] == max_replays > 1
                     else _replay(model, values, shared, kept, first))
            raw = model.predict_raw(trace)
        except SimulationDivergedError:
            return None
        raws[np.asarray(u, dtype=float).tobytes()] = raw
        return whitened(raw, scale)

    steps = np.full(len(names), math.log(SECANT_FIRST_FACTOR))
    result = secant_least_squares(residual, np.zeros(len(names)), r0, steps, lower, upper, max_replays,
                                  max_step=np.abs(steps))
    values = {n: start[n] * math.exp(float(x)) for n, x in zip(names, result.u)}
    return SecantStage(names, values, start, raws[np.asarray(result.u, dtype=float).tobytes()], result, scale,
                       time.perf_counter() - t0)


@dataclass(frozen=True)
class FirstReplay:
    """The secant stage's first replay, made before the stage (e.g. in another process).

    Attributes:
        values: the parameters it was replayed with (SI; all of them, as the stage passes them).
        trace: the replay, without states.
        resume: the start of the stage's later replays (:func:`resume_before_contact`), or None.
    """

    values: dict[str, float]
    trace: SimTrace
    resume: Resume | None


def first_probe_values(model, base: Mapping[str, float], names: Sequence[str]) -> dict[str, float]:
    """The parameters of :func:`secant_calibration`'s first replay when its first probe stays within the
    bounds: ``base``, the first of ``names`` at :data:`SECANT_FIRST_FACTOR` times its nominal value and
    the others at theirs (the stage probes one coordinate at a time), computed as the stage does."""
    steps = [math.log(SECANT_FIRST_FACTOR)] + [0.0] * (len(names) - 1)
    return {**dict(base), **{n: float(model.parameter_value(n)) * math.exp(x) for n, x in zip(names, steps)}}


def resume_before_contact(trace: SimTrace) -> Resume | None:
    """The start, from ``trace`` (kept with its states), of a replay whose parameters differ from its own
    only in :data:`CONTACT_ONSET_PARAMETERS`: its state :data:`CONTACT_MARGIN_STEPS` steps before the
    last step without gel force (module docstring).

    Args:
        trace: a replay with its states (``ObservationModel.simulate(keep_states=True)``); its wrench
            ``(K + 1, 6)`` is exactly zero while no contact acts on the gel.

    Returns:
        the :class:`~sysid.observation.Resume`, or None (the gel is loaded too early: replay from the start).

    Raises:
        ValueError: the trace has no states.
    """
    if trace.states is None:
        raise ValueError("resume_before_contact: the trace has no states (simulate(keep_states=True))")
    loaded = np.flatnonzero(np.any(np.asarray(trace.wrench) != 0.0, axis=1))
    first = int(loaded[0]) if loaded.size else len(trace.states)
    k = min(len(trace.states) - 1, first - 1 - CONTACT_MARGIN_STEPS)
    return Resume(k, trace.states[k], trace.head(k)) if k > 0 else None


def _replay(model, values: Mapping[str, float], shared: bool, kept: list,
            first: Callable[[], FirstReplay | None] | None) -> SimTrace:
    """One replay of the stage: ``first()`` when it was made with ``values``; else resumed from the kept
    start when ``shared`` and one is kept; else from t = 0 (keeping its states for the later replays
    when ``shared`` and this is the stage's first replay)."""
    made = first() if first is not None and not kept else None
    if made is not None and made.values == dict(values):
        kept.append(made.resume if shared else None)
        return made.trace
    if kept:
        return model.simulate(values, resume=kept[0]) if kept[0] is not None else model.simulate(values)
    if not shared:
        return model.simulate(values)
    trace = model.simulate(values, keep_states=True)
    kept.append(resume_before_contact(trace))
    return dataclasses.replace(trace, states=None)
