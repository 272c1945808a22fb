"""The reference world's flex card as a clamped strip under end loads: MuJoCo's answers beside the plate and
beam solutions that ``tests/sim_core/energies/test_card_known_answers.py`` checks our sheet against.

The card of :mod:`benchmarks.mujoco_world.mjcf` (a 2D flex grid, ``elastic2d="both"``, radius t/2, no contact
here, no gravity) with its vertex columns 0 and 1 pinned (a clamp; one pinned column is a hinge in both
engines), loaded on its free edge through ``xfrc_applied`` ramped over ``ramp`` s and held, with Rayleigh
damping so that the strip settles; prints the mean tip displacement and the analytic answer:

* ``lateral``: a tip load along z (cantilever, ``P L^3 / (3 EI)``);
* ``gravity``: the strip's own weight, no tip load (uniformly loaded cantilever, ``q L^4 / (8 EI)``);
* ``stretch``: tension along x (``F L / (E t W)``);
* ``inplane``: a pull along y (deep Timoshenko beam, ``F L^3 / (3 E I) + F L / (kappa G A)``);
* ``twist``: an end torque (twist rate ``T / (G J)``, ``G J = G W t^3 / 3``);
* ``buckle``: a compressive tip load ``ratio x P_cr`` (Euler, clamped-free) with a lateral load of 1e-3
  P_cr: the amplification of the lateral deflection, ``1 / (1 - P / P_cr)`` below P_cr (Southwell).

Usage (MuJoCo venv, README): ``python -m benchmarks.mujoco_world.strip_answers lateral stretch inplane twist
buckle``. Each case takes 5-30 s of one core.
"""

from __future__ import annotations

import argparse

import numpy as np

E, T_CARD, RHO = 3.0e9, 3.0e-4, 700.0  # the reference card: Pa, m, kg/m^3
LENGTH = 0.1  # m


def strip_xml(width: float, nx: int, ny: int, nu: float, damping: float, gravity: float = 0.0) -> str:
    """MJCF of the card strip along +x from x = 0, columns 0 and 1 pinned, gravity ``gravity`` m/s^2 along z (0:
    none), no contact."""
    mass = RHO * LENGTH * width * T_CARD
    return f"""<mujoco><compiler autolimits="true"/>
<option timestep="0.001" integrator="discrete" solver="Newton" gravity="0 0 {gravity}"/>
<worldbody>
<flexcomp name="card" type="grid" dim="2" count="{nx} {ny} 1" spacing="{LENGTH / (nx - 1)} {width / (ny - 1)} 0.01"
 pos="{LENGTH / 2} 0 0" radius="{T_CARD / 2}" mass="{mass}">
 <contact selfcollide="none" contype="0" conaffinity="0"/>
 <elasticity young="{E}" poisson="{nu}" thickness="{T_CARD}" damping="{damping}" elastic2d="both"/>
 <pin gridrange="0 0 1 {ny - 1}"/>
</flexcomp></worldbody></mujoco>"""


