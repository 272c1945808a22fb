"""Taichi element kernels (arch ``cpu`` | ``cuda``) of the hot elastic potentials, and backend selection.

``neohookean.py`` (:class:`TiStableNeoHookean`), ``membrane.py`` (:class:`TiStVKMembrane`) and
``bending.py`` (:class:`TiDiscreteShellBending`) subclass the NumPy reference potentials and
override ``energy``, ``gradient`` and ``hessian`` with Taichi kernels producing the same arrays
(tested to 1e-10 relative); construction, validation and ``parameter_gradient`` stay NumPy.

This package's ``__init__`` does not import Taichi: :func:`make_elastic_potential` with
``backend="numpy"`` never loads it. ``backend="taichi"`` needs
:func:`sim_core.ti_backend.init_backend` to have been called in this process.
"""

from __future__ import annotations

import importlib

from sim_core.errors import ConfigError
from sim_core.potentials.membrane import StVKMembrane
from sim_core.potentials.neohookean import StableNeoHookean

ELASTIC_BACKENDS: tuple[str, ...] = ("numpy", "taichi")
"""Names accepted by ``backend``."""

_CLASSES: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    "stvk_membrane": (("sim_core.potentials.membrane", "StVKMembrane"),
                      ("sim_core.ti_kernels.membrane", "TiStVKMembrane")),
    "discrete_shell_bending": (("sim_core.potentials.bending", "DiscreteShellBending"),
                               ("sim_core.ti_kernels.bending", "TiDiscreteShellBending")),
    "stable_neohookean": (("sim_core.potentials.neohookean", "StableNeoHookean"),
                          ("sim_core.ti_kernels.neohookean", "TiStableNeoHookean")),
}
"""Elastic potential kind -> (NumPy class, Taichi class) as (module, name)."""


def make_elastic_potential(kind: str, *args, backend: str = "numpy", **kwargs):
    """Build an elastic potential of ``kind`` on the NumPy reference or the Taichi kernels.

    Args:
        kind: ``"stvk_membrane"`` (:class:`~sim_core.potentials.membrane.StVKMembrane`),
            ``"discrete_shell_bending"`` (:class:`~sim_core.potentials.bending.DiscreteShellBending`)
            or ``"stable_neohookean"`` (:class:`~sim_core.potentials.neohookean.StableNeoHookean`).
        *args, **kwargs: the constructor arguments of that class.
        backend: ``"numpy"`` (reference) or ``"taichi"`` (the Taichi subclass; the arch is the one
            given to :func:`sim_core.ti_backend.init_backend`).

    Returns:
        the potential (follows ``sim_core.potentials.base.Potential``).

    Raises:
        ConfigError: unknown kind or backend; ``backend="taichi"`` before ``init_backend``; and
            whatever the constructor raises for bad parameters or meshes.
    """
    if kind not in _CLASSES:
        raise ConfigError(f"make_elastic_potential: unknown kind {kind!r}; use one of {tuple(_CLASSES)}")
    if backend not in ELASTIC_BACKENDS:
        raise ConfigError(f"make_elastic_potential: unknown backend {backend!r}; use one of {ELASTIC_BACKENDS}")
    module, name = _CLASSES[kind][ELASTIC_BACKENDS.index(backend)]
    cls = getattr(importlib.import_module(module), name)
    return cls(*args, **kwargs)


def use_taichi_kernels(elastic) -> list[str]:
    """Replace, in place, the potentials of an ``ElasticTerms`` that have a Taichi twin.

    A stop-gap until ``ElasticTerms`` selects the backend itself (see ``make_elastic_potential``):
    StVK membranes and Stable Neo-Hookean solids are rebuilt from their own parameters on the
    Taichi kernels; spring membranes and Kirchhoff bending have no Taichi twin and are kept.
    Hinge bending potentials already cached by ``ElasticTerms.bending`` are not touched.

    Args:
        elastic: a :class:`sim_core.elastic.ElasticTerms` (its ``membranes`` and ``solids`` dicts).

    Returns:
        the replaced terms as ``"<body>:<class>"`` strings.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    # optional heavy dependency: Taichi, loaded on a Taichi backend only
    from sim_core.ti_kernels.membrane import TiStVKMembrane
    from sim_core.ti_kernels.neohookean import TiStableNeoHookean

    x_rest = elastic.model.x_rest
    replaced = []
    for name, pot in list(elastic.membranes.items()):
        if type(pot) is StVKMembrane:
            elastic.membranes[name] = TiStVKMembrane(pot.triangles, x_rest, pot.youngs_modulus, pot.poisson_ratio,
                                                     pot.thickness)
            replaced.append(f"{name}:TiStVKMembrane")
    for name, pot in list(elastic.solids.items()):
        if type(pot) is StableNeoHookean:
            elastic.solids[name] = TiStableNeoHookean(pot.tets, x_rest, pot.youngs_modulus, pot.poisson_ratio)
            replaced.append(f"{name}:TiStableNeoHookean")
    return replaced
