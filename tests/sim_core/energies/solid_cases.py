"""A small gel block, deformed configurations and the element-by-name check shared by the solid elements' tests
(nodal pressure, Green strain, modified StVK)."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import pytest

from sim_core.mesh.tet import tet_box

E_GEL, NU_GEL = 3e5, 0.45


def gel_block():
    """3 x 2 x 2 cells of an elongated gel-like box (72 tets, 36 vertices)."""
    return tet_box((0.0186, 0.0143, 0.004), (4, 3, 3), (0.0, 0.0, 0.0))


def deformed(x: np.ndarray, seed: int, amplitude: float = 1.5e-4) -> np.ndarray:
    """``x`` plus Gaussian noise of ``amplitude`` m (seeded)."""
    return x + amplitude * np.random.default_rng(seed).standard_normal(x.shape)


def assert_chosen_by_name(element: str, reference: Callable[[Any], Any], misspelt: str) -> None:
    """``model.meta["solid_element"] = element`` gives the gel block's solid the class of ``reference(mesh)`` and its
    energy at a deformed state (to 1e-12); ``misspelt`` is refused by a ConfigError naming it.

    Raises:
        AssertionError: the element built is not ``reference``'s, or its energy differs.
    """
    from sim_core.builder import ModelBuilder
    from sim_core.elastic import ElasticTerms
    from sim_core.errors import ConfigError

    mesh = gel_block()
    builder = ModelBuilder()
    builder.add_solid("gel", mesh, {"youngs_modulus": E_GEL, "poisson_ratio": NU_GEL, "density": 1000.0})
    model = builder.finalize(meta={"solid_element": element})
    solid = ElasticTerms(model).solids["gel"]
    expected = reference(mesh)
    x = deformed(mesh.x, 5)
    assert type(solid) is type(expected)
    assert solid.energy(x) == pytest.approx(expected.energy(x), rel=1e-12)
    model.meta["solid_element"] = misspelt
    with pytest.raises(ConfigError, match=misspelt):
        ElasticTerms(model)
