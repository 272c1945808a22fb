"""The step sides of candidate lists from their int8 codes (sim_core/energies/contact/sides_kernel.py) equal the
host's (the int32 geometry codes copied back, decoded and placed by ``step_sides``) bit for bit, on random pairs with a
side memory and on Forming's contact set through steps and a trial point's new lists; the pair batch reading the placed
sides where they are evaluates as over the host's; the CUDA launch path emulated on the CPU arch (the arch query
answering "cuda")."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision.memory import ContactMemory
from sim_core.collision.step_sides import step_sides
from tests.sim_core.ti_kernels.conftest import TEST_ARCH
from tests.sim_core.ti_kernels.test_contact_setup import _batch, _forming_contact

_QUERIES = ("sim_core.ti_backend", "sim_core.energies.contact.setup_kernel", "sim_core.energies.contact.sides_kernel",
            "sim_core.energies.contact.batch_kernel", "sim_core.energies.contact.listed_kernel",
            "sim_core.energies.contact.copy_energy_kernel", "sim_core.ti_kernels.hash_grid")


_KEPT_ARRAYS = ("sim_core.ti_kernels.compaction", "sim_core.energies.contact.sides_kernel",
                "sim_core.energies.contact.batch_kernel", "sim_core.energies.contact.setup_kernel",
                "sim_core.energies.friction.kernel")


EMULATED_ONLY = ("compares CUDA's side launch, emulated on the CPU arch, with the host's sides, which only the CPU arch "
                 "computes (the default, and CI); under THINSHELL_TEST_ARCH=cuda the contact set takes the launch's "
                 "sides for real in every contact test of this folder (test_contact_setup, test_contact_batch)")
"""Why the emulation tests are left out on a GPU run."""


def _emulate_cuda(monkeypatch) -> None:
    """The arch query of the launches' callers answering "cuda" on the CPU arch (the loops stay serial), with the
    launches' per-thread arrays of this test's own (their device copies made here go with it: a later test on the
    CPU path finds none for the same kept arrays)."""
    import importlib

    from sim_core.ti_kernels.buffers import LaunchArrays

    modules = [importlib.import_module(name) for name in _QUERIES]  # all imported before any query is changed: a
    # module imported after would bind the changed query as its own, and keep it after the test
    for module in modules:
        if hasattr(module, "current_arch"):
            monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    for name in _KEPT_ARRAYS:
        monkeypatch.setattr(importlib.import_module(name), "_ARRAYS", LaunchArrays())


def _keyed(count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """``count`` distinct pairs ``(count, 2)`` int64, sorted, and their packed keys (a candidate list's)."""
    keys = np.sort(rng.choice(1 << 20, size=count, replace=False)).astype(np.int64)
    keys = (keys // 1000 << 32) | (keys % 1000)
    return np.stack([keys >> 32, keys & 0xFFFFFFFF], axis=1), keys


def _host_sides(x, vt, ee, pairs, keys, memories, min_sine):
    """The host path's ``(sides (p + q,), ee keep)``: ``pair_codes`` decoded, then ``step_sides`` (ContactSet's)."""
    from sim_core.energies.contact.setup_kernel import pair_codes

    geo = pair_codes(x, vt, ee, min_sine, {})
    vt_sides = step_sides(geo.vt_above, pairs[0], geo.vt_side, memories[0], keys[0])
    ee_sides = step_sides(geo.ee_keep & geo.ee_interior, pairs[1], geo.ee_side, memories[1], keys[1])
    return np.concatenate([vt_sides, ee_sides]), geo.ee_keep, geo


@pytest.mark.skipif(TEST_ARCH != "cpu", reason=EMULATED_ONLY)
@pytest.mark.parametrize("emulated", [False, True])
def test_the_codes_and_placed_step_sides_equal_the_hosts_bit_for_bit(ti_cpu, monkeypatch, emulated):
    """Random pairs of every region, a memory holding pairs above (its side kept, against the geometric one for
    some) and beside their face (its side not taken), the near-parallel threshold at several values and an empty
    kind: the int8 codes' geometry (every row and chosen rows) equals ``pair_codes``' and the placed sides and ``keep``
    equal the host path's exactly; on CUDA (emulated) the device codes and sides hold the same values."""
    from sim_core.energies.contact.sides_kernel import kept_rows, side_codes, step_sides_of

    if emulated:
        _emulate_cuda(monkeypatch)
    rng = np.random.default_rng(11)
    x, vertices = _batch(12)
    vt, ee = vertices[: len(vertices) // 2].astype(np.int32), vertices[len(vertices) // 3:].astype(np.int32)
    (vt_pairs, vt_keys), (ee_pairs, ee_keys) = _keyed(len(vt), rng), _keyed(len(ee), rng)
    memories = (ContactMemory("vertex_triangle"), ContactMemory("edge_edge"))
    for memory, pairs in zip(memories, (vt_pairs, ee_pairs)):
        rows = np.sort(rng.choice(len(pairs), size=len(pairs) // 3, replace=False))
        extra = np.array([[5000, 7], [6000, 1]], dtype=np.int64)  # remembered pairs outside the lists
        memory.update(np.concatenate([pairs[rows], extra]), rng.choice([-1.0, 1.0], size=len(rows) + 2))
    cache: dict = {}
    for min_sine in (0.1, 0.0, 0.6):
        for p_rows, q_rows in ((slice(None), slice(None)), (slice(0, 0), slice(None)), (slice(None), slice(0, 0))):
            lists = (np.ascontiguousarray(vt[p_rows]), np.ascontiguousarray(ee[q_rows]))
            pairs, keys = (vt_pairs[p_rows], ee_pairs[q_rows]), (vt_keys[p_rows], ee_keys[q_rows])
            want, keep, geo = _host_sides(x, *lists, pairs, keys, memories, min_sine)
            codes = side_codes(x, *lists, min_sine, cache if p_rows == q_rows else {})
            for name, got in zip(geo._fields, codes.geometry()):
                np.testing.assert_array_equal(got, getattr(geo, name), err_msg=name)
                assert got.dtype == getattr(geo, name).dtype, name
            some = (rng.permutation(len(lists[0]))[:40], rng.permutation(len(lists[1]))[:40])
            for got, want_rows in zip(codes.rows(*some), geo.rows(*some)):
                np.testing.assert_array_equal(got, want_rows)
            found = [m.found_in(k) for m, k in zip(memories, keys)]
            placed = step_sides_of(codes, (np.concatenate([found[0][0], found[1][0] + len(lists[0])]),
                                           np.concatenate([found[0][1], found[1][1]])))
            np.testing.assert_array_equal(placed.sides, want)
            # the edge-edge pairs kept: the host's keep, or on CUDA the rows the kept rows' launch made (no keep)
            np.testing.assert_array_equal(placed.kept_edge_edge_rows(), np.flatnonzero(keep))
            if emulated and len(want):
                np.testing.assert_array_equal(codes.device.to_numpy(), codes.both)
                np.testing.assert_array_equal(placed.device.to_numpy()[:len(want)], want)
                p = len(lists[0])
                layout = np.concatenate([np.arange(p), p + np.flatnonzero(keep)]).astype(np.int32)
                assert placed.ee_keep is None and placed.kept.ee_rows.dtype == np.int64
                np.testing.assert_array_equal(placed.kept.rows, layout)
                np.testing.assert_array_equal(placed.kept.device.to_numpy()[:len(layout)], layout)
            else:
                np.testing.assert_array_equal(placed.ee_keep, keep)
                assert codes.device is None and placed.device is None and placed.kept is None
            if p_rows == q_rows == slice(None) and min_sine == 0.1:
                # every case met: remembered sides kept against the geometric one, and left out beside the face
                above = geo.vt_above
                remembered = memories[0].lookup(vt_pairs)[1]
                assert np.any(above & remembered & (want[:len(vt)] != geo.vt_side))
                assert np.any(~above & remembered) and np.all(want[:len(vt)][~above] == 0.0)
                assert np.any(want[len(vt):] != 0.0) and np.any(keep) and np.any(~keep)
    with pytest.raises(ValueError, match="remembered row outside"):
        step_sides_of(codes, (np.array([len(codes.codes)]), np.array([1.0])))
    with pytest.raises(ValueError, match="without a device copy"):
        kept_rows(codes._replace(device=None))
    with pytest.raises(ValueError, match="C-contiguous int32"):
        side_codes(x, vt.astype(np.int64), ee, 0.1, {})


def sheet_mask(contact) -> np.ndarray:
    """Whether each vertex of the contact set's model is a sheet's, bool ``(n,)``."""
    sheet = np.zeros(contact.model.vertex_count, dtype=bool)
    for body in contact.model.bodies.values():
        if body.kind == "sheet":
            sheet[body.vertices] = True
    return sheet


def step_points(contact, x_n: np.ndarray, sheet: np.ndarray, rng, trial: bool) -> tuple[np.ndarray, list]:
    """``(y, points)``: a step's end ``y`` (``x_n`` jittered by a fifth of eps) and the points evaluated on the way,
    ``x_n``, ``y`` and, with ``trial``, a trial point whose sheet moved down past the margin (new lists, searched within
    the step)."""
    y = x_n + 0.2 * contact.eps * rng.normal(size=x_n.shape)
    points = [x_n, y]
    if trial:
        moved = y.copy()
        moved[sheet, 2] -= 1.2 * contact.margin
        points.append(moved)
    return y, points


def _forming_run(device_sides: bool, monkeypatch) -> list:
    """A pressed Forming contact set through two steps, a trial point of the second whose sheet moved past the
    margin (new lists, searched within the step) and its end: each point's pairs, sides, batch energy and gradient and
    the remembered sides, with the step sides by one launch or on the host."""
    from sim_core.contact_set import ContactSet

    monkeypatch.setattr(ContactSet, "device_sides", device_sides)
    contact, x = _forming_contact("taichi-cpu")
    rng = np.random.default_rng(7)
    x_n = x + 0.4 * contact.eps * rng.normal(size=x.shape)
    sheet = sheet_mask(contact)
    out = []
    memory = contact.begin_step(x_n, None)
    for k in range(2):
        y, points = step_points(contact, x_n, sheet, rng, bool(k))
        for point in points:
            vt, ee = contact.potentials(point, x_n, memory)[:2]
            out.append([vt.pairs, vt.sides, ee.pairs, ee.sides, vt.energy(point), ee.energy(point),
                        vt.gradient(point), ee.gradient(point), vt.active_distances(point)[1]])
        end = contact.end_step(y, memory)
        out.append([end.vertex_triangle.pairs, end.vertex_triangle.sides, end.edge_edge.pairs, end.edge_edge.sides])
        x_n = y
        memory = contact.begin_step(x_n, end)
    return out


@pytest.mark.skipif(TEST_ARCH != "cpu", reason=EMULATED_ONLY)
@pytest.mark.parametrize("emulated", [False, True])
def test_forming_contact_set_with_the_launchs_sides_equals_the_hosts(ti_cpu, monkeypatch, emulated):
    """Forming's contact set (pressed, two steps, a new search at a trial point, remembered sides from the first step)
    with the lists' int8 codes and the sides placed from them (the end of a step's codes serving the next one's start):
    the same pairs, sides, pair energies, gradients and distances, and the same memory, as with the host's sides, bit
    for bit; on CUDA (emulated) the pair batch reads the placed device sides, and the lists' int32 vertices are
    gathered where the search's sort left the keys (equal to the host's gather of every pair, which is never made
    for the kernels)."""
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.energies.contact import sides_kernel
    from sim_core.energies.contact.pair_lists import CandidateVertices
    from sim_core.energies.contact.reference import edge_edge_vertices, vertex_triangle_vertices
    from sim_core.ti_kernels.hash_candidates import HashCandidates

    host = _forming_run(False, monkeypatch)
    if emulated:
        _emulate_cuda(monkeypatch)
    launches = []
    kernel = sides_kernel._place_kernel
    monkeypatch.setattr(sides_kernel, "_place_kernel", lambda *a: (launches.append(a), kernel(*a))[1])
    batches = []
    made = PairBatch.__init__
    monkeypatch.setattr(PairBatch, "__init__", lambda self, *a, **k: (batches.append(k), made(self, *a, **k))[1])
    gathered, host_int32 = [], []
    gather = HashCandidates.device_vertices
    monkeypatch.setattr(HashCandidates, "device_vertices", lambda self, vt, ee: (
        lambda got: (gathered.append((self, vt, ee, got)), got)[1])(gather(self, vt, ee)))
    int32 = CandidateVertices.int32_vertices
    monkeypatch.setattr(CandidateVertices, "int32_vertices", lambda self: (host_int32.append(self), int32(self))[1])
    device = _forming_run(True, monkeypatch)
    # the sides placed on the device at each step's start and for the trial point's new lists (only there on CUDA)
    assert len(launches) >= 3 if emulated else not launches
    assert len(gathered) >= 2 and all((got is not None) == emulated for *_, got in gathered)
    assert not host_int32 if emulated else host_int32
    for search, vt, ee, got in gathered if emulated else ():
        assert len(vt) and len(ee)
        np.testing.assert_array_equal(got[0].to_numpy(), vertex_triangle_vertices(vt, search.triangles))
        np.testing.assert_array_equal(got[1].to_numpy(), edge_edge_vertices(ee, search.edges))
    given = [k.get("device_sides") is not None for k in batches]
    assert all(given) if emulated else not any(given)
    # on CUDA the batches' layout rows are those the kept rows' launch made (none built or sent by the host)
    rows_given = [k.get("device_rows") is not None for k in batches]
    assert all(rows_given) if emulated else not any(rows_given)
    assert len(host) == len(device)
    for want, got in zip(host, device):
        for a, b in zip(want, got):
            np.testing.assert_array_equal(a, b)
    assert len(host[-1][0]) and np.any(host[-2][1] != 0.0)  # remembered pairs, signed sides at a trial point
