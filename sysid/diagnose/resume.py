"""Replays that start from the nominal replay's state: the steps before an effect can act are the nominal's.

Bending plasticity changes a sheet only when a dihedral angle leaves its elastic range: the rest
angle ``theta_bar`` moves where ``|theta - theta_bar| > theta_yield`` (:func:`sim_core.energies.
bending.plastic_update`; the yield angle enters nothing else). With a flat rest shape, a replay that
differs from the nominal one only in ``sheet.yield_angle`` therefore takes exactly the nominal
replay's steps until the first step whose largest ``|theta|`` exceeds its yield angle; those steps
are not simulated again (:class:`~sysid.observation.Resume`). On a press-and-slide recording the
sheet reaches half its largest bend about half-way (``latency_s103``: step 198 of 384); as the
early approach steps are the cheap ones, each replay of the plasticity chain saves about a third of
a replay's time.

The signature engine's plasticity refit (:mod:`sysid.diagnose.plasticity_refit`) keeps no nominal
replay's states; its yield-angle search starts each replay from a replay it kept
(:class:`YieldReplays`: the gel's tack carrying the card, or the search's first replay), and the
tack's released replay starts from the carried one before the peel (:func:`resume_before_time`).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from sysid.diagnose.candidates import hinge_angle_history
from sysid.observation import Resume, SimTrace

YIELD_PARAMETER = "sheet.yield_angle"
"""The simulator parameter of bending plasticity (rad; inf: elastic)."""

MARGIN_STEPS = 2
"""Steps taken from the nominal replay stop this many steps before the first one whose largest
dihedral angle exceeds the yield angle (the angles here are computed from the observed sheet points,
the solver's from its own vertex positions: equal up to round-off)."""


def resume_at(trace: SimTrace, k: int) -> Resume | None:
    """The start of a replay that takes the first ``k`` steps of ``trace`` (kept states), None for ``k <= 0``
    (nothing shared: replay from the start)."""
    return Resume(k, trace.states[k], trace.head(k)) if k > 0 else None


class NominalResume:
    """Start of a diagnosis replay from the nominal replay (``ReplayScheduler.resume``).

    Args:
        theta: the nominal parameter set of the nominal replay.
        trace: the nominal replay, with its states (``ObservationModel.simulate(keep_states=True)``).
        angles: the largest dihedral angle per step of ``trace``
            (:func:`sysid.diagnose.candidates.hinge_angle_history`).

    Raises:
        ValueError: the trace has no states, or ``angles`` does not have one value per step.
    """

    def __init__(self, theta: Mapping[str, float], trace: SimTrace, angles: np.ndarray) -> None:
        if trace.states is None:
            raise ValueError("NominalResume: the nominal trace has no states (simulate(keep_states=True))")
        angles = np.asarray(angles, dtype=float)
        if angles.shape != (len(trace.states),):
            raise ValueError(f"NominalResume: {angles.shape} angles for {len(trace.states)} steps")
        self.theta = dict(theta)
        self.trace = trace
        self.angles = angles
        # the criterion holds for a nominal replay whose sheets stay elastic from a flat rest shape
        rest = trace.states[0].hinge_theta_bar
        self.enabled = (not math.isfinite(float(self.theta.get(YIELD_PARAMETER, math.inf)))
                        and all(not np.any(np.asarray(tb)) for tb in rest.values()))

    def start_step(self, params: Mapping[str, float]) -> int:
        """Last step of the nominal replay that the replay of ``params`` shares (0: none).

        Only a set that differs from the nominal one in the yield angle alone (finite, >= 0) shares
        steps, when the nominal sheets are elastic (no finite yield angle) from a flat rest shape: those before the first step whose largest angle exceeds it, less
        :data:`MARGIN_STEPS` (all of them when the angles never exceed it).
        """
        if not self.enabled:
            return 0
        keys = set(params) | set(self.theta)
        if {k for k in keys if params.get(k) != self.theta.get(k)} != {YIELD_PARAMETER}:
            return 0
        return elastic_steps(self.angles, float(params[YIELD_PARAMETER]))

    def __call__(self, params: Mapping[str, float]) -> Resume | None:
        """The :class:`~sysid.observation.Resume` of the replay of ``params``, None: from the start."""
        return resume_at(self.trace, self.start_step(params))


def elastic_steps(angles: np.ndarray, yield_angle: float) -> int:
    """Last step a replay with yield angle ``yield_angle`` shares with the elastic replay whose largest
    dihedral angle per step is ``angles`` (flat rest shape): the steps before the first one whose angle
    exceeds the yield angle, less :data:`MARGIN_STEPS`; every step when none does.

    Args:
        angles: largest ``|theta|`` per step ``(K + 1,)``, rad
            (:func:`sysid.diagnose.candidates.hinge_angle_history` of the elastic replay).
        yield_angle: rad.

    Returns:
        the step (0 when nothing is shared, or the yield angle is not a finite angle >= 0).
    """
    y = float(yield_angle)
    if not (math.isfinite(y) and y >= 0.0):
        return 0
    angles = np.asarray(angles, dtype=float)
    over = np.flatnonzero(angles > y * (1.0 - 1e-9))
    K = angles.size - 1
    first = int(over[0]) if over.size else K + 1 + MARGIN_STEPS
    return max(0, min(K, first - MARGIN_STEPS - 1))


def steps_before(step_times_s: np.ndarray, t_s: float) -> int:
    """Last step of a replay that a setting acting from simulated time ``t_s`` on leaves unchanged
    (the steps whose time is before ``t_s``, less :data:`MARGIN_STEPS`; e.g. the tack's release time
    ``adhesion.release_time``, compared with the step clock to a tolerance).

    Args:
        step_times_s: the replay's step times from its initial state ``(K + 1,)``, s, increasing.
        t_s: simulated time from which the setting acts, s.

    Returns:
        the step (0 when nothing is shared).
    """
    t = np.asarray(step_times_s, dtype=float)
    before = int(np.searchsorted(t, float(t_s), side="left"))  # steps 0..before-1 lie before t_s
    return max(0, min(t.size - 1, before - 1 - MARGIN_STEPS))


def resume_before_time(trace: SimTrace, t_s: float) -> Resume | None:
    """The start, from ``trace`` (kept with its states), of a replay whose parameters differ from its own
    only in a setting that acts from simulated time ``t_s`` on (the tack's release time,
    ``candidate.adhesion.release_time``): the steps before it (:func:`steps_before`).

    Returns:
        the :class:`~sysid.observation.Resume`, or None (nothing shared: replay from the start).

    Raises:
        ValueError: the trace has no states.
    """
    if trace.states is None:
        raise ValueError("resume_before_time: the trace has no states (simulate(keep_states=True))")
    t = (np.asarray(trace.t_ns, dtype=np.int64) - int(trace.t_ns[0])) * 1e-9
    k = steps_before(t, t_s)
    return resume_at(trace, k)


class YieldReplays:
    """The replays of the yield-angle search, each started from a kept replay where it takes the same steps.

    A replay with yield angle ``y`` takes the elastic replay's steps until the first step whose largest
    dihedral angle exceeds ``y`` (flat rest shape; :func:`elastic_steps`), and a kept replay is the
    elastic one for as long as its rest angles stay flat (no plastic update yet). The kept replay is
    ``base`` (the replay with the gel's tack and no release: the search's replays release it at
    ``release_setting``'s time, so they share its steps before that too, :func:`steps_before`), else
    the search's first replay. Each replay after it simulates only the steps after the shared ones
    (:class:`~sysid.observation.Resume`), with the same result to round-off.

    A replay announced by :meth:`prefetch` is made by ``worker`` (another process with the same model) while
    this one makes the replays asked before it; it is taken when it is asked for with that very angle.

    Args:
        model: the calibrated :class:`~sysid.observation.ObservationModel`.
        params: parameters of every replay but the yield angle.
        base: a replay with its states (``simulate(keep_states=True)``) of ``params`` without
            ``release_setting`` and without a yield angle, or None.
        release_setting: the setting of ``params`` that acts only from a simulated time on (s; the
            tack's release time), absent from ``base``'s parameters; None: none.
        worker: the process that makes prefetched replays (``submit(nominal, params, resume)`` and
            ``collect()``, :class:`~sysid.diagnose.probe_worker.ProbeWorker`), or None: every replay here.
        nominal: the model's nominal values (``ObservationModel.set_nominal``: the calibration's parameters),
            set by ``worker`` on its copy of the model.

    Attributes:
        shared_steps: per replay, the steps taken from the kept replay (0: simulated from the start).
        prefetched: the yield angles whose replay ``worker`` made.
    """

    def __init__(self, model: Any, params: Mapping[str, float], base: Any = None,
                 release_setting: str | None = None, worker: Any = None,
                 nominal: Mapping[str, float] | None = None) -> None:
        self.model, self.params = model, dict(params)
        self.worker, self.nominal = worker, dict(nominal or {})
        self._pending: float | None = None
        self.prefetched: list[float] = []
        self.shared_steps: list[int] = []
        self.limit = int(model.step_count)
        if release_setting is not None and release_setting in self.params:
            t = (np.asarray(model.step_times_ns, dtype=np.int64) - int(model.step_times_ns[0])) * 1e-9
            self.limit = steps_before(t, float(self.params[release_setting]))
        self.base, self.angles, self.elastic_until = None, None, 0
        if base is not None:
            self._keep(base)

    def _keep(self, trace: Any) -> None:
        """Keep ``trace`` (with its states) as the start of later replays where it is elastic."""
        states = getattr(trace, "states", None) or []
        flat = 0  # leading states whose rest angles are flat: no plastic update up to them
        while flat < len(states) and not any(np.any(np.asarray(tb)) for tb in states[flat].hinge_theta_bar.values()):
            flat += 1
        angles = hinge_angle_history(self.model, trace.sheet_points) if flat else None
        if angles is not None and angles.shape == (len(states),):
            self.base, self.angles, self.elastic_until = trace, angles, flat - 1

    def _start(self, yield_angle: float) -> int:
        """The last step a replay at ``yield_angle`` takes from the kept replay (0: none kept)."""
        return 0 if self.base is None else min(elastic_steps(self.angles, yield_angle), self.elastic_until, self.limit)

    def prefetch(self, yield_angle: float) -> None:
        """Have ``worker`` make the replay at ``yield_angle`` (rad) now, for a later call with that angle; only
        one resumed from the kept replay (the one this process would make), and one at a time."""
        k = self._start(yield_angle)
        if self.worker is None or self._pending is not None or k <= 0:
            return
        params = {**self.params, YIELD_PARAMETER: float(yield_angle)}
        if self.worker.submit(self.nominal, params, resume_at(self.base, k)):
            self._pending = float(yield_angle)

    def __call__(self, yield_angle: float) -> np.ndarray:
        """The replay at ``yield_angle`` (rad): its sheet points aligned to the recording ``(n, p, 3)`` m.

        Raises:
            SimulationDivergedError: the replay diverged.
        """
        params = {**self.params, YIELD_PARAMETER: float(yield_angle)}
        k = self._start(yield_angle)
        made = None
        if self._pending is not None and self._pending == float(yield_angle):
            self._pending = None
            made = self.worker.collect()  # None: it failed there; made here (and failing as it did)
        if made is not None:
            self.prefetched.append(float(yield_angle))
            trace = made
        elif k > 0:
            trace = self.model.simulate(params, resume=resume_at(self.base, k))
        elif self.base is None:
            trace = self.model.simulate(params, keep_states=True)
            self._keep(trace)
        else:
            trace = self.model.simulate(params)
        self.shared_steps.append(k)
        return np.asarray(self.model.predict(trace)["sheet_points"], dtype=float)
