"""MJCF of the reference world from a scene file (v1) and the true MuJoCo values (labels' ``mujoco``).

World frame z up, table plane at ``table.height``.

* Card: a 2D ``flexcomp`` grid of ``sheet.resolution`` vertices over ``sheet.size``, vertex (0, 0)
  at ``sheet.origin`` (mid-surface), collision radius = thickness / 2 (so the card lies on the
  table), ``elasticity`` young / poisson / thickness / Rayleigh damping with ``elastic2d="both"``
  and ``yield="0 bend_yield"`` (MuJoCo 4.0 shell bending plasticity; 0: elastic); the clamped edge
  pinned; mass = density x area x thickness.
* Gel: a 3D ``flexcomp`` grid (``GEL_COUNT`` vertices) of ``gel_size``, a child of the effector
  body, its top layer pinned to it, contact surface (bottom layer, inflated by ``GEL_RADIUS``) at
  the effector origin; young / poisson / Rayleigh damping; mass = density x volume.
* Effector: a body with three world-axis slide joints (``gravcomp``), mass ``ee_drive.mass``,
  driven by ``position`` actuators of stiffness ``kp`` and damping ratio ``dampratio`` (the
  3000 N/m Cartesian impedance).
* Contact: solref / solimp / elliptic cone / impratio of the labels on every contact. MuJoCo takes
  the larger of two friction coefficients, so card 0.3 with table 0.3 gives card-table 0.3 and the
  gel's coefficient gives gel-card; the gel's coefficient is switched between static and kinetic
  at run time (:mod:`benchmarks.mujoco_world.world`).
* Tack bonds (lift_fold): inactive ``connect`` equalities between candidate card vertices and the
  nearest gel bottom vertex, ``solref`` of the labels, ``solimp`` making each a spring of
  ``tack.BOND_STIFFNESS_N_PER_M`` at rest (vertex masses: flexcomp spreads a flex's mass evenly over
  its vertices), activated and re-anchored at run time (:mod:`benchmarks.mujoco_world.tack`).

Integrator ``discrete`` with the Newton solver: MuJoCo 4.0 integrates flex elasticity implicitly
only there (``implicitfast`` refuses flex elasticity).
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from benchmarks.mujoco_world.tack import BOND_STIFFNESS_N_PER_M, TackCandidate, bond_impedance, bond_solimp

GEL_COUNT = (10, 8, 3)
"""Gel grid vertices along x, y, thickness (spacing about 2 mm, the marker pitch)."""

GEL_RADIUS = 1.0e-4
"""Collision radius of the gel flex, m (its surface is offset so that contact starts at the effector origin)."""

CLAMP_GRIDRANGE = {"x0": lambda nx, ny: (0, 0, 0, ny - 1), "x1": lambda nx, ny: (nx - 1, 0, nx - 1, ny - 1),
                   "y0": lambda nx, ny: (0, 0, nx - 1, 0), "y1": lambda nx, ny: (0, ny - 1, nx - 1, ny - 1)}


def _v(xs: Sequence[float]) -> str:
    return " ".join(f"{float(x):.9g}" for x in xs)


def gel_bottom_rest(scene: Mapping[str, Any]) -> np.ndarray:
    """Rest positions of the gel's bottom-layer vertices in the effector frame (world-aligned), m, shape (nx*ny, 2)."""
    gx, gy, _ = scene["sensors"]["tactile"]["gel_size"]
    nx, ny, _ = GEL_COUNT
    xs = np.linspace(-gx / 2, gx / 2, nx)
    ys = np.linspace(-gy / 2, gy / 2, ny)
    return np.array([(x, y) for y in ys for x in xs])


def card_vertex_body(c: TackCandidate, ny: int) -> str:
    """MuJoCo body name of a candidate's card vertex (flexcomp grid index ``ix * ny + iy``)."""
    return f"card_{c.card_ix * ny + c.card_iy}"


def gel_vertex_body(c: TackCandidate) -> str:
    """MuJoCo body name of a candidate's gel bottom vertex (flexcomp grid index ``(ix * gny + iy) * gnz``, iz = 0)."""
    gnx, gny, gnz = GEL_COUNT
    iy, ix = divmod(c.gel_bottom, gnx)
    return f"gel_{(ix * gny + iy) * gnz}"


