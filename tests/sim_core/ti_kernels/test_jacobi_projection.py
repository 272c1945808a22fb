"""The Jacobi PSD projection of symmetric blocks (sim_core.ti_kernels.block_projection.jacobi_project_blocks,
used on CUDA) equals LAPACK's (numpy.linalg.eigh) for the block sizes of the fused elastic terms and
contact elements, definite blocks kept as they are."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.ti_kernels.block_projection import project_reduced_blocks  # noqa: E402 (Taichi imported here)
from tests.sim_core.ti_kernels.test_householder_projection import symmetric_blocks


@pytest.mark.parametrize("n", [3, 6, 9, 15])
@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_jacobi_projection_matches_lapack(ti_cpu, n, projection):
    blocks = symmetric_blocks(n)
    want = project_reduced_blocks(blocks.copy(), projection, method="lapack")
    got = project_reduced_blocks(blocks.copy(), projection, method="jacobi")
    scale = np.abs(blocks).max(axis=(1, 2))[:, None, None]
    assert np.all(np.abs(got - want) <= 1e-12 * scale)
    np.testing.assert_array_equal(got[:8], blocks[:8])
    np.testing.assert_allclose(got[10:12], blocks[10:12], rtol=0, atol=1e-12 * scale.max())
    assert np.abs(got[12] - blocks[12]).max() > 1e-7  # its negative eigenvalue clamped
    w = np.linalg.eigvalsh(got)
    assert w.min() >= -1e-12 * scale.max()
    if projection == "abs":  # |H| has the absolute eigenvalues of H
        np.testing.assert_allclose(np.sort(w, axis=1), np.sort(np.abs(np.linalg.eigvalsh(blocks)), axis=1),
                                   atol=1e-11 * scale.max())


def test_projection_method_is_checked(ti_cpu):
    with pytest.raises(ValueError, match="method"):
        project_reduced_blocks(np.eye(3)[None], "clamp", method="qr")


def test_the_device_projection_kernels_are_compiled_with_the_step_kernels(ti_cpu, monkeypatch):
    """``kernel_compile.compile_kernels`` compiles the device projection's kernels (on CUDA: emulated here), which
    one environment's projected Hessian (on the host) does not run."""
    from sim_core.energies.membrane.reference import SpringMembrane
    from sim_core.kernel_compile import compile_kernels
    from sim_core.mesh.sheet import grid_sheet, sheet_topology
    from sim_core.ti_kernels import block_projection as bp

    monkeypatch.setattr(bp, "current_arch", lambda: "cuda")
    bp.compile_kernels()
    for kernel in (bp.jacobi_project_blocks, bp.householder_project_blocks, bp.reduce_block_rows,
                   bp.expand_add_upper_rows, bp.add_upper_block_rows, bp._gather_block_columns, bp._block_rows):
        assert kernel._primal.compiled_kernels
    calls = []
    monkeypatch.setattr(bp, "compile_kernels", lambda: calls.append(1))
    sheet = grid_sheet((0.01, 0.01), (3, 3))
    membrane = SpringMembrane(sheet.triangles, sheet_topology(sheet.triangles)[0], sheet.x, 1.0, 1.0)
    compile_kernels([membrane], sheet.x)
    compile_kernels([membrane], sheet.x, projection="none")
    assert calls == [1]
