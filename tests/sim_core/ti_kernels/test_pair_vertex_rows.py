"""The contact potentials' vertices read by rows (``PairVertices``, sim_core/energies/contact/reference.py): where the
candidate lists' int32 vertices are gathered on the device (CUDA, emulated on the CPU arch), the host gathers no
candidate's int64 vertices when a list is built, and the rows the potentials read (the active pairs', the friction
set-up's, the Newton matrix's blocks, the releases, the end of a step) equal the whole gather's, so that the contact
set's pairs, sides, energies, gradients, Hessian blocks, friction rows and memory equal the host path's bit for bit
through steps and a trial point's new lists."""

from __future__ import annotations

import numpy as np
import pytest

from tests.sim_core.ti_kernels.conftest import TEST_ARCH
from tests.sim_core.ti_kernels.test_contact_setup import _forming_contact
from tests.sim_core.ti_kernels.test_step_sides_kernel import sheet_mask, step_points
from tests.support.emulated_cuda import emulate_cuda

EMULATED_ONLY = ("compares CUDA's lists (their vertices gathered on the device, emulated on the CPU arch) with the "
                 "host's whole int64 gathers, which only the CPU arch makes (the default, and CI); under "
                 "THINSHELL_TEST_ARCH=cuda every contact test of this folder takes the device path for real")
"""Why the emulation test is left out on a GPU run."""


def test_rows_equal_the_whole_gathers_and_read_only_the_rows():
    """A vertex-triangle and an edge-edge list's rows (``np.take``, int and bool indices, the kept edge-edge rows)
    equal the rows of the whole gathers without making them; whole reads (``np.asarray``, ``x[v]``, slices) gather once;
    ``same_vertices`` knows equal pairs over the same elements without gathering."""
    from sim_core.energies.contact.reference import (PairVertices, edge_edge_vertices, same_vertices,
                                                     vertex_triangle_vertices)

    rng = np.random.default_rng(3)
    triangles, edges = rng.integers(0, 400, (90, 3)), rng.integers(0, 400, (150, 2))
    vt = np.column_stack([rng.integers(0, 400, 500), rng.integers(0, 90, 500)])
    ee = np.sort(rng.integers(0, 150, (700, 2)), axis=1)
    x = rng.normal(size=(400, 3))
    for pairs, elements, gather in ((vt, triangles, vertex_triangle_vertices), (ee, edges, edge_edge_vertices)):
        want = gather(pairs, elements)
        rows = PairVertices(pairs, elements, gather)
        active = np.flatnonzero(rng.random(len(pairs)) < 0.1)
        mask = rng.random(len(pairs)) < 0.3
        assert np.shape(rows) == want.shape and len(rows) == len(want) and rows.dtype == want.dtype
        for got, expected in ((np.take(rows, active, axis=0), want[active]), (rows[active], want[active]),
                              (rows[mask], want[mask]), (rows.take(active[:0], axis=0), want[:0])):
            assert got.dtype == np.int64
            np.testing.assert_array_equal(got, expected)
        assert rows.whole_gathers == 0
        with pytest.raises(IndexError, match="boolean index of 3"):
            rows[np.ones(3, dtype=bool)]
        with pytest.raises(IndexError):
            rows.take(np.array([len(pairs)]), axis=0)
        assert same_vertices(rows, PairVertices(pairs.copy(), elements, gather)) and rows.whole_gathers == 0
        assert not same_vertices(rows, PairVertices(pairs[::-1].copy(), elements, gather))
        assert not same_vertices(rows, PairVertices(pairs, elements.copy(), gather))
        np.testing.assert_array_equal(x[rows], x[want])
        np.testing.assert_array_equal(rows[1:4], want[1:4])
        np.testing.assert_array_equal(np.asarray(rows, dtype=np.int32), want.astype(np.int32))
        assert rows.whole_gathers == 1 and not np.asarray(rows).flags.writeable
        copied = np.array(rows)  # (a copy of the kept array: writing it leaves the rows as they were)
        copied[:] = -1
        np.testing.assert_array_equal(np.asarray(rows), want)
        np.testing.assert_array_equal(np.take(rows, active, axis=0), want[active])  # (from the kept whole array)
        assert not same_vertices(rows, want) and same_vertices(want, want.copy())


def _pressed_forming():
    """The Forming contact set on the CPU kernels, its positions ``x`` and a start of step ``x^n`` ``(n, 3)`` m a fixed
    0.4 eps jitter away (read-only), its sheet's vertex mask, and the generator that drew the jitter (seed 11) for the
    steps' points."""
    contact, x = _forming_contact("taichi-cpu")
    rng = np.random.default_rng(11)
    x_n = x + 0.4 * contact.eps * rng.normal(size=x.shape)
    x_n.flags.writeable = False
    return contact, x, x_n, sheet_mask(contact), rng


