"""The lockstep line search's backtrack on the device (sim_core.ti_kernels.backtrack): over successive trial points,
each copy's slope and Armijo tests, acceptance, halving, backtrack count, kept energy and next step size equal the
host's (sim_core.batch.line_search: armijo_accepts and the loop's halvings) bit for bit, NaN and infinite slopes and
energies included, with the energies' device part read from the scalars' extra row or absent, and the host part sent
or left out where it is zero."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.batch.line_search import armijo_accepts

C = 1e-4  # SolverConfig's armijo_c


def _reference(state: dict, s: np.ndarray, energy: np.ndarray) -> dict:
    """The host line search's per-copy step (CopyLineSearch._line_search_copies, per-copy energies)."""
    out = {k: np.copy(v) for k, v in state.items()}
    cand = out["pending"] & np.isfinite(s) & (s <= out["bound"])
    ok = armijo_accepts(cand, energy, out["e0"], out["a"], out["slope"], C)
    out["energy"] = np.where(ok, energy, out["energy"])
    out["accepted"] |= ok
    out["taken"][ok] = out["a"][ok]
    out["pending"] &= ~ok
    out["backtracks"][out["pending"]] += 1
    out["halved"] = int(out["pending"].sum())
    out["a"][out["pending"]] *= 0.5
    out["alpha"] = np.where(out["pending"], out["a"], 0.0) + out["taken"]
    return out


def _scalars(s: np.ndarray, largest: np.ndarray, device_energy: np.ndarray | None):
    """The scalars kernel's int64 output (rows: slope bits, largest |g| bits, its NaN flag, ..., device energies)."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.copy_vectors import SCALARS
    from sim_core.ti_kernels.device_copy import new_ndarray

    B = len(s)
    rows = np.zeros((SCALARS + 1, B), dtype=np.int64)
    rows[0] = s.view(np.int64)
    rows[1] = np.where(np.isnan(largest), 0.0, largest).view(np.int64)
    rows[2] = np.isnan(largest)
    if device_energy is not None:
        rows[SCALARS] = device_energy.view(np.int64)
    out = new_ndarray(ti.i64, (rows.size,))
    out.from_numpy(rows.reshape(-1))
    return out


@pytest.mark.parametrize("with_device", [True, False], ids=["device-energies", "host-energies"])
def test_the_device_backtrack_decides_as_the_host_over_successive_trial_points(ti_cpu, with_device):
    from sim_core.ti_kernels.backtrack import DeviceBacktrack

    rng = np.random.default_rng(7)
    B = 257
    e0 = rng.normal(scale=1e-3, size=B)
    slope = -np.abs(rng.normal(scale=1e-3, size=B))
    slope[:5] = 0.0
    alpha = rng.uniform(0.1, 1.0, B)
    alpha[5:9] = 0.0  # open copies that take no step: accepted at once
    open_ = rng.random(B) < 0.9
    pending, accepted = open_ & (alpha > 0), open_ & (alpha == 0)
    bound = (1.0 - 2.0 * C) * np.abs(slope)
    search = DeviceBacktrack(B)
    trial = search.start(e0, slope, bound, np.where(pending, alpha, 0.0), pending, accepted, np.zeros(B), e0,
                         np.zeros(B, dtype=np.int64))
    state = {"pending": pending, "accepted": accepted, "a": np.where(pending, alpha, 0.0), "taken": np.zeros(B),
             "energy": e0.copy(), "backtracks": np.zeros(B, dtype=np.int64), "e0": e0, "slope": slope,
             "bound": bound}
    np.testing.assert_array_equal(trial, np.where(pending, alpha, 0.0) + 0.0)
    accepted_any = halved_any = False
    for k in range(6):
        # a trial's slope: mostly descending, some copies uphill, NaN or infinite; its energy near the start's
        s = np.where(rng.random(B) < 0.7, -np.abs(rng.normal(scale=1e-3, size=B)), rng.normal(scale=1e-3, size=B))
        s[rng.random(B) < 0.05] = np.nan
        s[rng.random(B) < 0.03] = np.inf
        s[:3] = bound[:3]  # on the slope test's bound: passes it
        s[13:20] = np.nan  # these copies halve at every trial point
        change = state["a"] * slope * rng.uniform(-0.5, 2.0, B)  # some meet Armijo's decrease, some do not
        change[10:12] = C * state["a"][10:12] * slope[10:12] + 1e-14 * np.abs(e0[10:12])  # exactly on the line
        host_part = rng.normal(scale=1e-4, size=B) if k != 2 else np.zeros(B)  # k = 2: nothing sent
        host_sums = rng.normal(scale=1e-5, size=B) if k != 2 else np.zeros(B)
        if with_device:
            device = e0 + change - host_part - host_sums
            device[rng.random(B) < 0.05] = np.nan
            energy = host_part + (device + host_sums)
        else:
            device = None
            energy = host_part + host_sums
            energy[: B // 2] = (e0 + change)[: B // 2]
            host_part = energy - host_sums
            energy = host_part + host_sums
        largest = np.abs(rng.normal(size=B))
        largest[rng.random(B) < 0.05] = np.nan
        got = search.decide(_scalars(s, largest, device), with_device, host_part, host_sums, C)
        state = _reference(state, s, energy)
        for name in ("pending", "accepted", "backtracks", "taken", "energy", "alpha", "halved"):
            np.testing.assert_array_equal(got[name], state[name], err_msg=f"{name} at trial {k}")
        np.testing.assert_array_equal(got["largest"], largest)
        accepted_any |= bool((got["accepted"] & ~accepted).any())
        halved_any |= got["halved"] > 0
    assert accepted_any and halved_any and state["pending"].any()  # every branch taken, some copies still pending
