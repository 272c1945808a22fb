"""Compare two recordings of the same motion kind phase by phase (a generated bag against a reference).

    python -m benchmarks.mujoco_world.compare REF_BAG OUR_BAG

press_slide: peak |F_z|, mean F_z / tangential force / marker z and shear (sensor frame) in the
press dwell and in the second half of the slide, the time of first contact (|F_z| > 1.5 N) and
the measured effector depth in the dwell.

lift_fold (the second move rises): press dwell F_z; in the hold (fold done, bonds on) the card's
arch (highest point of the card's y-mean profile, m, and where), the effector height, the mean
wrench (sensor frame: F_x < 0 pulls the gel toward the clamp, F_z > 0 pulls it down) and marker
shear; the largest pull along +F_z and -F_x between the tack and the peel; after the peel, the
card's final fold (highest point of the y-mean profile over the last 0.1 s) and how long after the
peel's start the card's highest point first comes within 1 mm of it, and how much that highest point
still moves over the last ``SETTLE_WINDOW_S`` (a settled card: about the sheet noise). Reads bags
with ``rosbags`` only.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader


SHEET_NY = 13
"""Rows of the contract's card grid along y (21 x 13, y outer)."""


SETTLE_WINDOW_S = 0.3
"""lift_fold: the card's highest point should be still over the recording's last this many seconds
(``final_fold_range_mm``, a check that the card has settled after the peel)."""


def load(bag: Path) -> dict[str, np.ndarray]:
    """Arrays of a bag: cmd/pose (N, 4: t x y z), wrench (N, 7: t F T), markers (M, 63, 5), t_markers (M,), sheet z max,
    the card's y-mean height and x per column (K, 21) at stamps ``ts`` (K,)."""
    out: dict[str, list] = {"cmd": [], "pose": [], "wrench": [], "markers": [], "tm": [], "sheet_zmax": [],
                            "sheet_profile": [], "sheet_x": [], "ts": []}
    with AnyReader([bag]) as r:
        for c, t, raw in r.messages():
            m = r.deserialize(raw, c.msgtype)
            ts = t * 1e-9
            if c.topic.endswith("pose_cmd"):
                out["cmd"].append([ts, m.pose.position.x, m.pose.position.y, m.pose.position.z])
            elif c.topic.endswith("ee/pose"):
                out["pose"].append([ts, m.pose.position.x, m.pose.position.y, m.pose.position.z])
            elif c.topic.endswith("wrench"):
                f, q = m.wrench.force, m.wrench.torque
                out["wrench"].append([ts, f.x, f.y, f.z, q.x, q.y, q.z])
            elif c.topic.endswith("markers"):
                out["markers"].append(np.frombuffer(bytes(m.data), dtype="<f4").reshape(-1, 5))
                out["tm"].append(ts)
            elif c.topic.endswith("sheet/points"):
                pts = np.frombuffer(bytes(m.data), dtype="<f4").reshape(-1, 3)
                out["sheet_zmax"].append(pts[:, 2].max())
                grid = pts.reshape(SHEET_NY, -1, 3)        # row-major, y outer
                out["sheet_profile"].append(grid[:, :, 2].mean(axis=0))
                out["sheet_x"].append(grid[:, :, 0].mean(axis=0))
                out["ts"].append(ts)
    return {k: np.asarray(v) for k, v in out.items()}


