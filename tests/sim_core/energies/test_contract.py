"""The potential contract (sim_core.energies.base): every potential class declares the methods of
:class:`Potential`, with their signatures, and the optional capabilities are declared protocols that
the potentials meant to have them meet."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import numpy as np
import pytest

import sim_core.candidates
import sim_core.energies
from sim_core.energies import base
from sim_core.energies.base import (CAPABILITIES, ConstantDiagonalHessian, CopyEnergies, DeviceCopyEnergies,
                                    DeviceGradient, DeviceHessian, ElasticEquivalent, HingeBending, KeepsDerivatives,
                                    PenaltyContact, Potential, SparseGradient, SplitPotential, SubsetHessian)

NOT_POTENTIALS = {
    "sim_core.energies.base": ({"HessianBlocks", "Potential", "FrozenPositionsKey", "BorrowedWorkspace"}
                               | {c.__name__ for c in CAPABILITIES}),
    "sim_core.energies.contact.reference": {"ContactFrames", "ListRows", "PairEvaluation", "PairVertices"},
    "sim_core.energies.contact.pair_lists": {"CandidateVertices", "BatchLayout"},
    "sim_core.energies.green_strain.reference": {"GreenStrainTets"},
    "sim_core.candidates.hook": {"CandidateHook", "StepHook", "GelContactFace"},
}
"""Public classes of the scanned packages that are not potentials (records, protocols, the hook, a mixin, a base of
two solids)."""

PACKAGES = (sim_core.energies, sim_core.candidates)


def _potential_classes() -> list[type]:
    """Every class defined in a module of ``sim_core.energies`` (its energy folders included) or
    ``sim_core.candidates``, private base classes included, except :data:`NOT_POTENTIALS` and the
    Taichi modules (``*kernel``: they import Taichi; their classes are tested against the references
    in ``tests/sim_core/ti_kernels``)."""
    found = []
    for package in PACKAGES:
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            if info.name.endswith("kernel"):
                continue
            module = importlib.import_module(info.name)
            for name, cls in vars(module).items():
                if (inspect.isclass(cls) and cls.__module__ == module.__name__
                        and name not in NOT_POTENTIALS.get(module.__name__, ())):
                    found.append(cls)
    return found


POTENTIAL_CLASSES = _potential_classes()

CONTRACT = {
    "energy": ["self", "x"],
    "gradient": ["self", "x"],
    "hessian": ["self", "x", "projection"],
    "parameter_gradient": ["self", "x", "name"],
}
"""The methods of :class:`Potential` and their parameters."""


def test_the_scan_finds_the_potentials():
    names = {c.__name__ for c in POTENTIAL_CLASSES}
    assert {"InertiaPotential", "GravityPotential", "ViscousDamping", "StVKMembrane", "SpringMembrane",
            "DiscreteShellBending", "KirchhoffBending", "StableNeoHookean", "NodalPressureNeoHookean", "NodalVolume", "VertexTriangleContact",
            "EdgeEdgeContact", "PlaneContact", "SphereContact", "LaggedFriction", "LaggedAdhesion",
            "MaxwellBranch", "SheetDamping", "StictionFriction", "AnisotropicBendingCorrection",
            } <= names


def test_the_protocol_declares_the_contract():
    """The Protocol itself names the methods this test checks (so the two cannot drift apart)."""
    for method, params in CONTRACT.items():
        assert list(inspect.signature(getattr(Potential, method)).parameters) == params
    assert "parameter_names" in Potential.__annotations__


@pytest.mark.parametrize("cls", POTENTIAL_CLASSES, ids=lambda c: f"{c.__module__}.{c.__name__}")
def test_every_potential_declares_the_contract(cls):
    for method, params in CONTRACT.items():
        fn = getattr(cls, method, None)
        assert callable(fn), f"{cls.__name__} lacks {method}()"
        assert list(inspect.signature(fn).parameters) == params, f"{cls.__name__}.{method} signature"
    hessian = inspect.signature(cls.hessian).parameters["projection"]
    assert hessian.default == "clamp", f"{cls.__name__}.hessian: projection defaults to 'clamp'"
    declared = "parameter_names" in vars(cls) or any("parameter_names" in vars(b) for b in cls.__mro__[1:-1])
    in_init = "self.parameter_names" in inspect.getsource(cls.__init__) if "__init__" in vars(cls) else False
    assert declared or in_init, f"{cls.__name__} declares no parameter_names"


def _declares(cls: type, protocol: type) -> bool:
    """Whether ``cls`` defines every method of ``protocol`` (data members are set per instance)."""
    methods = [n for n, v in vars(protocol).items() if inspect.isfunction(v) and not n.startswith("_")]
    return all(callable(getattr(cls, n, None)) for n in methods)


EXPECTED_CAPABILITIES = {
    ConstantDiagonalHessian: {"InertiaPotential", "ViscousDamping"},
    # LaggedAdhesion: its open pairs are its active set, which the simplified Newton test compares
    PenaltyContact: {"_PairPenalty", "VertexTriangleContact", "EdgeEdgeContact", "PlaneContact", "SphereContact",
                     "LaggedAdhesion"},
    KeepsDerivatives: {"_PairPenalty", "VertexTriangleContact", "EdgeEdgeContact"},
    HingeBending: {"DiscreteShellBending", "KirchhoffBending"},
    ElasticEquivalent: {"MaxwellBranch"},
    SubsetHessian: {"_PairPenalty", "VertexTriangleContact", "EdgeEdgeContact"},
    DeviceHessian: set(),  # the Taichi terms only (*kernel modules, not scanned: TAICHI_CAPABILITIES)
    # and the Taichi pair and friction potentials (not scanned: test_contact_batch.py, test_friction.py)
    SparseGradient: {"GravityPotential"},
    DeviceGradient: set(),  # the Taichi terms only (TAICHI_CAPABILITIES)
    # the lockstep batch's per-copy Armijo test: the terms of a stacked model's Newton loop on a Taichi backend
    CopyEnergies: {"_PairPenalty", "VertexTriangleContact", "EdgeEdgeContact", "PlaneContact", "SphereContact",
                   "LaggedFriction"},
    DeviceCopyEnergies: set(),  # the Taichi terms only (TAICHI_CAPABILITIES; and batch.lumped.LumpedQuadratic)
    SplitPotential: {"NodalPressureNeoHookean"},
}

TAICHI_CAPABILITIES = {
    DeviceHessian: {"sim_core.energies.contact.kernel._Batched", "sim_core.energies.contact.kernel.TiEdgeEdgeContact",
                    "sim_core.energies.contact.kernel.TiVertexTriangleContact",
                    "sim_core.energies.friction.kernel.TiLaggedFriction",
                    "sim_core.energies.friction.rows_kernel.DeviceLaggedFriction"},
    DeviceGradient: {"sim_core.energies.contact.kernel._Batched", "sim_core.energies.contact.kernel.TiEdgeEdgeContact",
                     "sim_core.energies.contact.kernel.TiVertexTriangleContact", "sim_core.fused_elastic.FusedElastic",
                     "sim_core.energies.friction.kernel.TiLaggedFriction",
                     "sim_core.energies.friction.rows_kernel.DeviceLaggedFriction",
                     "sim_core.energies.gravity.kernel.TiGravityPotential"},
    # the fused parts give their kernels' element energies (one sum cell an element: launch.element_terms)
    CopyEnergies: {"sim_core.energies.contact.kernel.TiEdgeEdgeContact",
                   "sim_core.energies.contact.kernel.TiVertexTriangleContact",
                   "sim_core.energies.friction.kernel.TiLaggedFriction",
                   "sim_core.energies.friction.rows_kernel.DeviceLaggedFriction",
                   "sim_core.energies.green_strain.fused_kernel.FusedGreenStrainSolid",
                   "sim_core.energies.hinge_bending.fused_kernel.FusedAnisotropicBending",
                   "sim_core.energies.kirchhoff_bending.fused_kernel.FusedKirchhoffBending",
                   "sim_core.energies.membrane.fused_spring_kernel.FusedSpringMembrane",
                   "sim_core.energies.membrane.fused_stvk_kernel.FusedStVKMembrane",
                   "sim_core.energies.neohookean.fused_kernel.FusedStableNeoHookean",
                   "sim_core.fused_elastic.FusedElastic", "sim_core.fused_elastic._ReferencePart"},
    # the line search's per-copy energies added where the kernels run, read once (copy_vectors.CopySums)
    DeviceCopyEnergies: {"sim_core.energies.contact.kernel._Batched",
                         "sim_core.energies.contact.kernel.TiEdgeEdgeContact",
                         "sim_core.energies.contact.kernel.TiVertexTriangleContact",
                         "sim_core.energies.friction.kernel.TiLaggedFriction",
                         "sim_core.energies.friction.rows_kernel.DeviceLaggedFriction", "sim_core.fused_elastic.FusedElastic"},
}
"""The classes of the Taichi modules (the energies' and candidates' ``*kernel`` modules and
:mod:`sim_core.fused_elastic`) that declare the device capabilities (the lockstep batch's device-resident path)."""


@pytest.mark.parametrize("protocol", CAPABILITIES, ids=lambda p: p.__name__)
def test_capabilities_are_declared_by_the_potentials_that_have_them(protocol):
    have = {c.__name__ for c in POTENTIAL_CLASSES if _declares(c, protocol)}
    assert have == EXPECTED_CAPABILITIES[protocol]


@pytest.mark.parametrize("protocol", list(TAICHI_CAPABILITIES), ids=lambda p: p.__name__)
def test_the_taichi_terms_that_declare_the_device_capabilities(protocol):
    """A scan of the Taichi modules (importing them needs no Taichi runtime) finds the listed declarers."""
    modules = [importlib.import_module("sim_core.fused_elastic")]
    for package in PACKAGES:
        modules += [importlib.import_module(info.name) for info in pkgutil.walk_packages(package.__path__,
                                                                                          package.__name__ + ".")
                    if info.name.endswith("kernel")]
    have = {f"{module.__name__}.{name}" for module in modules for name, cls in vars(module).items()
            if inspect.isclass(cls) and cls.__module__ == module.__name__ and _declares(cls, protocol)}
    assert have == TAICHI_CAPABILITIES[protocol]


def test_isinstance_checks_capabilities_of_instances():
    """Runtime checks on built potentials: a diagonal Hessian that equals the assembled blocks'
    diagonal; a hinge bending's theta stiffness and its product agree; a term without a capability
    is not mistaken for one."""
    from sim_core.energies.gravity.reference import GravityPotential
    from sim_core.energies.hinge_bending.reference import DiscreteShellBending
    from sim_core.energies.inertia.reference import InertiaPotential

    mass = np.array([1.0, 2.0, 3.0, 4.0])
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.2]])
    inertia = InertiaPotential(mass, x, 0.01)
    assert isinstance(inertia, Potential) and isinstance(inertia, ConstantDiagonalHessian)
    blocks = base.assemble_hessian([inertia.hessian(x)], 12).toarray()
    np.testing.assert_allclose(np.diag(blocks), inertia.hessian_diagonal(), rtol=1e-14)
    gravity = GravityPotential(mass, np.array([0, 0, -9.81]))
    assert isinstance(gravity, Potential) and not isinstance(gravity, ConstantDiagonalHessian)
    assert not isinstance(gravity, PenaltyContact) and not isinstance(gravity, HingeBending)
    bending = DiscreteShellBending(np.array([[0, 3, 1, 2]]), x, 1e-3)
    assert isinstance(bending, HingeBending)
    v = np.array([[1.0, -2.0]])
    np.testing.assert_array_equal(bending.theta_stiffness_product(v), bending.theta_stiffness() @ v)
    assert bending.theta_stiffness()[0, 0] == 2.0 * bending.hinge_stiffness[0]


