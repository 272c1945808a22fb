"""PSD-projected element Hessians of the fused path equal the reference projection and are PSD.

:mod:`sim_core.ti_kernels.block_projection` (translation-free reduction by GEMMs, batched
LAPACK eigen-decomposition, slot-map assembly), the per-triangle
Kirchhoff blocks of :func:`sim_core.energies.kirchhoff_bending.fused_kernel.kirchhoff_triangle_hessians`, and
:meth:`sim_core.fused_elastic.FusedElastic.projected_hessian_values` for every elastic term, against
:func:`sim_core.energies.base.project_psd`, the reference potentials and finite differences.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.assembly import HessianAssembler
from sim_core.energies.base import project_psd
from sim_core.energies.membrane.reference import project_psd_translation_free
from tests.sim_core.ti_kernels.test_fused_elastic import KINDS, _fused, _potentials
from tests.support.fd import fd_gradient, fd_hessian, relative_error


def _translation_invariant_blocks(k: int, m: int, seed: int, definite: int) -> np.ndarray:
    """``k`` symmetric ``3 m x 3 m`` blocks with the translations in their null space; the first
    ``definite`` are positive definite on the complement, the rest indefinite."""
    from sim_core.ti_kernels.block_projection import helmert_array

    rng = np.random.default_rng(seed)
    B = np.kron(helmert_array(m), np.eye(3))
    n = 3 * m - 3
    out = []
    for e in range(k):
        A = rng.standard_normal((n, n))
        R = A @ A.T + 0.1 * np.eye(n) if e < definite else A + A.T
        out.append(B @ R @ B.T)
    return np.array(out)


def _dense_upper(upper) -> np.ndarray:
    return (upper + upper.T).toarray() - np.diag(upper.diagonal())


def test_reduction_and_expansion_are_the_basis_products(ti_cpu):
    from sim_core.ti_kernels.block_projection import TranslationFreeProjector, helmert_array

    blocks = _translation_invariant_blocks(9, 6, 0, definite=4)
    projector = TranslationFreeProjector(6)
    B = np.kron(helmert_array(6), np.eye(3))
    assert np.allclose(B.T @ B, np.eye(15), atol=1e-15) and np.allclose(B.T @ np.tile(np.eye(3), (6, 1)), 0.0)
    reduced = projector.reduced(blocks)
    assert relative_error(reduced, B.T @ blocks @ B) < 1e-14
    assert relative_error(projector.expanded(reduced), blocks) < 1e-14  # translations are in the null space


@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_projected_reduced_blocks_equal_reference(ti_cpu, projection):
    from sim_core.ti_kernels.block_projection import project_reduced_blocks

    rng = np.random.default_rng(3)
    A = rng.standard_normal((12, 15, 15))
    blocks = A + np.swapaxes(A, 1, 2)
    blocks[:3] = A[:3] @ np.swapaxes(A[:3], 1, 2) + np.eye(15)  # definite
    out = project_reduced_blocks(blocks.copy(), projection)
    assert relative_error(out, project_psd(blocks, projection)) < 1e-13
    assert np.array_equal(out[:3], blocks[:3])  # no negative eigenvalue: not rebuilt
    assert np.linalg.eigvalsh(out).min() > -1e-12 * np.abs(out).max()
    assert relative_error(project_reduced_blocks(blocks[3:].copy(), projection), project_psd(blocks[3:], projection)) < 1e-13
    with pytest.raises(ValueError, match="unknown PSD projection"):
        project_reduced_blocks(blocks.copy(), "flip")


@pytest.mark.parametrize("projection", ["none", "clamp", "abs"])
def test_projector_adds_the_reference_projection(ti_cpu, projection):
    """Blocks with repeated vertices and fixed DoFs; the sum equals the reference blocks' assembly."""
    from sim_core.ti_kernels.block_projection import TranslationFreeProjector

    n_vertices = 10
    rng = np.random.default_rng(4)
    vertices = np.array([rng.choice(n_vertices, 6, replace=False) for _ in range(8)])
    vertices[2, 5] = vertices[2, 4]  # a repeated vertex (boundary edge of a Kirchhoff triangle)
    blocks = _translation_invariant_blocks(8, 6, 1, definite=3)
    free = np.ones(3 * n_vertices, bool)
    free[[0, 4, 29]] = False
    asm = HessianAssembler(3 * n_vertices)
    pattern = asm.static_pattern([vertices], free)
    values = np.zeros(pattern.keys.size)
    projector = TranslationFreeProjector(6)
    projector.add_projected(blocks, projection, pattern.slot_map(vertices), values)
    from sim_core.energies.base import HessianBlocks

    diag = np.ones(3 * n_vertices)
    H = asm.assemble_upper_values(pattern, values, [], diag, free)
    H_ref = asm.assemble_upper([HessianBlocks(vertices, project_psd_translation_free(blocks, projection))], [], diag,
                               free)
    assert relative_error(H.data, H_ref.data) < 1e-13
    if projection != "none":
        elastic = _dense_upper(asm.assemble_upper_values(pattern, values, [], np.zeros(3 * n_vertices), free))
        assert np.linalg.eigvalsh(elastic).min() > -1e-12 * np.abs(elastic).max()


