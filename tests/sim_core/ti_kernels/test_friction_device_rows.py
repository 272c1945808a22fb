"""The lagged friction rows built on the device (``sim_core.energies.friction.rows_kernel``): the rows equal the host
set-up's (frames and tangent bases bit for bit, normal forces and Coulomb coefficients), the friction's energy,
gradient, Hessian blocks and energies by copy from them equal the NumPy reference, the contact set builds them on
CUDA's path (emulated on the CPU arch) with nothing read back until a host array is asked for, and a Forming batch
stepped in lockstep through that path gives each copy its separate run's states."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from tests.sim_core.ti_kernels.conftest import TEST_ARCH
from tests.sim_core.ti_kernels.test_contact_setup import _batch, _forming_contact
from tests.support.emulated_cuda import emulate_cuda


EMULATED_ONLY = ("runs CUDA's friction path emulated on the CPU arch beside the host path, which only the CPU arch "
                 "runs (the default, and CI); under THINSHELL_TEST_ARCH=cuda the device rows run for real in this "
                 "module's other tests")
"""Why the emulation tests are left out on a GPU run."""


def _device(a: np.ndarray):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.transfer import upload

    return upload(ti.ndarray(ti.f64, a.shape), np.ascontiguousarray(a, dtype=np.float64))


def _rows_and_reference(seed: int, count: int = 300, split: int = 120):
    """A friction built by ``friction_on_device`` from random pairs and the reference ``LaggedFriction`` of the same
    pairs from the host set-up (``friction_frames``, host normal forces and coefficients), and ``x^n``."""
    from sim_core.energies.contact.setup_kernel import friction_frames
    from sim_core.energies.friction.rows_kernel import friction_on_device
    from sim_core.energies.friction.reference import LaggedFriction

    x, vertices = _batch(seed, count)
    rng = np.random.default_rng(seed)
    k = len(vertices)
    sides = rng.choice([-1.0, 0.0, 1.0], size=k)
    eps_vt, eps_ee, k_vt, k_ee = 2.0e-3, 1.5e-3, 300.0, 500.0
    d = np.where(np.arange(k) < split, eps_vt, eps_ee) * rng.uniform(0.0, 1.0, k)
    vertex_body = rng.integers(0, 3, len(x))
    table = np.array([[0.3, 0.5, 0.0], [0.5, 0.2, 0.7], [0.0, 0.7, 0.4]])
    x.flags.writeable = False
    friction = friction_on_device(x, None, vertices, sides, d, split, (eps_vt, eps_ee, k_vt, k_ee), vertex_body,
                                  table, 0.05, 0.01)
    weights, _, tangent = friction_frames(x, vertices, sides, split)
    second = np.concatenate([vertices[:split, 1], vertices[split:, 2]])
    lam = np.where(np.arange(k) < split, k_vt * (eps_vt - d), k_ee * (eps_ee - d))
    ref = LaggedFriction(vertices, weights, tangent, lam, table[vertex_body[vertices[:, 0]], vertex_body[second]], x,
                         0.05, 0.01)
    return friction, ref, x


def test_rows_built_on_the_device_equal_the_host_set_up(ti_cpu):
    """Weights and tangent bases bit for bit the frames launch's, ``lam = k_c (eps - d)`` and ``mu`` of each kind and
    body pair as the host computes them, read back in one copy at the first ask (none before)."""
    friction, ref, _ = _rows_and_reference(3)
    assert friction._host is None  # nothing read back by the set-up
    twin = pickle.loads(pickle.dumps(friction))  # a pickle holds the host arrays, read back for it
    assert twin._device_arrays is None
    np.testing.assert_array_equal(twin.tangent, ref.tangent)
    x = ref.x_prev + 1e-4
    np.testing.assert_allclose(twin.gradient(x), ref.gradient(x), rtol=0, atol=1e-12 * np.max(np.abs(ref.gradient(x))))
    for name in ("weights", "tangent", "lam", "mu"):
        np.testing.assert_array_equal(getattr(friction, name), getattr(ref, name), err_msg=name)
    np.testing.assert_array_equal(friction.vertices, ref.vertices)
    assert friction.eps_u == ref.eps_u
    assert np.any(ref.mu == 0) and np.any(ref.mu > 0) and np.ptp(ref.lam) > 0


@pytest.mark.parametrize("scale", [0.3, 30.0])  # sticking (mollified) and sliding pairs
def test_device_rows_evaluate_as_the_reference(ti_cpu, scale):
    """At positions moved from ``x^n`` by a fraction (or many) of ``eps_u``: the energy, the gradient added into a
    device array, the Hessian blocks left on the device and the energies by copy equal the NumPy reference's to
    round-off; a second friction's rows do not overwrite the first's while it exists."""
    from sim_core.ti_kernels.copy_vectors import CopySums

    friction, ref, x_n = _rows_and_reference(5)
    other, other_ref, _ = _rows_and_reference(6)
    rng = np.random.default_rng(8)
    x = x_n + rng.normal(scale=scale * ref.eps_u, size=x_n.shape)
    x.flags.writeable = False
    x_dev = _device(x)
    start = rng.normal(size=x.shape)
    gradient = _device(start)
    assert friction.add_gradient_on_device(x, x_dev, gradient) is None
    g_ref = ref.gradient(x)
    scale_g = np.max(np.abs(g_ref))
    np.testing.assert_allclose(gradient.to_numpy() - start, g_ref, rtol=0, atol=1e-12 * scale_g)
    assert np.isclose(friction.energy(x), ref.energy(x), rtol=1e-12, atol=0)
    blocks = friction.hessian_on_device(x)
    np.testing.assert_array_equal(blocks.vertices, ref.vertices)
    h_ref = ref.hessian(x).blocks
    np.testing.assert_allclose(blocks.blocks.to_numpy(), h_ref, rtol=0, atol=1e-12 * np.max(np.abs(h_ref)))
    assert friction.hessian_on_device(x + 1e-9) is None  # no evaluation kept there
    copies = 3
    copy_of_vertex = rng.integers(0, copies, x.shape[0])
    sums = CopySums(copy_of_vertex, copies)
    sums.zero()
    assert friction.add_copy_energies_on_device(x, x_dev, copy_of_vertex, sums)
    want = ref.copy_energies(x, copy_of_vertex, copies)
    np.testing.assert_allclose(sums.read(), want, rtol=1e-12, atol=1e-15 * np.max(np.abs(want)))
    assert np.ptp(want) > 0
    assert friction._host is None  # every evaluation above on the device rows
    # the other friction's rows are its own
    g_other = _device(np.zeros_like(x))
    other.add_gradient_on_device(x, x_dev, g_other)
    np.testing.assert_allclose(g_other.to_numpy(), other_ref.gradient(x), rtol=0,
                               atol=1e-12 * np.max(np.abs(other_ref.gradient(x))))
    np.testing.assert_array_equal(friction.weights, ref.weights)
    # host arrays asked for: the Taichi friction's host paths on them, and mu editable
    friction.mu = 2.0 * ref.mu
    ref.mu = 2.0 * ref.mu
    np.testing.assert_allclose(friction.gradient(x), ref.gradient(x), rtol=0, atol=2e-12 * scale_g)
    g2 = _device(np.zeros_like(x))
    friction.add_gradient_on_device(x, x_dev, g2)
    np.testing.assert_allclose(g2.to_numpy(), ref.gradient(x), rtol=0, atol=2e-12 * scale_g)


@pytest.mark.skipif(TEST_ARCH != "cpu", reason=EMULATED_ONLY)
def test_contact_set_builds_the_friction_rows_on_the_device_path(ti_cpu, monkeypatch):
    """On CUDA's path the contact set's friction of a pressed Forming state is a DeviceLaggedFriction whose rows, row
    sources, normal forces and coefficients equal the host path's bit for bit."""
    from sim_core.energies.friction.rows_kernel import DeviceLaggedFriction

    results = []
    for emulated in (False, True):
        if emulated:
            emulate_cuda(monkeypatch)
        contact, x = _forming_contact("taichi-cpu")
        x_n = x + 0.4 * contact.eps * np.random.default_rng(7).normal(size=x.shape)
        x_n.flags.writeable = False
        memory = contact.begin_step(x_n, None)
        results.append(contact.friction(x_n, 0.01, memory))
    host, device = results
    assert isinstance(device, DeviceLaggedFriction) and not isinstance(host, DeviceLaggedFriction)
    assert device._host is None and len(device.vertices) > 10
    for name in ("vertices", "weights", "tangent", "lam", "mu", "x_prev"):
        np.testing.assert_array_equal(getattr(device, name), getattr(host, name), err_msg=name)
    assert device.eps_u == host.eps_u and device.workspace is not None
    for a, b in zip(device.row_sources, host.row_sources):
        np.testing.assert_array_equal(a.pair_index, b.pair_index)


