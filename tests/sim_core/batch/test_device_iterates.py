"""The lockstep loop's vectors on the device (sim_core.batch.device_iterates, taichi-cpu): the stacked gradient summed
there equals the host's sum (a term adding its own gradient on the device, sparse rows and dense host gradients
uploaded), the lumped quadratic's device gradient and energy equal its host ones, and trial points are made there and
downloaded once into frozen host arrays."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.batch.iterates import HostIterates, summed_gradient
from sim_core.batch.lumped import LumpedQuadratic
from sim_core.batch.stacked import stack_models
from sim_core.energies.base import DeviceGradient, SparseGradient, declares, positions_key
from sim_core.energies.damping.reference import ViscousDamping
from sim_core.energies.gravity.reference import GravityPotential
from sim_core.energies.inertia.reference import InertiaPotential
from tests.support.batch_copies import pad_model


@pytest.fixture(scope="module")
def stacked():
    from sim_core.ti_backend import init_backend

    init_backend("cpu")
    return stack_models([pad_model() for _ in range(3)])


def _terms(stacked, rng):
    """A lumped quadratic (a device gradient), gravity (sparse rows) and two dense host terms, over the stacked
    vertices."""
    n = stacked.model.vertex_count
    mass = rng.uniform(1e-5, 1e-3, n)
    x_n = rng.normal(scale=0.05, size=(n, 3))
    inertia = InertiaPotential(mass, x_n + 1e-3 * rng.normal(size=(n, 3)), 5e-3)
    damping = ViscousDamping(mass, x_n, 2.0, 5e-3)
    gravity = GravityPotential(mass, np.array([0.0, 0.0, -9.81]))
    lumped = LumpedQuadratic(inertia, gravity, damping)
    assert declares(lumped, DeviceGradient) and declares(gravity, SparseGradient)
    return [lumped, gravity, InertiaPotential(mass, x_n, 5e-3), damping], x_n


def test_device_gradient_sum_equals_the_host_sum(stacked):
    from sim_core.batch.device_iterates import DeviceIterates

    rng = np.random.default_rng(1)
    terms, x_n = _terms(stacked, rng)
    host, device = HostIterates(stacked.index), DeviceIterates(stacked.index)
    x = x_n + 1e-3 * rng.normal(size=x_n.shape)
    fixed = np.flatnonzero(rng.uniform(size=3 * len(x)) < 0.1)
    it = device.start(x.copy())
    assert not it.host.flags.writeable and not isinstance(positions_key(it.host), tuple)  # keyed by identity
    g = device.download(device.gradient(terms, it, fixed)).reshape(-1)
    want = host.gradient(terms, host.start(x.copy()), fixed, fresh_first=True)
    scale = np.abs(summed_gradient(terms[:1], x)).max()
    np.testing.assert_allclose(g, want, rtol=0, atol=1e-14 * scale)
    assert np.all(g[fixed] == 0.0)
    # the lumped term's energy at the iterate it evaluated on the device: its partial sums, the host's to round-off
    lumped = terms[0]
    e_device = lumped.energy(it.host)
    assert e_device == pytest.approx(lumped.energy(x.copy()), rel=1e-13)


def test_trial_points_are_made_on_the_device_and_downloaded_frozen(stacked):
    from sim_core.batch.device_iterates import DeviceIterates

    rng = np.random.default_rng(2)
    host, device = HostIterates(stacked.index), DeviceIterates(stacked.index)
    x, d = rng.normal(size=(2, stacked.model.vertex_count, 3))
    alphas = np.array([1.0, 0.25, 0.0])
    got = device.trial(device.start(x.copy()), device.upload(d), alphas)
    want = host.trial(host.start(x.copy()), d.reshape(-1), alphas)
    np.testing.assert_array_equal(got.host, want.host)
    np.testing.assert_array_equal(device.download(got.device), want.host)
    assert not got.host.flags.writeable and got.host.base is None  # keyed by identity by the terms' caches
    mask = np.array([False, True, False])
    steepest = device.take_steepest(device.upload(d), device.upload(x), mask)
    want = host.take_steepest(d.reshape(-1).copy(), x.reshape(-1), mask)
    np.testing.assert_array_equal(device.download(steepest).reshape(-1), want)


def test_trial_points_in_reused_host_blocks_are_registered_and_equal(stacked):
    """With host blocks for the trial points (:class:`PinnedBlocks`; page-locked on CUDA, ordinary memory here) a
    trial point is the same values in a registered read-only array keyed by identity; its block is reused once it is
    gone."""
    from sim_core.batch.device_iterates import DeviceIterates
    from sim_core.energies.base import FrozenPositionsKey
    from sim_core.ti_kernels.device_copy import PinnedBlocks

    rng = np.random.default_rng(6)
    device = DeviceIterates(stacked.index)
    assert device.trial_blocks is None  # no page-locked memory on the CPU: new arrays of their own
    device.trial_blocks = PinnedBlocks((stacked.model.vertex_count, 3), page_locked=False)
    host = HostIterates(stacked.index)
    x, d = rng.normal(size=(2, stacked.model.vertex_count, 3))
    start, step = device.start(x.copy()), device.upload(d)
    for alphas in ([1.0, 0.5, 0.0], [0.25, 0.0, 2.0], [1.0, 1.0, 1.0]):
        got = device.trial(start, step, np.array(alphas))
        want = host.trial(host.start(x.copy()), d.reshape(-1), np.array(alphas))
        np.testing.assert_array_equal(got.host, want.host)
        assert got.host.base is not None and FrozenPositionsKey.holds(got.host)
        assert positions_key(got.host) == positions_key(got.host) and not isinstance(positions_key(got.host), tuple)
        del got
    assert device.trial_blocks.allocated == 1


def test_slopes_with_norms_and_maxima_equal_the_host_ones(stacked):
    """One read back of the device's slope and step norm, or slope and gradient maxima, gives the host vectors'
    values (a copy with a NaN, one with an infinity, one zero)."""
    from sim_core.batch.device_iterates import DeviceIterates

    host, device = HostIterates(stacked.index), DeviceIterates(stacked.index)
    rng = np.random.default_rng(6)
    g, d = rng.normal(size=(2, stacked.model.vertex_count, 3))
    g[stacked.index[1][4], 0] = np.nan
    d[stacked.index[2]] = 0.0
    d[stacked.index[0][1], 2] = np.inf
    dg, dd = device.upload(g), device.upload(d)
    for got, want in ((device.slope_and_norm(dg, dd), host.slope_and_norm(g.reshape(-1), d.reshape(-1))),
                      (device.slope_and_largest(dg, dd), host.slope_and_largest(g.reshape(-1), d.reshape(-1)))):
        with np.errstate(invalid="ignore"):
            np.testing.assert_allclose(got[0], want[0], rtol=1e-13, atol=1e-13)
        np.testing.assert_array_equal(got[1], want[1])
    slope, norm = host.slope_and_norm(g.reshape(-1), d.reshape(-1))
    assert np.isnan(slope[1]) and np.isnan(norm[0]) and norm[2] == 0.0 and np.isfinite(norm[1])
    assert np.isnan(host.slope_and_largest(g.reshape(-1), d.reshape(-1))[1][1])
