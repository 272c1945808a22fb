"""The pressed and sliding gel's marker depth per newton on the bundled reference recording (nominal_s101, MuJoCo 4.0).

Replayed through the effector's fitted drive at the scene's values (the calibration's own replay, without its sensor
gains), the load is the recording's, so the markers' mean depth per newton of normal load over the pressed dwell
(the 0.3 s before the slide) is the gel's compliance in compression. Both engines' contact faces slide out freely
while pressed (the edge markers move out by 0.93 of the depth in both; a Coulomb face that stuck: 0.3), so
that compliance is the frictionless layer's, whose converged value the engine's recording meets (31.9 N/mm here,
28.9-30 converged: docs/known_answers.md). Measured: the default gel 1.04x the recording's stiffness; the two-layer
mesh that was the default until session 51 1.134x (fails) (the calibration then asked for a depth scale of 1.30, now 1.21;
the rest is the slide, where the engine's gel softens and linear elasticity's stiffens: benchmarks log, session 51).
Asserted within 8 %, so the old mesh fails.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sysid.drive_calibration import fit_drive
from sysid.evidence import load_evidence, resample
from sysid.observation import ObservationModel

BAG = Path(__file__).resolve().parents[2] / "bags" / "nominal_s101"
STICK_SPEED = 2.4e-3  # m/s, contact.eps_v as the calibration's secant stage fits it on this recording


def _press_dwell(evidence) -> slice:
    """Marker samples of the 0.3 s before the slide begins (the effector has moved 0.2 mm sideways)."""
    t = evidence.t_ns["markers_xyz"]
    pose = resample(evidence.t_ns["pose"], evidence.pose, t)
    start = int(np.argmax(np.linalg.norm(pose[:, :2] - pose[0, :2], axis=1) > 2.0e-4))
    assert start > 30, "the recording must press before it slides"
    return slice(start - 30, start)


def _stiffness(markers: np.ndarray, fz: np.ndarray, window: slice) -> tuple[float, float]:
    """``(F_z / mean marker depth)`` in N/m over ``window`` and the edge markers' outward motion over the depth."""
    d = markers[window] - markers[0]
    depth = -d[:, :, 2].mean(axis=1)
    r = markers[0, :, :2] - markers[0, :, :2].mean(axis=0)
    rn = np.linalg.norm(r, axis=1)
    edge = rn > 0.007
    outward = (d[:, edge, :2] * (r[edge] / rn[edge, None])).sum(axis=2).mean(axis=1)
    return float(-fz[window].mean() / depth.mean()), float(outward.mean() / depth.mean())


def _replayed(evidence, until: slice, simulation: dict | None):
    """``((recorded markers, recorded F_z), (simulated markers, simulated F_z))`` on the marker samples up to the
    replay's end: the replay through the fitted drive at the scene's values and :data:`STICK_SPEED`, 0.05 s past
    ``until``'s end, the scene's ``simulation`` block overridden by ``simulation``."""
    t_markers = evidence.t_ns["markers_xyz"]
    model = ObservationModel(evidence, dt=0.01, t_max=t_markers[until.stop] / 1e9 + 0.05, arch="cpu",
                             simulation=simulation)
    drive = fit_drive(model)
    model.set_drive_stiffness(drive.replay_stiffness, drive.replay_damping)
    prediction = model.predict_raw(model.simulate({"contact.eps_v": STICK_SPEED}))
    n = prediction["markers_xyz"].shape[0]
    recorded_fz = resample(evidence.t_ns["wrench"], evidence.wrench, t_markers)[:n, 2]
    simulated_fz = resample(evidence.t_ns["wrench"][:prediction["wrench"].shape[0]], prediction["wrench"], t_markers[:n])[:, 2]
    return (evidence.markers_xyz[:n], recorded_fz), (prediction["markers_xyz"], simulated_fz)


