"""Bending plasticity of a sheet's hinges in one Taichi kernel (sim_core/energies/hinge_bending/plasticity_kernel.py)
against the NumPy rule on the reference dihedral angles; the stacked elastic terms of a lockstep batch use it."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.hinge_bending.reference import dihedral_angle, plastic_update
from sim_core.errors import ConfigError
from tests.support.batch_copies import pad_model


def _folded_sheet(rng):
    """The pad scene's model and its sheet's rest positions lifted by a random smooth fold plus noise (m)."""
    model = pad_model()
    x = model.x_rest.copy()
    sheet = model.bodies["sheet"]
    own = np.arange(sheet.vertex_start, sheet.vertex_stop)
    x[own, 2] += 4e-3 * np.sin(150.0 * x[own, 0]) + 5e-4 * rng.normal(size=len(own))
    return model, x


def test_kernel_moves_the_rest_angles_as_the_reference_rule(ti_cpu):
    from sim_core.energies.hinge_bending.plasticity_kernel import HingePlasticity

    rng = np.random.default_rng(5)
    model, x = _folded_sheet(rng)
    hinges = model.bodies["sheet"].hinges
    theta = dihedral_angle(x[hinges])
    theta_bar = 0.05 * rng.normal(size=len(hinges))
    gaps = np.sort(np.abs(theta - theta_bar))
    yield_angle = float(0.5 * (gaps[len(gaps) // 2 - 1] + gaps[len(gaps) // 2]))  # half yield, none at the limit
    want = plastic_update(theta, theta_bar, yield_angle)
    got = HingePlasticity(hinges).update(x, theta_bar, yield_angle)
    moved = want != theta_bar
    assert 0.3 < moved.mean() < 0.7
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)
    assert np.array_equal(got[~moved], theta_bar[~moved])  # the others keep their rest angle exactly
    # the yielded ones sit at the yield angle from the dihedral angle, on the side they were pushed from
    np.testing.assert_allclose(np.abs(theta - got)[moved], yield_angle, rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match=r"rest angles of shape \(3,\), expected"):
        HingePlasticity(hinges).update(x, theta_bar[:3], yield_angle)


def test_stacked_elastic_terms_update_as_the_elastic_terms(ti_cpu):
    from sim_core.batch.plasticity import StackedElasticTerms
    from sim_core.elastic import ElasticTerms

    rng = np.random.default_rng(9)
    model, x = _folded_sheet(rng)
    h = len(model.bodies["sheet"].hinges)
    theta_bar = {"sheet": 0.02 * rng.normal(size=h)}
    model.bodies["sheet"].material["yield_angle"] = 0.05
    want = ElasticTerms(model).plastic_update(x, theta_bar)
    got = StackedElasticTerms(model).plastic_update(x, theta_bar)
    assert got.keys() == want.keys()
    np.testing.assert_allclose(got["sheet"], want["sheet"], rtol=0, atol=1e-13)
    assert np.any(got["sheet"] != theta_bar["sheet"])
    model.bodies["sheet"].material["yield_angle"] = np.inf  # elastic: a copy of the rest angles
    got = StackedElasticTerms(model).plastic_update(x, theta_bar)["sheet"]
    assert np.array_equal(got, theta_bar["sheet"]) and got is not theta_bar["sheet"]
    model.bodies["sheet"].material["yield_angle"] = -0.1
    with pytest.raises(ConfigError, match="yield_angle must be >= 0 rad"):
        StackedElasticTerms(model).plastic_update(x, theta_bar)


def test_stacked_plastic_update_reads_the_device_positions_of_its_very_positions(ti_cpu):
    from sim_core.batch.plasticity import StackedElasticTerms
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.buffers import DeviceArray
    from sim_core.ti_kernels.transfer import upload

    rng = np.random.default_rng(11)
    model, x = _folded_sheet(rng)
    theta_bar = {"sheet": 0.02 * rng.normal(size=len(model.bodies["sheet"].hinges))}
    model.bodies["sheet"].material["yield_angle"] = 0.05
    terms = StackedElasticTerms(model)
    want = terms.plastic_update(x, theta_bar)["sheet"]
    other = x.copy()
    other[:, 2] *= 1.5  # other values on the device: shows which positions the kernel read
    terms.device_positions = (x, upload(DeviceArray(ti.f64).ensure(x.shape), other))
    got = terms.plastic_update(x, theta_bar)["sheet"]
    assert np.array_equal(got, StackedElasticTerms(model).plastic_update(other, theta_bar)["sheet"])
    assert not np.array_equal(got, want)
    # positions of another array (equal values): uploaded as before
    assert np.array_equal(terms.plastic_update(x.copy(), theta_bar)["sheet"], want)
