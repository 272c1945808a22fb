"""A vertex-triangle and an edge-edge potential linked by a PairBatch give, bit for bit, what each
gives on its own, with one kernel launch per new position for both."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.workspace import workspace_of

from tests.sim_core.ti_kernels.conftest import assert_same_sums
from tests.sim_core.ti_kernels.test_contact_distance import EPS, _near_parallel_edges, _random_pairs

K = 1.0e4


def _potentials(count: int = 400, vt_rows: slice = slice(None), ee_rows: slice = slice(None)):
    """Twin potential pairs over random pairs (every region, every side): one pair linked, one not."""
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.energies.contact.kernel import TiEdgeEdgeContact, TiVertexTriangleContact

    rng = np.random.default_rng(20)
    z = np.concatenate([_random_pairs(rng, count), _near_parallel_edges(rng, count // 4)])
    x = z.reshape(-1, 3)
    quads = np.arange(x.shape[0]).reshape(-1, 4)
    vt_pairs = np.stack([quads[:, 0], np.arange(len(quads))], axis=1)[vt_rows]
    triangles = quads[:, 1:]
    edges = np.arange(x.shape[0]).reshape(-1, 2)
    ee_pairs = np.stack([np.arange(0, len(edges), 2), np.arange(1, len(edges), 2)], axis=1)[ee_rows]
    vt_sides = rng.choice([-1.0, 0.0, 1.0], size=len(vt_pairs))
    ee_sides = rng.choice([-1.0, 0.0, 1.0], size=len(ee_pairs))

    def make():
        return (TiVertexTriangleContact(vt_pairs, triangles, vt_sides, K, EPS),
                TiEdgeEdgeContact(ee_pairs, edges, ee_sides, K, EPS))

    linked, alone = make(), make()
    PairBatch(*linked)
    return x, linked, alone


def _launches(monkeypatch) -> list:
    """Records ``(derivatives, pairs evaluated)`` of each batch kernel launch (and fails on any
    separate distance launch)."""
    from sim_core.energies.contact import batch_kernel as contact_batch, distance_kernel as contact_distance

    calls = []
    kernel = contact_batch._batch_kernel
    monkeypatch.setattr(contact_batch, "_batch_kernel", lambda *a: (calls.append((a[10], a[4])), kernel(*a)))

    def forbidden(*a):
        raise AssertionError("a separate distance kernel was launched")

    monkeypatch.setattr(contact_distance, "_values_kernel", forbidden)
    monkeypatch.setattr(contact_distance, "_derivatives_kernel", forbidden)
    return calls


@pytest.mark.parametrize("rows", [(slice(None), slice(None)), (slice(0, 0), slice(None)), (slice(None), slice(0, 0))])
def test_linked_potentials_equal_separate_ones_bit_for_bit_with_one_launch_per_position(ti_cpu, monkeypatch, rows):
    x, linked, alone = _potentials(vt_rows=rows[0], ee_rows=rows[1])
    y = x + 0.1 * EPS * np.random.default_rng(21).normal(size=x.shape)
    expected = []
    for pot in alone:  # separate kernels, before the launches are watched
        expected.append((pot.energy(x), pot.active_mask(x), pot.gradient(x), pot.hessian(x, "none"),
                         pot.hessian(x, "clamp"), pot.contact_frames(x).lam))
    expected_y = [(pot.gradient(y), pot.energy(y)) for pot in alone]
    calls = _launches(monkeypatch)
    for pot, (energy, mask, grad, h_none, h_clamp, lam) in zip(linked, expected):
        assert pot.energy(x) == energy
        np.testing.assert_array_equal(pot.active_mask(x), mask)
        np.testing.assert_array_equal(pot.active_vertices(x), pot.vertices[mask])
        np.testing.assert_array_equal(pot.contact_frames(x).lam, lam)
    total = len(linked[0].pairs) + len(linked[1].pairs)
    active = sum(int(np.count_nonzero(p.active_mask(x))) for p in linked)
    assert 0 < active < total
    assert calls == [(False, total)]  # values of both kinds at x: one launch
    from sim_core.energies.contact import batch_kernel as contact_batch

    ruled_out = np.count_nonzero(contact_batch.work_arrays(total)[1][:total] == -1)  # by the kernel's distance bounds
    assert 0 < ruled_out < total - active
    for pot, (energy, mask, grad, h_none, h_clamp, lam) in zip(linked, expected):
        np.testing.assert_array_equal(pot.gradient(x), grad)
        for h, h_ref in ((pot.hessian(x, "none"), h_none), (pot.hessian(x, "clamp"), h_clamp)):
            np.testing.assert_array_equal(h.vertices, h_ref.vertices)
            np.testing.assert_array_equal(h.blocks, h_ref.blocks)
    assert calls == [(False, total), (True, active)]  # derivatives of the active pairs of both: one more
    # new positions: gradient first (values and derivatives in one launch), then the energy is kept
    for pot, (grad, energy) in zip(linked, expected_y):
        np.testing.assert_array_equal(pot.gradient(y), grad)
        assert pot.energy(y) == energy
    assert calls == [(False, total), (True, active), (True, total)]


def test_a_kept_evaluation_is_not_replaced_by_a_less_complete_one(ti_cpu):
    x, (vt, ee), _ = _potentials(100)
    vt.gradient(x)  # both evaluated with derivatives at x
    kept = workspace_of(vt).get(vt, "evaluation")
    workspace_of(ee).take(ee, "evaluation")
    ee.energy(x)  # a values-only launch for ee: vt keeps its derivatives
    assert workspace_of(vt).get(vt, "evaluation") is kept and workspace_of(ee).get(ee, "evaluation").order == 0
    assert vt.kept_evaluation(x, 2) is not None and ee.kept_evaluation(x, 1) is None
    assert vt.kept_evaluation(x + 1e-9, 0) is None


def test_penalty_hessians_follow_a_changed_stiffness(ti_cpu, monkeypatch):
    """The kernel makes the penalty Hessians with the stiffness of the request; after a change of
    stiffness the Hessian is evaluated again, equal bit for bit to the separate potential's."""
    x, linked, alone = _potentials(200)
    for pot in linked:
        pot.hessian(x, "none")
    expected = []
    for ref in alone:  # separate kernels, before the launches are watched
        ref.stiffness = 3.0 * K
        expected.append((ref.hessian(x, "none"), ref.gradient(x), ref.energy(x)))
    calls = _launches(monkeypatch)
    for pot, (h_ref, g_ref, e_ref) in zip(linked, expected):
        pot.stiffness = 3.0 * K
        h = pot.hessian(x, "none")
        np.testing.assert_array_equal(h.vertices, h_ref.vertices)
        np.testing.assert_array_equal(h.blocks, h_ref.blocks)
        np.testing.assert_array_equal(pot.gradient(x), g_ref)
        assert pot.energy(x) == e_ref
    assert [derivatives for derivatives, _ in calls] == [True, True]  # one per stiffness change
    # the gradient and energy of another stiffness come from the kept distances, with no launch
    for pot, (_, g_ref, e_ref) in zip(linked, expected):
        pot.stiffness = 6.0 * K
        np.testing.assert_array_equal(pot.gradient(x), 2.0 * g_ref)  # (exact: a power-of-two factor)
        assert pot.energy(x) == 2.0 * e_ref
    assert len(calls) == 2


