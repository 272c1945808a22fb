"""The displacement bounds of ``covers`` where the positions' Taichi array is equal the host's, and the contact set's
``covers`` gives the same answers from the device array as from the host positions."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.contact_set import ContactSet
from tests.sim_core.test_contact_set import _two_grid_sheets


def _on_device(x: np.ndarray):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.transfer import upload

    return upload(new_ndarray(ti.f64, x.shape), x)


@pytest.mark.parametrize("seed, device_tables", [(0, False), (1, False), (0, True)])
def test_bounds_equal_the_hosts_per_segment_and_flag_nan(ti_cpu, monkeypatch, seed, device_tables):
    """Per segment and axis the largest and smallest ``x - x_search`` and the largest ``|x - x_search|`` equal
    NumPy's ``reduceat`` bit for bit (segments longer than a chunk, vertices before the first segment counted
    in the largest only); a NaN coordinate makes its segment's bounds and the largest NaN, no other's. With
    ``device_tables`` the arch query answers "cuda" (the CPU arch's loops stay serial): the chunk and segment
    tables are Taichi ndarrays sent once, no NumPy argument reaches a launch, and the bounds are the same."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import displacement_bounds as module
    from sim_core.ti_kernels.displacement_bounds import CHUNK, DisplacementBounds

    if device_tables:
        import sim_core.ti_backend

        monkeypatch.setattr(sim_core.ti_backend, "current_arch", lambda: "cuda")
        launches = []
        for name in ("_chunk_bounds", "_segment_bounds"):
            kernel = getattr(module, name)
            monkeypatch.setattr(module, name, lambda *a, kernel=kernel: (launches.append(a), kernel(*a))[1])

    rng = np.random.default_rng(seed)
    n = 3 * CHUNK + 77
    starts = np.array([5, 40, 41, 2 * CHUNK + 3])
    x_search = rng.normal(size=(n, 3))
    x = x_search + rng.normal(scale=1e-3, size=(n, 3))
    x[2] += 1.0  # before the first segment: the largest only
    bounds = DisplacementBounds(n, starts)
    high, low, largest = bounds(x_search, _on_device(x), kept=False)
    moved = x - x_search
    np.testing.assert_array_equal(high, np.maximum.reduceat(moved, starts, axis=0))
    np.testing.assert_array_equal(low, np.minimum.reduceat(moved, starts, axis=0))
    assert largest == float(np.abs(moved).max()) and largest > 1.0 - 1e-2
    x[60, 1] = np.nan  # segment 2 (from 41)
    high, low, largest = bounds(x_search, _on_device(x), kept=False)
    assert np.isnan(largest)
    assert np.all(np.isnan(high[2])) and np.all(np.isnan(low[2]))
    others = [0, 1, 3]
    np.testing.assert_array_equal(high[others], np.maximum.reduceat(moved, starts, axis=0)[others])
    if device_tables:
        assert len(launches) == 4 and not any(isinstance(a, np.ndarray) for args in launches for a in args)
        tables = {name: entry[1] for name, entry in bounds._device.items()}
        assert set(tables) == {"chunk_start", "first_chunk", "stop_chunk"}
        assert all(isinstance(t, ti.lang._ndarray.ScalarNdarray) for t in tables.values())
        assert launches[2][2] is tables["chunk_start"] and launches[3][1] is tables["first_chunk"]  # sent once
    with pytest.raises(ValueError, match="increase"):
        DisplacementBounds(n, np.array([4, 4]))


def test_covers_from_the_device_array_answers_as_from_the_host(ti_cpu):
    """``covers(x_search, x, x_device)`` on the Taichi backend equals ``covers(x_search, x)`` on the cases of the
    host test (a common translation, every vertex within margin / 2, sheets closing by 1.1 and 0.9 margin, a
    self-contact gap closing, NaN); a frozen search position is sent once, another one again."""
    host = _two_grid_sheets()
    cs = ContactSet(host.model, backend="taichi-cpu")
    x0 = cs.model.x_rest.copy()
    m = cs.margin
    cases = [x0 + np.array([3.0 * m, -5.0 * m, 2.0 * m])]
    x = x0.copy()
    x[:, 2] += 0.45 * m
    x[25:, 0] -= 0.45 * m
    cases.append(x)
    x = x0 + np.array([4.0 * m, 0.0, 0.0])
    x[25:, 2] -= 0.6 * m
    x[:25, 2] += 0.5 * m
    cases.append(x.copy())
    x[:25, 2] -= 0.2 * m
    cases.append(x.copy())
    x = x0 + 2.0 * m
    x[7, 1] += 1.1 * m
    cases.append(x.copy())
    x[7] = np.nan
    cases.append(x)
    x_search = x0.copy()
    x_search.flags.writeable = False
    answers = [host.covers(x_search, x) for x in cases]
    assert answers == [True, True, False, True, False, False]
    assert [cs.covers(x_search, x, _on_device(x)) for x in cases] == answers
    sent = cs._bounds._search[1]
    assert cs._bounds._search[0] is x_search  # kept: the same array object on the next calls
    other = x0 + 0.1 * m
    other.flags.writeable = False
    assert cs.covers(other, cases[0], _on_device(cases[0])) == host.covers(other, cases[0])
    assert cs._bounds._search[0] is other and cs._bounds._search[1] is sent  # sent again into the same array
    with pytest.raises(ValueError, match="positions must be"):
        cs.covers(x_search, cases[0], _on_device(cases[0][:-1]))