def test_kirchhoff_triangle_blocks_equal_reference_and_finite_differences(ti_cpu):
    pot, x_rest, deformed = _potentials("kirchhoff")
    fused, _ = _fused(pot, x_rest, np.ones(x_rest.size, bool))
    part = fused._parts[0]
    for seed in (0, 1, 2):
        x = np.ascontiguousarray(deformed(seed))
        blocks = part.triangle_hessians(x)
        assert relative_error(blocks, pot.hessian(x, "none").blocks) < 1e-12
    # per triangle: the block is the Hessian of that triangle's energy d^T M d (FD of its gradient)
    x = np.ascontiguousarray(deformed(5))
    blocks = part.triangle_hessians(x).copy()
    for t in (0, 5, 11):
        verts = pot.block_vertices[t]
        own = np.unique(verts)

        def energy_t(y, t=t):
            return pot.triangle_energy(y)[t]

        def grad_t(y):
            return fd_gradient(energy_t, y, h=1e-6)

        H_fd = fd_hessian(lambda y: _local_gradient(pot, y, t), x, h=1e-7)
        dofs = (3 * verts[:, None] + np.arange(3)).reshape(-1)
        H_local = np.zeros((x.size, x.size))
        np.add.at(H_local, (dofs[:, None], dofs[None, :]), blocks[t])
        sel = (3 * own[:, None] + np.arange(3)).reshape(-1)
        assert relative_error(H_local[np.ix_(sel, sel)], H_fd[np.ix_(sel, sel)]) < 1e-5
        assert relative_error(_local_gradient(pot, x, t), grad_t(x)) < 1e-5


def _local_gradient(pot, x: np.ndarray, t: int) -> np.ndarray:
    """dE_T/dx of triangle ``t``'s energy ``d^T M d`` (sum_k 2 (M d)_k dtheta_k/dx), shape ``(n, 3)``."""
    theta = pot.theta(x)
    grad_h = pot.theta_gradient(x)
    d = pot._triangle_deviation(theta)[t]
    f = 2.0 * pot.triangle_stiffness[t] @ d
    g = np.zeros_like(x)
    for k in range(3):
        h = pot.triangle_hinge[t, k]
        if h >= 0:
            np.add.at(g, pot.hinges[h], f[k] * grad_h[h])
    return g


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_fused_projected_hessian_equals_reference_and_is_psd(ti_cpu, kind, projection):
    pot, x_rest, deformed = _potentials(kind)
    n = x_rest.shape[0]
    free = np.ones(3 * n, bool)
    free[[0, 1, 2, 7, 3 * n - 1]] = False
    fused, asm = _fused(pot, x_rest, free)
    zero = np.zeros(3 * n)
    for seed in (0, 1):
        x = deformed(seed)
        values = fused.projected_hessian_values(x, projection)
        H = asm.assemble_upper_values(fused.pattern, values, [], zero, free)
        H_ref = asm.assemble_upper([pot.hessian(x, projection)], [], zero, free)
        assert np.array_equal(H.indptr, H_ref.indptr) and np.array_equal(H.indices, H_ref.indices)
        assert relative_error(H.data, H_ref.data) < 1e-12
        dense = _dense_upper(H)
        assert np.linalg.eigvalsh(dense).min() > -1e-10 * np.abs(dense).max()
        # the exact Hessian of these configurations is indefinite: the projection changed something
        exact = _dense_upper(asm.assemble_upper_values(fused.pattern, fused.hessian_values(x), [], zero, free))
        if kind != "spring_membrane":
            assert np.linalg.eigvalsh(exact).min() < 0


