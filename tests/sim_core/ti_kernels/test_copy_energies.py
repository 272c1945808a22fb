"""The fused elastic kernels' energies split by copy (CopyEnergies, copy_vectors.copy_energies): on disjoint copies of a
mesh, each copy's share is the energy of the same potential on that copy alone, and the shares add up to the
stacked energy."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.assembly import HessianAssembler
from sim_core.energies.hinge_bending.reference import DiscreteShellBending
from sim_core.energies.kirchhoff_bending.reference import KirchhoffBending
from sim_core.energies.membrane.reference import SpringMembrane, StVKMembrane
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.mesh.sheet import grid_sheet, sheet_topology
from sim_core.mesh.tet import tet_box

KINDS = ("snh", "spring_membrane", "kirchhoff", "stvk_membrane", "anisotropic_bending", "hinge_reference_part")


def _potential(kind: str, copies: int):
    """(potential over ``copies`` disjoint copies of one mesh, its rest positions, one copy's vertex count); copy
    ``c``'s vertices are rows ``c n .. (c + 1) n - 1``, translated by ``0.1 c`` m along x."""
    if kind == "snh":
        mesh = tet_box((0.01, 0.01, 0.01), (3, 3, 3), (0.0, 0.0, 0.0))
        elements = {"tets": mesh.tets}
    else:
        mesh = grid_sheet((0.02, 0.015), (4, 3), (0.0, 0.0, 0.0))
        topo = sheet_topology(mesh.triangles)
        elements = {"triangles": mesh.triangles, "edges": topo.edges, "hinges": topo.hinges}
    n = mesh.x.shape[0]
    e = {k: np.concatenate([v + c * n for c in range(copies)]) for k, v in elements.items()}
    x = np.concatenate([mesh.x + [0.1 * c, 0.0, 0.0] for c in range(copies)])
    if kind == "snh":
        return StableNeoHookean(e["tets"], x, 3e5, 0.45), x, n
    h = elements["hinges"].shape[0]  # one copy's hinges; their rest angles the same in every copy
    if kind == "spring_membrane":
        return SpringMembrane(e["triangles"], e["edges"], x, 1000.0, 800.0), x, n
    if kind == "kirchhoff":
        rest_angles = np.tile(np.linspace(-0.3, 0.4, h), copies)
        return KirchhoffBending(e["triangles"], e["hinges"], x, 2e-3, 0.3, rest_angles), x, n
    if kind == "stvk_membrane":
        return StVKMembrane(e["triangles"], x, 1e6, 0.3, 3e-4), x, n
    bending = DiscreteShellBending(e["hinges"], x, 2e-3, np.tile(np.linspace(0.2, -0.1, h), copies))
    if kind == "anisotropic_bending":
        from sim_core.candidates.anisotropic_bending import AnisotropicBendingCorrection

        return AnisotropicBendingCorrection(bending, x, 0.4), x, n
    return bending, x, n  # no fused kernel: a reference part, which does not split its energy


def _fused(pot, x_rest: np.ndarray):
    from sim_core.fused_elastic import FusedElastic

    fused = FusedElastic([pot])
    fused.bind(HessianAssembler(x_rest.size).static_pattern(fused.block_vertex_arrays(x_rest),
                                                            np.ones(x_rest.size, bool)))
    return fused


@pytest.mark.parametrize("kind", KINDS)
def test_fused_energy_split_by_copy_is_each_copys_own_energy(ti_cpu, kind):
    copies = 3
    stacked, x_rest, n = _potential(kind, copies)
    one, one_rest, _ = _potential(kind, 1)
    rng = np.random.default_rng(7)
    x = x_rest + 1.5e-3 * rng.standard_normal(x_rest.shape)
    x[:, 2] += 2e-3 * np.sin(150.0 * x_rest[:, 0])
    copy_of_vertex = np.repeat(np.arange(copies), n)
    fused = _fused(stacked, x_rest)
    split = fused.copy_energies(x, copy_of_vertex, copies)
    if kind == "hinge_reference_part":
        assert split is None  # DiscreteShellBending has no per-copy energies: the caller falls back
        return
    assert split.shape == (copies,)
    alone = _fused(one, one_rest)
    for c in range(copies):  # copy c alone, moved back to the first copy's place (the energies are translation-free)
        own = alone.energy(x[c * n:(c + 1) * n] - [0.1 * c, 0.0, 0.0])
        assert split[c] == pytest.approx(own, rel=1e-11, abs=1e-18)
    assert np.sum(split) == pytest.approx(fused.energy(x), rel=1e-12)
    assert np.ptp(split) > 1e-3 * np.max(np.abs(split))  # the copies' energies differ: a real split


def test_copy_energies_of_one_element_a_copy_are_the_elements_terms(ti_cpu):
    """One sum cell an element (launch.element_cells): with each hinge its own copy, the hinge energy kernel's sums by
    copy are the hinges' own terms, and they add up to the kernel's sum; elements of one copy add up in it."""
    from sim_core.energies.hinge_bending.fused_kernel import weighted_hinge_energy
    from sim_core.ti_kernels.copy_vectors import copy_energies

    pot, x_rest, _ = _potential("hinge_reference_part", 1)
    x = x_rest.copy()
    x[:, 2] += 2e-3 * np.sin(150.0 * x_rest[:, 0])
    hinges = np.ascontiguousarray(pot.hinges, dtype=np.int32)
    h = hinges.shape[0]
    weight = np.linspace(1.0, 2.0, h)
    theta_bar = np.ascontiguousarray(pot.hinge_theta_bar, dtype=np.float64)
    terms = copy_energies(weighted_hinge_energy, np.arange(h, dtype=np.int32), h, {}, x, hinges, theta_bar, weight)
    np.testing.assert_allclose(terms, weight * (pot.theta(x) - theta_bar) ** 2, rtol=1e-12, atol=1e-20)
    assert np.sum(terms) == pytest.approx(weighted_hinge_energy(x, hinges, theta_bar, weight), rel=1e-13)
    halves = copy_energies(weighted_hinge_energy, (np.arange(h) >= h // 2).astype(np.int32), 3, {}, x, hinges,
                           theta_bar, weight)
    np.testing.assert_allclose(halves, [terms[:h // 2].sum(), terms[h // 2:].sum(), 0.0], rtol=1e-13, atol=1e-20)
    none = copy_energies(weighted_hinge_energy, np.zeros(0, dtype=np.int32), 2, {}, x, hinges[:0], theta_bar[:0],
                         weight[:0])
    np.testing.assert_array_equal(none, [0.0, 0.0])


def test_device_array_split_equals_the_host_one(ti_cpu, monkeypatch):
    """The CUDA path (positions uploaded once, the parts' constant arrays as Taichi ndarrays) of three fused parts
    together gives each copy's own energy; on the CPU arch, run there with the arch query answering "cuda", it also
    gives the same per-copy energies as the NumPy-argument path (which only the CPU arch runs)."""
    import sim_core.energies.kirchhoff_bending.fused_kernel as kirchhoff_kernel
    import sim_core.energies.membrane.fused_spring_kernel as spring_kernel
    import sim_core.ti_backend as backend
    from sim_core.fused_elastic import FusedElastic

    copies = 2
    kinds = ("snh", "spring_membrane", "kirchhoff")
    parts = [_potential(kind, copies) for kind in kinds]
    offsets = np.cumsum([0] + [x.shape[0] for _, x, _ in parts])
    x_rest = np.concatenate([x for _, x, _ in parts])
    # one model of three disjoint bodies, each of two copies: copy c is copy c of every body
    pots = [StableNeoHookean(parts[0][0].tets, x_rest, 3e5, 0.45),
            SpringMembrane(parts[1][0].triangles + offsets[1], parts[1][0].edges + offsets[1], x_rest, 1000.0, 800.0),
            KirchhoffBending(parts[2][0].triangles + offsets[2], parts[2][0].hinges + offsets[2], x_rest, 2e-3, 0.3,
                             parts[2][0].hinge_theta_bar)]
    copy_of_vertex = np.concatenate([np.repeat(np.arange(copies), n) for _, _, n in parts])
    x = x_rest + 1e-3 * np.random.default_rng(3).standard_normal(x_rest.shape)

    def split():
        fused = FusedElastic(pots)
        fused.bind(HessianAssembler(x.size).static_pattern(fused.block_vertex_arrays(x_rest), np.ones(x.size, bool)))
        return fused, fused.copy_energies(x, copy_of_vertex, copies)

    if ti_cpu != "cuda":  # the NumPy-argument path first, then the CUDA path emulated
        fused_host, host = split()
        assert not fused_host._on_device()
        for module in (backend, kirchhoff_kernel, spring_kernel):
            monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    fused_dev, dev = split()
    assert fused_dev._on_device()
    if ti_cpu != "cuda":
        np.testing.assert_allclose(dev, host, rtol=1e-13)
        assert np.sum(host) == pytest.approx(fused_host.energy(x), rel=1e-12)
    # each copy's own energy: every body's copy c alone, moved back to the first copy's place
    alone = [(_fused(*_potential(kind, 1)[:2]), n) for kind, (_, _, n) in zip(kinds, parts)]
    for c in range(copies):
        own = sum(part.energy(x[start + c * n:start + (c + 1) * n] - [0.1 * c, 0.0, 0.0])
                  for (part, n), start in zip(alone, offsets[:-1]))
        assert dev[c] == pytest.approx(own, rel=1e-11, abs=1e-18)


def test_add_by_copy_kernel_on_device_arrays(ti_cpu):
    """The GPU path's sum by copy (copy_vectors._add_by_copy) on Taichi ndarrays: each value added into its copy."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import device_copy, transfer
    from sim_core.ti_kernels.copy_vectors import _add_by_copy

    rng = np.random.default_rng(2)
    values = rng.standard_normal(1000)
    element_copy = rng.integers(0, 7, 1000).astype(np.int32)
    values_dev = transfer.upload(device_copy.new_ndarray(ti.f64, (1000,)), values)
    copy_dev = device_copy.new_ndarray(ti.i32, (1000,))
    copy_dev.from_numpy(element_copy)
    sums = device_copy.new_ndarray(ti.f64, (8,))
    sums.fill(0.0)
    _add_by_copy(values_dev, copy_dev, sums, 1000)
    np.testing.assert_allclose(transfer.download(sums), np.bincount(element_copy, weights=values, minlength=8),
                               rtol=1e-13, atol=1e-13)


def _device(values: np.ndarray):
    """A float64 Taichi ndarray holding ``values``."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.transfer import upload

    return upload(new_ndarray(ti.f64, values.shape), values)


def test_fused_parts_add_their_copy_energies_into_one_copy_sums(ti_cpu):
    """``FusedElastic.add_copy_energies_on_device`` (DeviceCopyEnergies): the parts' kernels at the device positions
    add into one CopySums (on CUDA in device memory, read once), on top of what it holds: its sums are the host split;
    a fused term with a reference part adds nothing and says so."""
    from sim_core.energies.base import DeviceCopyEnergies, declares
    from sim_core.ti_kernels.copy_vectors import CopySums

    copies = 3
    kinds = ("snh", "spring_membrane", "kirchhoff", "stvk_membrane", "anisotropic_bending")
    parts = [_potential(kind, copies) for kind in kinds]
    x_rest = np.concatenate([x for _, x, _ in parts])
    offsets = np.cumsum([0] + [x.shape[0] for _, x, _ in parts])
    copy_of_vertex = np.concatenate([np.repeat(np.arange(copies), n) for _, _, n in parts])
    x = x_rest + 1e-3 * np.random.default_rng(5).standard_normal(x_rest.shape)
    sums = CopySums(copy_of_vertex, copies)
    base = np.array([1.0, -2.0, 0.5])
    for k, kind in enumerate(kinds):  # one body at a time, at its rows of the whole positions
        pot, body_rest, _ = _potential(kind, copies)
        rows = slice(offsets[k], offsets[k + 1])
        fused = _fused(pot, body_rest)
        assert declares(fused, DeviceCopyEnergies)
        host = fused.copy_energies(x[rows], copy_of_vertex[rows], copies)
        sums.zero()
        sums.add(base)
        assert fused.add_copy_energies_on_device(x[rows], _device(np.ascontiguousarray(x[rows])), copy_of_vertex[rows],
                                                 sums)
        np.testing.assert_allclose(sums.read(), base + host, rtol=1e-12)
    reference, body_rest, n = _potential("hinge_reference_part", copies)
    sums.zero()
    assert not _fused(reference, body_rest).add_copy_energies_on_device(body_rest, _device(body_rest),
                                                                        np.repeat(np.arange(copies), n), sums)
    np.testing.assert_array_equal(sums.read(), np.zeros(copies))


def test_copy_sums_block_is_one_at_a_time(ti_cpu):
    from sim_core.ti_kernels.copy_vectors import CopySums

    first, second = CopySums(np.zeros(3, np.int64), 1), CopySums(np.zeros(3, np.int64), 1)
    with first:
        with pytest.raises(RuntimeError, match="already active"):
            second.__enter__()
    with second:  # the first block has ended
        assert second.read().shape == (1,)


def test_lumped_quadratic_adds_its_copy_energies_by_vertex_copy(ti_cpu):
    """The lumped inertia / gravity / damping term (DeviceCopyEnergies): ``w_v / 2 |x_v - y_v|^2`` of the device
    positions summed by copy in one launch, ``E_0`` per copy on the host: its host split, which sums to its energy."""
    from sim_core.batch.lumped import LumpedQuadratic
    from sim_core.energies.damping.reference import ViscousDamping
    from sim_core.energies.gravity.reference import GravityPotential
    from sim_core.energies.inertia.reference import InertiaPotential
    from sim_core.ti_kernels.copy_vectors import CopySums

    rng = np.random.default_rng(11)
    n, copies, dt = 500, 7, 5e-3
    mass = rng.uniform(1e-4, 1e-3, n)
    mass[[3, 40]] = 0.0  # vertices without mass: no term
    x_prev = rng.standard_normal((n, 3)) * 1e-2
    x_hat = x_prev + 1e-4 * rng.standard_normal((n, 3))
    lumped = LumpedQuadratic(InertiaPotential(mass, x_hat, dt), GravityPotential(mass, np.array([0.0, 0.0, -9.81])),
                             ViscousDamping(mass, x_prev, 2.0, dt))
    copy_of_vertex = np.sort(rng.integers(0, copies - 1, n))  # the last copy has no vertex
    x = x_hat + 3e-4 * rng.standard_normal((n, 3))
    host = lumped.copy_energies(x, copy_of_vertex, copies)
    sums = CopySums(copy_of_vertex, copies)
    sums.zero()
    assert lumped.add_copy_energies_on_device(x, _device(x), copy_of_vertex, sums)
    got = sums.read()
    np.testing.assert_allclose(got, host, rtol=1e-12, atol=1e-15 * np.max(np.abs(host)))
    assert got[-1] == 0.0 and np.sum(got) == pytest.approx(lumped.energy(x), rel=1e-12)


@pytest.mark.parametrize("scale", [0.3, 20.0])  # times eps_u: the mollified and the sliding branch of f0
def test_friction_adds_its_copy_energies_at_its_kept_device_evaluation(ti_cpu, scale):
    """The Taichi friction (DeviceCopyEnergies): at the positions its last ``add_gradient_on_device`` evaluated, one
    launch adds each pair's ``c_k f0(|u_k|)`` into its first vertex's copy: the reference split by copy; at other
    positions (no kept evaluation) it adds nothing and says so."""
    from sim_core.energies.friction.kernel import TiLaggedFriction
    from sim_core.ti_kernels.copy_vectors import CopySums
    from tests.sim_core.energies import test_friction as ref_tests

    rng = np.random.default_rng(17)
    ref, x_prev = ref_tests._random_friction(rng, p=40, n=60)
    tik = TiLaggedFriction(ref.vertices, ref.weights, ref.tangent, ref.lam, ref.mu, ref.x_prev, ref.eps_v, ref.dt)
    x = x_prev + rng.normal(scale=scale * ref_tests.EPS_U, size=x_prev.shape)
    x.flags.writeable = False
    copies = 4
    copy_of_vertex = rng.integers(0, copies, x.shape[0])
    sums = CopySums(copy_of_vertex, copies)
    sums.zero()
    assert not tik.add_copy_energies_on_device(x, _device(x), copy_of_vertex, sums)
    tik.add_gradient_on_device(x, _device(x), _device(np.zeros_like(x)))
    assert tik.add_copy_energies_on_device(x, _device(x), copy_of_vertex, sums)
    want = ref.copy_energies(x, copy_of_vertex, copies)
    np.testing.assert_allclose(sums.read(), want, rtol=1e-12, atol=1e-15 * np.max(np.abs(want)))
    assert np.ptp(want) > 0
