"""Normal load against depth of rigid indenters on a gel block bonded to a rigid base (known answers).

The project's gel (Stable Neo-Hookean tets, linearised to E, nu) under the penalty contact of sim_core,
at small strain (depth / contact radius <= 0.14):

- **Sphere, Hertz on a bonded layer.** ``F = 4/3 E* sqrt(R) d^(3/2)`` (Johnson, *Contact Mechanics*,
  1985, eq. 4.22-4.23) times Dimitriadis et al.'s bonded-layer factor in ``chi = sqrt(R d) / h``
  (Biophys. J. 82, 2798-2810, 2002, eq. 11-13; :func:`sim_core.indentation.bonded_layer_sphere_factor`).
- **Flat punch, Sneddon.** ``F = 2 a E* d`` (Sneddon 1965; Johnson eq. 3.38) times the first-order
  bonded-layer factor ``1 - 2 alpha_0 / pi (a / h)`` (:func:`sim_core.indentation.bonded_layer_punch_factor`):
  only the formulas are checked here; the punch itself is :mod:`tests.sim_core.test_known_answers_flat_punch`
  (a gel whose node rings follow the rim: a structured grid read 1.11 of it at a / h = 5).

The 3 % target needs a / h >= 5-7: on the 30 mm block at h 0.1 mm (85.7k DoF, 180 s) the sphere's
F / (F_Hertz x layer factor) is 1.022 / 1.019; in CI the 8 mm block at h 0.12 mm gives 1.036 / 1.030 and
is asserted within 4 % with the error falling from h 0.2 mm (docs/known_answers.md, benchmarks log
session 50). The thickness law is checked separately: two blocks of the same surface mesh, 2 and 8 mm
thick, differ by the layer factor (the discretisation error is common to both).
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core import indentation as ind
from sim_core.mesh.tet import box_face_vertices
from sim_core.model import ContactSettings
from sim_core.solver import SolverConfig

E, NU = 3e5, 0.3
TIGHT = SolverConfig(tol_velocity=1e-9, max_iterations=100, projection="abs")
"""Newton stop at max |dx| < 1 nm (dt 1 s): 0.01 % of the smallest depth here."""


def _sphere_sweep(thickness: float, h: float = 2e-4, radius: float = 5e-3,
                  d_max: float = 1e-4) -> tuple[ind.IndentationResult, float]:
    a = np.sqrt(radius * d_max)
    gel = ind.graded_gel_block(6e-3, thickness, h, 1.3 * a, 0.6 * a, 1.6)
    eps = 1e-2 * d_max
    contact = ContactSettings(stiffness=1e4, eps=eps, eps_v=1e-3, self_contact=False, candidate_margin=d_max + eps)
    sphere = ind.RigidSphere(np.array([0.0, 0.0, radius]), radius)
    setup = ind.build_indentation(gel, box_face_vertices(gel, 2, "min"), sphere, E, NU, contact, indenter_lift=eps,
                                  solver_config=TIGHT)
    return ind.run_depth_sweep(setup, [0.5 * d_max, d_max], 0.5 * d_max), radius + eps


@pytest.fixture(scope="module")
def sphere_layers():
    """Exact sphere R 5 mm to 0.05 / 0.1 mm (a = 0.50 / 0.71 mm) into 12 x 12 mm blocks 2 and 8 mm thick
    (chi = 0.25-0.35 and 0.06-0.09), h 0.2 mm near the contact."""
    return {t: _sphere_sweep(t) for t in (2e-3, 8e-3)}


def test_bonded_layer_factor_explains_the_thickness_dependence(sphere_layers):
    """The thin block presses 1.20 / 1.34x harder than the thick one; divided by Dimitriadis' factor both give
    the same F / F_Hertz within 3.5 % (measured: 0.2 % / 2.5 % at 0.05 / 0.1 mm; corrected ratios 1.070 /
    1.073 thin, 1.068 / 1.047 thick). Without the factor they differ by 20-34 %, so a wrong layer law (or a
    base that is not bonded) fails."""
    corrected = {}
    for t, (res, radius) in sphere_layers.items():
        raw = res.force / ind.hertz_force(res.depth, radius, E, NU)
        corrected[t] = raw / ind.bonded_layer_sphere_factor(res.depth, radius, t, NU)
    thin, thick = sphere_layers[2e-3][0].force, sphere_layers[8e-3][0].force
    assert np.all(thin / thick > 1.15), thin / thick
    np.testing.assert_allclose(corrected[2e-3] / corrected[8e-3], 1.0, atol=0.035)


def test_sphere_on_a_bonded_layer_matches_hertz_times_the_layer_factor(sphere_layers):
    """F / (F_Hertz x layer factor) on the CI mesh (a / h = 2.5-3.5) is within 1.00-1.12 (measured 1.068 /
    1.047: the linear tets' stiffness, which falls to 1.022 / 1.019 at a / h = 5-7 on the 30 mm block,
    docs/known_answers.md), and F grows as d^(3/2) (exponent within 0.06; measured 1.507)."""
    res, radius = sphere_layers[8e-3]
    ratio = res.force / (ind.hertz_force(res.depth, radius, E, NU)
                         * ind.bonded_layer_sphere_factor(res.depth, radius, 8e-3, NU))
    assert np.all((ratio > 1.0) & (ratio < 1.12)), ratio
    exponent = np.log(res.force[1] / res.force[0]) / np.log(res.depth[1] / res.depth[0])
    assert exponent == pytest.approx(1.5, abs=0.06)


def _corrected(res: ind.IndentationResult, radius: float, thickness: float) -> np.ndarray:
    return res.force / (ind.hertz_force(res.depth, radius, E, NU)
                        * ind.bonded_layer_sphere_factor(res.depth, radius, thickness, NU))


def test_hertz_error_falls_with_the_mesh_to_four_percent(sphere_layers):
    """Refining the 8 mm block from h 0.2 to 0.12 mm near the contact (a / h 4.2-5.9, 30.3k DoF) brings F /
    (F_Hertz x layer factor) from 1.068 / 1.047 to 1.036 / 1.030: within 4 %, the error smaller at both
    depths. The sequence h 0.3 / 0.25 / 0.2 / 0.15 / 0.12 / 0.1 mm gives 1.084 / 1.061 / 1.047 / 1.038 /
    1.030 / 1.031 at 0.1 mm (benchmarks log): the 3 % target needs h <= 0.12 mm here, and the 30 mm block
    (no lateral edge within 20 a) reaches 1.022 / 1.019 at h 0.1 mm."""
    coarse = _corrected(*sphere_layers[8e-3], 8e-3)
    res, radius = _sphere_sweep(8e-3, h=1.2e-4)
    fine = _corrected(res, radius, 8e-3)
    assert np.all(fine < coarse), (fine, coarse)
    assert np.all(np.abs(fine - 1.0) < 0.04), fine


def test_layer_factors_reduce_to_the_half_space_and_match_hand_values():
    """Thick layers give 1; at nu = 0.3 the first-order coefficient -2 alpha_0 / pi is 0.8806 (Dimitriadis
    et al. 2002, eq. 12: alpha_0 = -1.3832); Sneddon's punch is 2 a E* d."""
    a0, _ = ind.bonded_layer_coefficients(0.3)
    assert a0 == pytest.approx(-(1.2876 - 1.4678 * 0.3 + 1.3442 * 0.09) / 0.7, rel=1e-12)
    assert -2.0 * a0 / np.pi == pytest.approx(0.8806, abs=1e-4)
    assert ind.bonded_layer_sphere_factor(1e-4, 5e-3, 1e3, 0.3) == pytest.approx(1.0, abs=1e-5)
    assert ind.bonded_layer_punch_factor(1e-3, 1e3, 0.3) == pytest.approx(1.0, abs=1e-5)
    chi = np.sqrt(5e-3 * 1e-4) / 8e-3
    assert ind.bonded_layer_sphere_factor(1e-4, 5e-3, 8e-3, 0.3) == pytest.approx(1.0 + 0.8806 * chi, abs=0.01)
    assert ind.flat_punch_force(2e-5, 1e-3, 3e5, 0.3) == pytest.approx(2e-3 * 3e5 / 0.91 * 2e-5, rel=1e-12)