@pytest.mark.parametrize("kind", ("snh", "spring_membrane", "kirchhoff"))
def test_projected_hessian_of_marked_vertices_sums_the_elements_touching_them(ti_cpu, kind):
    """With a vertex mask, only the elements touching a marked vertex are projected and added: the rows and
    columns of the vertices that no other element touches equal the whole projected matrix's, and the
    values differ from the whole matrix's elsewhere."""
    from sim_core.fused_elastic import FusedElastic

    pot, x_rest, deformed = _potentials(kind)
    n = x_rest.shape[0]
    free = np.ones(3 * n, bool)
    free[[0, 1, 2]] = False
    fused, asm = _fused(pot, x_rest, free)
    x = deformed(3)
    marked = np.zeros(n, dtype=bool)
    marked[: n // 3] = True
    elements = fused.block_vertex_arrays(x_rest)[0]
    touching = np.asarray(marked)[elements].any(axis=1)
    assert 0 < touching.sum() < len(elements)
    got = fused.projected_hessian_values(x, "clamp", marked)
    whole = fused.projected_hessian_values(x, "clamp")
    inner = ~np.isin(np.arange(n), elements[~touching])  # vertices no unmarked element touches
    dofs = np.flatnonzero(np.repeat(inner, 3) & free)
    zero = np.zeros(3 * n)
    H_got = _dense_upper(asm.assemble_upper_values(fused.pattern, got, [], zero, free))
    H_whole = _dense_upper(asm.assemble_upper_values(fused.pattern, whole, [], zero, free))
    assert dofs.size > 0
    np.testing.assert_allclose(H_got[np.ix_(dofs, dofs)], H_whole[np.ix_(dofs, dofs)], rtol=1e-12,
                               atol=1e-12 * np.abs(H_whole).max())
    assert not np.allclose(got, whole)  # the unmarked elements' blocks are left out


@pytest.mark.parametrize("method", ("jacobi", "lapack", None))
@pytest.mark.parametrize("projection", ("none", "clamp", "abs"))
def test_projection_of_listed_blocks_by_kernels_adds_what_the_host_projection_adds(ti_cpu, projection, method):
    """``add_projected_rows`` (reduction, expansion and scatter of the upper triangles through the packed upper slot
    table as kernels, the path of device arrays; the reduced blocks projected by the Jacobi kernel or by LAPACK on
    the host) adds, for the listed blocks, the sums ``add_projected`` adds for those blocks through the full slot
    map (NumPy reduction and LAPACK), to round-off; the unlisted blocks add nothing. The slot map keeps one entry
    of each local pair, the upper or the lower one (as the assembler's), or both in one slot for a DoF repeated in
    an element (added twice)."""
    from sim_core.ti_kernels.block_projection import TranslationFreeProjector, upper_slot_table

    rng = np.random.default_rng(11)
    m, k, nnz = 6, 40, 500
    n = 3 * m
    projector = TranslationFreeProjector(m)
    reduced = rng.normal(size=(k, n - 3, n - 3))
    reduced = reduced + reduced.transpose(0, 2, 1)  # indefinite symmetric blocks
    noise = rng.normal(size=(k, n, n))
    blocks = np.ascontiguousarray(projector.expanded(reduced) + 1e-3 * (noise + noise.transpose(0, 2, 1)))
    slots = rng.integers(-1, nnz, size=(k, n, n)).astype(np.int32)
    strict_upper = np.triu(np.ones((n, n), dtype=bool), 1)
    side = rng.random((k, n, n)) < 0.5  # per pair r < s: the upper entry kept, else the lower one
    slots = np.where(strict_upper & ~side, -1, slots)
    slots = np.where(strict_upper.T & side.transpose(0, 2, 1), -1, slots).astype(np.int32)
    slots[3, 1, 4] = slots[3, 4, 1] = slots[3, 1, 1] = slots[3, 4, 4] = 7  # local DoFs 1 and 4 one global DoF
    rows = np.array([3, 0, 17, 39, 5], dtype=np.int32)
    want = np.zeros(nnz)
    projector.add_projected(blocks[rows], projection, slots[rows], want)
    got = np.zeros(nnz)
    upper = upper_slot_table(slots)
    projector.add_projected_rows(blocks, projection, upper, rows, got, method=method)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-11 * np.abs(want).max())
    with pytest.raises(ValueError, match="add_projected_rows: unknown method 'qr'"):
        projector.add_projected_rows(blocks, projection, upper, rows, got, method="qr")
    if projection != "none":  # the projection changed the blocks (they have negative eigenvalues)
        plain = np.zeros(nnz)
        projector.add_projected(blocks[rows], "none", slots[rows], plain)
        assert np.abs(plain - want).max() > 1e-3 * np.abs(want).max()