def test_batches_sharing_the_work_arrays_keep_their_own_results(ti_cpu):
    """Every batch launches on the same kept work arrays; each evaluation copies its rows out, so a
    batch evaluated after another (more pairs, then fewer) leaves the first one's results as they were."""
    x, linked, alone = _potentials(300)
    y, small, small_alone = _potentials(40)
    expected = [(ref.gradient(x), ref.hessian(x, "none").blocks) for ref in alone]
    expected_small = [(ref.gradient(y), ref.hessian(y, "none").blocks) for ref in small_alone]
    for pot in linked:
        pot.hessian(x, "none")
    for pot in small:
        pot.hessian(y, "none")
    for pots, exp, xx in ((linked, expected, x), (small, expected_small, y)):
        for pot, (g, h) in zip(pots, exp):
            np.testing.assert_array_equal(pot.gradient(xx), g)
            np.testing.assert_array_equal(pot.hessian(xx, "none").blocks, h)


def test_two_pass_derivatives_equal_the_one_pass_bit_for_bit(ti_cpu, monkeypatch):
    """``PairBatch.two_pass`` (CUDA's default): the gradient at new positions from the distances of every
    pair, then the derivatives of the active ones: the same values in two launches (bit for bit on the
    CPU's serial sums; on CUDA, like the other bit-for-bit tests here, to round-off)."""
    from sim_core.energies.contact import batch_kernel as contact_batch

    x, linked, alone = _potentials()
    y = x + 0.1 * EPS * np.random.default_rng(22).normal(size=x.shape)
    expected = [(pot.gradient(y), pot.energy(y), pot.hessian(y, "none").blocks) for pot in alone]
    monkeypatch.setattr(contact_batch.PairBatch, "two_pass", True)
    calls = _launches(monkeypatch)
    for pot, (grad, energy, hess) in zip(linked, expected):
        np.testing.assert_array_equal(pot.gradient(y), grad)
        assert pot.energy(y) == energy
        np.testing.assert_array_equal(pot.hessian(y, "none").blocks, hess)
    total = len(linked[0].pairs) + len(linked[1].pairs)
    active = sum(int(np.count_nonzero(p.active_mask(y))) for p in linked)
    assert calls == [(False, total), (True, active)]