def _forming_steps() -> list:
    """A pressed Forming contact set through two steps, a trial point of the second whose sheet moved past the
    margin (new lists searched within the step), with at each point its pairs, sides, energies, gradients and Hessian
    blocks, the friction rows at each step's start, the releases of stale sides and the remembered sides at each end;
    also the potentials made on the way."""
    contact, x, x_n, sheet, rng = _pressed_forming()
    out, pots = [], []
    memory = contact.begin_step(x_n, None)
    for k in range(2):
        friction = contact.friction(x_n, 0.01, memory)
        out.append([np.asarray(friction.vertices), np.asarray(friction.lam), np.asarray(friction.mu)]
                   + [s.pair_index for s in friction.row_sources])
        y, points = step_points(contact, x_n, sheet, rng, bool(k))
        for point in points:
            vt, ee = contact.potentials(point, x_n, memory)[:2]
            pots += [vt, ee]
            row = [vt.pairs, vt.sides, ee.pairs, ee.sides, vt.energy(point), ee.energy(point), vt.gradient(point),
                   ee.gradient(point)]
            for pot in (vt, ee):
                blocks = pot.hessian(point, "none")
                row += [blocks.vertices, blocks.blocks, pot.contact_frames(point).vertices]
            out.append(row)
        out.append([contact.release_stale_sides(y, memory)])
        end = contact.end_step(y, memory)
        out.append([end.vertex_triangle.pairs, end.vertex_triangle.sides, end.edge_edge.pairs, end.edge_edge.sides])
        x_n = y
        x_n.flags.writeable = False
        memory = contact.begin_step(x_n, end)
    return out, pots


@pytest.mark.skipif(TEST_ARCH != "cpu", reason=EMULATED_ONLY)
def test_forming_contact_set_reading_vertex_rows_equals_the_host_gathers(ti_cpu, monkeypatch):
    """Forming's contact set on CUDA's path (emulated): every pair potential's vertices are read by rows and never
    gathered whole, the lists' int64 vertices are never made, and every result (pairs, sides, energies, gradients,
    Hessian blocks and their vertices, contact frames, friction rows, releases, memory) equals the host path's, which
    gathers every candidate's vertices, bit for bit."""
    from sim_core.energies.contact.reference import PairVertices

    host, host_pots = _forming_steps()
    emulate_cuda(monkeypatch)
    whole = []
    gather = PairVertices.__array__
    monkeypatch.setattr(PairVertices, "__array__", lambda self, *a, **k: (whole.append(self), gather(self, *a, **k))[1])
    device, device_pots = _forming_steps()
    assert all(isinstance(pot.vertices, np.ndarray) for pot in host_pots)
    assert all(isinstance(pot.vertices, PairVertices) for pot in device_pots) and not whole
    assert len(host) == len(device)
    for want, got in zip(host, device):
        assert len(want) == len(got)
        for a, b in zip(want, got):
            np.testing.assert_array_equal(a, b)
    assert any(len(row) > 1 and len(row[0]) for row in host[-1:])  # remembered pairs at the end
    assert len(host[0][0]) and len(host[1][8]) and len(host[1][11])  # friction rows, both kinds' Hessian blocks


def test_list_rows_equal_the_whole_gathers_and_read_only_the_rows():
    """``ListRows`` (an edge-edge potential's kept pairs and sides): rows by ``np.take``, int and bool indices equal the
    whole gather's rows without making it; arithmetic, comparisons, slices and array methods read the whole array,
    gathered once and read-only; ``same_rows`` knows the same base and rows without gathering; bad rows raise."""
    from sim_core.energies.contact.reference import ListRows, same_rows

    rng = np.random.default_rng(5)
    ee = np.sort(rng.integers(0, 150, (700, 2)), axis=1)
    sides = rng.choice([-1.0, 0.0, 1.0], 700)
    kept = np.flatnonzero(rng.random(700) < 0.8)
    for base in (ee, sides):
        want = base[kept]
        rows = ListRows(base, kept)
        active = np.flatnonzero(rng.random(len(kept)) < 0.1)
        mask = rng.random(len(kept)) < 0.3
        assert np.shape(rows) == want.shape and len(rows) == len(want) and rows.dtype == want.dtype
        assert rows.ndim == want.ndim and rows.size == want.size
        for got, expected in ((np.take(rows, active, axis=0), want[active]), (rows[active], want[active]),
                              (rows[mask], want[mask]), (rows.take(active[:0], axis=0), want[:0])):
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, expected)
        assert rows.whole_gathers == 0
        assert same_rows(rows, ListRows(base, kept)) and rows.whole_gathers == 0
        assert same_rows(rows, ListRows(base.copy(), kept.copy())) and rows.whole_gathers == 0
        assert not same_rows(rows, ListRows(base, kept[1:])) and not same_rows(rows, ListRows(base[::-1].copy(), kept))
        assert not same_rows(rows, want) and rows.whole_gathers == 0  # (beside an array: not known, nothing gathered)
        with pytest.raises(IndexError, match="boolean index of 3"):
            rows[np.ones(3, dtype=bool)]
        with pytest.raises(IndexError):
            rows.take(np.array([len(kept)]), axis=0)
        np.testing.assert_array_equal(rows != 0, want != 0)
        np.testing.assert_array_equal(2.0 * rows, 2.0 * want)
        np.testing.assert_array_equal(rows[1:4], want[1:4])
        assert rows.tolist() == want.tolist() and rows.min() == want.min()
        assert rows.whole_gathers == 1 and not np.asarray(rows).flags.writeable
        assert same_rows(want, want.copy()) and not same_rows(want, want[::-1].copy())
    np.testing.assert_array_equal(np.take(ListRows(sides, kept), np.arange(3)), sides[kept[:3]])  # (1-D, axis None)