def test_projected_hessian_needs_bind_and_a_known_projection(ti_cpu):
    from sim_core.fused_elastic import FusedElastic

    pot, x_rest, deformed = _potentials("kirchhoff")
    with pytest.raises(RuntimeError, match="bind"):
        FusedElastic([pot]).projected_hessian_values(x_rest, "clamp")
    fused, _ = _fused(pot, x_rest, np.ones(x_rest.size, bool))
    with pytest.raises(ValueError, match="unknown PSD projection"):
        fused.projected_hessian_values(deformed(0), "flip")


def test_solver_projected_fallback_equals_reference_path(ti_cpu):
    """Forming steps whose Newton loop falls back to the projected Hessian: the fused path
    (projected values in the static slots) takes the same iterations to the same positions."""
    from sim_core.control import Control
    from sim_core.scenes.task_scene import load_task_scene, task_initial_state
    from sim_core.simulation import Simulation
    from sim_core.tasks.trajectories import forming_benchmark_offsets, pose_targets
    from thinshell_ros.paths import bundled_scene

    from sim_core.solver import SolverConfig

    runs = []
    for backend in ("numpy", "taichi-cpu"):
        model = load_task_scene(bundled_scene("forming"))
        sim = Simulation(model, solver_config=SolverConfig(backend=backend))
        sim.state = task_initial_state(model)
        effector = next(iter(model.effectors))
        targets = pose_targets(model.effectors[effector].initial_pose, forming_benchmark_offsets(49))
        infos = []
        for k in range(2):  # the bench trajectory's step 1 refuses the exact Hessian once
            control = Control()
            control.effector_pose_target[effector] = targets[k]
            infos.append(sim.step(control))
        runs.append((sim.state.x.copy(), [(i.iterations, i.projected_iterations) for i in infos]))
    (x_ref, it_ref), (x_fused, it_fused) = runs
    assert sum(p for _, p in it_ref) > 0
    assert it_fused == it_ref
    assert np.max(np.abs(x_fused - x_ref)) < 1e-12


