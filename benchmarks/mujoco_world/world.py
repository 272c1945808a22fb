"""Run the MuJoCo reference world along a commanded motion and record its true signals at every step.

What is recorded (every ``timestep``, world frame unless said):

* ``cmd``: the commanded effector position (m, (T, 3)); ``ee``: the measured one (m, (T, 3)).
* ``wrench``: net contact force ON the gel and its torque about the effector origin, in world
  (N, N m, (T, 6)): the sum over every contact whose one side is the gel flex of
  ``+/- (f_n n + f_t1 t1 + f_t2 t2)`` (MuJoCo's contact force acts on the contact's second object
  along the frame; elliptic cones keep it in ``efc_force[efc_address : +3]``).
* ``gel_bottom``: the gel's bottom-layer vertices (m, (T, nx*ny, 3), y outer, x inner).
* ``sheet``: the card vertices in the contract's order (row-major, y outer), m, (T, 273, 3).

Stiction (static > kinetic gel-card friction): MuJoCo has one Coulomb coefficient per contact,
so the gel's coefficient is switched before every step: static while the gel's contact layer sticks
to the card (mean tangential speed of the gel vertices touching the card below ``STICK_SPEED``),
kinetic once it slips (above ``SLIP_SPEED``), with hysteresis between (``stiction_switch="speed"``,
the default). Partial slip at the patch's edge brings that mean speed over ``SLIP_SPEED`` long before the
tangential load nears the static limit, so the load never overshoots its sliding level by much
(``sysid/diagnose/signatures/friction.py``, "Known limits"). ``stiction_switch="load"`` switches to
kinetic at gross breakaway instead: once the tangential load on the gel reaches ``SLIP_LOAD_FRACTION`` of
the static limit ``mu_s F_n``, or the contact layer moves at ``SLIP_CMD_FRACTION`` of the command's
tangential speed (at least ``SLIP_GROSS_SPEED``); it sticks again below ``STICK_SPEED``. That is the
textbook stick-slip (the load rises to ``mu_s F_n`` and falls to ``mu_k F_n`` at breakaway).

Tack (lift_fold, :mod:`benchmarks.mujoco_world.tack`): at ``tack_on_s`` every candidate bond whose
card vertex lies under the gel footprint is re-anchored at the current relative position and
activated; a bond whose force exceeds ``bond_strength_N`` breaks; all are released at ``tack_off_s``
(the peel). The wrench includes the active bonds' force (sign: ``bond_wrench`` of :func:`run`). From the
peel on, each step is ``PEEL_SUBSTEPS`` MuJoCo steps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Mapping

import mujoco
import numpy as np

from benchmarks.mujoco_world import tack as tack_mod
from benchmarks.mujoco_world.mjcf import GEL_COUNT, build_mjcf, card_vertex_body, gel_bottom_rest, gel_vertex_body
from benchmarks.mujoco_world.motion import Motion

SLIP_SPEED = 2.0e-3
"""Mean tangential speed of the gel's contact layer above which it slips (kinetic friction), m/s."""

STICK_SPEED = 0.5e-3
"""... and below which it sticks again (static friction), m/s."""

SLIP_LOAD_FRACTION = 0.97
"""``stiction_switch="load"``: kinetic once the tangential load reaches this fraction of ``mu_s F_n``."""

SLIP_CMD_FRACTION, SLIP_GROSS_SPEED = 0.5, 5.0e-3
"""``stiction_switch="load"``: ... or once the contact layer's mean tangential speed exceeds this fraction of the
command's tangential speed and this speed (m/s): gross slip where the load saturates below the fraction."""

STICTION_SWITCHES = ("speed", "load")

PEEL_SUBSTEPS = 2
"""From the peel on, each recorded step is this many MuJoCo steps of ``timestep / PEEL_SUBSTEPS``: the
release of the stretched bonds is a stiff transient that the 1 ms step does not integrate here
(nominal_s109's re-run from its peel state: at 1 ms the card is flung to 24 mm and the gel's vertices
move 8.4 mm; at 0.5 ms the card falls flat within 0.1 s and the gel relaxes by 0.34 mm)."""

CONTACT_BAND = 3.0e-4
"""A gel bottom vertex within this height above the card's top surface counts as touching, m."""


@dataclass
class Recording:
    """True signals of one run at every step (see module docstring for shapes and units)."""

    t: np.ndarray
    cmd: np.ndarray
    ee: np.ndarray
    wrench: np.ndarray
    gel_bottom: np.ndarray
    sheet: np.ndarray
    gel_bottom_rest: np.ndarray
    stats: dict[str, Any] = field(default_factory=dict)