def test_hessians_kept_on_the_device_are_the_host_ones_and_give_the_same_vertex_blocks(ti_cpu, monkeypatch):
    """With ``PairBatch.device_hessian`` the penalty Hessians stay in the kernel's ndarray: read back they equal
    the host path's bit for bit, and the batched CG's product of the vertex blocks expanded from them on the
    device equals the product of the blocks expanded from the host copies (to round-off: sums by atomic adds,
    in no fixed order on a parallel arch, as the per-vertex gradient sums)."""
    from sim_core.energies.base import DeviceHessian, declares
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.ti_kernels.buffers import DeviceHessianBlocks
    from sim_core.ti_kernels.pcg import BatchedPCG, VertexBlocks

    x, linked, alone = _potentials()
    y = x + 0.1 * EPS * np.random.default_rng(22).normal(size=x.shape)
    PairBatch(*alone)
    monkeypatch.setattr(PairBatch, "two_pass", True)  # the derivatives of known active pairs: the device path
    expected = []
    for pot in alone:
        monkeypatch.setattr(PairBatch, "device_hessian", False)
        expected.append((pot.gradient(y), pot.hessian(y, "none"), pot.hessian(y, "clamp"),
                         pot.parameter_gradient(y, "stiffness")))
        assert pot.hessian_on_device(y) is None  # held on the host
    monkeypatch.setattr(PairBatch, "device_hessian", True)
    on_device = []
    for pot, (grad, h_none, h_clamp, dgrad_dk) in zip(linked, expected):
        assert declares(pot, DeviceHessian)
        np.testing.assert_allclose(pot.gradient(y), grad, rtol=0, atol=1e-13 * np.abs(grad).max())
        kept = pot.hessian_on_device(y)
        assert isinstance(kept, DeviceHessianBlocks) and kept.blocks.shape == h_none.blocks.shape
        np.testing.assert_array_equal(kept.vertices, h_none.vertices)
        np.testing.assert_array_equal(kept.blocks.to_numpy(), h_none.blocks)
        np.testing.assert_array_equal(pot.hessian(y, "none").blocks, h_none.blocks)
        np.testing.assert_array_equal(pot.hessian(y, "clamp").blocks, h_clamp.blocks)
        assert workspace_of(pot).get(pot, "evaluation").distances.grad is None  # on the device until asked for
        np.testing.assert_array_equal(pot.parameter_gradient(y, "stiffness"), dgrad_dk)  # (they are read here)
        on_device.append(kept)
    free = np.ones(x.size, dtype=bool)
    free[::7] = False
    from_device = VertexBlocks.from_element_blocks(on_device, free)
    from_host = VertexBlocks.from_element_blocks([e[1] for e in expected], free)
    np.testing.assert_array_equal(from_device.values, from_host.values)
    p = np.random.default_rng(23).normal(size=x.size)
    products = []
    for blocks in (from_device, from_host):
        solver = BatchedPCG()
        solver.factorize(sp_identity(x.size), blocks)
        products.append(solver.matvec(p))
    assert np.abs(products[1] - p).max() > 0  # the contact blocks take part
    np.testing.assert_allclose(products[0], products[1], rtol=0, atol=1e-13 * np.abs(products[1]).max())


def sp_identity(n: int):
    """The identity as a CSR upper triangle."""
    import scipy.sparse as sp

    return sp.identity(n, format="csr")


@pytest.mark.parametrize("device_arguments", [False, True])
def test_pairs_naming_some_vertices_sum_their_gradient_there_and_zero_elsewhere(ti_cpu, monkeypatch, device_arguments):
    """The kernel sees the pairs' own vertices only (``PairBatch.own``); with pairs that name a third of the
    positions the gradients, energies and Hessians are the separate potentials' (bit for bit on the CPU's serial
    sums), exactly zero on the other rows, through the host arguments and through CUDA's device arguments (the
    positions of the pairs' vertices uploaded, their summed gradient rows downloaded and spread)."""
    from sim_core.energies.contact import batch_kernel as contact_batch

    x, linked, alone = _potentials(vt_rows=slice(0, 150), ee_rows=slice(0, 60))
    batch = linked[0]._batch
    named = np.zeros(len(x), dtype=bool)
    named[np.concatenate([pot.vertices for pot in linked[:2]]).ravel()] = True
    assert len(batch.own) == np.count_nonzero(named) < 0.5 * len(x)
    y = x + 0.1 * EPS * np.random.default_rng(23).normal(size=x.shape)
    expected = [(pot.gradient(y), pot.energy(y), pot.hessian(y, "none").blocks) for pot in alone]
    if device_arguments:
        monkeypatch.setattr(contact_batch, "current_arch", lambda: "cuda")
    for pot, (grad, energy, hess) in zip(linked, expected):
        got = pot.gradient(y)
        assert np.any(got[named] != 0.0) and not np.any(got[~named])
        np.testing.assert_array_equal(got, grad)
        assert pot.energy(y) == energy
        np.testing.assert_array_equal(pot.hessian(y, "none").blocks, hess)
        # the same gradient as the rows of the pairs' distinct vertices (SparseGradient), or dense when not linked
        vertices, rows = pot.gradient_rows(y)
        assert len(np.unique(vertices)) == len(vertices) == len(batch.own)
        spread = np.zeros_like(grad)
        spread[vertices] = rows
        np.testing.assert_array_equal(spread, grad)
    for pot, (grad, _, _) in zip(alone, expected):
        vertices, rows = pot.gradient_rows(y)
        assert vertices is None
        np.testing.assert_array_equal(rows, grad)
    for pot, twin in zip(linked, alone):  # the regions (on CUDA copied back after the gradient sums, in one copy)
        got, want = (workspace_of(p).get(p, "evaluation").distances for p in (pot, twin))
        assert len(np.unique(want.region)) > 3
        np.testing.assert_array_equal(got.region, want.region)
        np.testing.assert_array_equal(got.d, want.d)
    frozen = y.copy()  # read-only and owning its memory: kept evaluations keyed by identity, the same values
    frozen.flags.writeable = False
    for pot, (grad, energy, hess) in zip(linked, expected):
        np.testing.assert_array_equal(pot.gradient(frozen), grad)
        assert pot.energy(frozen) == energy
        np.testing.assert_array_equal(pot.hessian(frozen, "none").blocks, hess)


