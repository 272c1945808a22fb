"""``python -m benchmarks.bench_fit``: time a material fit on a whole recording (issue: 3 parameters, 4 s).

Runs ``thinshell sysid`` in-process on a bag (default: the bundled ``bags/nominal_s101``, a 3.6 s
press-slide recording made by an independent engine) with the three default parameters (bending
stiffness, gel modulus, gel-sheet friction) over the whole recording, into a temporary output
directory (or ``--out``), and prints the wall time with the fit's own figures. Results are recorded
by hand in ``docs/benchmarks_log.md``.

Usage::

    python -m benchmarks.bench_fit [--bag DIR] [--params a,b,c] [--t-max S] [--dt S] [--json] [--out DIR]
                          [-- extra thinshell sysid options]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence

from sysid.cli import sysid_main

DEFAULT_PARAMS = "sheet.bending_stiffness,gel.youngs_modulus,friction.gel_sheet"


def build_parser(default_bag: str | Path | None = None) -> argparse.ArgumentParser:
    """The argument parser of ``python -m benchmarks.bench_fit``; ``default_bag`` is the ``--bag`` default
    (required when None)."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_fit", description="time a material fit on a recording")
    p.add_argument("--bag", default=None if default_bag is None else str(default_bag), required=default_bag is None,
                   help="bag directory (default: the caller's; the bundled nominal_s101 when run as a script)")
    p.add_argument("--params", default=DEFAULT_PARAMS, help="parameters to fit (default: %(default)s)")
    p.add_argument("--t-max", type=float, default=None, help="fit only the first T s (default: whole recording)")
    p.add_argument("--dt", type=float, default=0.01, help="simulation step in s (default: %(default)s)")
    p.add_argument("--out", default=None, help="keep the fit's output here (default: a temporary directory)")
    p.add_argument("--json", action="store_true", help="print one JSON line")
    p.add_argument("extra", nargs="*", help="further `thinshell sysid` options (after --)")
    return p


def bench_sysid_main(argv: Sequence[str] | None = None, default_bag: str | Path | None = None) -> int:
    """Run the benchmark; returns the exit code (that of ``thinshell sysid`` on failure).

    ``default_bag`` is the recording used without ``--bag`` (``--bag`` is required when None).

    The ``--json`` line has the keys ``bag``, ``params``, ``duration_s`` (fitted span of the
    recording), ``steps``, ``dt``, ``wall_s`` (the whole command), ``fit_wall_s`` (the fit itself),
    ``iterations``, ``sim_runs``, ``status``, ``values`` {name: [initial, fitted]}, ``rms``
    {channel: [before, after]}, ``python``, ``machine``.
    """
    args = build_parser(default_bag).parse_args(list(sys.argv[1:] if argv is None else argv))
    with tempfile.TemporaryDirectory(prefix="thinshell_bench_sysid_") as tmp:
        out = Path(args.out) if args.out else Path(tmp) / "fit"
        cmd = [args.bag, "--params", args.params, "--dt", str(args.dt), "--out", str(out), "--quiet", *args.extra]
        if args.t_max is not None:
            cmd += ["--t-max", str(args.t_max)]
        if args.out:
            cmd.append("--force")
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(sys.stderr):  # keep stdout for the benchmark's own record
            code = sysid_main(cmd)
        wall = time.perf_counter() - t0
        if code != 0:
            print(f"python -m benchmarks.bench_fit: thinshell sysid failed (exit {code})", file=sys.stderr)
            return code
        doc = json.loads((out / "fit.json").read_text(encoding="utf-8"))
    diag, metrics = doc["diagnostics"], doc["metrics"]
    record = {
        "bench": "sysid", "bag": str(args.bag), "params": args.params.split(","),
        "duration_s": diag["step_count"] * diag["dt"], "steps": diag["step_count"], "dt": diag["dt"],
        "wall_s": wall, "fit_wall_s": diag["wall_time_s"], "iterations": diag["iterations"],
        "sim_runs": diag["sim_runs"], "status": diag["status"],
        "values": {name: [p["initial"], p["value"]] for name, p in doc["fit"]["parameters"].items()},
        "rms": {ch: [metrics["rms_initial"][ch]["rms"], metrics["rms_final"][ch]["rms"]] for ch in metrics["rms_final"]},
        "python": platform.python_version(), "machine": f"{platform.machine()} x{_cpus()}",
    }
    if args.json:
        print(json.dumps(record))
    else:
        print(f"python -m benchmarks.bench_fit: {record['bag']}: {len(record['params'])} parameters, "
              f"{record['duration_s']:.2f} s of recording ({record['steps']} steps of {record['dt']} s)")
        for name, (a, b) in record["values"].items():
            print(f"  {name}: {a:.6g} -> {b:.6g}")
        print(f"  {record['iterations']} iterations, {record['sim_runs']} replays, status {record['status']}; "
              f"fit {record['fit_wall_s']:.1f} s, command {record['wall_s']:.1f} s")
    return 0


def _cpus() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


if __name__ == "__main__":
    from thinshell_ros.paths import bundled_bag

    sys.exit(bench_sysid_main(default_bag=bundled_bag()))