def _simulated_over_recorded(simulation: dict | None = None) -> tuple[float, float, float, float]:
    """``(k_recorded, k_simulated, outward_recorded, outward_simulated)`` over the press dwell: stiffness in N/m
    and the edge markers' outward motion over the depth, the scene's ``simulation`` block overridden by
    ``simulation``."""
    evidence = load_evidence(BAG, include_image="auto")
    window = _press_dwell(evidence)
    recorded, simulated = _replayed(evidence, window, simulation)
    k_recorded, out_recorded = _stiffness(*recorded, window)
    k_simulated, out_simulated = _stiffness(*simulated, window)
    return k_recorded, k_simulated, out_recorded, out_simulated


def test_the_pressed_gels_depth_per_newton_is_the_recordings():
    k_recorded, k_simulated, out_recorded, out_simulated = _simulated_over_recorded()
    assert out_recorded > 0.8 and out_simulated > 0.8  # both faces slide out while pressed (Coulomb-stuck: 0.3)
    assert k_recorded == pytest.approx(31.9e3, rel=0.02)
    assert k_simulated / k_recorded == pytest.approx(1.0, abs=0.08)


def test_the_nodal_pressure_gel_meets_the_recordings_depth_per_newton():
    """The same replay with the gel element that does not lock (``simulation.gel_element:
    nodal_pressure_neohookean``) on the same default mesh: measured 1.013x the recording's stiffness, where the
    default Stable Neo-Hookean tets give 1.044x. Asserted within 3 %, which the default element fails."""
    k_recorded, k_simulated, _, out_simulated = _simulated_over_recorded({"gel_element": "nodal_pressure_neohookean"})
    assert out_simulated > 0.8
    assert k_simulated / k_recorded == pytest.approx(1.0, abs=0.03)


def _slide(evidence) -> slice:
    """Marker samples of the slide at speed: after the press dwell, the effector's lateral speed above half its
    peak."""
    t = evidence.t_ns["markers_xyz"]
    pose = resample(evidence.t_ns["pose"], evidence.pose, t)
    lateral = np.linalg.norm(pose[:, :2] - pose[0, :2], axis=1)
    speed = np.gradient(lateral, t / 1e9)
    moving = np.flatnonzero((speed > 0.5 * speed.max()) & (np.arange(t.size) > _press_dwell(evidence).stop))
    return slice(int(moving[0]), int(moving[-1]))


def _slide_over_press(simulation: dict | None) -> tuple[float, float]:
    """``(recorded, simulated)`` ratio of the marker stiffness ``F_z / mean marker depth`` during the slide to the
    press dwell's, the replay through the fitted drive with the scene's ``simulation`` overridden by ``simulation``."""
    evidence = load_evidence(BAG, include_image="auto")
    press, slide = _press_dwell(evidence), _slide(evidence)
    ratios = [_stiffness(*run, slide)[0] / _stiffness(*run, press)[0] for run in _replayed(evidence, slide, simulation)]
    return ratios[0], ratios[1]


def test_the_green_strain_gel_softens_in_the_slide_as_the_recording():
    """The slide's depth gap is the gel's law. At constant depth the recording's markers sink further once the slide
    begins (``F_z / mean z`` during the slide 0.82 of the press dwell's); the default Stable Neo-Hookean gel stiffens
    (1.18: linear elasticity of a finite pad at mu 0.8, docs/known_answers.md) whatever the stick speed (0.6 / 2.4 /
    10 mm/s give slide stiffnesses within 0.3 %). The Green-strain law of the engine that made the recording (Saint
    Venant-Kirchhoff, ``simulation.gel_element: green_strain``), on this project's own default mesh: 0.85. Asserted:
    the Green-strain gel within 5 % of the recording's ratio, the default gel above it by more than 25 %."""
    recorded, green = _slide_over_press({"gel_element": "green_strain"})
    assert recorded == pytest.approx(0.82, abs=0.02)
    assert green / recorded == pytest.approx(1.0, abs=0.05)
    _, default = _slide_over_press(None)
    assert default / recorded > 1.25