@pytest.mark.parametrize("two_pass, device_gradient", [(False, False), (True, True)])
def test_gradients_added_on_the_device_are_the_host_gradients_with_the_energy_and_the_kept_hessians(
        ti_cpu, monkeypatch, two_pass, device_gradient):
    """``add_gradient_on_device`` (:class:`~sim_core.energies.base.DeviceGradient`) with the positions read from their
    ndarray (the host array's values are never read: NaN here): a nonzero device array becomes that array plus
    :meth:`gradient` (bit for bit on the CPU's serial sums), the energy returned is :meth:`energy`, and the Hessian
    at those positions is then kept (no further launch, the same blocks); through one launch (CPU) or CUDA's two
    with the sums left in the kernel's ndarray (``PairBatch.device_gradient``), read on the host when asked. A
    potential not linked to a batch adds its host gradient."""
    from sim_core.energies.base import DeviceGradient, declares
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.transfer import download, upload

    x, linked, alone = _potentials(vt_rows=slice(0, 150), ee_rows=slice(0, 60))  # pairs naming a third of x
    rng = np.random.default_rng(24)
    y = x + 0.1 * EPS * rng.normal(size=x.shape)
    expected = [(pot.gradient(y), pot.energy(y), pot.hessian(y, "none")) for pot in alone]
    assert all(np.any(grad != 0.0) and energy > 0.0 for grad, energy, _ in expected)
    monkeypatch.setattr(PairBatch, "two_pass", two_pass)
    monkeypatch.setattr(PairBatch, "device_gradient", device_gradient)
    x_device, g_device = new_ndarray(ti.f64, y.shape), new_ndarray(ti.f64, y.shape)
    upload(x_device, y)
    base = rng.normal(size=y.shape)
    upload(g_device, base)
    host = np.full_like(y, np.nan)  # frozen: the evaluations are keyed by this object, its values never read
    host.flags.writeable = False
    calls = _launches(monkeypatch)
    total = base.copy()
    for pot, (grad, energy, _) in zip(linked, expected):
        assert declares(pot, DeviceGradient)
        assert pot.add_gradient_on_device(host, x_device, g_device) == energy
        total += grad
    np.testing.assert_array_equal(download(g_device), total)
    assert [derivatives for derivatives, _ in calls] == ([False, True] if two_pass else [True])
    for pot, (grad, energy, h) in zip(linked, expected):
        np.testing.assert_array_equal(pot.hessian(host, "none").blocks, h.blocks)
        np.testing.assert_array_equal(pot.hessian(host, "none").vertices, h.vertices)
        np.testing.assert_array_equal(pot.gradient(host), grad)  # (device sums: read on the host now)
        assert pot.energy(host) == energy
    assert len(calls) == (2 if two_pass else 1)
    upload(g_device, base)
    for pot, (grad, energy, _) in zip(alone, expected):
        assert pot.add_gradient_on_device(y, x_device, g_device) == energy
    np.testing.assert_array_equal(download(g_device), total)


def test_the_kernels_list_of_active_pairs_is_read_in_increasing_row_order(ti_cpu):
    """On a parallel arch the kernel appends the active pairs in no fixed order: the list (its length in row 0, then
    ``[row, distance]`` rows) is read back sorted by row, each distance with its row (the CPU's serial list, in order
    already, read as it is); from a device copy, a first read shorter than the list reads the rest after it."""
    from sim_core.energies.contact.batch_kernel import _sorted_found
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.transfer import upload

    rng = np.random.default_rng(25)
    rows = np.sort(rng.choice(10_000, size=300, replace=False))
    distances = rng.uniform(0.0, EPS, size=300)
    for order in (np.arange(300), rng.permutation(300)):
        listed = np.full((321, 2), np.nan)  # a longer kept array: 300 written
        listed[0, 0] = 300
        listed[1:301, 0], listed[1:301, 1] = rows[order], distances[order]
        device = upload(new_ndarray(ti.f64, listed.shape), listed)
        for got_rows, got_d in (_sorted_found(listed, listed, 1), _sorted_found(np.zeros_like(listed), device, 64),
                                _sorted_found(np.zeros_like(listed), device, 400)):
            assert got_rows.dtype == np.int64
            np.testing.assert_array_equal(got_rows, rows)
            np.testing.assert_array_equal(got_d, distances)
    none = np.zeros((4, 2))
    assert [len(a) for a in _sorted_found(none, none, 1)] == [0, 0]


