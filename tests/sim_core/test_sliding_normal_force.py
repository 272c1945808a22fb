"""Normal force of a gel pad sliding at constant depth on a rigid table (known solutions).

The reference recordings' press-and-slide replays show the normal force rising when the pad starts
sliding at constant depth. Three exact statements separate a defect from physics:

- without friction the problem is invariant under translation along the table, so the normal force
  at constant depth cannot change when the pad slides (any change would be a defect of the contact
  or of the kinematic drive);
- reversing the slide reverses the friction and leaves the (symmetric) pad's normal force unchanged,
  so the change is even in ``mu``: a change that grows linearly in ``mu`` (lagged-friction normal
  component, a tilted tangent basis) would be a defect;
- at small strain the whole change is linear elasticity of the finite block under the friction
  traction ``mu p`` (Johnson, *Contact Mechanics*, 1985, ch. 7: the normal-tangential coupling; on a
  half space ``beta = (1 - 2 nu) / (2 (1 - nu))``, 0.09 at nu = 0.45, and the load at a given depth
  changes only at order ``(beta mu)^2``; a block 4 mm thick and 18.6 mm long couples far more). Its
  answer is computed independently by :mod:`tests.support.linear_fe` (P1 linear elasticity, Hooke's
  law, the same tets, nothing of sim_core's energies, contact or friction): the steady slide's normal
  force over the frictionless one is 1.013 / 1.040 / 1.137 at mu = 0.2 / 0.4 / 0.8 on this 6 x 5 x 3
  pad, and the simulator (penalty contact, lagged IPC friction, Stable Neo-Hookean gel) gives
  1.013 / 1.039 / 1.144 (session 50, docs/known_answers.md).

So the rise of the pad's normal force with sliding friction is the linear elasticity of a finite pad
(+14 % at mu = 0.8, +4 % at 0.4 for nu = 0.45; weaker at nu = 0.3), present at any depth (it is not
the hyperelastic Poynting effect, which vanishes at small strain: the rise is 11.5 / 10.0 / 6.4 % at
0.18 / 0.25 / 0.45 mm of gel compression), and not a defect of the contact or friction.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from sim_core.control import Control
from sim_core.scenes import load_scene
from sim_core.scenes.scene_file import load_yaml
from sim_core.simulation import Simulation
from tests.support.linear_fe import linear_stiffness, sliding_block_reaction

PRESS_SLIDE = Path(__file__).resolve().parents[2] / "config" / "scenes" / "press_slide.yaml"


def _scene(mu: float) -> dict:
    return {
        "version": 1, "name": "gel_on_table", "dt": 0.01, "gravity": [0.0, 0.0, 0.0],
        "table": {"height": 0.0, "friction": mu},
        # the card lies far from the pad: the gel presses the bare table
        "sheet": {"size": [0.02, 0.02], "resolution": [3, 3], "thickness": 0.0003, "density": 700.0,
                  "origin": [0.5, 0.0, 0.00015], "clamped_edge": "x0",
                  "material": {"youngs_modulus": 3.0e9, "poisson_ratio": 0.3, "bending_stiffness": 0.0074}},
        "sensors": {"tactile": {"effector": "ee", "gel_size": [0.0186, 0.0143, 0.004],
                                "gel_material": {"youngs_modulus": 3.0e5, "poisson_ratio": 0.45, "density": 1100.0},
                                "friction": 0.8, "marker_grid": [3, 3], "marker_pitch": 0.004,
                                "camera": {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "width": 320,
                                           "height": 240, "distance": 0.025}}},
        "effectors": {"ee": {"initial_pose": [0.0, 0.0, 0.001, 1.0, 0.0, 0.0, 0.0]}},
        "simulation": {"gel_resolution": [6, 5, 3]},
    }


@lru_cache(maxsize=None)
def _press_then_slide(mu: float, depth: float = 3.0e-4) -> tuple[float, float]:
    """Normal force (N) pressed at rest ``depth`` (m) below the table's top, and sliding at the same
    depth (steady state)."""
    sim = Simulation(load_scene(_scene(mu)), dt=0.01)
    path = [(0.0, 0.001 - (0.001 + depth) * k / 20) for k in range(1, 21)] + [(0.0, -depth)] * 10
    path += [(0.01 * k / 40, -depth) for k in range(1, 41)]
    forces = []
    for x, z in path:
        sim.step(Control({"ee": np.array([x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}))
        forces.append(-sim.observe().tactile["tactile"].wrench[2])
    return float(forces[29]), float(np.mean(forces[-10:]))


def test_frictionless_sliding_keeps_the_normal_force():
    pressed, sliding = _press_then_slide(0.0)
    assert pressed > 1.0
    assert sliding == pytest.approx(pressed, rel=1e-5)


def test_friction_changes_the_normal_force_at_second_order_only():
    base, _ = _press_then_slide(0.0)
    _, low = _press_then_slide(0.3)
    _, high = _press_then_slide(0.8)
    rise_low, rise_high = low / base - 1.0, high / base - 1.0
    assert 0.0 < rise_low < 0.05
    # quadratic in mu: (0.8 / 0.3)^2 = 7.1; a first-order defect would give 2.7
    assert 4.5 < rise_high / rise_low < 11.0


def test_sliding_rise_of_the_normal_force_is_the_linear_elasticity_of_the_pad():
    """The steady slide's normal force over the frictionless one equals linear elasticity's answer for
    the same pad (independent P1 solver, :mod:`tests.support.linear_fe`) within 1.5 % of the normal
    force at mu = 0.4 and 0.8 (measured: -0.0 % / +0.6 %) at 0.1 mm below the table's top (0.25 mm of gel
    compression with the contact offset, 6 % strain; at 0.3 mm, 11 % strain, the finite strain adds 2 %);
    the linear answer itself is a rise of 4 % / 14 %, so a simulator without the coupling, or with a
    defect of the size of the rise, fails."""
    frictionless = _linear_reaction(0.0)[2]
    base, _ = _press_then_slide(0.0, 1e-4)
    for mu in (0.4, 0.8):
        reaction = _linear_reaction(mu)
        assert reaction[0] == pytest.approx(-mu * reaction[2], rel=1e-9)  # full slip: Coulomb everywhere
        linear = reaction[2] / frictionless
        _, sliding = _press_then_slide(mu, 1e-4)
        assert linear > 1.0 + 0.05 * mu**2
        assert sliding / base == pytest.approx(linear, abs=0.015), (mu, sliding / base, linear)


def _linear_reaction(mu: float) -> np.ndarray:
    """Linear elasticity's steady-slide reaction (N, shape (3,)) of the scene's 6 x 5 x 3 pad pressed 0.1 mm
    (:func:`tests.support.linear_fe.sliding_block_reaction`)."""
    model = load_scene(_scene(0.0))
    gel = model.bodies["gel"]
    x = model.x_rest[gel.vertex_start:gel.vertex_stop]
    stiffness = linear_stiffness(x, gel.tets - gel.vertex_start, 3.0e5, 0.45)
    top = np.flatnonzero(np.isclose(x[:, 2], x[:, 2].max()))
    bottom = np.flatnonzero(np.isclose(x[:, 2], x[:, 2].min()))
    return sliding_block_reaction(stiffness, top, bottom, 1e-4, mu)


def _linear_rise(mu: float) -> float:
    """Linear elasticity's steady-slide normal force over the frictionless one for the 6 x 5 x 3 pad."""
    return _linear_reaction(mu)[2] / _linear_reaction(0.0)[2]