def _forming_steps_without_releases() -> list:
    """:func:`_forming_steps` without the releases of stale sides (a line search's failure, which reads every pair's
    side): a pressed Forming contact set through two steps, a trial point with new lists in the second; each step's
    set-up made twice (the second's potentials take the first's evaluation of ``x^n``: equal pairs and sides, compared),
    its friction rows (vertices, weights, tangent bases, normals, ``lam``, ``mu``, sources), each point's energies,
    gradients, Hessian blocks, frames and distances, each end's memory."""
    contact, x, x_n, sheet, rng = _pressed_forming()
    out, pots = [], []
    state_memory = None
    for k in range(2):
        for _ in range(2):  # the step's set-up twice: the second's potentials take the first's evaluation of x^n
            memory = contact.begin_step(x_n, state_memory)
            friction = contact.friction(x_n, 0.01, memory)
            out.append([friction.vertices, friction.weights, friction.tangent, friction.normal, friction.lam,
                        friction.mu] + [s.pair_index for s in friction.row_sources])
        y, points = step_points(contact, x_n, sheet, rng, bool(k))
        for point in points:
            vt, ee = contact.potentials(point, x_n, memory)[:2]
            pots.append(ee)
            row = [vt.energy(point), ee.energy(point), vt.gradient(point), ee.gradient(point)]
            for pot in (vt, ee):
                blocks = pot.hessian(point, "none")
                row += [blocks.vertices, blocks.blocks, pot.contact_frames(point).vertices,
                        pot.contact_frames(point).normal, pot.active_distances(point)[1]]
            out.append(row)
        end = contact.end_step(y, memory)
        out.append([end.vertex_triangle.pairs, end.vertex_triangle.sides, end.edge_edge.pairs, end.edge_edge.sides])
        x_n = y
        x_n.flags.writeable = False
        state_memory = end
    return out, pots, contact


@pytest.mark.skipif(TEST_ARCH != "cpu", reason=EMULATED_ONLY)
def test_edge_edge_pairs_and_sides_read_by_rows_equal_the_host_takes(ti_cpu, monkeypatch):
    """Forming's contact set on CUDA's path (emulated): the edge-edge potential's pairs and sides are the kept rows of
    the list and of its sides (``ListRows``), never gathered whole through friction set-ups, energies, gradients,
    Hessian blocks, frames and the ends of steps, and every result (friction rows with their frames, energies,
    gradients, blocks, frames, distances, memory) equals that of the host's takes of every kept row (the contact set
    with ``ListRows`` replaced by ``np.take``) bit for bit; the pairs and sides equal those takes."""
    from sim_core import contact_set as contact_set_module
    from sim_core.energies.contact.reference import ListRows

    emulate_cuda(monkeypatch)
    whole = []
    gather = ListRows.__array__
    monkeypatch.setattr(ListRows, "__array__", lambda self, *a, **k: (whole.append(self), gather(self, *a, **k))[1])
    rows_run, rows_pots, contact = _forming_steps_without_releases()
    assert not whole and all(isinstance(pot.pairs, ListRows) and isinstance(pot.sides, ListRows) for pot in rows_pots)
    for pot in rows_pots:  # the rows of the list and of the sides the contact set kept
        for got in (pot.pairs, pot.sides):
            base, kept = got.base_rows
            np.testing.assert_array_equal(np.asarray(got), np.take(base, kept, axis=0))
    monkeypatch.setattr(contact_set_module, "ListRows", lambda base, kept: np.take(base, kept, axis=0))
    host_run, host_pots, _ = _forming_steps_without_releases()
    assert all(isinstance(pot.pairs, np.ndarray) for pot in host_pots)
    for a, b in zip(rows_pots, host_pots):
        np.testing.assert_array_equal(np.asarray(a.pairs), b.pairs)
        np.testing.assert_array_equal(np.asarray(a.sides), b.sides)
    assert len(host_run) == len(rows_run)
    for want, got in zip(host_run, rows_run):
        assert len(want) == len(got)
        for a, b in zip(want, got):
            np.testing.assert_array_equal(a, b)
    assert len(host_run[0][0]) and len(host_run[0][2])  # friction rows and their frames at the first step
    assert any(len(pot.pairs) for pot in host_pots) and len(host_run[2][10])  # edge-edge Hessian blocks
