"""Coverage of the fit's 2-sigma intervals on this simulator's recordings with a concealed difference.

Usage::

    PYTHONPATH=. python benchmarks/sysid_coverage.py OUT_DIR [CONCEALED,...] [SEED,...]

For each concealed difference (``tests/sysid/concealed.py``: gel_mesh_fine, table_friction_0.5,
gel_nu_0.40, contact_stiffness_x3) and seed, a recording is written to ``OUT_DIR``, the gel modulus and
gel-sheet friction are fitted (``sysid.fit.fit(robust="hac", nuisance=DEFAULT_NUISANCE)``) and the
error is compared with the Gauss-Newton, scaled, HAC-only, block-bootstrap and reported robust
(HAC + nuisance) 1-sigma, and with the interval the fit reports (``interval``: :mod:`sysid.identifiability`, the
prior range of :data:`sysid.calibration.CALIBRATION_BOUNDS` around the start, ``--profile-replays`` replays a side).
Prints one JSON line per fit and the coverage of each 2-sigma interval; writes ``OUT_DIR/rows.json``.
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path

import sysid.fit as fit_module
from sysid.calibration import CALIBRATION_BOUNDS
from sysid.covariance import model_robust_covariance
from sysid.fit_region import sigma_of
from sysid.identifiability import prior_ranges
from sysid.evidence import load_evidence
from sysid.fit import DEFAULT_NUISANCE, fit
from sysid.observation import ObservationModel
from tests.sysid.concealed import CONCEALED, concealed_recording
from tests.sysid.simbag import DT

PARAMS = ("gel.youngs_modulus", "friction.gel_sheet")
KINDS = ("sigma", "sigma_scaled", "sigma_hac", "sigma_boot", "sigma_robust", "interval")


def main(argv: list[str]) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="sysid_coverage.py", description=__doc__.split("\n")[0])
    p.add_argument("out", help="output folder (recordings and rows.json)")
    p.add_argument("concealed", nargs="?", default=",".join(CONCEALED),
                   help="comma list of concealed differences (default: all of tests/sysid/concealed.py)")
    p.add_argument("seeds", nargs="?", default="1,2", help="comma list of seeds (default 1,2)")
    p.add_argument("--profile-replays", type=int, default=0,
                   help="replays on each side of each parameter's profile (sysid.identifiability; default 0)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    concealed = args.concealed.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    captured = {}

    def capture(model, J, r, method="hac", seed=0):  # the final J and r of the fit, for the bootstrap
        captured.update(model=model, J=J, r=r)
        return model_robust_covariance(model, J, r, method, seed)

    fit_module.model_robust_covariance = capture
    rows = []
    for seed in seeds:
        for name in concealed:
            t0 = time.perf_counter()
            bag, truth = concealed_recording(out / f"{name}_s{seed}", name, seed)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                model = ObservationModel(load_evidence(bag), dt=DT)
            start = {n: model.parameter_value(n) for n in PARAMS}
            res = fit(model, PARAMS, robust="hac", nuisance=DEFAULT_NUISANCE,
                      prior=prior_ranges(start, CALIBRATION_BOUNDS), profile_replays=args.profile_replays)
            boot = model_robust_covariance(captured["model"], captured["J"], captured["r"], "block_bootstrap")
            s_boot = sigma_of(res.specs, res.values, boot.covariance_u)
            s_hac = sigma_of(res.specs, res.values, res.robust.time_covariance_u)
            row = {"concealed": name, "seed": seed, "status": res.status, "reduced_chi2": res.reduced_chi2,
                   "replays": res.sim_runs, "wall_s": time.perf_counter() - t0, "lag_bins": res.robust.lag_bins,
                   "params": {n: {"truth": truth[n], "value": res.values[n], "sigma": res.sigma[n],
                                  "sigma_scaled": res.sigma_scaled[n], "sigma_hac": s_hac[n],
                                  "sigma_boot": s_boot[n], "sigma_robust": res.sigma_robust[n],
                                  "interval": [res.intervals[n].lower, res.intervals[n].upper],
                                  "identified": res.intervals[n].identified} for n in PARAMS}}
            rows.append(row)
            print(json.dumps(row), flush=True)
            (out / "rows.json").write_text(json.dumps(rows, indent=1))
    values = [p for r in rows for p in r["params"].values()]
    for kind in KINDS:
        hits = sum(p[kind][0] <= p["truth"] <= p[kind][1] if kind == "interval" else
                   abs(p["value"] - p["truth"]) <= 2.0 * p[kind] for p in values)
        print(f"{kind}: 2-sigma interval covers {hits} / {len(values)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
