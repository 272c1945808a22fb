"""The tactile gel's lateral stiffness at the scene's default mesh is the layer's shear stiffness.

With the effector's drive in the replay the force is the recording's, and the markers' lateral motion is the
lateral load over the gel's shear stiffness. A flat rigid plate pressed into the reference scene's gel pad
(18.6 x 14.3 x 4 mm, E = 3e5 Pa, nu = 0.45, back face fixed) and then slid while it sticks (friction 0.8, stick
regularisation 1 um) shears the layer between two rigid faces: the stiffness is ``G A / t`` (simple shear,
``G = E / (2 (1 + nu))``; the layer's bending at this width adds under 2 %: Gent and Meinecke, "Compression,
bending, and shear of bonded rubber blocks", Polym. Eng. Sci. 10(1), 1970). So the lateral marker gap against
another engine (docs/benchmarks_log.md, 2026-11-27, session 50, 49drive) is not our gel's shear.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.control import Control
from sim_core.indentation import build_indentation
from sim_core.mesh.sheet import TriMesh
from sim_core.mesh.tet import tet_box
from sim_core.model import ContactSettings
from sim_core.scenes.tactile_scene import default_gel_resolution

GEL = (0.0186, 0.0143, 0.004)  # m, the reference scenes' gel_size
E, NU = 3.0e5, 0.45
DEFAULT_RESOLUTION = tuple(default_gel_resolution(GEL, 0.002))  # the scene's default mesh at a 2 mm marker pitch


def test_the_default_gel_shears_as_a_bonded_layer():
    gx, gy, gt = GEL
    gel = tet_box(GEL, DEFAULT_RESOLUTION, (-gx / 2, -gy / 2, -gt))  # contact face z = 0, back face z = -t
    half = 0.03
    plate = TriMesh(np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]]),
                    np.array([[0, 1, 2], [0, 2, 3]]))
    setup = build_indentation(gel, np.flatnonzero(np.isclose(gel.x[:, 2], -gt)), plate, E, NU,
                              ContactSettings(stiffness=2.0e5, eps=4.0e-4, eps_v=1.0e-6, self_contact=False),
                              friction=0.8, indenter_lift=None, indenter_vertices_vs_gel=False)
    sim = setup.simulation(1.0)  # dt = 1 s: each step a static equilibrium
    plate_body = setup.model.bodies[setup.indenter_body]
    top = np.flatnonzero(np.isclose(gel.x[:, 2], 0.0))
    marked = top[(np.abs(gel.x[top, 0]) <= 0.008 + 1e-9) & (np.abs(gel.x[top, 1]) <= 0.006 + 1e-9)]  # the 9 x 7 markers' area
    x0 = sim.state.x[:len(gel.x)].copy()
    pose0 = sim.state.effector_pose[setup.effector].copy()
    control = Control()

    def move(dz: float, dx: float) -> None:
        pose = pose0.copy()
        pose[2] -= dz
        pose[0] += dx
        control.effector_pose_target[setup.effector] = pose
        sim.step(control)

    for k in range(1, 5):
        move(0.5e-4 * k, 0.0)  # 0.2 mm into the gel
    for k in range(1, 7):
        move(2.0e-4, 0.5e-4 * k)  # then 0.3 mm across it, stuck
    force = sim.state.contact_force[plate_body.vertex_start:plate_body.vertex_stop].sum(axis=0)
    shear = float(np.mean(sim.state.x[marked, 0] - x0[marked, 0]))
    assert shear == pytest.approx(3.0e-4, rel=0.02)  # the face sticks to the plate
    shear_modulus = E / (2.0 * (1.0 + NU))
    assert abs(force[0]) / shear == pytest.approx(shear_modulus * gx * gy / gt, rel=0.05)