@pytest.mark.skipif(TEST_ARCH != "cpu", reason=EMULATED_ONLY)
def test_lockstep_forming_on_the_device_rows_equals_separate_runs(ti_cpu, monkeypatch):
    """Three Forming copies stepped in lockstep on CUDA's paths (emulated on the CPU arch; the envelope solver, each
    step's friction from device rows, none of its host arrays read; the candidate lists' vertices gathered where the
    search's sort left their keys, the potentials reading theirs by rows, none gathered whole; the edge-edge pairs kept
    and the pair batches' layout rows made on the device from the side codes): copies 0 and 2 end
    every step where their separate runs (CPU arch, host friction rows) end, to the solver's tolerance, a step ended
    by the simplified Newton test on the envelope's kept factors as well; copy 1, started from a non-finite velocity,
    fails alone at its first step and keeps its last good state."""
    import copy

    from sim_core.control import Control
    from sim_core.energies.friction import rows_kernel as device_rows
    from sim_core.simulation import Simulation
    from sim_core.solver_config import SolverConfig

    from sim_core.bench.batch import _FormingRun
    from sim_core.energies.contact.reference import PairVertices
    from sim_core.ti_kernels.hash_candidates import HashCandidates

    steps = 3
    run = _FormingRun(3, steps, "taichi-cpu", lockstep=True, linear_solver="envelope")
    model, effector = run.batch.sims[0].model, run.effector
    separate = []
    for i in (0, 2):
        alone = Simulation(copy.deepcopy(model), solver_config=SolverConfig(backend="taichi-cpu"))
        alone.state = run.batch.states[i].copy()
        separate.append([alone.step(Control(effector_pose_target={effector: run.targets[i][k]})) and alone.state.copy()
                         for k in range(steps)])
    sheet = model.bodies["sheet"].vertices
    run.batch.sims[1].state.v[sheet[len(sheet) // 2]] = [0.0, 0.0, np.nan]
    start = run.batch.states[1].copy()
    built = []
    original = device_rows.friction_on_device
    monkeypatch.setattr(device_rows, "friction_on_device", lambda *a: built.append(original(*a)) or built[-1])
    gathered = []
    gather = HashCandidates.device_vertices
    monkeypatch.setattr(HashCandidates, "device_vertices", lambda *a: gathered.append(gather(*a)) or gathered[-1])
    from sim_core.energies.contact import sides_kernel

    kept = []  # the kept edge-edge rows and the pair batch's layout rows made on the device at each step's sides
    made = sides_kernel.kept_rows
    monkeypatch.setattr(sides_kernel, "kept_rows", lambda codes: kept.append(made(codes)) or kept[-1])
    whole = []  # the potentials' vertices read whole (none: the rows they use, PairVertices)
    read_whole = PairVertices.__array__
    monkeypatch.setattr(PairVertices, "__array__", lambda self, *a, **k: (whole.append(self),
                                                                          read_whole(self, *a, **k))[1])
    emulate_cuda(monkeypatch)
    tol = SolverConfig().tol_velocity * 0.005
    stops = []  # the steps' simplified Newton stops (the envelope's kept factors: no last factorisation)
    for k in range(steps):
        res = run.batch.step([Control(effector_pose_target={effector: t[k]}) for t in run.targets])
        info = run.batch.lockstep.solver.last_stacked_info
        stops.append(info.simplified_stops)
        assert info.factorizations >= info.iterations - info.simplified_stops
        assert res.failed_now == ([1] if k == 0 else [])
        for i, ref in zip((0, 2), separate):
            assert np.max(np.abs(run.batch.states[i].x - ref[k].x)) <= tol, (i, k)
    assert any(stops)  # (the separate runs' host solver runs the same test)
    assert len(built) >= steps and all(f._host is None for f in built)  # (step 0 again without copy 1)
    assert gathered and all(g is not None for g in gathered) and not whole
    assert isinstance(run.batch.lockstep.solver.contact._cache[2][1].vertices, PairVertices)
    assert len(kept) >= steps  # the batches' layout rows from the device (none built or sent by the host)
    batch = run.batch.lockstep.solver.contact._cache[2][1]._batch
    assert any(batch._device["all_rows"][1] is k.device for k in kept)
    assert list(run.batch.active) == [True, False, True] and "non-finite" in run.batch.failures[1]
    np.testing.assert_array_equal(run.batch.states[1].x, start.x)