def test_declares_answers_as_isinstance():
    """``base.declares`` (a capability decided once per class, data members on the instance) gives the
    ``isinstance`` answer of every capability for built potentials, and False for None."""
    from sim_core.energies.contact.reference import PlaneContact, VertexTriangleContact
    from sim_core.energies.gravity.reference import GravityPotential
    from sim_core.energies.hinge_bending.reference import DiscreteShellBending
    from sim_core.energies.inertia.reference import InertiaPotential

    mass = np.array([1.0, 2.0, 3.0, 4.0])
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.2]])
    terms = [InertiaPotential(mass, x, 0.01), GravityPotential(mass, np.array([0, 0, -9.81])),
             DiscreteShellBending(np.array([[0, 3, 1, 2]]), x, 1e-3),
             PlaneContact(np.arange(4), np.array([0.0, 0.0, 1.0]), 0.0, 1e3, 1e-3),
             VertexTriangleContact(np.array([[3, 0]]), np.array([[0, 1, 2]]), np.zeros(1), 1e3, 1e-3)]
    for term in terms:
        for capability in CAPABILITIES:
            assert base.declares(term, capability) == isinstance(term, capability), (term, capability)
    assert sum(base.declares(t, c) for t in terms for c in CAPABILITIES) >= 5
    assert not any(base.declares(None, c) for c in CAPABILITIES)