@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_spring_membrane_projected_blocks_equal_reference_block_by_block(ti_cpu, projection):
    """Each projected edge block (closed form) and triangle block (reduced eigen-decomposition) of the
    fused spring membrane equals the reference's ``hessian(x, projection)`` block to 1e-12 relative,
    at configurations with stretched and compressed edges and with grown and shrunk triangles."""
    from sim_core.energies.membrane.reference import SpringMembrane
    from tests.sim_core.ti_kernels.test_fused_elastic import _deformed_sheet, _sheet

    mesh, topo = _sheet(3, 2)
    free = np.ones(mesh.x.size, bool)
    zero = np.zeros(mesh.x.size)
    xs = [_deformed_sheet(mesh.x, seed, amplitude=4e-3) for seed in (0, 1)]
    stretch = np.concatenate([np.linalg.norm(x[topo.edges[:, 1]] - x[topo.edges[:, 0]], axis=1) for x in xs])
    rest = np.linalg.norm(mesh.x[topo.edges[:, 1]] - mesh.x[topo.edges[:, 0]], axis=1)
    assert np.any(stretch < np.tile(rest, 2)) and np.any(stretch > np.tile(rest, 2))
    elements = [(np.zeros((0, 3), int), topo.edges[[e]]) for e in range(topo.edges.shape[0])]
    elements += [(mesh.triangles[[t]], np.zeros((0, 2), int)) for t in range(mesh.triangles.shape[0])]
    for triangles, edges in elements:
        pot = SpringMembrane(triangles, edges, mesh.x, 1000.0, 800.0)
        fused, asm = _fused(pot, mesh.x, free)
        for x in xs:
            H = _dense_upper(asm.assemble_upper_values(fused.pattern, fused.projected_hessian_values(x, projection),
                                                       [], zero, free))
            H_ref = _dense_upper(asm.assemble_upper([pot.hessian(x, projection)], [], zero, free))
            assert np.abs(H - H_ref).max() <= 1e-12 * np.abs(H_ref).max()


@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_spring_membrane_projection_by_kernels_adds_what_the_host_path_adds(ti_cpu, projection):
    """The spring membrane's projection by kernels alone (its CUDA path, run here on the CPU arch: triangle
    blocks, Jacobi projection, scatter and the edges' closed form) adds the host path's sums (LAPACK) to
    1e-11 relative, for every element and for the elements touching a vertex mask; the projection
    changed the deformed sheet's exact Hessian."""
    from sim_core.energies.membrane.fused_spring_kernel import FusedSpringMembrane

    pot, x_rest, deformed = _potentials("spring_membrane")
    n = x_rest.shape[0]
    fused, _ = _fused(pot, x_rest, np.ones(3 * n, bool))
    part = FusedSpringMembrane(pot)
    part.bind(fused.pattern)
    x = np.ascontiguousarray(deformed(3))
    marked = np.zeros(n, dtype=bool)
    marked[: n // 3] = True
    for vertices in (None, marked):
        want = np.zeros(fused.pattern.keys.size)
        part.add_projected(x, projection, want, vertices=vertices)
        got = np.zeros(fused.pattern.keys.size)
        part.add_projected_by_kernels(x, projection, got, vertices=vertices)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-11 * np.abs(want).max())
        exact = np.zeros(fused.pattern.keys.size)
        part.add_projected(x, "none", exact, vertices=vertices)
        assert np.abs(exact - want).max() > 1e-6 * np.abs(want).max()


