"""Wall time of one finite-difference Jacobian's replays (2p replays of a recording), serial against batched.

Usage: ``python benchmarks/jacobian_replays.py BAG [--arch cpu|cuda|numpy] [--t-max S] [--params a,b,c]
[--fd-step 0.01] [--same] [--repeat N]``. Builds the recording's observation model
(``sysid.observation.ObservationModel``), replays it once at the nominal values (the simulation built, the kernels
compiled), then replays the 2p central difference points ``u +- h e_i`` of ``sysid.fit`` (log coordinates for
positive parameters) one after another (``ObservationModel.simulate``) and as one lockstep batch
(``sysid.replay_batch.simulate_batch``), and prints one JSON record: both walls (``--repeat`` times, alternated;
the speed-up of the fastest of each), the largest gap between the two per channel in noise units and, per
parameter, the gap between the two central-difference columns of the whitened residual against the column's norm.
``--same``
replays 2p copies at the nominal values instead (one material group in the stacked model: what the batch costs
when its copies share their materials).
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("bag")
    ap.add_argument("--arch", default="cpu", choices=("numpy", "cpu", "cuda"))
    ap.add_argument("--t-max", type=float, default=None)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--params", default="sheet.bending_stiffness,gel.youngs_modulus,friction.gel_sheet")
    ap.add_argument("--fd-step", type=float, default=0.01)
    ap.add_argument("--same", action="store_true", help="every copy at the nominal values")
    ap.add_argument("--repeat", type=int, default=1, help="serial and batched replays, alternated, this many times")
    args = ap.parse_args()
    from sysid.evidence import load_evidence
    from sysid.fit import parameter_spec
    from sysid.observation import ObservationModel
    from sysid.replay_batch import simulate_batch

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(args.bag), dt=args.dt, t_max=args.t_max, arch=args.arch)
    t = time.perf_counter()
    model.simulate({})
    first = time.perf_counter() - t
    names = args.params.split(",")
    specs = [parameter_spec(n, model.parameter_value(n)) for n in names]
    sets = []
    for i in range(len(specs)):
        for sign in (1.0, -1.0):
            sets.append({} if args.same else {s.name: s.to_value(sign * args.fd_step if j == i else 0.0)
                                              for j, s in enumerate(specs)})
    serial_s, batched_s = [], []
    for _ in range(args.repeat):  # alternated, so that a change of the machine's load falls on both
        t = time.perf_counter()
        serial = [model.simulate(p) for p in sets]
        serial_s.append(round(time.perf_counter() - t, 2))
        t = time.perf_counter()
        batched, report = simulate_batch(model, sets)
        batched_s.append(round(time.perf_counter() - t, 2))
    gaps = {}
    for ch in ("markers_xyz", "markers_uv", "wrench", "sheet_points"):
        if ch in model.sigma:
            gaps[ch] = max(float(abs((a.channel(ch) - b.channel(ch)) / model.sigma[ch]).max())
                           for a, b in zip(serial, batched) if a is not None and b is not None)
    columns = {}  # the central-difference column of each parameter, both ways: their gap against its size
    for i, spec in enumerate(specs):
        if not args.same and all(x is not None for x in (*batched[2 * i:2 * i + 2], *serial[2 * i:2 * i + 2])):
            ends = [[model.residuals(model.predict(t)) for t in pair] for pair in
                    (serial[2 * i:2 * i + 2], batched[2 * i:2 * i + 2])]
            col_s, col_b = ((rp - rm) / (2.0 * args.fd_step) for rp, rm in ends)
            columns[spec.name] = {"norm": float(f"{np.linalg.norm(col_s):.4g}"),
                                  "relative_gap": float(f"{np.linalg.norm(col_b - col_s) / np.linalg.norm(col_s):.3g}")}
    print(json.dumps({
        "bag": args.bag, "arch": args.arch, "steps": model.step_count, "replays": len(sets), "same": args.same,
        "first_replay_s": round(first, 2), "serial_s": serial_s, "batched_s": batched_s,
        "speedup": round(min(serial_s) / min(batched_s), 3),
        "batches": report.batches, "serial_fallbacks": report.serial,
        "resumed": report.resumed, "max_gap_sigma": {k: float(f"{v:.3g}") for k, v in gaps.items()},
        "diverged": [i for i, b in enumerate(batched) if b is None], "jacobian_columns": columns,
    }))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
