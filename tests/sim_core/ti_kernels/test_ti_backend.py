"""Taichi backend initialisation and backend selection: idempotence, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.errors import ConfigError
from sim_core.mesh.tet import tet_box


def test_init_is_idempotent_and_reports_the_arch(ti_cpu):
    from sim_core.ti_backend import current_arch, init_backend

    assert ti_cpu == "cpu"
    assert init_backend("cpu") == "cpu"
    assert current_arch() == "cpu"


def test_unknown_arch_and_arch_switch_raise(ti_cpu):
    from sim_core.ti_backend import init_backend

    with pytest.raises(ConfigError, match="unknown Taichi arch 'vulkan'"):
        init_backend("vulkan")
    with pytest.raises(ConfigError, match="already initialised with arch 'cpu'.*'cuda'"):
        init_backend("cuda")


def test_make_elastic_potential_selects_the_backend(ti_cpu):
    from sim_core.energies.neohookean.kernel import TiStableNeoHookean
    from sim_core.energies.registry import make_elastic_potential

    mesh = tet_box((0.01, 0.01, 0.01), (2, 2, 2), (0.0, 0.0, 0.0))
    ref = make_elastic_potential("stable_neohookean", mesh.tets, mesh.x, 3e5, 0.2)
    tik = make_elastic_potential("stable_neohookean", mesh.tets, mesh.x, 3e5, 0.2, backend="taichi")
    assert type(ref) is StableNeoHookean and isinstance(tik, TiStableNeoHookean)
    x = mesh.x + 1e-3 * np.random.default_rng(0).standard_normal(mesh.x.shape)
    assert np.allclose(tik.gradient(x), ref.gradient(x), rtol=0, atol=1e-10 * np.abs(ref.gradient(x)).max())
    with pytest.raises(ConfigError, match="unknown kind 'spring'"):
        make_elastic_potential("spring", mesh.tets, mesh.x, 3e5, 0.2)
    with pytest.raises(ConfigError, match="unknown backend 'warp'"):
        make_elastic_potential("stable_neohookean", mesh.tets, mesh.x, 3e5, 0.2, backend="warp")
    with pytest.raises(ConfigError, match="poisson_ratio"):
        make_elastic_potential("stable_neohookean", mesh.tets, mesh.x, 3e5, 0.7, backend="taichi")


def test_unknown_projection_raises(ti_cpu):
    from sim_core.energies.neohookean.kernel import TiStableNeoHookean

    mesh = tet_box((0.01, 0.01, 0.01), (2, 2, 2), (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="unknown PSD projection 'flip'"):
        TiStableNeoHookean(mesh.tets, mesh.x, 3e5, 0.2).hessian(mesh.x, "flip")
