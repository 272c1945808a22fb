"""The Taichi lagged friction equals the NumPy reference and passes its finite-difference checks."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.friction.reference import LaggedFriction
from sim_core.workspace import workspace_of
from tests.sim_core.energies import test_friction as ref_tests
from tests.sim_core.ti_kernels.conftest import relative_error

EPS_U = ref_tests.EPS_U


def _twin(ref: LaggedFriction):
    from sim_core.energies.friction.kernel import TiLaggedFriction

    return TiLaggedFriction(ref.vertices, ref.weights, ref.tangent, ref.lam, ref.mu, ref.x_prev, ref.eps_v, ref.dt)


@pytest.mark.parametrize("scale", [0.0, 0.3 * EPS_U, EPS_U, 20 * EPS_U])
def test_energy_gradient_hessian_equal_the_reference(ti_cpu, scale):
    rng = np.random.default_rng(31)
    ref, x_prev = ref_tests._random_friction(rng, p=40, n=30)
    tik = _twin(ref)
    x = x_prev + rng.normal(scale=scale, size=x_prev.shape)
    assert tik.energy(x) == pytest.approx(ref.energy(x), rel=1e-12)
    assert relative_error(tik.gradient(x), ref.gradient(x)) < 1e-12
    h_ti, h_ref = tik.hessian(x, "none"), ref.hessian(x, "none")
    assert np.array_equal(h_ti.vertices, h_ref.vertices)
    assert relative_error(h_ti.blocks, h_ref.blocks) < 1e-12


def test_one_vertex_pairs_and_no_pairs(ti_cpu):
    """Pairs against an obstacle (one block vertex, plane / sphere frames) and an empty set."""
    from sim_core.energies.friction.kernel import TiLaggedFriction

    rng = np.random.default_rng(32)
    n = 6
    x_prev = rng.normal(size=(n, 3)) * 1e-3
    tangent = np.repeat(np.eye(3)[None, :, :2], 3, axis=0)
    ref = LaggedFriction(np.array([[0], [2], [5]]), np.ones((3, 1)), tangent, np.ones(3), 0.4, x_prev, 0.01, 5e-3)
    tik = _twin(ref)
    x = x_prev + rng.normal(scale=1e-4, size=x_prev.shape)
    assert tik.energy(x) == pytest.approx(ref.energy(x), rel=1e-12)
    assert relative_error(tik.gradient(x), ref.gradient(x)) < 1e-12
    assert relative_error(tik.hessian(x).blocks, ref.hessian(x).blocks) < 1e-12
    empty = TiLaggedFriction(np.zeros((0, 4), int), np.zeros((0, 4)), np.zeros((0, 3, 2)), np.zeros(0), 0.5,
                             x_prev, 0.01, 5e-3)
    assert empty.energy(x) == 0.0
    assert not np.any(empty.gradient(x))
    assert empty.hessian(x).blocks.shape == (0, 12, 12)


@pytest.mark.parametrize("scale, regime", [(0.3 * EPS_U, "mollified"), (20 * EPS_U, "sliding")])
def test_finite_differences_psd_and_mu(ti_cpu, scale, regime):
    rng = np.random.default_rng(20 if regime == "sliding" else 21)
    ref, x_prev = ref_tests._random_friction(rng)
    ref_tests.check_friction_fd_psd_and_mu(_twin(ref), x_prev, rng, scale, regime, psd_tol=1e-12)


def test_the_contact_set_builds_it_on_the_taichi_backend(ti_cpu):
    """Forming after a few steps of the benchmark trajectory: the same frozen pairs, the Taichi class."""
    from sim_core.bench.forming import run_forming
    from sim_core.contact_set import ContactSet
    from sim_core.energies.friction.kernel import TiLaggedFriction
    from thinshell_ros.paths import bundled_scene

    states = []
    import sim_core.simulation as simulation

    step = simulation.Simulation.step

    def recording_step(self, control):
        info = step(self, control)
        states.append((self.model, self.state.x.copy(), self.state.contact_memory))
        return info

    simulation.Simulation.step = recording_step
    try:
        run_forming(bundled_scene("forming"), 12, arch="numpy")
    finally:
        simulation.Simulation.step = step
    model, x, memory = states[-1]
    ref = ContactSet(model).friction(x, 5e-3, memory)
    contact = ContactSet(model, backend="taichi-cpu")
    tik = contact.friction(x, 5e-3, contact.begin_step(x, memory))
    assert type(ref) is LaggedFriction and type(tik) is TiLaggedFriction
    np.testing.assert_array_equal(tik.vertices, ref.vertices)
    np.testing.assert_array_equal(tik.lam, ref.lam)
    x_new = x + 1e-5
    assert tik.energy(x_new) == pytest.approx(ref.energy(x_new), rel=1e-12)


def test_hessian_kept_from_the_gradient_launch_equals_the_hessian_kernel(ti_cpu, monkeypatch):
    """The gradient's launch also computes the blocks; the next hessian at the same x and
    coefficients takes them (no launch), bit for bit a Hessian-only launch's; an edited mu, another x
    or a second call launch a Hessian-only request again."""
    from sim_core.energies.friction import kernel as ti_friction

    rng = np.random.default_rng(33)
    ref, x_prev = ref_tests._random_friction(rng, p=40, n=30)
    tik = _twin(ref)
    x = x_prev + rng.normal(scale=0.5 * EPS_U, size=x_prev.shape)
    fresh = tik.hessian(x).blocks  # a Hessian-only launch
    launches = []
    kernel = ti_friction._friction_kernel
    monkeypatch.setattr(ti_friction, "_friction_kernel",
                        lambda *a: (launches.append(1) if a[7] == ti_friction._HESSIAN else None, kernel(*a)))
    grad = tik.gradient(x)
    assert relative_error(grad, ref.gradient(x)) < 1e-12
    np.testing.assert_array_equal(tik.hessian(x).blocks, fresh)
    assert launches == []
    np.testing.assert_array_equal(tik.hessian(x).blocks, fresh)  # kept for one call only
    assert launches == [1]
    tik.gradient(x)
    tik.mu = 2.0 * tik.mu
    assert relative_error(tik.hessian(x).blocks, 2.0 * fresh) < 1e-15
    assert launches == [1, 1]
    tik.gradient(x)
    y = x + 1e-3 * EPS_U
    assert relative_error(tik.hessian(y).blocks, ref.hessian(y).blocks * 2.0) < 1e-12
    assert launches == [1, 1, 1]


def test_keep_derivatives_keeps_the_values_of_the_separate_requests(ti_cpu, monkeypatch):
    """``keep_derivatives(x)`` (one launch) keeps energy, gradient and blocks that equal the energy-only launch's
    and the gradient-Hessian launch's bit for bit; energy, gradient and the following hessian at an
    equal x read them (no other launch); an edited mu or another x launches the separate requests."""
    from sim_core.energies.friction import kernel as ti_friction

    rng = np.random.default_rng(35)
    ref, x_prev = ref_tests._random_friction(rng, p=40, n=30)
    fresh, kept = _twin(ref), _twin(ref)
    x = x_prev + rng.normal(scale=0.7 * EPS_U, size=x_prev.shape)
    energy, grad = fresh.energy(x), fresh.gradient(x)
    blocks = fresh.hessian(x).blocks
    kept.keep_derivatives(x)
    launches = []
    kernel = ti_friction._friction_kernel
    monkeypatch.setattr(ti_friction, "_friction_kernel", lambda *a: (launches.append(a[7]), kernel(*a))[1])
    assert kept.energy(x.copy()) == energy
    np.testing.assert_array_equal(kept.gradient(x.copy()), grad)
    np.testing.assert_array_equal(kept.hessian(x.copy()).blocks, blocks)
    assert launches == []
    assert workspace_of(kept).get(kept, "derivatives") is None  # dropped by the gradient call
    kept.keep_derivatives(x)
    y = x + 0.1 * EPS_U
    assert kept.energy(y) == fresh.energy(y)
    everything = ti_friction._ENERGY | ti_friction._GRADIENT | ti_friction._HESSIAN
    assert launches == [everything, ti_friction._ENERGY, ti_friction._ENERGY]
    kept.mu = 2.0 * kept.mu
    assert kept.energy(x) == pytest.approx(2.0 * energy, rel=1e-14)
    assert launches[-1] == ti_friction._ENERGY
    empty = ti_friction.TiLaggedFriction(np.zeros((0, 4), int), np.zeros((0, 4)), np.zeros((0, 3, 2)), np.zeros(0),
                                         0.5, x_prev, 0.01, 0.01)
    empty.keep_derivatives(x)
    assert empty.energy(x) == 0.0 and not np.any(empty.gradient(x))


def test_a_second_gradient_at_the_same_x_is_the_kept_one_then_nothing_is_kept(ti_cpu, monkeypatch):
    """A gradient request at the x (coefficients, eps_u) of the previous one returns that gradient
    without a launch and keeps nothing; another x, an edited mu or a third request launch again."""
    from sim_core.energies.friction import kernel as ti_friction

    rng = np.random.default_rng(37)
    ref, x_prev = ref_tests._random_friction(rng, p=40, n=30)
    x = x_prev + rng.normal(scale=0.6 * EPS_U, size=x_prev.shape)
    launches = []
    kernel = ti_friction._friction_kernel
    monkeypatch.setattr(ti_friction, "_friction_kernel", lambda *a: (launches.append(a[7]), kernel(*a))[1])
    for first in ("gradient", "keep_derivatives"):
        tik = _twin(ref)
        launches.clear()
        if first == "keep_derivatives":
            tik.keep_derivatives(x)
        grad = tik.gradient(x)
        grad[0] = 1e9  # the caller's array: the kept one is another
        again = tik.gradient(x.copy())
        assert relative_error(again, ref.gradient(x)) < 1e-12 and len(launches) == 1
        assert workspace_of(tik).get(tik, "gradient") is None
        np.testing.assert_array_equal(tik.gradient(x), again)
        assert len(launches) == 2
    tik.mu = 2.0 * tik.mu
    assert relative_error(tik.gradient(x), 2.0 * ref.gradient(x)) < 1e-12 and len(launches) == 3
    y = x + 0.1 * EPS_U
    assert relative_error(tik.gradient(y), 2.0 * ref.gradient(y)) < 1e-12 and len(launches) == 4


def test_pairs_naming_few_vertices_give_the_reference_there_and_zero_elsewhere(ti_cpu):
    """The kernel sees the pairs' own vertices only: with 6 pairs over 400 vertices the energy, gradient and
    blocks are the reference's (1e-12), the gradient exactly zero on the vertices no pair names, also when the
    kept gradient and the kept derivatives of an equal ``x`` are returned again."""
    rng = np.random.default_rng(36)
    ref, x_prev = ref_tests._random_friction(rng, p=6, n=400)
    tik = _twin(ref)
    x = x_prev + rng.normal(scale=0.7 * EPS_U, size=x_prev.shape)
    named = np.zeros(len(x), dtype=bool)
    named[ref.vertices.ravel()] = True
    assert np.count_nonzero(named) <= 24
    expected = ref.gradient(x)
    assert tik.energy(x) == pytest.approx(ref.energy(x), rel=1e-12)
    first, again = tik.gradient(x), tik.gradient(x.copy())  # the second: the kept gradient
    tik.keep_derivatives(x)
    kept = tik.gradient(x)  # the kept derivatives'
    for grad in (first, again, kept):
        assert grad.shape == x.shape and relative_error(grad, expected) < 1e-12 and not np.any(grad[~named])
    assert again is not first and not np.shares_memory(again, first)
    assert relative_error(tik.hessian(x).blocks, ref.hessian(x, "none").blocks) < 1e-12
    # the same gradient as the rows of the pairs' distinct vertices (SparseGradient): first, again (kept), kept
    # derivatives'
    y = x + rng.normal(scale=0.1 * EPS_U, size=x.shape)
    expected = ref.gradient(y)
    got = [tik.gradient_rows(y), tik.gradient_rows(y.copy())]
    tik.keep_derivatives(y)
    got.append(tik.gradient_rows(y))
    for vertices, rows in got:
        assert len(np.unique(vertices)) == len(vertices) == np.count_nonzero(named)
        spread = np.zeros_like(y)
        spread[vertices] = rows
        assert relative_error(spread, expected) < 1e-12
