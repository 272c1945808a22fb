"""The projected retry's contact pair blocks of a lockstep batch's marked copies (:func:`projected_subset_blocks`).

A lockstep batch retries the copies whose exact Newton matrix the batched CG found indefinite with the PSD-projected
one (:meth:`sim_core.batch.lockstep.LockstepSolver._direction_pcg`): of the contact pair penalties it needs the
projected blocks of the retried copies' pairs only. Their projection is per block (``project_psd`` of each exact
``(12, 12)`` block), so it is made here for those blocks alone, by a projection kernel (Householder-QL or cyclic
Jacobi, :data:`~sim_core.ti_kernels.block_projection.DEVICE_KERNELS`) on the GPU, and, where the pair kernel left the
exact blocks on the device (:class:`~sim_core.energies.base.DeviceHessian`), without any block crossing to the host.
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import DeviceHessian, HessianBlocks, declares


def projected_subset_blocks(term, x: np.ndarray, projection: str, vertices: np.ndarray, method: str,
                            projector=None):
    """The PSD-projected blocks of a :class:`~sim_core.energies.base.SubsetHessian` term whose projection is per
    block (the contact pair penalties): the exact blocks of the pairs whose first vertex is marked in ``vertices``
    (bool ``(N,)``), projected with ``method``. Equal to ``term.hessian_of_vertices(x, projection, vertices)`` to
    round-off.

    Args:
        term: the pair potential.
        x: positions ``(N, 3)`` in m.
        projection: "clamp" or "abs".
        vertices: bool ``(N,)``, closed under the pairs (whole copies).
        method: ``"householder"`` or ``"jacobi"``: that kernel (:data:`~sim_core.ti_kernels.block_projection.
            DEVICE_KERNELS`), every block at once where the kernels run; ``"lapack"``:
            :func:`~sim_core.ti_kernels.block_projection.project_reduced_blocks` on the host.
        projector: None, or a :class:`~sim_core.ti_kernels.block_projection.BlockRowsProjector`: with a kernel
            and the term's exact blocks kept on the device (``hessian_on_device``), the marked pairs' blocks are
            gathered, projected and left there, returned as
            :class:`~sim_core.ti_kernels.buffers.DeviceHessianBlocks` (the projector's array: the next call
            overwrites it); else the term's exact blocks of the marked pairs (:meth:`hessian_of_vertices`, on the
            host) projected by :func:`~sim_core.ti_kernels.block_projection.project_reduced_blocks`, which
            rebuilds only the blocks with a negative eigenvalue.

    Returns:
        :class:`~sim_core.energies.base.HessianBlocks` or :class:`~sim_core.ti_kernels.buffers.DeviceHessianBlocks`
        ``(c, 12, 12)`` (N/m) of the marked pairs, in the term's order.

    Raises:
        ValueError: unknown projection or method.
    """
    # Taichi kernels: a Taichi backend
    from sim_core.ti_kernels.block_projection import DEVICE_KERNELS, project_reduced_blocks
    from sim_core.ti_kernels.buffers import DeviceHessianBlocks, DeviceRows

    kept = term.hessian_on_device(x) if projector is not None and method in DEVICE_KERNELS and declares(
        term, DeviceHessian) else None
    if kept is not None:
        rows = np.flatnonzero(np.asarray(vertices)[kept.vertices[:, 0]])
        out = projector.project(kept.blocks.array, kept.blocks.start, rows, projection, method)
        return DeviceHessianBlocks(kept.vertices[rows], DeviceRows(out, 0, rows.size))
    exact = term.hessian_of_vertices(x, "none", vertices)
    blocks = np.array(exact.blocks, dtype=np.float64)  # an own copy, projected in place
    return HessianBlocks(exact.vertices, project_reduced_blocks(blocks, projection, method))