@pytest.mark.parametrize("device", [False, True])
def test_packed_launches_equal_the_default_ones_bit_for_bit(ti_cpu, monkeypatch, device):
    """``PairBatch.packed`` (CUDA's default for a single environment): every pair measured in one launch, its results
    packed in pair order into one array read back in one copy (a second one when the active list outgrows the guess):
    the evaluations equal the default launches' (values, then derivatives at new positions; derivatives at once;
    pairs of one kind only), through device arrays too (``device``: the arch query answering "cuda" on the CPU arch,
    whose serial loops keep the sums in pair order). Bit for bit on the CPU; on CUDA the sums to round-off
    (``assert_same_sums``)."""
    import importlib

    from sim_core.energies.contact import batch_kernel as contact_batch

    rng = np.random.default_rng(26)
    for rows in ((slice(None), slice(None)), (slice(0, 0), slice(None)), (slice(None), slice(0, 0))):
        x, linked, alone = _potentials(300, *rows)
        points = [x + 0.1 * EPS * rng.normal(size=x.shape) for _ in range(3)]
        expected = []
        for y in points:
            expected.append([(pot.energy(y), pot.active_mask(y), pot.gradient(y), pot.hessian(y, "none").blocks,
                              pot.contact_frames(y).lam) for pot in alone])
        monkeypatch.setattr(contact_batch.PairBatch, "packed", True)
        if device:
            for name in ("sim_core.ti_backend", "sim_core.energies.contact.batch_kernel"):
                monkeypatch.setattr(importlib.import_module(name), "current_arch", lambda: "cuda")
        calls = []
        kernel = contact_batch._packed_kernel
        monkeypatch.setattr(contact_batch, "_packed_kernel", lambda *a: (calls.append(a[11]), kernel(*a)))
        contact_batch._ARRAYS.packed_guess = 0  # the first read too short: the rest read after it
        for k, (y, exp) in enumerate(zip(points, expected)):
            for pot, (energy, mask, grad, hess, lam) in zip(linked, exp):
                if k != 1:  # the values first, then the derivatives of the same positions
                    assert_same_sums(pot.energy(y), energy)
                    np.testing.assert_array_equal(pot.active_mask(y), mask)
                assert_same_sums(pot.gradient(y), grad)
                blocks = pot.hessian(y, "none").blocks
                assert blocks.shape == hess.shape
                if hess.size:  # (a kind without active pairs: no blocks)
                    assert_same_sums(blocks, hess)
                assert_same_sums(pot.energy(y), energy)
                frames = pot.contact_frames(y).lam
                assert frames.shape == lam.shape
                if lam.size:
                    assert_same_sums(frames, lam)
        assert calls == [0, 1, 1, 0, 1], calls
        assert sum(int(np.count_nonzero(exp[1])) for exp in expected[0]) > 0
        monkeypatch.undo()


