"""The released card's fall: the scenes' card, pinned at its x0 edge, let go straight from a ramp, against the rigid
rod pinned at one end.

A lift-and-fold recording ends with the gel letting the card go (nominal_s109: the tip 18-19 mm up). The card is
pinned along one vertex column (``clamped_edge: x0``, a hinge), so once let go it turns down about that edge. Its
bending stiffness keeps it nearly straight (a uniform load's sag over the card's 0.1 m is ~0.2 mm against the
fall's 18 mm), so the tip follows the rigid rod pinned at one end: ``I = m L^2 / 3``, gravity's moment
``m g (L / 2) cos(theta)``, so ``theta'' = -(3 g / 2 L) cos(theta)`` (e.g. Meriam & Kraige, *Engineering
Mechanics: Dynamics*, fixed-axis rotation of a slender bar), the tip at ``L sin(theta)``; from rest at 18 mm it
lands in 49.9 ms.

* Resolved in time (1 ms steps) the card's tip is the rod's within 0.3 mm through the fall and lands within 2 ms
  of it: this simulator's undamped card falls as the physics says.
* At the replays' 10 ms step (:class:`sysid.observation.ObservationModel` ``dt=0.01``) the card runs ahead of
  the rod (0.64 / 1.35 / 2.09 / 2.83 mm after 1-4 steps, measured): the implicit (backward) Euler step takes each
  step's end acceleration and velocity, a first-order lead ``n dt^2 a / 2`` in the tip's drop after n steps. The
  tip is backward Euler's rigid rod at that step within 0.3 mm (measured 0.13), not the rod's. This is the replay's side of nominal_s109's fall mismatch (the replay's card lands
  ~30 ms after the peel where the recording's takes ~80: docs/benchmarks_log.md, session 57, s57-49lift); the
  reference engine's side, its 1 ms step slowing the fall of a card with the flex's Rayleigh damping, is measured
  there with ``benchmarks/mujoco_world/fall_answers.py``.

The gel is held 50 mm above the card (no contact); the NumPy backend (no kernels to compile): ~2-4 s a case.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from sim_core.scenes.scene_file import load_yaml
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig

SCENE = Path(__file__).resolve().parents[2] / "config" / "scenes" / "press_slide.yaml"
TIP0 = 0.018
"""The tip's height at the release, m (nominal_s109's card at its peel: 17.4-18.8 mm)."""


def _card_fall(dt: float, duration: float = 0.06) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The scene's card let go straight from the ramp at ``TIP0``, at rest: times ``(n,)`` s, the free edge's
    mean height above the pinned edge ``(n,)`` m, the card's length L m and gravity g m/s^2."""
    scene = load_yaml(SCENE.read_text())
    scene["effectors"]["ee"]["initial_pose"] = [0.05, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0]  # the gel out of reach
    sim = Simulation.from_scene(scene, dt=dt, solver_config=SolverConfig(backend="numpy"))
    sheet = sim.model.bodies["sheet"]
    idx = np.arange(sheet.vertex_start, sheet.vertex_stop)
    ox, oz = float(scene["sheet"]["origin"][0]), float(scene["sheet"]["origin"][2])
    length = float(scene["sheet"]["size"][0])
    theta0 = np.arcsin(TIP0 / length)
    arm = sim.state.x[idx, 0] - ox
    sim.state.x[idx, 0] = ox + arm * np.cos(theta0)  # turned rigidly about the pinned column (arm 0)
    sim.state.x[idx, 2] = oz + arm * np.sin(theta0)
    tip = idx[np.isclose(arm, arm.max())]
    t, z = [], []
    for k in range(int(round(duration / dt))):
        sim.step()
        t.append((k + 1) * dt)
        z.append(float(sim.state.x[tip, 2].mean()) - oz)
    return np.array(t), np.array(z), length, float(-scene["gravity"][2])


def _rod(length: float, g: float):
    """The rigid rod's tip height ``t -> m`` (0 once landed) and its landing time, s."""
    rate = 1.5 * g / length
    sol = solve_ivp(lambda t, y: [y[1], -rate * np.cos(y[0])], (0.0, 0.2), [np.arcsin(TIP0 / length), 0.0],
                    dense_output=True, events=lambda t, y: y[0], rtol=1e-10, atol=1e-12)
    land = float(sol.t_events[0][0])
    return (lambda t: np.where(t < land, length * np.sin(np.maximum(sol.sol(np.minimum(t, land))[0], 0.0)), 0.0)), land


def _rod_backward_euler(length: float, g: float, dt: float, n: int) -> np.ndarray:
    """The rigid rod's tip height after each of ``n`` backward-Euler steps of ``dt`` (``theta_{k+1} = theta_k +
    dt w_{k+1}``, ``w_{k+1} = w_k - dt (3 g / 2 L) cos(theta_{k+1})``), 0 once landed, m."""
    rate = 1.5 * g / length
    theta, w, out = np.arcsin(TIP0 / length), 0.0, []
    for _ in range(n):
        th = brentq(lambda th: th - theta - dt * (w - dt * rate * np.cos(th)), theta - 1.0, theta + 1.0)
        w, theta = (th - theta) / dt, th
        out.append(length * np.sin(max(theta, 0.0)))
    return np.array(out)


def test_the_released_card_falls_as_the_rigid_rod_pinned_at_its_edge():
    """1 ms steps: the tip within 0.3 mm of the rod through the fall (measured <= 0.24 mm), on the table within 2 ms
    of the rod's landing (49.9 ms; measured 49 ms)."""
    t, z, length, g = _card_fall(0.001)
    tip, land = _rod(length, g)
    falling = t < land - 0.003
    assert np.max(np.abs(z[falling] - tip(t[falling]))) < 3e-4
    landed = t[np.argmax(z < 5e-4)]
    assert abs(landed - land) < 0.002 + 1e-9 and 0.048 < land < 0.052


def test_at_the_replays_step_the_card_lands_early_by_backward_eulers_lead():
    """10 ms steps: the tip is backward Euler's rod (within 0.3 mm) and ahead of the rod (at 30 ms 9.46 against 11.55 mm
    measured, about the first-order lead ``n dt^2 a / 2``, 2.2 mm after 3 steps at ``a = 1.5 g``); landed by 50 ms."""
    dt = 0.01
    t, z, length, g = _card_fall(dt)
    tip, land = _rod(length, g)
    euler = _rod_backward_euler(length, g, dt, t.size)
    falling = euler > 5e-4
    assert np.max(np.abs(z[falling] - euler[falling])) < 3e-4
    lead = tip(t[:3]) - z[:3]
    assert np.all(lead > 0.5 * np.arange(1, 4) * dt**2 * 1.5 * g / 2.0)
    assert z[4] < 5e-4 and land > 0.049
