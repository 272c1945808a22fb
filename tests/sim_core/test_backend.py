"""The solver's declared backend (sim_core.backend, SolverConfig.backend): names validated with the
allowed values in the message, the command-line arch names mapped to backends."""

from __future__ import annotations

import pytest

from sim_core.backend import BACKEND_CHOICES, BACKENDS, backend_arch, backend_of_arch, check_backend, uses_taichi
from sim_core.errors import ConfigError
from sim_core.solver import SolverConfig


def test_the_default_backend_is_the_numpy_reference():
    assert SolverConfig().backend == "numpy"
    assert set(BACKENDS) < set(BACKEND_CHOICES) and "auto" in BACKEND_CHOICES


@pytest.mark.parametrize("name", ["gpu", "taichi", "", None, "CPU"])
def test_an_unknown_backend_is_a_config_error_naming_the_allowed_values(name):
    with pytest.raises(ConfigError, match=r"solver backend must be one of numpy, taichi-cpu, taichi-cuda, auto; got "):
        SolverConfig(backend=name)
    with pytest.raises(ConfigError, match=r"node parameter 'backend' must be one of"):
        check_backend(name, "node parameter 'backend'")


def test_arch_names_map_to_backends():
    assert [backend_of_arch(a) for a in ("numpy", "cpu", "cuda")] == ["numpy", "taichi-cpu", "taichi-cuda"]
    assert [backend_arch(b) for b in BACKENDS] == [None, "cpu", "cuda"]
    assert [uses_taichi(b) for b in BACKENDS] == [False, True, True]
    with pytest.raises(ConfigError, match="arch must be one of numpy, cpu, cuda; got 'gpu'"):
        backend_of_arch("gpu")
    with pytest.raises(ConfigError, match="backend must be one of numpy, taichi-cpu, taichi-cuda; got 'auto'"):
        backend_arch("auto")  # only concrete backends have an arch
