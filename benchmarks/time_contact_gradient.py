"""Time the contact pair potentials' gradient at new trial points of a lockstep batch: host rows against the device.

Usage: ``python benchmarks/time_contact_gradient.py --arch cuda --B 1024 [--trials 8]``.
Steps ``B`` Forming copies in lockstep twice (``parts_lockstep.stepped_forming``), takes the contact set's pair
potentials of the last iterate and the stacked positions ``x`` (``(N, 3)``, m), and evaluates their gradient at
``--trials`` new trial points (``x`` plus 1 um of noise, each a new read-only array, as the lockstep's trial
points are):

- ``host``: ``gradient_rows`` of both potentials added into a host ``(3 N,)`` array at their vertices, as
  ``sim_core.batch.iterates.summed_gradient`` adds a :class:`~sim_core.energies.base.SparseGradient` term;
- ``device`` (where the potentials declare :class:`~sim_core.energies.base.DeviceGradient`): ``add_gradient_on_device``
  of both into a Taichi ndarray, the positions read from their ndarray (uploaded before the clock starts, as the
  lockstep keeps them on the device), then a device synchronisation.

Prints the wall time a trial point (median and minimum, ms) of each, the launches' pair and vertex counts, and the
largest difference between the two gradients relative to the largest entry.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=16)
    ap.add_argument("--trials", type=int, default=8)
    args = ap.parse_args()
    from sim_core.energies import base
    from sim_core.energies.base import declares
    from sim_core.ti_backend import init_backend, ti

    from parts_lockstep import stepped_forming  # (benchmarks/, the script's folder)

    init_backend(args.arch)
    run = stepped_forming(args.B, args.arch, horizon=2)
    engine = run.batch.lockstep
    vt, ee = engine.solver.contact._last_pots
    x0 = np.array(engine.state.x, dtype=np.float64)
    n = len(x0)
    batch = vt._batch
    print(f"B={args.B}: {n} vertices, {len(vt.pairs)} + {len(ee.pairs)} pairs, {len(batch.own)} vertices named")
    rng = np.random.default_rng(0)

    def trial() -> np.ndarray:
        x = x0 + 1.0e-6 * rng.normal(size=x0.shape)
        x.flags.writeable = False
        return x

    def host(x: np.ndarray) -> np.ndarray:
        g = np.zeros(3 * n)
        for pot in (vt, ee):
            vertices, rows = pot.gradient_rows(x)
            g.reshape(-1, 3)[vertices] += rows
        return g

    times = {"host": [], "device": []}
    results = {}
    for _ in range(args.trials + 1):  # the first of each: not timed
        x = trial()
        t = time.perf_counter()
        results["host"] = host(x)
        times["host"].append(time.perf_counter() - t)
    if declares(vt, base.DeviceGradient):
        from sim_core.ti_kernels.device_copy import new_ndarray
        from sim_core.ti_kernels.transfer import download, upload

        x_device, g_device = new_ndarray(ti.f64, x0.shape), new_ndarray(ti.f64, x0.shape)
        zeros = np.zeros(x0.shape)
        for _ in range(args.trials + 1):
            x = trial()
            upload(x_device, x)
            upload(g_device, zeros)
            ti.sync()
            t = time.perf_counter()
            for pot in (vt, ee):
                pot.add_gradient_on_device(x, x_device, g_device)
            ti.sync()
            times["device"].append(time.perf_counter() - t)
        expected = host(x)
        got = download(g_device).reshape(-1)
        scale = float(np.abs(expected).max()) or 1.0
        print(f"largest |device - host| / largest |host| at the last trial point: "
              f"{float(np.abs(got - expected).max()) / scale:.2e}")
    for name, values in times.items():
        if values[1:]:
            ms = [1e3 * v for v in values[1:]]
            print(f"{name:7s} gradient of both pair potentials at a new trial point: "
                  f"median {statistics.median(ms):.2f} ms, min {min(ms):.2f} ms over {len(ms)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
