"""``thinshell indent``: fit the gel's modulus to measured indentation depth / force pairs.

Usage::

    thinshell indent [--config FILE (default: the packaged FEATS config)] [--out DIR] [--force]
                     [--quadratic split|corners] [--friction MU] [--initial-modulus PA]
                     [--max-evaluations N]

Builds the gel + rigid indenter model of the data set (:func:`sysid.indentation_fit.build_indentation_setup`),
fits Young's modulus by the scaling iteration of :func:`sysid.indentation_fit.fit_youngs_modulus`
(each evaluation is a quasi-static depth sweep) and writes ``indent_fit.json``, ``force_depth.png``
and ``report.md``. The output directory is filled in a hidden sibling and renamed into place at the
end; an existing one is refused unless ``--force``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from sim_core.errors import ThinShellError
from sim_core.indentation import run_depth_sweep
from sim_core.provenance import git_revision
from sysid.data import FEATS_INDENTATION, data_file
from sysid.indentation_fit import build_indentation_setup, fit_youngs_modulus, load_indentation_config
from sysid.results import package_versions, staged_directory

PROG = "thinshell indent"
DEFAULT_CONFIG = data_file(FEATS_INDENTATION)
"""The FEATS data set's config (packaged ``sysid/data/feats_indentation.yaml``)."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``thinshell indent``."""
    p = argparse.ArgumentParser(prog=PROG, description="Fit the gel's Young's modulus to indentation measurements.")
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="indentation data set YAML (default: FEATS)")
    p.add_argument("--out", help="output directory (default: ./indent_<config name>)")
    p.add_argument("--force", action="store_true", help="replace an existing output directory")
    p.add_argument("--quadratic", choices=("split", "corners"), default="split",
                   help="10-node tets: 8 linear tets each on all nodes (default) or corners only "
                        "(8x fewer tets, faster, stiffer: volumetric locking at nu 0.475)")
    p.add_argument("--friction", type=float, default=None,
                   help="gel-indenter Coulomb coefficient (default: the config's `friction`)")
    p.add_argument("--initial-modulus", type=float, default=3.0e5, help="starting E in Pa (default: %(default)s)")
    p.add_argument("--max-evaluations", type=int, default=6, help="depth sweeps allowed (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    return p


def indent_main(argv: Sequence[str] | None = None) -> int:
    """Run ``thinshell indent`` with ``argv`` (default ``sys.argv[1:]``).

    Returns:
        0 on success; 2 for a usage error (existing output without ``--force``, bad value); 1 for a
        thinshell error (bad config or mesh, a sweep that does not converge, no fit), each reported
        as one line on stderr.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    config = Path(args.config)
    out = Path(args.out) if args.out else Path.cwd() / f"indent_{config.stem}"
    if (out.exists() or out.is_symlink()) and not args.force:
        return _error(f"output directory {out} exists (use --force to replace it)")
    if not (np.isfinite(args.initial_modulus) and args.initial_modulus > 0):
        return _error(f"--initial-modulus must be a positive number of Pa, got {args.initial_modulus}")
    if args.friction is not None and not (np.isfinite(args.friction) and args.friction >= 0):
        return _error(f"--friction must be a finite number >= 0, got {args.friction}")
    if args.max_evaluations < 1:
        return _error(f"--max-evaluations must be >= 1, got {args.max_evaluations}")
    try:
        return _run(args, argv, config, out)
    except ThinShellError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1


def _error(message: str) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return 2


def _run(args: argparse.Namespace, argv: list[str], config: Path, out: Path) -> int:
    cfg = load_indentation_config(config)
    if args.friction is not None:
        cfg.friction = float(args.friction)
    t0 = time.perf_counter()
    setup = build_indentation_setup(cfg, args.initial_modulus, args.quadratic)
    increment = float(cfg.simulation.get("max_increment", 2.5e-4))
    gel = setup.model.bodies[setup.gel_body]
    mesh_info = {"quadratic": args.quadratic, "gel_vertices": int(gel.vertex_stop - gel.vertex_start),
                 "gel_tets": int(len(gel.tets)), "dofs": int(setup.model.x_rest.size),
                 "indenter": setup.model.bodies[setup.indenter_body].kind}
    if mesh_info["indenter"] == "sphere":
        mesh_info["indenter_radius_m"] = setup.model.bodies[setup.indenter_body].material["radius"]
    _say(args, f"{config.name}: {mesh_info['gel_tets']} gel tets ({args.quadratic}), {mesh_info['dofs']} DoF, "
               f"{cfg.depth.size} depths up to {1e3 * cfg.depth.max():.3g} mm, friction {cfg.friction}")
    sweeps = []

    def simulate(E: float) -> np.ndarray:
        t = time.perf_counter()
        res = run_depth_sweep(setup, cfg.depth, increment, youngs_modulus=E)
        sweeps.append({"youngs_modulus": E, "force": res.force.tolist(), "steps": res.steps,
                       "newton_iterations": res.newton_iterations, "wall_s": time.perf_counter() - t})
        _say(args, f"sweep {len(sweeps)}: E = {E:.5g} Pa -> F/F_meas = "
                   f"{np.array2string(res.force / cfg.force, precision=3)} ({sweeps[-1]['wall_s']:.0f} s)")
        return res.force

    fit = fit_youngs_modulus(simulate, cfg.force, cfg.poisson_ratio, args.initial_modulus,
                             max_evaluations=args.max_evaluations)
    doc = {
        "schema": "thinshell.indent_fit/1",
        "config": str(config),
        "youngs_modulus_pa": fit.youngs_modulus,
        "poisson_ratio": fit.poisson_ratio,
        "friction": cfg.friction,
        "mu_pa": fit.mu,
        "c10_pa": fit.c10,
        "reference_c10_pa": cfg.reference_c10 if np.isfinite(cfg.reference_c10) else None,
        "c10_relative_to_reference": (fit.c10 / cfg.reference_c10 - 1.0) if np.isfinite(cfg.reference_c10) else None,
        "depth_m": cfg.depth.tolist(),
        "force_measured_n": cfg.force.tolist(),
        "force_model_n": fit.force_model.tolist(),
        "force_relative_error": fit.relative_error.tolist(),
        "history": [{"youngs_modulus": e, "objective": o} for e, o in fit.history],
        "sweeps": sweeps,
        "mesh": mesh_info,
        "wall_time_s": time.perf_counter() - t0,
        "provenance": {"git_revision": git_revision()[0], "versions": package_versions(),
                       "command": [PROG, *argv], "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())},
    }
    with staged_directory(out, args.force) as staging:
        (staging / "indent_fit.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        _plot(doc, staging / "force_depth.png")
        (staging / "report.md").write_text(_markdown(doc), encoding="utf-8")
    print(f"  E = {fit.youngs_modulus:.5g} Pa (nu {fit.poisson_ratio}), C10 = {fit.c10 / 1e6:.4g} MPa"
          + (f" vs reference {cfg.reference_c10 / 1e6:.4g} MPa ({100 * doc['c10_relative_to_reference']:+.1f} %)"
             if doc["reference_c10_pa"] else ""))
    print(f"  force errors: {np.array2string(100 * fit.relative_error, precision=1)} %  ({doc['wall_time_s']:.0f} s)")
    print(f"report: {out / 'report.md'} (also indent_fit.json, force_depth.png)")
    return 0


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(f"{PROG}: {text}", file=sys.stderr, flush=True)


def _plot(doc: dict, path: Path) -> Path:
    """Measured vs fitted force over depth (and the first sweep, at the initial modulus)."""
    import matplotlib  # optional heavy dependency: matplotlib, for plots only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # optional heavy dependency: matplotlib, for plots only

    d = 1e3 * np.asarray(doc["depth_m"])
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.plot(d, doc["force_measured_n"], "ko", label="measured")
    first = doc["sweeps"][0]
    ax.plot(d, first["force"], "--", color="0.6", label=f"initial E = {first['youngs_modulus'] / 1e3:.0f} kPa")
    ax.plot(d, doc["force_model_n"], "-", color="C0", label=f"fitted E = {doc['youngs_modulus_pa'] / 1e3:.0f} kPa")
    ax.set_xlabel("indenter displacement (mm)")
    ax.set_ylabel("normal force (N)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _markdown(doc: dict) -> str:
    """A short human report of an ``indent_fit.json`` document."""
    lines = ["# Indentation fit", "", f"Data set: `{doc['config']}`; gel mesh: {doc['mesh']['gel_tets']} linear tets "
             f"({doc['mesh']['quadratic']} quadratic elements), {doc['mesh']['dofs']} DoF; indenter: "
             + (f"exact sphere R = {1e3 * doc['mesh']['indenter_radius_m']:.4g} mm" if doc["mesh"]["indenter"] == "sphere"
                else "rigid surface mesh") + f"; gel-indenter Coulomb friction {doc['friction']}.", "",
             f"- Young's modulus E = {doc['youngs_modulus_pa']:.5g} Pa (Poisson ratio {doc['poisson_ratio']} held fixed)",
             f"- Neo-Hookean C10 = mu / 2 = {doc['c10_pa'] / 1e6:.4g} MPa"]
    if doc["reference_c10_pa"]:
        lines.append(f"- reference C10 = {doc['reference_c10_pa'] / 1e6:.4g} MPa: "
                     f"{100 * doc['c10_relative_to_reference']:+.1f} %")
    lines += ["", "| depth (mm) | measured (N) | fitted (N) | error |", "|---|---|---|---|"]
    for d, fm, fs, e in zip(doc["depth_m"], doc["force_measured_n"], doc["force_model_n"], doc["force_relative_error"]):
        lines.append(f"| {1e3 * d:.3g} | {fm:.4g} | {fs:.4g} | {100 * e:+.1f} % |")
    lines += ["", f"{len(doc['sweeps'])} depth sweeps, {doc['wall_time_s']:.0f} s.", "", "![force vs depth](force_depth.png)", ""]
    return "\n".join(lines)


def main() -> None:
    """Console entry point (``python -m sysid.indentation_cli``)."""
    sys.exit(indent_main())


if __name__ == "__main__":
    main()