@pytest.mark.parametrize("two_pass", [False, True, "packed", "packed on device"])
def test_batches_over_a_candidate_lists_layout_equal_batches_over_their_own_pairs(ti_cpu, monkeypatch, two_pass):
    """A batch over the layout of candidate lists (``PairBatch(layout=CandidateVertices.batch_layout(rows))``: every
    vertex-triangle candidate and some edge-edge ones, read as rows of the compaction of every candidate's vertices)
    gives the energies, gradients, active pairs, distances and Hessians of a batch over its own pairs (bit for bit on
    the CPU's serial sums), in one launch or two, or in the packed launch (``PairBatch.packed``, the laid batch only;
    "on device": the arch query answering "cuda" on the CPU arch, the device arrays' paths); a second step's batch over
    the same lists with other edge-edge rows and sides shares the first's vertex indices and their device cache. A
    layout whose first rows are not the vertex-triangle pairs is refused."""
    import importlib

    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.energies.contact.kernel import TiEdgeEdgeContact, TiVertexTriangleContact
    from sim_core.energies.contact.pair_lists import CandidateVertices

    x, linked, _ = _potentials()
    vt_list, ee_list = linked[0].pairs, linked[1].pairs
    triangles, edges = np.arange(x.shape[0]).reshape(-1, 4)[:, 1:], np.arange(x.shape[0]).reshape(-1, 2)  # as made
    lists = CandidateVertices(vt_list, ee_list, triangles, edges, vertex_count=len(x))  # (on device: compacted there)
    rng = np.random.default_rng(25)
    y = x + 0.1 * EPS * rng.normal(size=x.shape)
    packed = two_pass in ("packed", "packed on device")
    monkeypatch.setattr(PairBatch, "two_pass", False if packed else two_pass)
    if two_pass == "packed on device":
        for name in ("sim_core.ti_backend", "sim_core.energies.contact.batch_kernel"):
            monkeypatch.setattr(importlib.import_module(name), "current_arch", lambda: "cuda")
    batches = []
    for keep in (rng.random(len(ee_list)) > 0.3, rng.random(len(ee_list)) > 0.5):
        rows = np.flatnonzero(keep)
        vt_sides = rng.choice([-1.0, 0.0, 1.0], size=len(vt_list))
        ee_sides = rng.choice([-1.0, 0.0, 1.0], size=len(rows))

        def make(layout=None):
            pots = (TiVertexTriangleContact(vt_list, triangles, vt_sides, K, EPS, vertices=lists.vt_vertices),
                    TiEdgeEdgeContact(ee_list[rows], edges, ee_sides, K, EPS, vertices=lists.ee_vertices[rows]))
            batches.append(PairBatch(*pots, layout=layout))
            batches[-1].packed = packed and layout is not None  # (the batch over its own pairs: the default launches)
            return pots

        laid, own = make(lists.batch_layout(rows)), make()
        for pot, twin in zip(laid, own):
            np.testing.assert_array_equal(pot.gradient(y), twin.gradient(y))
            assert pot.energy(y) == twin.energy(y)
            np.testing.assert_array_equal(pot.active_mask(y), twin.active_mask(y))
            np.testing.assert_array_equal(pot.active_distances(y)[1], twin.active_distances(y)[1])
            np.testing.assert_array_equal(pot.hessian(y, "none").blocks, twin.hessian(y, "none").blocks)
            assert pot.energy(x) == twin.energy(x)
        assert 0 < np.count_nonzero(laid[1].active_mask(y)) < len(rows)
    assert batches[2]._layout.local is batches[0]._layout.local is lists.batch_layout(rows).local
    assert batches[2]._layout.device is batches[0]._layout.device is lists.device
    layout = lists.batch_layout(rows)  # the last step's rows, those of ``own``
    with pytest.raises(ValueError, match="vertex-triangle pairs not its first rows"):
        PairBatch(*own, layout=layout._replace(rows=layout.rows[::-1].copy()))


def test_a_batch_takes_its_sides_by_layout_row_from_the_caller(ti_cpu):
    """``PairBatch(..., sides=...)``: the sides of every layout row in one array (the vertex-triangle pairs', then every
    edge-edge candidate's; rows outside the batch never read) are taken as they are, and the batch evaluates as one
    that scatters the potentials' sides itself, bit for bit; sides of another length or dtype are refused. The contact
    set's step sides are that array (one array for both kinds: ``ContactSet._pair_sides``)."""
    from sim_core.contact_set import ContactSet
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.energies.contact.kernel import TiEdgeEdgeContact, TiVertexTriangleContact
    from sim_core.energies.contact.pair_lists import CandidateVertices
    from tests.sim_core.test_contact_set import _forming_model_deformed

    x, linked, _ = _potentials()
    vt_list, ee_list = linked[0].pairs, linked[1].pairs
    triangles, edges = np.arange(x.shape[0]).reshape(-1, 4)[:, 1:], np.arange(x.shape[0]).reshape(-1, 2)  # as made
    lists = CandidateVertices(vt_list, ee_list, triangles, edges)
    rng = np.random.default_rng(26)
    rows = np.flatnonzero(rng.random(len(ee_list)) > 0.3)
    whole = rng.choice([-1.0, 0.0, 1.0], size=len(vt_list) + len(ee_list))
    y = x + 0.1 * EPS * rng.normal(size=x.shape)
    results = []
    for given in (None, whole):
        pots = (TiVertexTriangleContact(vt_list, triangles, whole[:len(vt_list)], K, EPS, vertices=lists.vt_vertices),
                TiEdgeEdgeContact(ee_list[rows], edges, whole[len(vt_list):][rows], K, EPS,
                                  vertices=lists.ee_vertices[rows]))
        batch = PairBatch(*pots, layout=lists.batch_layout(rows), sides=given)
        assert (batch.sides is whole) == (given is not None)
        results.append([(pot.energy(y), pot.gradient(y), pot.hessian(y, "none").blocks) for pot in pots])
    for want, got in zip(*results):
        assert want[0] == got[0]
        np.testing.assert_array_equal(want[1], got[1])
        np.testing.assert_array_equal(want[2], got[2])
    for wrong in (whole[1:], whole.astype(np.float32)):
        with pytest.raises(ValueError, match="sides of shape"):
            PairBatch(*pots, layout=lists.batch_layout(rows), sides=wrong)
    model, xf = _forming_model_deformed(1)
    cs = ContactSet(model, broad_phase="spatial_hash", backend="taichi-cpu")
    cs.begin_step(xf, None)
    vt, ee = cs.potentials(xf, xf, cs.begin_step(xf, None))[:2]
    assert len(vt.pairs) > 50 and len(ee.pairs) > 50
    assert vt._batch.sides is vt.sides.base  # the step sides' one array
    _, vt_list, ee_list = cs._candidates
    made = np.zeros(len(vt_list) + len(ee_list))
    made[:len(vt_list)] = vt.sides
    made[len(vt_list):][cs._cache[3]] = ee.sides
    np.testing.assert_array_equal(vt._batch.sides, made)