def phases(d: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """(start, end) times of the press dwell and the slide, from the command."""
    cmd = d["cmd"]
    moving = np.linalg.norm(np.diff(cmd[:, 1:], axis=0), axis=1) > 1e-9
    edges = np.flatnonzero(np.diff(moving.astype(int)))
    t = cmd[:, 0]
    # moves: press [e0, e1], slide [e2, e3], lift [e4, e5]
    return {"dwell": (t[edges[1]], t[edges[2]]), "slide": (t[edges[2]], t[edges[3]]),
            "slide_late": (0.5 * (t[edges[2]] + t[edges[3]]), t[edges[3]])}


def summary(d: dict[str, np.ndarray]) -> dict[str, float]:
    w, mk, tm = d["wrench"], d["markers"], d["tm"]
    ph = phases(d)
    out = {"peak_abs_Fz_N": float(np.abs(w[:, 3]).max())}
    on = np.flatnonzero(np.abs(w[:, 3]) > 1.5)
    out["first_contact_s"] = float(w[on[0], 0]) if on.size else float("nan")
    rest = mk[0, :, :3]
    for name, (a, b) in (("dwell", ph["dwell"]), ("slide_late", ph["slide_late"])):
        sel = (w[:, 0] >= a) & (w[:, 0] <= b)
        out[f"{name}_Fz_N"] = float(w[sel, 3].mean())
        out[f"{name}_Ft_N"] = float(np.linalg.norm(w[sel, 1:3].mean(axis=0)))
        sm = (tm >= a) & (tm <= b)
        disp = mk[sm, :, :3] - rest
        out[f"{name}_marker_dz_um"] = float(disp[:, :, 2].mean() * 1e6)
        out[f"{name}_marker_shear_um"] = float(np.linalg.norm(disp[:, :, :2].mean(axis=(0, 1))) * 1e6)
        out[f"{name}_marker_dz_min_um"] = float(disp[:, :, 2].mean(axis=0).min() * 1e6)
        pz = d["pose"][(d["pose"][:, 0] >= a) & (d["pose"][:, 0] <= b), 3]
        out[f"{name}_ee_z_mm"] = float(pz.mean() * 1e3)
    a, b = ph["slide_late"]
    sel = (w[:, 0] >= a) & (w[:, 0] <= b)
    sm = (tm >= a) & (tm <= b)
    f_dir = w[sel, 1:3].mean(axis=0)
    m_dir = (mk[sm, :, :2] - rest[:, :2]).mean(axis=(0, 1))
    out["slide_cos_force_vs_marker_shear"] = float(f_dir @ m_dir / (np.linalg.norm(f_dir) * np.linalg.norm(m_dir)))
    out["sheet_zmax_mm"] = float(d["sheet_zmax"].max() * 1e3)
    out["duration_s"] = float(d["cmd"][-1, 0])
    return out


def _moves(d: dict[str, np.ndarray]) -> list[tuple[float, float, np.ndarray]]:
    cmd = d["cmd"]
    moving = np.linalg.norm(np.diff(cmd[:, 1:], axis=0), axis=1) > 1e-9
    edges = np.flatnonzero(np.diff(moving.astype(int)))
    return [(cmd[a + 1, 0], cmd[b + 1, 0], cmd[b + 1, 1:] - cmd[a + 1, 1:]) for a, b in zip(edges[::2], edges[1::2])]


def is_lift_fold(d: dict[str, np.ndarray]) -> bool:
    """A lift_fold's second move rises (a press_slide's slides at constant height)."""
    return _moves(d)[1][2][2] > 1e-3


def summary_lift_fold(d: dict[str, np.ndarray]) -> dict[str, float]:
    """The lift_fold quantities of the module docstring (N, mm, um, s)."""
    w, mk, tm, ts, prof = d["wrench"], d["markers"], d["tm"], d["ts"], d["sheet_profile"]
    (p0, p1, _), (f0, f1, _), (k0, _, _) = _moves(d)[:3]
    out = {"peak_abs_Fz_N": float(np.abs(w[:, 3]).max())}
    sel = (w[:, 0] >= p1) & (w[:, 0] <= f0)
    out["dwell_Fz_N"] = float(w[sel, 3].mean())
    hold = (f1, k0)
    sw = (w[:, 0] >= hold[0]) & (w[:, 0] <= hold[1])
    for i, ax in enumerate(("Fx", "Fy", "Fz")):
        out[f"hold_{ax}_N"] = float(w[sw, 1 + i].mean())
    ss = (ts >= hold[0]) & (ts <= hold[1])
    mean_prof = prof[ss].mean(axis=0)
    j = int(np.argmax(mean_prof))
    out["hold_arch_z_mm"] = float(mean_prof[j] * 1e3)
    out["hold_arch_x_mm"] = float(d["sheet_x"][ss].mean(axis=0)[j] * 1e3)
    sp = (d["pose"][:, 0] >= hold[0]) & (d["pose"][:, 0] <= hold[1])
    out["hold_ee_z_mm"] = float(d["pose"][sp, 3].mean() * 1e3)
    sm = (tm >= hold[0]) & (tm <= hold[1])
    disp = mk[sm, :, :3] - mk[0, :, :3]
    out["hold_marker_shear_x_um"] = float(disp[:, :, 0].mean() * 1e6)
    out["hold_marker_dz_um"] = float(disp[:, :, 2].mean() * 1e6)
    lifted = (w[:, 0] >= f0) & (w[:, 0] <= k0)
    out["max_pull_Fz_N"] = float(w[lifted, 3].max())
    out["max_pull_minus_Fx_N"] = float(-w[lifted, 1].min())
    out["initial_fold_mm"] = float(prof[:5].max(axis=1).mean() * 1e3)
    final = float(prof[ts >= ts[-1] - 0.1].mean(axis=0).max())
    out["final_fold_mm"] = final * 1e3
    top_end = prof[ts >= ts[-1] - SETTLE_WINDOW_S].max(axis=1)
    out["final_fold_range_mm"] = float((top_end.max() - top_end.min()) * 1e3)
    after = np.flatnonzero((ts >= k0) & (prof.max(axis=1) <= final + 1e-3))
    out["card_down_after_peel_s"] = float(ts[after[0]] - k0) if after.size else float("nan")
    out["duration_s"] = float(d["cmd"][-1, 0])
    return out


def main(argv: list[str]) -> int:
    a, b = load(Path(argv[0])), load(Path(argv[1]))
    kind = summary_lift_fold if is_lift_fold(a) else summary
    ref, ours = kind(a), kind(b)
    print(f"{'quantity':34s} {'reference':>12s} {'ours':>12s} {'ours/ref':>9s}")
    for k in ref:
        r, o = ref[k], ours[k]
        ratio = o / r if abs(r) > 1e-12 else float("nan")
        print(f"{k:34s} {r:12.4g} {o:12.4g} {ratio:9.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
