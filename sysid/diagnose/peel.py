"""The peel of a tacky gel read from a recording: when the recorded sheet leaves the gel's face.

A gel whose tack carries a card up (candidate ``adhesion``, :mod:`sim_core.candidates.adhesion`)
lets it go at some time of the lift: the card drops away from the face, or the gel moves off
while the card stays. The simulator's bonds break only past their release opening, so a card that
hangs from a gel that stops in the air is carried to the end; the recording tells when the real
bonds let go. This module reads that time from the recorded sheet points and the gel's contact
face of a replay in which the gel carries the card (its face follows the commanded pose):

    gap(t) = min_z(face(t)) - max_z(sheet points of the recording under the face at t),

"under the face": the points whose ``(x, y)`` lie in the face's bounding box. The gel touches the
sheet where ``gap`` is below the bond's release opening (``adhesion.release``; 1.25 mm by default,
about 25 times the sheet-point noise of the reference recordings); the peel is the last row in
touch after the first touch, before the first row where the recorded sheet is farther than that
from the face. A gel that never carries the card peels as soon as it lifts off, so bonds released
at that time carry nothing (the same replay as without them).
"""

from __future__ import annotations

import numpy as np


def gel_face_vertices(sim_model) -> np.ndarray:
    """Global indices of the gels' contact-face vertices (every tactile sensor's ``contact_triangles``).

    Args:
        sim_model: ``sim_core`` Model (``sensors`` with ``contact_triangles``).

    Returns:
        sorted int64 indices ``(v,)`` (empty without a tactile sensor).
    """
    parts = [np.unique(np.asarray(s.contact_triangles, dtype=np.int64)) for s in sim_model.sensors.values()
             if getattr(s, "contact_triangles", None) is not None]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