def build_mjcf(scene: Mapping[str, Any], truth: Mapping[str, Any], ee_start: Sequence[float],
               tack: Sequence[TackCandidate] = ()) -> str:
    """The MJCF text of the world.

    Args:
        scene: scene.yaml (v1) as a dict (geometry, camera, marker grid).
        truth: the labels' ``mujoco`` dict (timestep, sheet, gel, friction, contact, ee_drive, tack).
        ee_start: initial effector position in world (m, shape (3,)).
        tack: bond candidates (lift_fold), each an inactive connect equality.

    Raises:
        KeyError: a missing key in ``scene`` or ``truth``.
        ValueError: an unknown clamped edge.
    """
    sh, gel, fr, con, drive = truth["sheet"], truth["gel"], truth["friction"], truth["contact"], truth["ee_drive"]
    sx, sy = scene["sheet"]["size"]
    nx, ny = scene["sheet"]["resolution"]
    ox, oy, oz = scene["sheet"]["origin"]
    thick = float(sh["thickness"])
    card_mass = float(sh["density"]) * sx * sy * thick
    edge = scene["sheet"].get("clamped_edge", "none")
    if edge not in CLAMP_GRIDRANGE and edge != "none":
        raise ValueError(f"unknown clamped_edge {edge!r}")
    pin = f'<pin gridrange="{_v(CLAMP_GRIDRANGE[edge](nx, ny))}"/>' if edge != "none" else ""
    gx, gy, gz = scene["sensors"]["tactile"]["gel_size"]
    gnx, gny, gnz = GEL_COUNT
    gel_mass = float(gel["density"]) * gx * gy * gz
    solref, solimp = _v(con["solref"]), _v(con["solimp"])
    table = scene.get("table", {"height": 0.0})
    bonds = []
    if tack:
        bond_d = bond_impedance(card_mass / (nx * ny), gel_mass / (gnx * gny * gnz), BOND_STIFFNESS_N_PER_M,
                                truth["tack"]["solref"])
    for k, c in enumerate(tack):
        bonds.append(f'<connect name="tack_{k}" body1="{card_vertex_body(c, ny)}" body2="{gel_vertex_body(c)}" '
                     f'anchor="0 0 0" active="false" solref="{_v(truth["tack"]["solref"])}" '
                     f'solimp="{_v(bond_solimp(bond_d))}"/>')
    equality = f"<equality>{''.join(bonds)}</equality>" if bonds else ""
    return f"""<mujoco model="thinshell_reference_world">
  <compiler autolimits="true"/>
  <option timestep="{float(truth['timestep'])}" integrator="discrete" solver="Newton" cone="{con['cone']}"
          impratio="{float(con['impratio'])}" gravity="{_v(scene.get('gravity', [0, 0, -9.81]))}"/>
  <worldbody>
    <geom name="table" type="plane" size="0.3 0.3 0.01" pos="0 0 {float(table['height'])}"
          friction="{float(fr['sheet_table'])}" solref="{solref}" solimp="{solimp}"/>
    <flexcomp name="card" type="grid" dim="2" count="{nx} {ny} 1" spacing="{_v([sx / (nx - 1), sy / (ny - 1), 0.01])}"
              pos="{_v([ox + sx / 2, oy + sy / 2, oz])}" radius="{thick / 2}" mass="{card_mass}">
      <contact selfcollide="none" friction="{float(fr['sheet_table'])}" solref="{solref}" solimp="{solimp}"/>
      <elasticity young="{float(sh['young'])}" poisson="{float(sh['poisson'])}" thickness="{thick}"
                  damping="{float(sh['rayleigh_damping'])}" elastic2d="{sh.get('elastic2d', 'both')}"
                  yield="0 {float(sh['bend_yield'])}"/>
      {pin}
    </flexcomp>
    <body name="ee" pos="{_v(ee_start)}" gravcomp="1">
      <joint name="ee_x" type="slide" axis="1 0 0"/>
      <joint name="ee_y" type="slide" axis="0 1 0"/>
      <joint name="ee_z" type="slide" axis="0 0 1"/>
      <geom name="ee_mass" type="box" size="{_v([gx / 2, gy / 2, 0.001])}" pos="0 0 {gz + 0.002}"
            mass="{float(drive['mass'])}" contype="0" conaffinity="0"/>
      <flexcomp name="gel" type="grid" dim="3" count="{gnx} {gny} {gnz}"
                spacing="{_v([gx / (gnx - 1), gy / (gny - 1), gz / (gnz - 1)])}"
                pos="0 0 {gz / 2 + GEL_RADIUS}" radius="{GEL_RADIUS}" mass="{gel_mass}">
        <contact selfcollide="none" friction="{float(fr['gel_sheet_kinetic'])}" solref="{solref}" solimp="{solimp}"/>
        <elasticity young="{float(gel['young'])}" poisson="{float(gel['poisson'])}"
                    damping="{float(gel['rayleigh_damping'])}"/>
        <pin gridrange="0 0 {gnz - 1} {gnx - 1} {gny - 1} {gnz - 1}"/>
      </flexcomp>
    </body>
  </worldbody>
  {equality}
  <actuator>
    <position name="drive_x" joint="ee_x" kp="{float(drive['kp_N_per_m'])}" dampratio="{float(drive['dampratio'])}"/>
    <position name="drive_y" joint="ee_y" kp="{float(drive['kp_N_per_m'])}" dampratio="{float(drive['dampratio'])}"/>
    <position name="drive_z" joint="ee_z" kp="{float(drive['kp_N_per_m'])}" dampratio="{float(drive['dampratio'])}"/>
  </actuator>
</mujoco>
"""

