"""The reference world's flex card let go straight from a ramp: its fall against the rigid rod pinned at one edge,
by the flex's Rayleigh damping and the time step (MuJoCo's side of ``tests/sim_core/test_known_answers_card_fall.py``).

The card of :mod:`benchmarks.mujoco_world.mjcf` (a 2D flex grid 21 x 13 over 0.1 x 0.06 m, ``elastic2d="both"``,
E 3 GPa, nu 0.3, t 0.3 mm, 700 kg/m^3, collision radius t / 2, the ``discrete`` integrator with the Newton solver),
its x0 column pinned (the scenes' ``clamped_edge: x0``: a hinge), turned rigidly about that column so that its free
edge stands ``--tip`` above the table, at rest, let go under gravity over the table plane (contact as the
reference world's). Prints the free edge's mean height every 5 ms and when it reaches the table, beside the rigid
rod's ``theta'' = -(3 g / 2 L) cos(theta)`` (landing 49.9 ms from 18 mm). A rigid turn strains nothing, so a
damping proportional to the strain rates (the flex's ``damping``, s) cannot slow it in the continuum; what slows
it in a case here is the time step.

Usage (MuJoCo venv, README): ``python -m benchmarks.mujoco_world.fall_answers [--tip 0.018] [--damping 0 0.002
0.02] [--dt 0.001 0.00025]``. ~1 s of one core a case.
"""

from __future__ import annotations

import argparse

import numpy as np
from benchmarks.mujoco_world.strip_answers import E, LENGTH, RHO, T_CARD

WIDTH, NX, NY = 0.06, 21, 13
CONTACT = 'solref="0.001 1" solimp="0.999 0.9999 0.0001 0.5 2"'  # the reference bags' labels (contact)


def fall_xml(damping: float, dt: float, tip: float) -> str:
    """MJCF of the card turned about its pinned x0 column so that its free edge is ``tip`` m up."""
    mass = RHO * LENGTH * WIDTH * T_CARD
    pitch = -np.degrees(np.arcsin(tip / LENGTH))
    return f"""<mujoco><compiler autolimits="true"/>
<option timestep="{dt}" integrator="discrete" solver="Newton" gravity="0 0 -9.81"/>
<worldbody><geom type="plane" size="0.3 0.3 0.01" friction="0.3" {CONTACT}/>
<body name="hinge" euler="0 {pitch} 0" pos="0 0 {T_CARD / 2}">
<flexcomp name="card" type="grid" dim="2" count="{NX} {NY} 1" spacing="{LENGTH / (NX - 1)} {WIDTH / (NY - 1)} 0.01"
 pos="{LENGTH / 2} 0 0" radius="{T_CARD / 2}" mass="{mass}">
 <contact selfcollide="none" friction="0.3" {CONTACT}/>
 <elasticity young="{E}" poisson="0.3" thickness="{T_CARD}" damping="{damping}" elastic2d="both"/>
 <pin gridrange="0 0 0 {NY - 1}"/>
</flexcomp></body></worldbody></mujoco>"""


def fall(damping: float, dt: float, tip: float, duration: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and the free edge's mean height above the table (m), every step."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(fall_xml(damping, dt, tip))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    adr, num = model.flex_vertadr[0], model.flex_vertnum[0]
    edge = np.arange(num) // NY == NX - 1
    t, z = [], []
    for k in range(int(round(duration / dt))):
        mujoco.mj_step(model, data)
        t.append((k + 1) * dt)
        z.append(float(data.flexvert_xpos[adr:adr + num, 2][edge].mean()) - T_CARD / 2)
    return np.array(t), np.array(z)


def rod_landing(tip: float, g: float = 9.81, h: float = 1e-6) -> float:
    """The rigid rod's time to the table from rest with its free end ``tip`` up, s (classical Runge-Kutta in
    steps of ``h``; the MuJoCo venv has no SciPy)."""
    rate = 1.5 * g / LENGTH

    def f(y):
        return np.array([y[1], -rate * np.cos(y[0])])

    y, t = np.array([np.arcsin(tip / LENGTH), 0.0]), 0.0
    while y[0] > 0.0:
        k1 = f(y)
        k2 = f(y + 0.5 * h * k1)
        k3 = f(y + 0.5 * h * k2)
        k4 = f(y + h * k3)
        y_next = y + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        if y_next[0] <= 0.0:
            return t + h * y[0] / (y[0] - y_next[0])
        y, t = y_next, t + h
    return t


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tip", type=float, default=0.018)
    parser.add_argument("--damping", type=float, nargs="+", default=[0.0, 0.002, 0.02])
    parser.add_argument("--dt", type=float, nargs="+", default=[0.001, 0.00025])
    args = parser.parse_args(argv)
    print(f"rigid rod: lands {rod_landing(args.tip) * 1e3:.1f} ms")
    for damping in args.damping:
        for dt in args.dt:
            t, z = fall(damping, dt, args.tip)
            every = max(1, int(round(0.005 / dt)))
            landed = t[np.argmax(z < 5e-4)] if np.any(z < 5e-4) else float("nan")
            print(f"damping {damping:g} s, dt {dt:g} s: lands {landed * 1e3:.1f} ms; edge (mm) every 5 ms: "
                  + " ".join(f"{v * 1e3:.1f}" for v in z[every - 1::every]))


if __name__ == "__main__":
    main()