def points_under(sheet: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Which sheet points ``(p, 3)`` m lie under a gel face ``(v, 3)`` m (inside its x-y bounding box): bool ``(p,)``."""
    lo, hi = face[:, :2].min(axis=0), face[:, :2].max(axis=0)
    return np.all((sheet[:, :2] >= lo) & (sheet[:, :2] <= hi), axis=1)


def face_gap(sheet: np.ndarray, face: np.ndarray) -> float:
    """Vertical gap (m) between a gel face and the recorded sheet points under it.

    Args:
        sheet: recorded sheet points ``(p, 3)`` m, world (z up).
        face: the gel's contact-face vertices ``(v, 3)`` m, world.

    Returns:
        ``min z(face) - max z(points under the face)``; ``inf`` when no point lies under it.
    """
    under = points_under(sheet, face)
    if not under.any():
        return float("inf")
    return float(face[:, 2].min() - sheet[under, 2].max())


def peel_time(t_sheet: np.ndarray, sheet: np.ndarray, t_face: np.ndarray, face: np.ndarray,
              opening: float) -> float | None:
    """Time at which the recorded sheet leaves the gel (module docstring).

    Args:
        t_sheet: recorded sheet rows' times ``(n,)`` s.
        sheet: recorded sheet points ``(n, p, 3)`` m.
        t_face: replay step times ``(K + 1,)`` s, same clock, increasing.
        face: the gel's contact face per step ``(K + 1, v, 3)`` m (each row taken at the step nearest
            the sheet row).
        opening: largest gap (m, > 0) at which the gel still holds the sheet (the bond's release opening).

    Returns:
        the time (s) of the last row in touch before the first row apart that follows a touch;
        None when the gel never touches the sheet or never leaves it.

    Raises:
        ValueError: ``opening`` not > 0, or mismatched shapes.
    """
    if not opening > 0.0:
        raise ValueError(f"peel_time: opening must be > 0 m, got {opening}")
    t_sheet, t_face = np.asarray(t_sheet, dtype=float), np.asarray(t_face, dtype=float)
    if sheet.shape[0] != t_sheet.shape[0] or face.shape[0] != t_face.shape[0]:
        raise ValueError(f"peel_time: {sheet.shape[0]} sheet rows for {t_sheet.shape[0]} times, "
                         f"{face.shape[0]} face rows for {t_face.shape[0]} times")
    j = np.clip(np.searchsorted(t_face, t_sheet), 0, t_face.size - 1)
    prev = np.clip(j - 1, 0, t_face.size - 1)
    j = np.where(np.abs(t_face[prev] - t_sheet) < np.abs(t_face[j] - t_sheet), prev, j)
    touch = np.array([face_gap(sheet[k], face[j[k]]) < opening for k in range(t_sheet.size)])
    first = np.flatnonzero(touch)
    if first.size == 0:
        return None
    apart = np.flatnonzero(~touch[first[0]:])
    if apart.size == 0:
        return None
    return float(t_sheet[first[0] + apart[0] - 1])


ADHESION_PARAMETER = "candidate.adhesion"
"""The simulator parameter of the gel's tack: bond strength per pair, N."""

RELEASE_TIME_SETTING = "candidate.adhesion.release_time"
"""The simulator setting of the time (s, simulation clock) from which every adhesion bond is broken."""


def tack_with_peel(model, params, t_sheet: np.ndarray, sheet: np.ndarray, beta: float,
                   keep_carried: bool = False) -> dict | None:
    """Simulator parameters of a gel that carries the card with its tack and lets go at the recorded peel.

    One replay with the bonds on (``candidate.adhesion = beta``, no release time) keeps its vertex
    positions (its states with ``keep_carried``); the gel's contact face of that replay and the
    recorded sheet give the peel time (:func:`peel_time`, at the bonds' release opening); the bonds
    are then set to break at it. A replay with the release takes that replay's steps before the peel
    unchanged, so it can start from its states (:func:`sysid.diagnose.resume.resume_before_time`).

    Args:
        model: the calibrated ``sysid.observation.ObservationModel`` (``simulate``, ``evidence``,
            ``simulation()``).
        params: its calibrated simulator parameters.
        t_sheet: recorded sheet rows' times ``(n,)`` s from the recording's start.
        sheet: recorded sheet points ``(n, p, 3)`` m.
        beta: bond strength per pair, N (> 0).
        keep_carried: also return the replay with the bonds and no release, with its states.

    Returns:
        ``{"params": the calibrated ones with the tack and its release time, "peel_s": recording
        time of the peel, "beta": beta}``, and with ``keep_carried`` ``"carried"``: that replay
        (``sysid.observation.SimTrace`` with ``states``); None when the simulator has no adhesion
        candidate, the scene no gel face, or the recorded sheet never touches or never leaves the gel.

    Raises:
        SimulationDivergedError: the replay with the bonds diverged.
    """
    from sim_core.candidates.hook import CandidateHook
    from sim_core.errors import ConfigError

    sim = model.simulation()
    try:
        sim.get_parameter(ADHESION_PARAMETER)
    except ConfigError:
        return None
    face_idx = gel_face_vertices(sim.model)
    if face_idx.size == 0 or not beta > 0.0:
        return None
    carried = {**dict(params), ADHESION_PARAMETER: float(beta)}
    trace = model.simulate(carried, keep_positions=not keep_carried, keep_states=keep_carried)
    t_face = (np.asarray(trace.t_ns, dtype=np.int64) - int(model.evidence.start_ns)) * 1e-9
    opening = CandidateHook({"adhesion": float(beta)}).setting("adhesion.release")
    x = np.stack([s.x for s in trace.states]) if keep_carried else np.asarray(trace.positions)
    face = x[:, face_idx]
    t_peel = peel_time(t_sheet, sheet, t_face, face, opening)
    if t_peel is None:
        return None
    out = {"params": {**carried, RELEASE_TIME_SETTING: max(t_peel - float(t_face[0]), 1e-9)},
           "peel_s": t_peel, "beta": float(beta)}
    return {**out, "carried": trace} if keep_carried else out
