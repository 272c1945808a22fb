"""Backend selection of the elastic potentials: the NumPy reference or its Taichi twin, by kind.

The kinds and their classes are registered by the energy folders (``ELASTIC_KINDS`` in
``sim_core/energies/<energy>/__init__.py``). This module does not import Taichi:
:func:`make_elastic_potential` with ``backend="numpy"`` never loads it; ``backend="taichi"`` needs
:func:`sim_core.ti_backend.init_backend` to have been called in this process.
"""

from __future__ import annotations

import importlib

from sim_core.energies import green_strain, hinge_bending, membrane, modified_stvk, neohookean, nodal_pressure
from sim_core.energies.membrane import StVKMembrane
from sim_core.energies.neohookean import StableNeoHookean
from sim_core.errors import ConfigError

ELASTIC_BACKENDS: tuple[str, ...] = ("numpy", "taichi")
"""Names accepted by ``backend``."""

ELASTIC_KINDS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    **membrane.ELASTIC_KINDS, **hinge_bending.ELASTIC_KINDS, **neohookean.ELASTIC_KINDS,
    **nodal_pressure.ELASTIC_KINDS, **green_strain.ELASTIC_KINDS, **modified_stvk.ELASTIC_KINDS}
"""Elastic potential kind -> (NumPy class, Taichi class) as (module, name)."""


def make_elastic_potential(kind: str, *args, backend: str = "numpy", **kwargs):
    """Build an elastic potential of ``kind`` on the NumPy reference or the Taichi kernels.

    Args:
        kind: ``"stvk_membrane"`` (:class:`~sim_core.energies.membrane.StVKMembrane`),
            ``"discrete_shell_bending"`` (:class:`~sim_core.energies.hinge_bending.reference.DiscreteShellBending`)
            ``"stable_neohookean"`` (:class:`~sim_core.energies.neohookean.reference.StableNeoHookean`)
            ``"nodal_pressure_neohookean"``
            (:class:`~sim_core.energies.nodal_pressure.reference.NodalPressureNeoHookean`, NumPy on both backends),
            ``"green_strain"`` (:class:`~sim_core.energies.green_strain.reference.GreenStrainSolid`) or
            ``"modified_stvk"`` (:class:`~sim_core.energies.modified_stvk.reference.ModifiedStVKSolid`, NumPy on both
            backends).
        *args, **kwargs: the constructor arguments of that class.
        backend: ``"numpy"`` (reference) or ``"taichi"`` (the Taichi subclass; the arch is the one
            given to :func:`sim_core.ti_backend.init_backend`).

    Returns:
        the potential (follows ``sim_core.energies.base.Potential``).

    Raises:
        ConfigError: unknown kind or backend; ``backend="taichi"`` before ``init_backend``; and
            whatever the constructor raises for bad parameters or meshes.
    """
    if kind not in ELASTIC_KINDS:
        raise ConfigError(f"make_elastic_potential: unknown kind {kind!r}; use one of {tuple(ELASTIC_KINDS)}")
    if backend not in ELASTIC_BACKENDS:
        raise ConfigError(f"make_elastic_potential: unknown backend {backend!r}; use one of {ELASTIC_BACKENDS}")
    module, name = ELASTIC_KINDS[kind][ELASTIC_BACKENDS.index(backend)]
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
    from sim_core.energies.membrane.kernel import TiStVKMembrane
    from sim_core.energies.neohookean.kernel import TiStableNeoHookean

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
