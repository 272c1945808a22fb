"""Terms that add their gradient into a device array at device positions (capability DeviceGradient).

For the fused elastic terms, the Taichi friction and gravity: ``add_gradient_on_device`` into a nonzero device
array gives that array plus the term's ``gradient(x)`` (bit for bit on the CPU, where the loops are serial and the
kernels the same; to round-off on CUDA: ``assert_same_sums``), returns ``energy(x)``, and keeps the evaluation of
``x``: the Hessian values (blocks) then read are those of a fresh evaluation, and a second call adds the kept
gradient without running the kernels again. The kernels read the positions from the device array, not from ``x``.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.base import DeviceGradient, DeviceHessian, declares
from tests.sim_core.energies import test_friction as ref_tests
from tests.sim_core.ti_kernels.conftest import assert_same_sums, relative_error
from tests.sim_core.ti_kernels.test_fused_elastic import KINDS, _fused, _potentials


def _device(values: np.ndarray):
    """A float64 Taichi ndarray holding ``values``."""
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.transfer import upload
    from sim_core.ti_backend import ti

    return upload(new_ndarray(ti.f64, values.shape), values)


def _frozen(x: np.ndarray) -> np.ndarray:
    """A read-only copy of ``x`` (keyed by identity, as the lockstep's iterates)."""
    x = np.array(x, dtype=np.float64)
    x.flags.writeable = False
    return x


def _no_kernels(monkeypatch, fused) -> None:
    """Make any further evaluation of ``fused``'s parts fail (what is added must come from the kept evaluation)."""
    def fail(*args):
        raise AssertionError("the kernels ran again")

    for part in fused._parts:
        monkeypatch.setattr(part, "evaluate", fail)


@pytest.mark.parametrize("kind", KINDS)
def test_fused_elastic_adds_its_gradient_and_keeps_the_evaluation(ti_cpu, monkeypatch, kind):
    pot, x_rest, deformed = _potentials(kind)
    n = x_rest.shape[0]
    free = np.ones(3 * n, bool)
    free[[0, 1, 2, 7]] = False
    fused, _ = _fused(pot, x_rest, free)
    fresh, _ = _fused(pot, x_rest, free)
    assert declares(fused, DeviceGradient)
    x = _frozen(deformed(1))
    g = fresh.gradient(x)
    energy = fresh.energy(x)  # kept from the fused evaluation
    assert energy == pytest.approx(pot.energy(x), rel=1e-12) and np.abs(g).max() > 0
    base = np.random.default_rng(3).normal(scale=np.abs(g).max(), size=g.shape)
    gd = _device(base)
    returned = fused.add_gradient_on_device(x, _device(x), gd)
    assert (returned is None) == fused._on_device()  # on CUDA the energy stays on the device until asked for
    assert_same_sums(fused.energy(x), energy)
    assert_same_sums(gd.to_numpy(), base + g)
    assert_same_sums(fused.hessian_values(x), fresh.hessian_values(x))
    assert_same_sums(fused.gradient(x), g)
    assert fused.energy(x) == fused.add_gradient_on_device(x, _device(x), _device(np.zeros_like(g)))
    _no_kernels(monkeypatch, fused)  # at the same x the kept gradient is added, the kernels do not run
    again = _device(base)
    fused.add_gradient_on_device(x, _device(x), again)
    assert_same_sums(again.to_numpy(), base + g)
    with pytest.raises(ValueError, match="gradient_device of shape"):
        fused.add_gradient_on_device(x, _device(x), _device(np.zeros((n + 1, 3))))


@pytest.mark.parametrize("kind", KINDS[:5])
def test_fused_kernels_read_the_device_positions(ti_cpu, kind):
    """The fused parts' kernels read ``x_device``: device positions other than ``x`` give their gradient (on the
    CPU arch every fused part; on CUDA the parts whose arrays live on the device, the others evaluated at ``x`` on
    the host)."""
    pot, x_rest, deformed = _potentials(kind)
    free = np.ones(x_rest.size, bool)
    fused, _ = _fused(pot, x_rest, free)
    x, y = _frozen(deformed(2)), deformed(3)
    read = y if ti_cpu == "cpu" or fused._on_device() else x
    assert fused._on_device() == (ti_cpu == "cuda" and kind in ("snh", "spring_membrane", "kirchhoff"))
    gd = _device(np.zeros_like(x))
    fused.add_gradient_on_device(x, _device(y), gd)
    assert fused.energy(x) == pytest.approx(pot.energy(read), rel=1e-12)
    assert relative_error(gd.to_numpy(), pot.gradient(read)) < 1e-12
    assert relative_error(pot.gradient(y), pot.gradient(x)) > 1e-3


def test_fused_elastic_keeps_gradient_and_values_on_the_device_on_the_cuda_path(ti_cpu, monkeypatch):
    """The CUDA path (every part a device part: gradient and Hessian values left in device arrays, the gradient
    added there), run on the test arch with the arch query answering "cuda": the host path's sums; a line
    search's kept evaluation (``evaluate``) is added without running the kernels again; with a part that has no
    device kernel the host evaluation's gradient is added."""
    import sim_core.energies.kirchhoff_bending.fused_kernel as kirchhoff_kernel
    import sim_core.energies.membrane.fused_spring_kernel as spring_kernel
    import sim_core.ti_backend as backend
    from sim_core.assembly import HessianAssembler
    from sim_core.fused_elastic import FusedElastic

    membrane, x_rest, deformed = _potentials("spring_membrane")
    bending = _potentials("kirchhoff")[0]
    hinge = _potentials("hinge_reference_part")[0]
    free = np.ones(x_rest.size, bool)
    free[:4] = False
    expected = {}
    for terms in ((membrane, bending), (membrane, bending, hinge)):
        host = FusedElastic(list(terms))
        host.bind(HessianAssembler(x_rest.size).static_pattern(host.block_vertex_arrays(x_rest), free))
        x = _frozen(deformed(4))
        expected[len(terms)] = (x, host.gradient(x), host.energy(x), host.hessian_values(x).copy(), host.pattern)
    for module in (backend, kirchhoff_kernel, spring_kernel):
        monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    for terms in ((membrane, bending), (membrane, bending, hinge)):
        x, g, energy, values, pattern = expected[len(terms)]
        fused = FusedElastic(list(terms))
        fused.block_vertex_arrays(x_rest)
        fused.bind(pattern)
        assert fused._on_device() == (len(terms) == 2)
        base = np.random.default_rng(5).normal(size=g.shape)
        gd = _device(base)
        returned = fused.add_gradient_on_device(x, _device(x), gd)
        assert (returned is None) == (len(terms) == 2)  # the device evaluation's energy not read yet
        assert_same_sums(fused.energy(x), energy)
        assert_same_sums(gd.to_numpy(), base + g)
        device_values = fused.hessian_values_device(x)
        assert (device_values is not None) == (len(terms) == 2)
        if device_values is not None:
            assert_same_sums(device_values.to_numpy()[: values.size], values)
        assert_same_sums(fused.hessian_values(x), values)
        assert_same_sums(fused.gradient(x), g)
    y = _frozen(deformed(6))  # a trial point kept by the line search, then added
    fused = FusedElastic([membrane, bending])
    fused.block_vertex_arrays(x_rest)
    fused.bind(expected[2][4])
    fused.evaluate(y)
    _no_kernels(monkeypatch, fused)
    gd = _device(np.zeros_like(y))
    fused.add_gradient_on_device(y, _device(y), gd)
    assert relative_error(gd.to_numpy(), membrane.gradient(y) + bending.gradient(y)) < 1e-12
    monkeypatch.undo()
    for module in (backend, kirchhoff_kernel, spring_kernel):
        monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    # a device evaluation's energy left unread is read before the next evaluation reuses the sum cells
    z = _frozen(deformed(7))
    fused.add_gradient_on_device(z, _device(z), _device(np.zeros_like(z)))
    assert callable(fused._kept[1])
    assert fused.energy(y) == pytest.approx(membrane.energy(y) + bending.energy(y), rel=1e-12)  # another block
    assert not callable(fused._kept[1])
    assert fused.energy(z) == pytest.approx(membrane.energy(z) + bending.energy(z), rel=1e-12)


def _friction(seed: int, scale: float):
    from sim_core.energies.friction.kernel import TiLaggedFriction

    rng = np.random.default_rng(seed)
    ref, x_prev = ref_tests._random_friction(rng, p=40, n=60)
    twins = [TiLaggedFriction(ref.vertices, ref.weights, ref.tangent, ref.lam, ref.mu, ref.x_prev, ref.eps_v, ref.dt)
             for _ in range(2)]
    x = _frozen(x_prev + rng.normal(scale=scale, size=x_prev.shape))
    return ref, twins, x


@pytest.mark.parametrize("scale", [0.3 * ref_tests.EPS_U, 20 * ref_tests.EPS_U])
def test_friction_adds_its_gradient_and_keeps_the_evaluation(ti_cpu, scale):
    ref, (tik, fresh), x = _friction(41, scale)
    assert declares(tik, DeviceGradient) and declares(tik, DeviceHessian)
    g = fresh.gradient(x)
    assert relative_error(g, ref.gradient(x)) < 1e-12
    base = np.random.default_rng(4).normal(scale=np.abs(g).max(), size=g.shape)
    gd = _device(base)
    energy = tik.add_gradient_on_device(x, _device(x), gd)
    assert_same_sums(energy, fresh.energy(x))
    assert energy == pytest.approx(ref.energy(x), rel=1e-12)
    assert_same_sums(gd.to_numpy(), base + g)
    assert_same_sums(tik.hessian(x).blocks, fresh.hessian(x).blocks)
    assert tik.energy(x) == energy
    assert_same_sums(tik.gradient(x), g)
    vertices, rows = tik.gradient_rows(x)
    assert_same_sums(rows, g[vertices])
    tik.add_gradient_on_device(x, _device(x), gd)  # the kept rows added again
    assert relative_error(gd.to_numpy(), base + 2.0 * g) < 1e-14
    tik.mu = 0.5 * tik.mu  # other coefficients: evaluated afresh
    fresh.mu = tik.mu
    gd = _device(np.zeros_like(g))
    assert_same_sums(tik.add_gradient_on_device(x, _device(x), gd), fresh.energy(x))
    assert_same_sums(gd.to_numpy(), fresh.gradient(x))
    y = _frozen(x + 1e-3 * ref_tests.EPS_U)  # other positions: not the kept evaluation's
    assert_same_sums(tik.hessian(y).blocks, fresh.hessian(y.copy()).blocks)
    # the kept blocks are in host arrays on the CPU arch, in device memory on CUDA
    assert (tik.hessian_on_device(x) is None) == (ti_cpu == "cpu")


def test_friction_reads_the_device_positions_and_keeps_blocks_on_the_device_on_the_cuda_path(ti_cpu, monkeypatch):
    """With the arch query answering "cuda" (the kernel's arrays as Taichi ndarrays): the positions are read from
    ``x_device``, and the Hessian blocks stay in the kernel's device array (``hessian_on_device``) until the next
    evaluation at other positions; an empty friction adds nothing. The host path's launches (energy, gradient and
    blocks packed into one device array, copied back at once) give the twin's values."""
    import sim_core.energies.friction.kernel as friction_kernel
    import sim_core.ti_backend as backend
    from sim_core.ti_kernels.buffers import DeviceHessianBlocks, LaunchArrays

    ref, (tik, fresh), x = _friction(42, 0.5 * ref_tests.EPS_U)
    y = x + np.random.default_rng(6).normal(scale=0.2 * ref_tests.EPS_U, size=x.shape)
    expected = fresh.gradient(y)
    z = _frozen(y + 1e-3 * ref_tests.EPS_U)
    host_path = fresh.energy(z), fresh.gradient(z), fresh.hessian(z).blocks
    monkeypatch.setattr(friction_kernel, "_ARRAYS", LaunchArrays())  # this test's device arrays only
    for module in (backend, friction_kernel):
        monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    host_twin = friction_kernel.TiLaggedFriction(ref.vertices, ref.weights, ref.tangent, ref.lam, ref.mu, ref.x_prev,
                                                 ref.eps_v, ref.dt)
    for got, want in zip((host_twin.energy(z), host_twin.gradient(z), host_twin.hessian(z).blocks), host_path):
        assert_same_sums(got, want)
    assert not isinstance(friction_kernel._ARRAYS.device()["packed"][1], np.ndarray)  # the device array's path
    gd = _device(np.zeros_like(x))
    reads = []
    copy_back = friction_kernel.copy_back
    monkeypatch.setattr(friction_kernel, "copy_back", lambda *a, **k: reads.append(a[1]) or copy_back(*a, **k))
    # key x, device positions y: nothing read back (the energy stays on the device until asked for)
    assert tik.add_gradient_on_device(x, _device(y), gd) is None and reads == []
    assert tik.add_gradient_on_device(x, _device(y), _device(np.zeros_like(x))) is None and reads == []  # kept rows
    assert tik.energy(x) == pytest.approx(ref.energy(y), rel=1e-12) and len(reads) == 1
    assert tik.energy(x) == pytest.approx(ref.energy(y), rel=1e-12) and len(reads) == 1  # read once, then kept
    assert relative_error(gd.to_numpy(), expected) < 1e-12
    kept = tik.hessian_on_device(x)
    assert isinstance(kept, DeviceHessianBlocks) and np.array_equal(kept.vertices, tik.vertices)
    assert relative_error(kept.blocks.to_numpy(), ref.hessian(y).blocks) < 1e-12
    assert relative_error(tik.hessian(x).blocks, ref.hessian(y).blocks) < 1e-12
    other = _frozen(y)
    tik.add_gradient_on_device(other, _device(other), _device(np.zeros_like(x)))
    assert tik.hessian_on_device(x) is None and tik.hessian_on_device(other) is not None
    empty = friction_kernel.TiLaggedFriction(np.zeros((0, 4), int), np.zeros((0, 4)), np.zeros((0, 3, 2)),
                                             np.zeros(0), 0.5, x, 0.01, 5e-3)
    gd = _device(np.ones_like(x))
    assert empty.add_gradient_on_device(x, _device(x), gd) == 0.0 and np.all(gd.to_numpy() == 1.0)
    assert empty.hessian_on_device(x) is None


def test_friction_pairs_of_one_vertex_after_pairs_of_four(ti_cpu):
    """Pairs against an obstacle (one block vertex) evaluated on the device path after pairs of four vertices (the
    thread's kept arrays of another block size): their own blocks ``(p, 3, 3)`` and gradient."""
    from sim_core.energies.friction.kernel import TiLaggedFriction

    _, (four, _), x4 = _friction(43, 0.5 * ref_tests.EPS_U)
    four.add_gradient_on_device(x4, _device(x4), _device(np.zeros_like(x4)))
    rng = np.random.default_rng(44)
    x_prev = rng.normal(size=(6, 3)) * 1e-3
    args = (np.array([[0], [2], [5]]), np.ones((3, 1)), np.repeat(np.eye(3)[None, :, :2], 3, axis=0), np.ones(3), 0.4,
            x_prev, 0.01, 5e-3)
    one, fresh = TiLaggedFriction(*args), TiLaggedFriction(*args)
    x = _frozen(x_prev + rng.normal(scale=1e-4, size=x_prev.shape))
    gd = _device(np.zeros_like(x))
    assert_same_sums(one.add_gradient_on_device(x, _device(x), gd), fresh.energy(x))
    assert_same_sums(gd.to_numpy(), fresh.gradient(x))
    blocks = one.hessian(x).blocks
    assert blocks.shape == (3, 3, 3)
    assert_same_sums(blocks, fresh.hessian(x).blocks)


def test_gravity_adds_its_constant_gradient(ti_cpu):
    from sim_core.energies.gravity.kernel import TiGravityPotential
    from sim_core.energies.gravity.reference import GravityPotential

    rng = np.random.default_rng(7)
    mass = rng.uniform(0.5, 2.0, size=50)
    ref, tik = GravityPotential(mass, [0.1, -0.3, -9.81]), TiGravityPotential(mass, [0.1, -0.3, -9.81])
    assert declares(tik, DeviceGradient)
    x = rng.normal(size=(50, 3))
    base = rng.normal(size=x.shape)
    gd = _device(base)
    assert tik.add_gradient_on_device(x, _device(x), gd) == pytest.approx(ref.energy(x), rel=1e-12)
    assert_same_sums(gd.to_numpy(), base + ref.gradient(x))
    assert tik.energy(x) == ref.energy(x) and np.array_equal(tik.gradient(x), ref.gradient(x))
    with pytest.raises(ValueError, match="x_device of shape"):
        tik.add_gradient_on_device(x, _device(x[:-1]), gd)