def test_a_batch_holds_its_potentials_weakly_and_goes_with_them(ti_cpu):
    """No reference cycle between a batch and its potentials: with the collector off, the batch is freed with
    them; with one of them gone, the other still evaluates through it, bit for bit as on its own."""
    import gc
    import weakref

    x, linked, alone = _potentials()
    vt = linked[0]
    batch = weakref.ref(vt._batch)
    y = x + 0.1 * EPS * np.random.default_rng(30).normal(size=x.shape)
    enabled = gc.isenabled()
    gc.disable()
    try:
        del linked  # the edge-edge potential is gone
        assert batch() is not None and batch().ee is None and batch().vt is vt
        np.testing.assert_array_equal(vt.gradient(y), alone[0].gradient(y))
        assert vt.energy(y) == alone[0].energy(y)
        np.testing.assert_array_equal(vt.hessian(y, "none").blocks, alone[0].hessian(y, "none").blocks)
        del vt
        assert batch() is None
    finally:
        if enabled:
            gc.enable()


@pytest.mark.parametrize("two_pass", [False, True], ids=["one-pass", "two-pass"])
def test_penalty_energies_by_copy_are_summed_where_the_launch_left_the_distances(ti_cpu, monkeypatch, two_pass):
    """``add_copy_energies_on_device`` (:class:`~sim_core.energies.base.DeviceCopyEnergies`) after the gradient at
    ``y``: each potential's ``0.5 k_c (d - eps)^2`` by the copy of its pairs' first vertices, summed from the batch's
    last launch (no read of the pairs), equal to the NumPy split of the unlinked twin (``copy_energies``) to round-off,
    after one launch (CPU) or CUDA's two; it follows a changed stiffness; nothing is added (False) before an evaluation
    of ``y``, after another batch's launch took the work arrays, or at another ``eps``; a copy with no active pair
    gets exactly 0."""
    from sim_core.energies.base import DeviceCopyEnergies, declares
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.ti_kernels.copy_vectors import CopySums

    x, linked, alone = _potentials()
    rng = np.random.default_rng(25)
    y = x + 0.1 * EPS * rng.normal(size=x.shape)
    B = 6
    copy_of_vertex = rng.integers(0, B - 1, size=len(x))  # the last copy has no vertex: no pair
    wanted = {}
    for scale in (1.0, 3.0):  # the twins' host split, before the launches are watched
        for pot in alone:
            pot.stiffness = K * scale
        wanted[scale] = [pot.copy_energies(y, copy_of_vertex, B) for pot in alone]
    monkeypatch.setattr(PairBatch, "two_pass", two_pass)
    calls = _launches(monkeypatch)
    sums = CopySums(copy_of_vertex, B)
    for pot in linked:
        assert declares(pot, DeviceCopyEnergies)
        assert not pot.add_copy_energies_on_device(y, None, copy_of_vertex, sums)  # no evaluation of y yet
    for pot in linked:
        pot.gradient(y)
    launches = len(calls)
    assert launches == (2 if two_pass else 1)
    for scale in (1.0, 3.0):
        for pot, want in zip(linked, wanted[scale]):
            pot.stiffness = K * scale
            assert np.count_nonzero(want[:-1]) == B - 1 and want[-1] == 0.0
            sums.zero()
            assert pot.add_copy_energies_on_device(y, None, copy_of_vertex, sums)
            got = sums.read()
            np.testing.assert_allclose(got, want, rtol=1e-13, atol=0.0)
            assert got[-1] == 0.0
    assert len(calls) == launches  # summed from the launch's arrays: no new launch
    x_small, small, _ = _potentials(40)
    small[0].gradient(x_small)  # another batch's launch takes the work arrays
    sums.zero()
    assert not any(pot.add_copy_energies_on_device(y, None, copy_of_vertex, sums) for pot in linked)
    z = y + 0.01 * EPS
    for pot in linked:
        pot.gradient(z)  # launched at z, then another eps: no kept evaluation of z at it
        pot.eps = 0.5 * EPS
    assert not any(pot.add_copy_energies_on_device(z, None, copy_of_vertex, sums) for pot in linked)
    assert not np.any(sums.read())


