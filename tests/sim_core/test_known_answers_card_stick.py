"""Tangential load before gross slip of the gel pad on the clamped card (press_slide.yaml) and on a bare table.

Which Cattaneo-Mindlin applies. The recordings' pad is flat (18.6 x 14.3 x 4 mm, top held by the
effector), not a sphere, so Hertz-Mindlin's ``1 - (1 - delta / delta_slip)^(3/2)`` does not. For a flat
contact Mindlin's analysis (Johnson, *Contact Mechanics*, 1985, sec. 7.2: a flat punch under a tangential
force; Mindlin 1949) gives a stick traction with the same edge singularity as the pressure, so with
uncoupled bodies (``beta = 0``) nothing slips before gross slip: ``Q = K_t delta`` up to ``mu P``, with
``K_t`` the tangential stiffness in full stick. For this finite pad ``K_t`` is not a formula: it is solved
independently by :func:`tests.support.linear_fe.linear_stiffness` on the pad's tets (top held, bottom
moved tangentially in full stick). The card adds a compliance in series: its membrane between the clamp
and the pad, ``k_card = E t w / L`` (3 GPa x 0.3 mm x 60 mm / 50.7 mm = 1.07e6 N/m, 0.6 % of the pad's
6.8e3 N/m); the card's bending and its table friction (0.3) carry no tangential load in series.

Measured (session 51, 0.1 mm below the table's or card's top, slide steps of 20 um, ``contact_eps_v``
1e-5 m/s, i.e. a stick regularisation ``eps_v dt`` of 0.1 um): the initial slope dQ / d delta over K_t

| gel-card friction | bare table | card (over K_t in series with k_card) |
|---|---|---|
| 50 (full stick) | 0.986 | 0.997 |
| 5 | 0.969 | 0.978 |
| 0.8 (the card's) | 0.871 | 0.869 |

So in full stick the simulator is Mindlin's line within 1.4 %, with or without the card. At the card's
mu = 0.8 it is 13 % softer on both: the finite pad's edges slip (the pressing already loads them
tangentially, their pressure and shear singularities differ for a bonded pad at nu = 0.45, beta = 0.09),
and the slip vanishes as mu grows. That is physics of a finite pad, not of the card: the card changes
the curve by 1 %. At the scene default ``contact_eps_v`` 0.01 m/s (``eps_v dt`` 0.1 mm at dt 0.01 s, 50 um
at press_slide.yaml's 5 ms) the slope at mu 0.8 on the card is 0.45 of K_t: the lagged friction's stick
is then a soft spring ``mu f_n / (eps_v dt)`` per vertex, and the replays' pre-slip curves are half as stiff
as Mindlin's (at mu 50 the same spring is stiff: 0.98).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
import scipy.sparse.linalg as spl

from sim_core.control import Control
from sim_core.scenes import load_scene
from sim_core.scenes.scene_file import load_yaml
from sim_core.simulation import Simulation
from tests.sim_core.test_sliding_normal_force import PRESS_SLIDE, _scene
from tests.support.linear_fe import linear_stiffness

DEPTH, STEP = 1e-4, 2e-5
"""Press below the table's / card's top and slide increment, m."""
CARD_E, CARD_T, CARD_W, CARD_L = 3.0e9, 3.0e-4, 0.06, 0.06 - 0.0093
"""press_slide.yaml's card: modulus Pa, thickness, width across the slide, clamp (x = 0) to the pad's near edge, m."""


def _model_scene(card: bool, mu: float) -> tuple[dict, float, float]:
    if card:
        scene = load_yaml(PRESS_SLIDE.read_text())
        scene["sensors"]["tactile"]["friction"] = mu
        scene["simulation"] = {"gel_resolution": [6, 5, 3], "contact_eps_v": 1e-5}
        scene["dt"] = 0.01
        top, x0 = 3e-4, 0.06
        scene["effectors"]["ee"]["initial_pose"] = [x0, 0.0, top + 1e-3, 1.0, 0.0, 0.0, 0.0]
        return scene, top, x0
    scene = _scene(mu)
    scene["simulation"]["contact_eps_v"] = 1e-5
    return scene, 0.0, 0.0


@lru_cache(maxsize=None)
def _stick_slope(card: bool, mu: float) -> tuple[float, float, float]:
    """Press the pad DEPTH into the card / table, rest, then slide 10 steps of STEP along +x: the slope of the
    resisting tangential force over steps 2-8 (N/m), the pressed normal force P (N) and the last Q / (mu P)."""
    scene, top, x0 = _model_scene(card, mu)
    sim = Simulation(load_scene(scene), dt=0.01)
    path = [(0.0, top + 1e-3 - (1e-3 + DEPTH) * k / 20) for k in range(1, 21)] + [(0.0, top - DEPTH)] * 5
    path += [(STEP * k, top - DEPTH) for k in range(1, 11)]
    wrench = []
    for x, z in path:
        sim.step(Control({"ee": np.array([x0 + x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}))
        wrench.append(sim.observe().tactile["tactile"].wrench.copy())
    wrench = np.asarray(wrench)
    q = -wrench[25:, 0]
    slope = np.polyfit(STEP * np.arange(2, 9), q[1:8], 1)[0]
    pressed = -wrench[24, 2]
    return float(slope), float(pressed), float(q[-1] / (mu * pressed))


@lru_cache(maxsize=None)
def _full_stick_stiffness() -> float:
    """K_t (N/m) of the scene's 6 x 5 x 3 pad: top held, every bottom vertex moved 1 m along x (full stick),
    P1 linear elasticity (E 3e5 Pa, nu 0.45)."""
    model = load_scene(_scene(0.0))
    gel = model.bodies["gel"]
    x = model.x_rest[gel.vertex_start:gel.vertex_stop]
    k = linear_stiffness(x, gel.tets - gel.vertex_start, 3.0e5, 0.45)
    top = np.flatnonzero(np.isclose(x[:, 2], x[:, 2].max()))
    bottom = np.flatnonzero(np.isclose(x[:, 2], x[:, 2].min()))
    fixed = np.zeros(k.shape[0], dtype=bool)
    fixed[(3 * np.concatenate([top, bottom])[:, None] + np.arange(3)).reshape(-1)] = True
    u = np.zeros(k.shape[0])
    u[3 * bottom] = 1.0
    free = ~fixed
    u[free] = spl.spsolve(k[free][:, free].tocsc(), -(k @ u)[free])
    return float((k @ u)[3 * bottom].sum())


def test_full_stick_follows_mindlins_flat_contact_line_with_and_without_the_card():
    """At gel-card friction 50 (nothing slips) the slope of Q against the slide is K_t within 3 % on the bare
    table (measured 0.986) and K_t in series with the card's membrane on the card (measured 0.997). A card that
    slid on the table (its friction is 0.3) instead of loading its clamp would fail."""
    k_t = _full_stick_stiffness()
    k_card = CARD_E * CARD_T * CARD_W / CARD_L
    bare, _, _ = _stick_slope(False, 50.0)
    on_card, _, _ = _stick_slope(True, 50.0)
    assert bare / k_t == pytest.approx(1.0, abs=0.03)
    assert on_card / (1.0 / (1.0 / k_t + 1.0 / k_card)) == pytest.approx(1.0, abs=0.03)


def test_at_the_cards_friction_the_card_changes_the_pre_slip_curve_by_its_compliance_only():
    """At the card's mu = 0.8 the pad's edges slip before gross slip (module docstring): the slope is 0.80-0.95
    of K_t on both (measured 0.871 bare, 0.863 card), the card's within 3 % of the bare table's (0.99), and the
    load stays below mu P (Q / mu P 0.12 / 0.39 after 0.2 mm). The scene default's stick regularisation
    (contact_eps_v 0.01 m/s: 0.45 on the card) fails."""
    k_t = _full_stick_stiffness()
    bare, _, q_bare = _stick_slope(False, 0.8)
    on_card, _, q_card = _stick_slope(True, 0.8)
    assert 0.80 < bare / k_t < 0.95 and 0.80 < on_card / k_t < 0.95, (bare / k_t, on_card / k_t)
    assert on_card / bare == pytest.approx(1.0, abs=0.03)
    assert 0.0 < q_bare < 1.0 and 0.0 < q_card < 1.0
