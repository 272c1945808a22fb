"""The compaction of index arrays on the device (sim_core/ti_kernels/compaction.py) equals the host's
``compact_indices`` exactly, where the arrays are NumPy ones (the CPU arch), Taichi ndarrays (the arch query answering
"cuda" on the CPU arch, or a real GPU under ``THINSHELL_TEST_ARCH=cuda``); and a candidate list's pair batch layout made
that way gives the batch of the host's layout."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.unique import compact_indices
from tests.sim_core.ti_kernels.conftest import TEST_ARCH, assert_same_sums


def _parts(seed: int, p: int, q: int, size: int, m: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Two int32 index arrays ``(p, m)``, ``(q, m)`` in ``[0, size)`` with repeats and unnamed values (a gap of
    whole chunks among them)."""
    rng = np.random.default_rng(seed)
    values = np.concatenate([np.arange(size // 3), np.arange(size // 2, size)])
    named = rng.choice(values, size=max(size // 4, 1), replace=False)
    return (rng.choice(named, size=(p, m)).astype(np.int32), rng.choice(named, size=(q, m)).astype(np.int32))


def _host(local) -> np.ndarray:
    return local if isinstance(local, np.ndarray) else local.to_numpy()


def _emulate_cuda(monkeypatch) -> list:
    """The arch query answering "cuda" on the CPU arch (the loops stay serial); returns the list of the kernel's
    launches' arguments (recorded from now on)."""
    import sim_core.ti_backend
    from sim_core.ti_kernels import compaction

    monkeypatch.setattr(sim_core.ti_backend, "current_arch", lambda: "cuda")
    launches: list = []
    kernel = compaction._compact_kernel
    monkeypatch.setattr(compaction, "_compact_kernel", lambda *a: (launches.append(a), kernel(*a))[1])
    return launches


@pytest.mark.parametrize("emulated", [False, True])
@pytest.mark.parametrize("p, q, size, m", [(300, 700, 5000, 4), (0, 50, 3000, 4), (40, 0, 1024, 4), (7, 3, 9, 2),
                                           (1, 1, 1, 4)])
def test_the_device_compaction_equals_the_hosts(ti_cpu, monkeypatch, emulated, p, q, size, m):
    """``own`` (int64, sorted distinct values) and ``local`` (int32 positions, the first part's rows then the
    second's) equal ``compact_indices`` of the two parts' concatenation exactly; with device copies (emulated or a
    GPU) ``local`` stays a Taichi ndarray, no NumPy array reaches the launch, and the parts' copies are kept in the
    given cache under the given names (sent once: a second call finds them)."""
    from sim_core.ti_kernels.compaction import compact_on_device
    from sim_core.ti_kernels.scan import SCAN_CHUNK as CHUNK

    launches = _emulate_cuda(monkeypatch) if emulated else None
    first, second = _parts(p + q + size, p, q, size, m)
    want_own, want_local = compact_indices((first, second), dtype=np.int32, size=size)
    assert size < CHUNK or len(want_own) < size  # (unnamed values among several chunks)
    device: dict = {}
    for _ in range(2):
        own, local = compact_on_device(first, second, size, device, ("a", "b"))
        assert own.dtype == np.int64 and _host(local).dtype == np.int32
        np.testing.assert_array_equal(own, want_own)
        np.testing.assert_array_equal(_host(local), want_local)
        np.testing.assert_array_equal(own[_host(local)], np.concatenate([first, second]))
    on_gpu = emulated or TEST_ARCH == "cuda"
    assert isinstance(local, np.ndarray) != on_gpu
    if on_gpu:
        assert {name for name, part in zip("ab", (first, second)) if len(part)} <= set(device)
        assert all(device[name][0] is part for name, part in zip("ab", (first, second)) if len(part))
    if emulated:
        assert len(launches) == 2 and not any(isinstance(a, np.ndarray) for args in launches for a in args)


def test_the_device_compaction_refuses_what_the_host_refuses(ti_cpu):
    """An index outside ``[0, size)`` raises IndexError (as ``compact_indices`` with a size does); indices that are
    not C-contiguous int32 of one width raise ValueError; no indices give empty arrays."""
    from sim_core.ti_kernels.compaction import compact_on_device

    first, second = _parts(5, 20, 30, 200)
    for bad in (200, -1):
        wrong = second.copy()
        wrong[7, 2] = bad
        with pytest.raises(IndexError, match=r"outside \[0, 200\)"):
            compact_on_device(first, wrong, 200)
    with pytest.raises(IndexError):
        compact_indices((first, np.where(second == second[0, 0], 200, second)), dtype=np.int32, size=200)
    for wrong in (second.astype(np.int64), second[:, :2].copy(), np.asfortranarray(second)):
        with pytest.raises(ValueError, match="C-contiguous int32"):
            compact_on_device(first, wrong, 200)
    own, local = compact_on_device(first[:0], second[:0], 200)
    assert own.shape == (0,) and own.dtype == np.int64 and local.shape == (0, 4) and local.dtype == np.int32


@pytest.mark.parametrize("two_pass", [False, True])
def test_a_candidate_lists_device_layout_gives_the_batch_of_the_hosts(ti_cpu, monkeypatch, two_pass):
    """On CUDA (emulated on the CPU arch, or a GPU) a candidate list's batch layout is made on the device (``local`` a
    Taichi ndarray, copied back once when asked for) and equals the host's; a pair batch over it gives the active pairs,
    distances and Hessians of the batch over the host's layout bit for bit, its energies and gradients too (on a GPU
    to the round-off of its parallel sums: ``assert_same_sums``)."""
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.energies.contact.kernel import TiEdgeEdgeContact, TiVertexTriangleContact
    from sim_core.energies.contact.pair_lists import CandidateVertices
    from tests.sim_core.ti_kernels.test_contact_batch import EPS, K, _potentials

    x, linked, _ = _potentials(vt_rows=slice(0, None, 2), ee_rows=slice(1, None, 3))  # vertices no pair names
    vt, ee, sides = linked[0].pairs, linked[1].pairs, (linked[0].sides, linked[1].sides)
    triangles, edges = np.arange(x.shape[0]).reshape(-1, 4)[:, 1:], np.arange(x.shape[0]).reshape(-1, 2)  # as made
    rows = np.flatnonzero(np.arange(len(ee)) % 3 != 1)
    host = CandidateVertices(vt, ee, triangles, edges).batch_layout(rows)  # (no vertex count: on the host)
    assert isinstance(host.local, np.ndarray)
    monkeypatch.setattr(PairBatch, "two_pass", two_pass)
    _emulate_cuda(monkeypatch)
    lists = CandidateVertices(vt, ee, triangles, edges, vertex_count=len(x))
    layout = lists.batch_layout(rows)
    assert not isinstance(layout.local, np.ndarray) and layout.local_on_device() is layout.local
    assert lists.batch_layout(rows[:5]).local is layout.local and layout.host_local() is layout.host_local()
    assert len(host.own) < len(x)
    np.testing.assert_array_equal(layout.own, host.own)
    np.testing.assert_array_equal(layout.host_local(), host.local)
    np.testing.assert_array_equal(layout.rows, host.rows)
    y = x + 0.1 * EPS * np.random.default_rng(4).normal(size=x.shape)
    results = []
    for laid in (host, layout):
        pots = (TiVertexTriangleContact(vt, triangles, sides[0], K, EPS, vertices=lists.vt_vertices),
                TiEdgeEdgeContact(ee[rows], edges, sides[1][rows], K, EPS, vertices=lists.ee_vertices[rows]))
        PairBatch(*pots, layout=laid)
        results.append([(pot.energy(y), pot.gradient(y), pot.active_distances(y), pot.hessian(y, "none").blocks)
                        for pot in pots])
    assert results[0][0][2][0].size and results[0][1][2][0].size  # both kinds touch
    for want, got in zip(*results):
        assert_same_sums(got[0], want[0])
        assert_same_sums(got[1], want[1])
        for a, b in zip(want[2], got[2]):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(want[3], got[3])