@pytest.mark.parametrize("capacity", [None, 1], ids=["guessed", "overflow"])
def test_the_listed_launch_equals_the_two_passes_bit_for_bit_in_one_launch(ti_cpu, monkeypatch, capacity):
    """``PairBatch.listed`` (CUDA's default): the derivatives at new positions in one launch whose active list is
    ordered on the device between its passes give the two passes' active pairs, distances, regions, gradients, energies
    and Hessians bit for bit (the CPU's serial sums), and the pair penalties' energies by copy from that launch; with
    room for fewer active pairs than there are (``overflow``), a second launch with room for all."""
    from sim_core.energies.contact import batch_kernel as contact_batch
    from sim_core.energies.contact import listed_kernel
    from sim_core.ti_kernels.copy_vectors import CopySums

    x, linked, _ = _potentials()
    _, twins, _ = _potentials()
    y = x + 0.1 * EPS * np.random.default_rng(26).normal(size=x.shape)
    copy_of_vertex = np.random.default_rng(27).integers(0, 4, size=len(x))
    monkeypatch.setattr(contact_batch.PairBatch, "two_pass", True)
    expected = [(pot.gradient(y), pot.energy(y), pot.hessian(y, "none"), pot.active_mask(y),
                 workspace_of(pot).get(pot, "evaluation").distances, pot.copy_energies(y, copy_of_vertex, 4))
                for pot in twins]  # the two passes
    monkeypatch.setattr(contact_batch.PairBatch, "listed", True)
    if capacity is not None:
        linked[0]._batch._found_rows = capacity
    calls = _launches(monkeypatch)
    listed_calls = []
    kernel = listed_kernel._listed_kernel
    monkeypatch.setattr(listed_kernel, "_listed_kernel", lambda *a: (listed_calls.append(a[6]), kernel(*a)))
    for pot in linked:
        pot.gradient(y)
    assert calls == [] and len(listed_calls) == (1 if capacity is None else 2)
    sums = CopySums(copy_of_vertex, 4)
    for pot, (grad, energy, hess, mask, distances, split) in zip(linked, expected):
        got = workspace_of(pot).get(pot, "evaluation").distances
        assert np.count_nonzero(mask) > 0
        np.testing.assert_array_equal(pot.active_mask(y), mask)
        np.testing.assert_array_equal(got.d, distances.d)
        np.testing.assert_array_equal(got.region, distances.region)
        assert len(np.unique(got.region)) > 3
        np.testing.assert_array_equal(pot.gradient(y), grad)
        assert pot.energy(y) == energy
        np.testing.assert_array_equal(pot.hessian(y, "none").blocks, hess.blocks)
        np.testing.assert_array_equal(pot.hessian(y, "none").vertices, hess.vertices)
        sums.zero()
        assert pot.add_copy_energies_on_device(y, None, copy_of_vertex, sums)
        np.testing.assert_allclose(sums.read(), split, rtol=1e-13, atol=0.0)
    assert calls == [] and len(listed_calls) == (1 if capacity is None else 2)  # all kept from the launch


@pytest.mark.parametrize("listed", [False, True])
def test_device_rows_are_reused_only_once_no_evaluation_holds_them(ti_cpu, monkeypatch, listed):
    """The launches whose Hessian and distance-gradient rows stay on the device (``PairBatch.device_hessian``) take
    arrays no evaluation holds (``buffers.unheld_rows``): a Hessian kept by a caller keeps its values through later
    launches at other positions (its array is not handed to them), every launch's Hessians equal the host path's bit
    for bit, and once the earlier evaluations are gone the launches allocate no device array."""
    from sim_core.energies.contact import batch_kernel
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.ti_kernels import buffers, device_copy

    # this thread's spare device arrays from no earlier test (else the first launches here may take theirs)
    monkeypatch.setitem(batch_kernel._ARRAYS.__dict__, "_spares", {})
    x, linked, alone = _potentials()
    PairBatch(*alone)
    rng = np.random.default_rng(28)
    points = [x + 0.1 * EPS * rng.normal(size=x.shape) for _ in range(7)]
    monkeypatch.setattr(PairBatch, "two_pass", True)
    monkeypatch.setattr(PairBatch, "listed", listed)
    monkeypatch.setattr(PairBatch, "device_hessian", False)
    expected = [[pot.hessian(y, "none").blocks for pot in alone] for y in points]  # the host path
    made = []
    new = device_copy.new_ndarray
    monkeypatch.setattr(device_copy, "new_ndarray", lambda *a: (made.append(a[1]), new(*a))[1])
    monkeypatch.setattr(PairBatch, "device_hessian", True)

    def fresh(rows):  # the rows downloaded now (not a DeviceRows' kept host copy)
        return buffers.DeviceRows(rows.array, rows.start, rows.stop).to_numpy()

    held = [pot.hessian_on_device(points[0]) for pot in linked]
    for y, hess in zip(points[1:4], expected[1:4]):
        for pot, blocks in zip(linked, hess):
            got = pot.hessian_on_device(y)
            assert all(got.blocks.array is not h.blocks.array for h in held)
            np.testing.assert_array_equal(fresh(got.blocks), blocks)
    for pot, kept, blocks in zip(linked, held, expected[0]):
        assert np.count_nonzero(blocks) and kept.blocks.shape == blocks.shape
        np.testing.assert_array_equal(fresh(kept.blocks), blocks)
    del held, got
    before = len(made)
    for y, hess in zip(points[4:], expected[4:]):
        for pot, blocks in zip(linked, hess):
            np.testing.assert_array_equal(fresh(pot.hessian_on_device(y).blocks), blocks)
    assert before > 0 and len(made) == before