def settle(width: float, nx: int, ny: int, nu: float, tip_force, duration: float = 3.0, ramp: float = 1.5,
           damping: float = 0.02, gravity: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Rest positions ``(n, 3)`` (flexcomp order: index ``ix * ny + iy``) and displacements after the load.

    ``tip_force(y)`` gives the force (N, shape ``(m, 3)``) on the m free-edge vertices at lateral positions
    ``y`` (m); it is ramped linearly over ``ramp`` s and held until ``duration``.
    """
    import mujoco

    model = mujoco.MjModel.from_xml_string(strip_xml(width, nx, ny, nu, damping, gravity))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    adr, num = model.flex_vertadr[0], model.flex_vertnum[0]
    bodies = model.flex_vertbodyid[adr:adr + num]
    x0 = data.flexvert_xpos[adr:adr + num].copy()
    tip = np.arange(num) // ny == nx - 1
    force = np.asarray(tip_force(x0[tip, 1] - x0[:, 1].mean()), dtype=float)
    for k in range(int(duration / model.opt.timestep)):
        data.xfrc_applied[bodies[tip], :3] = min(1.0, k * model.opt.timestep / ramp) * force
        mujoco.mj_step(model, data)
    return x0, data.flexvert_xpos[adr:adr + num] - x0


def edge_weights(y: np.ndarray) -> np.ndarray:
    """Trapezoidal weights of the free edge's vertices (half at both corners), summing to 1."""
    w = np.where(np.isclose(np.abs(y), np.abs(y).max()), 0.5, 1.0)
    return w / w.sum()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="+", choices=("lateral", "gravity", "stretch", "inplane", "twist", "buckle"))
    args = parser.parse_args(argv)
    nu, width, nx, ny = 0.3, 0.06, 21, 13
    held = LENGTH * (1.0 - 1.0 / (nx - 1))  # in plane: held up to column 1
    bent = LENGTH * (1.0 - 0.5 / (nx - 1))  # bending: the discrete clamp at dx / 2
    G = E / (2.0 * (1.0 + nu))
    for case in args.cases:
        if case == "lateral":
            p = 1e-3
            _, u = settle(width, nx, ny, nu, lambda y: np.outer(edge_weights(y), (0, 0, p)))
            beam = p * bent**3 / (3.0 * E * T_CARD**3 / 12.0 * width)
            print(f"lateral {p} N: tip w {u[-ny:, 2].mean():.4e} m, beam E t^3 W / 12: {beam:.4e} m")
        elif case == "gravity":
            _, u = settle(width, nx, ny, nu, lambda y: np.zeros((y.size, 3)), gravity=-9.81)
            beam = RHO * T_CARD * 9.81 * width * bent**4 / (8.0 * E * T_CARD**3 / 12.0 * width)
            print(f"gravity: tip sag {-u[-ny:, 2].mean():.4e} m, beam q L^4 / (8 E t^3 W / 12): {beam:.4e} m "
                  f"(ratio {-u[-ny:, 2].mean() / beam:.3f})")
        elif case == "stretch":
            f = 10.0
            _, u = settle(width, nx, ny, nu, lambda y: np.outer(edge_weights(y), (f, 0, 0)), 0.6, 0.3)
            print(f"stretch {f} N: tip u {u[-ny:, 0].mean():.4e} m, bar {f * held / (E * T_CARD * width):.4e} m")
        elif case == "inplane":
            f = 1.0
            _, u = settle(width, nx, ny, nu, lambda y: np.outer(edge_weights(y), (0, f, 0)), 0.6, 0.3)
            beam = f * held**3 / (3.0 * E * T_CARD * width**3 / 12.0) + f * held / (5.0 / 6.0 * G * T_CARD * width)
            print(f"inplane {f} N: tip v {u[-ny:, 1].mean():.4e} m, Timoshenko {beam:.4e} m")
        elif case == "twist":
            torque = 1e-4
            x0, u = settle(width, nx, ny, nu, lambda y: np.c_[0 * y, 0 * y, torque * y / np.sum(y**2)], 1.0, 0.5)
            y = x0[:, 1] - x0[:, 1].mean()
            ix = np.arange(len(x0)) // ny
            rotation = [np.polyfit(y[ix == i], u[ix == i, 2], 1)[0] for i in range(nx)]
            rate = np.polyfit(np.arange(6, 15) * LENGTH / (nx - 1), rotation[6:15], 1)[0]
            GJ = G * width * T_CARD**3 / 3.0
            print(f"twist {torque} N m: rate {rate:.4f} rad/m, Saint-Venant {torque / GJ:.4f} rad/m "
                  f"(G J effective / G J = {torque / GJ / rate:.2f})")
        else:
            col_w, col_ny = 0.006, 3  # a narrow column with nu = 0: EI = E t^3 W / 12
            p_cr = np.pi**2 * E * T_CARD**3 / 12.0 * col_w / (4.0 * bent**2)
            q = 1e-3 * p_cr
            w0 = settle(col_w, nx, col_ny, 0.0, lambda y: np.outer(edge_weights(y), (0, 0, q)), 4.0, 2.0, 0.05)[1]
            for ratio in (0.5, 0.8, 0.95, 1.1):
                u = settle(col_w, nx, col_ny, 0.0, lambda y: np.outer(edge_weights(y), (-ratio * p_cr, 0, q)),
                           4.0, 2.0, 0.05)[1]
                amp = u[-col_ny:, 2].mean() / w0[-col_ny:, 2].mean()
                print(f"buckle P / P_cr {ratio}: amplification {amp:.2f} (Southwell at P_cr: "
                      f"{1.0 / (1.0 - ratio) if ratio < 1 else float('inf'):.2f}), tip u {u[-col_ny:, 0].mean():.3e} m")


if __name__ == "__main__":
    main()