@pytest.mark.parametrize("kind", ("snh", "spring_membrane", "kirchhoff"))
def test_the_blocks_of_listed_elements_are_the_whole_evaluations_to_the_bit(ti_cpu, kind):
    """The fused parts' block kernels over listed rows (a lockstep retry's marked elements: the Neo-Hookean
    projected blocks, the spring membrane's and Kirchhoff bending's exact triangle blocks) write each listed block bit
    for bit as the evaluation of every element does, and leave the other blocks as they were."""
    from sim_core.energies.kirchhoff_bending.fused_kernel import FusedKirchhoffBending, kirchhoff_triangle_hessians
    from sim_core.energies.membrane.fused_spring_kernel import FusedSpringMembrane, spring_membrane_triangle_blocks
    from sim_core.energies.neohookean.fused_kernel import FusedStableNeoHookean
    from sim_core.energies.neohookean.kernel import evaluate_snh_hessian, evaluate_snh_hessian_rows

    pot, x_rest, deformed = _potentials(kind)
    fused, _ = _fused(pot, x_rest, np.ones(x_rest.size, bool))
    x = np.ascontiguousarray(deformed(5))
    part = {"snh": FusedStableNeoHookean, "spring_membrane": FusedSpringMembrane,
            "kirchhoff": FusedKirchhoffBending}[kind](pot)
    part.bind(fused.pattern)
    if kind == "snh":
        k, m = part._tets.shape[0], 12

        def blocks_of(rows, out):
            evaluate_snh_hessian_rows(x, part._tets, part._dFdx, part._vol, pot.mu, pot.lam, 1, rows, rows.size, out)
    elif kind == "spring_membrane":
        k, m = part._triangles.shape[0], 9

        def blocks_of(rows, out):
            spring_membrane_triangle_blocks(x, part._triangles, part._area0, pot.k_area, rows, rows.size, out)
    else:
        k, m = part._tri_hinge.shape[0], 18

        def blocks_of(rows, out):
            kirchhoff_triangle_hessians(x, part._hinges, part._theta_bar, part._tri_hinge, part._tri_local,
                                        part._stiffness, np.zeros_like(part._scratch), rows, rows.size, out)
    whole = np.zeros((k, m, m))
    blocks_of(np.arange(k, dtype=np.int32), whole)
    if kind == "snh":
        every = np.zeros((k, m, m))
        evaluate_snh_hessian(x, part._tets, part._dFdx, part._vol, pot.mu, pot.lam, 1, every)
        np.testing.assert_array_equal(whole, every)
    rows = np.flatnonzero(np.random.default_rng(1).random(k) < 0.4).astype(np.int32)
    assert 0 < rows.size < k and np.abs(whole).max() > 0.0
    got = np.full(whole.shape, 7.0)
    blocks_of(rows, got)
    np.testing.assert_array_equal(got[rows], whole[rows])
    np.testing.assert_array_equal(got[np.setdiff1d(np.arange(k), rows)], 7.0)


def test_marked_rows_are_the_elements_touching_a_marked_vertex():
    """``marked_rows``: the rows with any vertex marked (a mask not closed under the elements too), increasing int32;
    every row without a mask; a mask closed under the elements gives the same rows by the first vertex alone."""
    from sim_core.ti_kernels.block_projection import marked_rows

    rng = np.random.default_rng(5)
    for m in (1, 3, 4, 6):
        elements = rng.integers(0, 200, size=(500, m)).astype(np.int32)
        mask = rng.random(200) < 0.1
        before = mask.copy()
        got = marked_rows(elements, mask)
        np.testing.assert_array_equal(mask, before)  # the mask is read only
        assert got.dtype == np.int32
        np.testing.assert_array_equal(got, np.flatnonzero([mask[e].any() for e in elements]))
        np.testing.assert_array_equal(marked_rows(elements, None), np.arange(500))
        assert marked_rows(elements[:0], mask).size == 0
    # a mask closed under the elements (whole copies of 20 vertices, each element within one copy): by the first
    # vertex alone, the same rows
    copy_of = rng.integers(0, 10, size=500)
    elements = (20 * copy_of[:, None] + rng.integers(0, 20, size=(500, 4))).astype(np.int32)
    mask = np.repeat(rng.random(10) < 0.4, 20)
    want = marked_rows(elements, mask)
    assert 0 < want.size < 500
    np.testing.assert_array_equal(marked_rows(elements, mask, closed=True), want)
