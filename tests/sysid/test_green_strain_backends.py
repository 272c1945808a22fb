"""A press-slide replayed with the Green-strain gel is the same on the NumPy reference and the Taichi backend.

The bundled reference recording (nominal_s101, MuJoCo 4.0) replayed through a series drive (3,000 N/m, the
engine's; 10 N s/m) with ``simulation.gel_element: green_strain`` until 0.175 s into its slide (the pad pressed
with 4.4 N and dragged 2.8 mm over the card, 3.5 N of friction): once with ``arch="numpy"`` (the reference
:class:`~sim_core.energies.green_strain.reference.GreenStrainSolid` and NumPy contact) and once on ``taichi-cpu``,
where the gel is the fused kernel (:class:`~sim_core.energies.green_strain.fused_kernel.FusedGreenStrainSolid`,
counted). Every observed channel agrees to well within the solver's tolerance (``tol_velocity`` 1e-4 m/s: 1 um a
10 ms step): measured 2e-10 m in the markers, 3e-6 px in the pixels (the markers' difference through the camera, ~1.2e4
px/m) and 6.7e-6 N in the wrench from the contact's onset on, where the drive's first Newton iterate is the
contact's ``x^n`` (:func:`sysid.replay_drive.inertial_start`); 1e-16 m and 5e-13 N with every vertex carried on at
its velocity, which started Newton nearer the answer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sysid.evidence import load_evidence
from sysid.observation import ObservationModel

BAG = Path(__file__).resolve().parents[2] / "bags" / "nominal_s101"
T_MAX = 1.8  # s: the slide begins at 1.625 s


def _replay(evidence, arch: str) -> dict[str, np.ndarray]:
    model = ObservationModel(evidence, dt=0.01, t_max=T_MAX, arch=arch, simulation={"gel_element": "green_strain"})
    model.set_drive_stiffness(3000.0, 10.0)
    return model.predict_raw(model.simulate({"contact.eps_v": 2.4e-3}))


def test_a_green_strain_press_slide_replays_alike_on_both_backends(monkeypatch):
    from sim_core.energies.green_strain.fused_kernel import FusedGreenStrainSolid

    evaluated = []
    evaluate = FusedGreenStrainSolid.evaluate
    monkeypatch.setattr(FusedGreenStrainSolid, "evaluate", lambda self, *a: evaluated.append(1) or evaluate(self, *a))
    evidence = load_evidence(BAG, include_image="auto")
    reference = _replay(evidence, "numpy")
    assert not evaluated
    taichi = _replay(evidence, "cpu")
    assert len(evaluated) > 100  # the gel ran in the fused kernel
    fz, f_xy = reference["wrench"][-1, 2], np.linalg.norm(reference["wrench"][-1, :2])
    assert fz < -3.0 and f_xy > 0.5 * abs(fz)  # N: pressed, and dragged with friction (measured 4.4 and 3.5 N)
    sheared = reference["markers_xyz"][-1, :, :2] - reference["markers_xyz"][0, :, :2]
    assert np.max(np.abs(sheared)) > 3e-4  # m: the gel's markers carried sideways (measured 0.6 mm)
    for channel in ("markers_xyz", "sheet_points"):
        assert np.max(np.abs(taichi[channel] - reference[channel])) < 1e-8, channel  # m
    assert np.max(np.abs(taichi["wrench"] - reference["wrench"])) < 1e-5 * np.max(np.abs(reference["wrench"]))
    assert np.max(np.abs(taichi["markers_uv"] - reference["markers_uv"])) < 1e-4  # px: the markers' 1e-8 m
