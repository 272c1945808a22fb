"""Compare two press_slide recordings phase by phase (same-kind check of a generated bag against a reference).

    python -m benchmarks.mujoco_world.compare REF_BAG OUR_BAG

Prints, for each recording: peak |F_z|, mean F_z / tangential force / marker z and shear (sensor
frame) in the press dwell and in the second half of the slide, the time of first contact
(|F_z| > 1.5 N) and the measured effector depth in the dwell. Reads bags with ``rosbags`` only.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader


def load(bag: Path) -> dict[str, np.ndarray]:
    """Arrays of a bag: cmd/pose (N, 4: t x y z), wrench (N, 7: t F T), markers (M, 63, 5), t_markers (M,), sheet z max."""
    out: dict[str, list] = {"cmd": [], "pose": [], "wrench": [], "markers": [], "tm": [], "sheet_zmax": []}
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
                out["sheet_zmax"].append(np.frombuffer(bytes(m.data), dtype="<f4").reshape(-1, 3)[:, 2].max())
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


def main(argv: list[str]) -> int:
    ref, ours = summary(load(Path(argv[0]))), summary(load(Path(argv[1])))
    print(f"{'quantity':34s} {'reference':>12s} {'ours':>12s} {'ours/ref':>9s}")
    for k in ref:
        r, o = ref[k], ours[k]
        ratio = o / r if abs(r) > 1e-12 else float("nan")
        print(f"{k:34s} {r:12.4g} {o:12.4g} {ratio:9.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