def run(scene: Mapping[str, Any], truth: Mapping[str, Any], motion: Motion, log=print, probe=None,
        bond_wrench: str = "reference", stiction_switch: str = "speed") -> Recording:
    """Simulate ``motion`` in the world of ``scene`` with the true values ``truth`` (labels' ``mujoco``).

    ``bond_wrench``: how the tack bonds enter the wrench (``tack.BOND_WRENCH_CONVENTIONS``).

    ``probe(k, t, model, data)``, when given, is called after every step (diagnostics).
    ``stiction_switch``: when the gel's friction passes from static to kinetic (module docstring).

    Raises:
        RuntimeError: the simulation produced a non-finite state.
        ValueError: an unknown ``stiction_switch``.
    """
    if stiction_switch not in STICTION_SWITCHES:
        raise ValueError(f"stiction_switch must be one of {STICTION_SWITCHES}, got {stiction_switch!r}")
    tack = (tack_mod.tack_candidates(scene, motion.start[:2], gel_bottom_rest(scene))
            if motion.tack_on_s is not None else [])
    model = mujoco.MjModel.from_xml_string(build_mjcf(scene, truth, motion.start, tack))
    data = mujoco.MjData(model)
    dt = model.opt.timestep
    n_steps = int(np.floor(motion.duration_s / dt + 1e-9)) + 1
    card_id, gel_id = 0, 1
    cadr, gadr = model.flex_vertadr[card_id], model.flex_vertadr[gel_id]
    cnum, gnum = model.flex_vertnum[card_id], model.flex_vertnum[gel_id]
    gnx, gny, gnz = GEL_COUNT
    bottom = np.array([gadr + (ix * gny + iy) * gnz for iy in range(gny) for ix in range(gnx)])
    nx, ny = scene["sheet"]["resolution"]
    sheet_order = np.array([cadr + ix * ny + iy for iy in range(ny) for ix in range(nx)])
    contact_z = scene["sheet"]["origin"][2] + truth["sheet"]["thickness"] / 2
    mu_k, mu_s = float(truth["friction"]["gel_sheet_kinetic"]), float(truth["friction"]["gel_sheet_static"])
    stiction = mu_s > mu_k
    bond_max = float(truth["tack"]["bond_strength_N"])
    start = np.asarray(motion.start, dtype=float)

    t = np.arange(n_steps) * dt
    cmd = motion.command(t)
    rec_ee = np.zeros((n_steps, 3))
    rec_w = np.zeros((n_steps, 6))
    rec_gel = np.zeros((n_steps, bottom.size, 3))
    rec_sheet = np.zeros((n_steps, sheet_order.size, 3))
    slipping, n_switch, bonds_formed, bonds_broken = False, 0, 0, 0
    tacked = False
    bond_peak = np.zeros(len(tack))
    card_bodies = np.array([model.body(card_vertex_body(c, ny)).id for c in tack], dtype=int)
    gel_bodies = np.array([model.body(gel_vertex_body(c)).id for c in tack], dtype=int)
    gel_xy = np.asarray(scene["sensors"]["tactile"]["gel_size"][:2], dtype=float)
    prev_gel = None
    t0 = time.perf_counter()
    ee_body = model.body("ee").id
    for k in range(n_steps):
        peeled = bool(tack) and k > 0 and t[k - 1] >= motion.tack_off_s
        n_sub = PEEL_SUBSTEPS if peeled else 1
        model.opt.timestep = dt / n_sub
        for j in range(1, n_sub + 1):
            data.ctrl[:] = (cmd[k] if j == n_sub else motion.command(t[k] - dt + j * dt / n_sub)) - start
            mujoco.mj_step(model, data)
        model.opt.timestep = dt
        # mj_step's position stage and constraint solve describe the state at t[k]
        ee = data.xpos[ee_body].copy()
        rec_ee[k] = ee
        rec_gel[k] = data.flexvert_xpos[bottom]
        rec_sheet[k] = data.flexvert_xpos[sheet_order]
        rec_w[k] = _gel_wrench(model, data, gel_id, ee)
        if tack and tacked:
            active = data.eq_active[: len(tack)].astype(bool)
            f_bond = tack_mod.bond_forces(data, tack_mod.bond_rows(data, len(tack), mujoco))
            bond_peak = np.maximum(bond_peak, np.linalg.norm(f_bond, axis=1) * active)
            rec_w[k] += tack_mod.bond_wrench(f_bond, data.xpos[gel_bodies], active, ee, bond_wrench)
        if not np.all(np.isfinite(rec_gel[k])):
            raise RuntimeError(f"non-finite state at t = {t[k]:.3f} s")
        # stiction: friction for the next step from the contact layer's slip speed
        gel_now = rec_gel[k]
        if stiction:
            touching = gel_now[:, 2] < contact_z + CONTACT_BAND + 2e-4
            if prev_gel is not None and touching.any():
                speed = np.linalg.norm((gel_now[touching, :2] - prev_gel[touching, :2]).mean(axis=0)) / dt
                if slipping:
                    new = speed > STICK_SPEED
                elif stiction_switch == "speed":
                    new = speed > SLIP_SPEED
                else:
                    v_cmd = np.linalg.norm(cmd[k, :2] - cmd[max(k - 1, 0), :2]) / dt
                    f_t, f_n = np.linalg.norm(rec_w[k, :2]), abs(rec_w[k, 2])
                    new = bool(f_t >= SLIP_LOAD_FRACTION * mu_s * f_n > 0.0
                               or speed > max(SLIP_CMD_FRACTION * v_cmd, SLIP_GROSS_SPEED))
                n_switch += int(new != slipping)
                slipping = new
            elif not touching.any():
                slipping = False
            model.flex_friction[gel_id, 0] = mu_k if slipping else mu_s
        prev_gel = gel_now.copy()
        # tack bonds
        if tack and tacked and t[k] >= motion.tack_off_s:
            data.eq_active[: len(tack)] = 0
        elif tack and tacked:
            brk = tack_mod.bonds_to_break(f_bond, active, bond_max)
            data.eq_active[: len(tack)][brk] = 0
            bonds_broken += int(brk.sum())
        elif tack and t[k] >= motion.tack_on_s:
            tacked = True
            bonds_formed = _form_bonds(model, data, card_bodies, gel_bodies, ee[:2], gel_xy)
        if probe is not None:
            probe(k, t[k], model, data)
        if k % 500 == 0:
            log(f"  t={t[k]:.2f}s ee_z={ee[2] * 1e3:.3f}mm Fz={rec_w[k, 2]:.3f}N ncon={data.ncon} "
                f"{time.perf_counter() - t0:.0f}s")
    stats = {"wall_s": round(time.perf_counter() - t0, 1), "steps": int(n_steps),
             "warnings": int(np.sum(data.warning.number)), "tack_bonds_formed": int(bonds_formed),
             "tack_bonds_broken": int(bonds_broken), "friction_switches": int(n_switch),
             "max_normal_force_N": float(np.max(np.abs(rec_w[:, 2])))}
    if tack:
        stats["peel_substeps"] = PEEL_SUBSTEPS
        stats["tack_bond_peak_force_N"] = [round(float(x), 4) for x in bond_peak]
    return Recording(t, cmd, rec_ee, rec_w, rec_gel, rec_sheet,
                     np.c_[gel_bottom_rest(scene), np.zeros(bottom.size)], stats)