@lru_cache(maxsize=None)
def _card_press_then_slide(mu: float, direction: float) -> tuple[float, float, float]:
    """press_slide.yaml's clamped card under the same pad (gel-card friction ``mu``), pressed 0.1 mm
    into the card's top and slid 10 mm along ``direction`` (+1: away from the clamp at x = 0): normal
    force pressed and sliding (N), and the card's highest point after the slide (m)."""
    scene = load_yaml(PRESS_SLIDE.read_text())
    scene["sensors"]["tactile"]["friction"] = mu
    scene["simulation"] = {"gel_resolution": [6, 5, 3]}
    top, depth, x0 = 3e-4, 1e-4, 0.06
    scene["effectors"]["ee"]["initial_pose"] = [x0, 0.0, top + 1e-3, 1.0, 0.0, 0.0, 0.0]
    sim = Simulation(load_scene(scene), dt=0.01)
    path = [(0.0, top + 1e-3 - (1e-3 + depth) * k / 20) for k in range(1, 21)] + [(0.0, top - depth)] * 10
    path += [(direction * 0.01 * k / 40, top - depth) for k in range(1, 41)]
    forces = []
    for x, z in path:
        sim.step(Control({"ee": np.array([x0 + x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}))
        forces.append(-sim.observe().tactile["tactile"].wrench[2])
    sheet = sim.model.bodies["sheet"]
    card_top = float(sim.state.x[sheet.vertex_start:sheet.vertex_stop, 2].max())
    return float(forces[29]), float(np.mean(forces[-10:])), card_top


@pytest.mark.parametrize("direction", [1.0, -1.0], ids=["away_from_clamp", "towards_clamp"])
def test_clamped_card_between_pad_and_table_keeps_the_pads_linear_rise(direction):
    """With press_slide.yaml's clamped card (0.3 mm, 3 GPa) between the pad and the table, the steady slide's
    normal force over the frictionless one stays within 0.045 of the rigid table's linear answer (1.137 at
    mu = 0.8; measured 1.121 sliding away from the clamp, 1.169 towards it, where the card is pushed into
    compression) and the card stays flat (< 0.1 mm above its rest height). At 0.4 mm the card slid towards
    its clamp buckles into a fold (11.8 mm high, normal +22 %): that part of a replay's rise is the card's."""
    base, _, _ = _card_press_then_slide(0.0, 1.0)  # frictionless: the slide direction does not matter
    _, sliding, card_top = _card_press_then_slide(0.8, direction)
    assert sliding / base == pytest.approx(_linear_rise(0.8), abs=0.045), sliding / base
    assert card_top < 1.5e-4 + 1e-4, card_top
