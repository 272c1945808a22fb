"""Generate one labelled recording of the MuJoCo reference world (bag + scene.yaml + label.yaml).

    python -m benchmarks.mujoco_world.generate OUT_DIR --scene REF_BAG/scene.yaml \
        --variant stiction --magnitude 1.5 --motion press_slide --seed 201 [--direction +x]
    python -m benchmarks.mujoco_world.generate OUT_DIR --scene ... --like LABELS.yaml:nominal_s101

``--like`` takes the variant, magnitude, motion and true values of a labelled recording (used to
re-run a reference recording's motion for comparison); otherwise they are drawn from ``--seed``.

Variants (``VARIANTS``) and their magnitude:
  nominal (none); stiction: static / kinetic gel-card friction; damped: gel Rayleigh damping (s),
  the card's raised to 0.02 s as in the reference; plastic: card bend yield strain;
  latency: tactile latency (s); lens: k1; force_bias: bias scale in noise sigmas; gel_creep: tau (s).
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from benchmarks.mujoco_world import motion as motion_mod
from benchmarks.mujoco_world.observe import NOISE, SENSOR_QUAT_XYZW, observe

VARIANTS = {"nominal": "none", "stiction": "physics", "damped": "physics", "plastic": "physics",
            "latency": "data", "lens": "data", "force_bias": "data", "gel_creep": "data"}
MAGNITUDE_KEY = {"stiction": "static_over_kinetic_friction", "damped": "gel_rayleigh_damping_s",
                 "plastic": "sheet_bend_yield_strain", "latency": "tactile_latency_s", "lens": "k1",
                 "force_bias": "bias_scale_sigma", "gel_creep": "tau_s"}


def nominal_truth(scene: Mapping[str, Any]) -> dict[str, Any]:
    """The reference world's MuJoCo values at the scene's nominal materials (labels' ``mujoco`` format)."""
    sh, tac = scene["sheet"], scene["sensors"]["tactile"]
    E, nu, t = float(sh["material"]["youngs_modulus"]), float(sh["material"]["poisson_ratio"]), float(sh["thickness"])
    return {"timestep": 0.001,
            "sheet": {"young": E, "poisson": nu, "thickness": t, "density": float(sh["density"]), "elastic2d": "both",
                      "rayleigh_damping": 0.002, "bend_yield": 0.0,
                      "bending_stiffness_D": E * t**3 / (12 * (1 - nu**2)), "clamped_edge": sh["clamped_edge"]},
            "gel": {"young": float(tac["gel_material"]["youngs_modulus"]),
                    "poisson": float(tac["gel_material"]["poisson_ratio"]),
                    "density": float(tac["gel_material"]["density"]), "rayleigh_damping": 0.003, "stretch_yield": 0.0},
            "friction": {"gel_sheet_kinetic": float(tac["friction"]), "gel_sheet_static": float(tac["friction"]),
                         "sheet_table": float(scene["table"]["friction"])},
            "contact": {"solref": [0.001, 1.0], "solimp": [0.999, 0.9999, 0.0001, 0.5, 2.0], "cone": "elliptic",
                        "impratio": 1.0},
            "ee_drive": {"kp_N_per_m": 3000.0, "dampratio": 1.0, "mass": 0.08},
            "tack": {"bond_strength_N": 0.25, "solref": [0.005, 1.0]}}


def jitter(truth: dict[str, Any], rng: np.random.Generator, frac: float) -> dict[str, Any]:
    """Material jitter of up to ``frac`` (uniform): card E, gel E, gel nu (half as much, < 0.49), both frictions."""
    out = copy.deepcopy(truth)
    if frac <= 0:
        return out
    u = lambda: 1.0 + rng.uniform(-frac, frac)  # noqa: E731
    out["sheet"]["young"] *= u()
    s = out["sheet"]
    s["bending_stiffness_D"] = s["young"] * s["thickness"] ** 3 / (12 * (1 - s["poisson"] ** 2))
    out["gel"]["young"] *= u()
    out["gel"]["poisson"] = min(0.49, out["gel"]["poisson"] * (1.0 + rng.uniform(-frac, frac) / 2))
    k = u()
    out["friction"]["gel_sheet_kinetic"] *= k
    out["friction"]["gel_sheet_static"] *= k
    out["friction"]["sheet_table"] *= u()
    return out


def apply_variant(truth: dict[str, Any], variant: str, magnitude: float | None, rng: np.random.Generator,
                  ) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any] | None]:
    """Truth with the physics effect applied, the data effects for :func:`observe`, and effect_params for the labels.

    Raises:
        ValueError: unknown variant or a missing magnitude.
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; one of {sorted(VARIANTS)}")
    if variant != "nominal" and magnitude is None:
        raise ValueError(f"variant {variant} needs --magnitude")
    truth = copy.deepcopy(truth)
    effects: dict[str, Any] = {}
    effect_params = None
    if variant == "stiction":
        truth["friction"]["gel_sheet_static"] = truth["friction"]["gel_sheet_kinetic"] * magnitude
    elif variant == "damped":
        truth["gel"]["rayleigh_damping"] = magnitude
        truth["sheet"]["rayleigh_damping"] = 0.02
        effect_params = {"sheet_rayleigh_damping_s": 0.02}
    elif variant == "plastic":
        truth["sheet"]["bend_yield"] = magnitude
    elif variant == "latency":
        effects["tactile_latency_s"] = magnitude
    elif variant == "lens":
        effects["k1"] = magnitude
    elif variant == "gel_creep":
        effects["gel_creep_tau_s"] = magnitude
    elif variant == "force_bias":
        sig = np.array([NOISE["force_xy"], NOISE["force_xy"], NOISE["force_z"]] + [NOISE["torque"]] * 3)
        sgn = rng.choice([-1.0, 1.0], size=6)
        effect_params = {"offset": list(sgn * magnitude * sig * rng.uniform(0.5, 1.0, 6)),
                         "drift_per_s": list(rng.uniform(-0.5, 0.5, 6) * magnitude * sig),
                         "wobble_amp": list(rng.uniform(0.1, 0.3, 6) * magnitude * sig),
                         "wobble_period_s": float(rng.uniform(2.0, 5.0)),
                         "wobble_phase": list(rng.uniform(0, 2 * np.pi, 6))}
        effect_params = {k: (v if isinstance(v, float) else [float(x) for x in v]) for k, v in effect_params.items()}
        effects["force_bias"] = effect_params
    return truth, effects, effect_params


def _motion_from_labels(m: Mapping[str, Any], contact_z: float) -> motion_mod.Motion:
    if m["kind"] == "press_slide":
        return motion_mod.press_slide(m["start_xy"], m["depth"], m["slide"], m["height"], m["v_press"],
                                      m["v_slide"], m["v_lift"], contact_z)
    return motion_mod.lift_fold_like(m, contact_z)


def generate(out_dir: Path, scene: dict[str, Any], variant: str, magnitude: float | None, seed: int,
             motion_kind: str = "press_slide", direction: str | None = None, jitter_frac: float = 0.1,
             like: Mapping[str, Any] | None = None, log=print, bond_wrench: str = "reference",
             short: bool = False, stiction_switch: str = "speed") -> dict[str, Any]:
    """Simulate and write one recording; returns its labels entry (reference format).

    ``short``: a short press_slide (:data:`benchmarks.mujoco_world.motion.SHORT_PRESS_SLIDE`);
    ``stiction_switch``: :func:`benchmarks.mujoco_world.world.run`'s (written to the label)."""
    from benchmarks.mujoco_world.bagwrite import write_bag
    from benchmarks.mujoco_world.world import run

    rng = np.random.default_rng(seed)
    contact_z = float(scene["sheet"]["origin"][2]) + float(scene["sheet"]["thickness"]) / 2
    if like is not None:
        variant, seed = like["variant"], int(like["seed"])
        magnitude = None if like["magnitude"] is None else float(next(iter(like["magnitude"].values())))
        motion = _motion_from_labels(like["motion"], contact_z)
        truth = copy.deepcopy(like["mujoco"])
        jitter_frac = float(like["material_jitter"])
        base = nominal_truth(scene)
        base.update({k: truth[k] for k in base})
        truth, effects, effect_params = base, {}, like.get("effect_params")
        if like["magnitude"] is not None and VARIANTS[variant] == "data":
            effects = {"latency": {"tactile_latency_s": magnitude}, "lens": {"k1": magnitude},
                       "gel_creep": {"gel_creep_tau_s": magnitude}, "force_bias": {"force_bias": effect_params}}[variant]
    else:
        motion = (motion_mod.sample_press_slide(rng, contact_z, direction, short) if motion_kind == "press_slide"
                  else motion_mod.sample_lift_fold(rng, contact_z))
        truth = jitter(nominal_truth(scene), rng, jitter_frac)
        truth, effects, effect_params = apply_variant(truth, variant, magnitude, rng)
    log(f"{out_dir.name}: {variant} {magnitude} {motion.kind} {motion.duration_s:.2f}s")
    rec = run(scene, truth, motion, log=log, bond_wrench=bond_wrench, stiction_switch=stiction_switch)
    streams = observe(rec, scene, motion.duration_s, effects, rng)
    out_scene = copy.deepcopy(scene)
    out_scene["dt"] = float(truth["timestep"])
    out_scene["effectors"]["ee"]["initial_pose"] = [float(x) for x in motion.start] + list(SENSOR_QUAT_XYZW)
    counts = write_bag(out_dir, streams, SENSOR_QUAT_XYZW)
    (out_dir / "scene.yaml").write_text(yaml.safe_dump(out_scene, sort_keys=False), encoding="utf-8")
    label = {"bag": out_dir.name, "variant": variant, "kind": VARIANTS[variant], "seed": int(seed),
             "magnitude": None if variant == "nominal" else {MAGNITUDE_KEY[variant]: float(magnitude)},
             "effect_params": effect_params, "material_jitter": float(jitter_frac),
             "motion": motion.labels(), "mujoco": _plain(truth), "sim": rec.stats,
             "messages": counts, "generator": "benchmarks/mujoco_world (thinshell), MuJoCo 4.0.0"}
    if motion.tack_on_s is not None:
        label["bond_wrench"] = bond_wrench
    if variant == "stiction":
        label["stiction_switch"] = stiction_switch
    (out_dir / "label.yaml").write_text(yaml.safe_dump({out_dir.name: label}, sort_keys=False), encoding="utf-8")
    return label


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--scene", type=Path, required=True, help="scene.yaml (v1) giving the geometry and nominal values")
    ap.add_argument("--variant", default="nominal", choices=sorted(VARIANTS))
    ap.add_argument("--magnitude", type=float)
    ap.add_argument("--motion", default="press_slide", choices=["press_slide", "lift_fold"])
    ap.add_argument("--direction", choices=["+x", "-x", "+y", "-y", "diag"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jitter", type=float, default=0.1, help="material jitter fraction (0.1: up to 10 %%)")
    ap.add_argument("--like", help="LABELS.yaml:NAME: re-run that labelled recording's variant, motion and values")
    ap.add_argument("--bond-wrench", default="reference", choices=["reference", "physical"],
                    help="tack bonds in the wrench: the force on the card as the reference records it, or on the gel")
    ap.add_argument("--short", action="store_true",
                    help="a short press_slide (2.3-2.7 s: shortest rests, 10-12 mm slide; motion.SHORT_PRESS_SLIDE)")
    ap.add_argument("--stiction-switch", default="speed", choices=["speed", "load"],
                    help="static -> kinetic friction when the contact layer moves (speed, the default) or at gross "
                         "breakaway, the load at the static limit (load); world.py's docstring")
    a = ap.parse_args(argv)
    scene = yaml.safe_load(a.scene.read_text(encoding="utf-8"))
    like = None
    if a.like:
        path, name = a.like.rsplit(":", 1)
        like = yaml.safe_load(Path(path).read_text(encoding="utf-8"))[name]
    generate(a.out_dir, scene, a.variant, a.magnitude, a.seed, a.motion, a.direction, a.jitter, like,
             bond_wrench=a.bond_wrench, short=a.short,
             stiction_switch=a.stiction_switch)
    return 0


if __name__ == "__main__":
    sys.exit(main())