def _gel_wrench(model, data, gel_id: int, origin: np.ndarray) -> np.ndarray:
    """Net contact force on the gel flex and torque about ``origin``, world (N, N m), shape (6,)."""
    n = data.ncon
    if n == 0:
        return np.zeros(6)
    con = data.contact
    flex = con.flex[:n]
    sign = np.where(flex[:, 1] == gel_id, 1.0, np.where(flex[:, 0] == gel_id, -1.0, 0.0))
    adr = con.efc_address[:n]
    use = (sign != 0.0) & (adr >= 0)
    if not use.any():
        return np.zeros(6)
    adr = adr[use]
    f = np.stack([data.efc_force[adr], data.efc_force[adr + 1], data.efc_force[adr + 2]], axis=1)
    frame = con.frame[:n][use].reshape(-1, 3, 3)
    fw = np.einsum("ci,cij->cj", f, frame) * sign[use][:, None]
    tw = np.cross(con.pos[:n][use] - origin, fw)
    return np.r_[fw.sum(axis=0), tw.sum(axis=0)]


def _form_bonds(model, data, card_bodies: np.ndarray, gel_bodies: np.ndarray, ee_xy, gel_xy) -> int:
    """Activate the bonds whose card vertex lies under the gel footprint, anchored at the pair's current offset."""
    p1, p2 = data.xpos[card_bodies], data.xpos[gel_bodies]
    form = tack_mod.under_footprint(p1[:, :2], ee_xy, gel_xy)
    for k in np.nonzero(form)[0]:
        model.eq_data[k, 0:3] = 0.0
        model.eq_data[k, 3:6] = p1[k] - p2[k]
        data.eq_active[k] = 1
    return int(form.sum())
