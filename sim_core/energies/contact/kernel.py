"""Vertex-triangle and edge-edge penalty contact with the pair distances on Taichi kernels.

:class:`TiVertexTriangleContact` and :class:`TiEdgeEdgeContact` subclass the NumPy reference
potentials of :mod:`sim_core.energies.contact.reference` and replace only the contact distance and its
derivatives (:mod:`sim_core.energies.contact.distance_kernel`); the penalty algebra, side handling,
and ``parameter_gradient`` stay the reference's. The distances and gradients equal the reference
bit for bit, the distance Hessians to round-off (1e-15 relative). On its own, every pair is
measured by the kernel (no NumPy prefilter: the kernel is cheaper than the NumPy bounds). The contact frames (friction's
closest-point weights and normals) come from one launch of
:func:`sim_core.energies.contact.setup_kernel.contact_frames` (equal to the reference to round-off).
Linked by a :class:`~sim_core.energies.contact.batch_kernel.PairBatch`, a vertex-triangle and an edge-edge
potential are evaluated together, one launch for both, with the distance bounds inside the kernel
(same results).
"""

from __future__ import annotations

import numpy as np

from sim_core.collision.distances import DistanceDerivatives
from sim_core.energies.base import positions_key
from sim_core.energies.contact import distance_kernel as contact_distance, setup_kernel as contact_setup
from sim_core.energies.contact.gradient_kernel import add_rows_on_device
from sim_core.energies.contact.reference import ContactFrames, EdgeEdgeContact, PairEvaluation, VertexTriangleContact
from sim_core.ti_kernels.buffers import DeviceHessianBlocks
from sim_core.workspace import workspace_of


def _frames(pot, x: np.ndarray, point_first: bool) -> ContactFrames:
    """The reference ``contact_frames`` of ``pot`` with weights and normals from one kernel launch."""
    act, dd = pot._evaluate(x, 0)  # the kept evaluation of x when there is one
    vertices = pot.vertices[act]
    weights, normal = contact_setup.contact_frames(x, vertices, pot.sides[act], point_first)
    return ContactFrames(vertices, weights, normal, pot.stiffness * (pot.eps - dd.d), act)


class _Batched:
    """Evaluation through a :class:`~sim_core.energies.contact.batch_kernel.PairBatch` when the potential
    is linked to one (the contact set links its step's two pair potentials), else on its own."""

    _batch = None

    def kept_evaluation(self, x: np.ndarray, order: int) -> tuple[np.ndarray, DistanceDerivatives] | None:
        """The kept evaluation ``(active, distances)`` of positions ``x`` ``(n, 3)`` if it holds
        derivatives up to ``order`` (0, 1 or 2), else None (see the reference ``_evaluate``)."""
        kept = self._kept(positions_key(x), order)
        return None if kept is None else (kept.active, kept.dd if order > 0 else kept.distances)

    def hessian_on_device(self, x: np.ndarray) -> DeviceHessianBlocks | None:
        """The unprojected Hessian blocks of the active pairs at ``x`` ``(n, 3)`` (capability
        :class:`~sim_core.energies.base.DeviceHessian`) when the pair batch kept them on the device
        (:attr:`~sim_core.energies.contact.batch_kernel.PairBatch.device_hessian`), else None."""
        if self._batch is None:
            return None
        evaluation = self._evaluation(x, 2)
        blocks = evaluation.hessian_blocks
        if (evaluation.active.size == 0 or blocks is None or blocks[0] != self.stiffness
                or isinstance(blocks[1], np.ndarray)):
            return None
        return DeviceHessianBlocks(evaluation.active_vertices(self.vertices), blocks[1])

    def gradient_rows(self, x: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """:meth:`gradient` as the rows of the pairs' distinct vertices (capability
        :class:`~sim_core.energies.base.SparseGradient`) where the pair batch summed them there, else
        ``(None, gradient)``."""
        return self._evaluation(x, 1).gradient_rows(self.stiffness, self.vertices)

    def add_gradient_on_device(self, x: np.ndarray, x_device: object, gradient_device: object) -> float:
        """Add :meth:`gradient` at ``x`` ``(n, 3)`` (m) into the Taichi float64 ndarray ``gradient_device`` ``(n, 3)``
        (N) on the device, the pair batch reading the positions from ``x_device`` (their ndarray) when it evaluates
        (capability :class:`~sim_core.energies.base.DeviceGradient`; the host's ``g[vertices] += rows``, the same
        sums); returns :meth:`energy` at ``x`` (J). The evaluation of ``x`` is kept as :meth:`gradient` keeps it
        (the Hessian at ``x`` then needs no launch)."""
        if self._batch is None:
            add_rows_on_device(gradient_device, None, self.gradient(x))
            return self.energy(x)
        evaluation = self._evaluation(x, 1, x_device)
        summed = evaluation.summed_rows(self.stiffness)
        if summed is not None:
            self._batch.add_gradient(gradient_device, summed)
        else:  # an evaluation made for another stiffness or without the batch: the host's gradient
            vertices, rows = evaluation.gradient_rows(self.stiffness, self.vertices)
            add_rows_on_device(gradient_device, vertices, rows)
        return evaluation.energy(self.stiffness)

    def add_copy_energies_on_device(self, x: np.ndarray, x_device: object, copy_of_vertex: np.ndarray,
                                    sums: object) -> bool:
        """Add :meth:`copy_energies` at ``x`` ``(n, 3)`` (J by copy) into ``sums`` (a
        :class:`~sim_core.ti_kernels.copy_vectors.CopySums` over ``copy_of_vertex``; capability
        :class:`~sim_core.energies.base.DeviceCopyEnergies`) where the pair batch's last launch measured ``x``: its
        distances summed by copy where they are (:meth:`~sim_core.energies.contact.batch_kernel.PairBatch.
        add_copy_energies`), nothing read back; True with nothing added where ``x``'s kept evaluation has no active
        pair; False (nothing added) without such an evaluation or launch (``x_device`` is not read: the distances
        are the launch's)."""
        if self._batch is None:
            return False
        key = positions_key(x)
        kept = self._kept(key, 0)
        if kept is None:
            return False
        if kept.active.size == 0:
            return True
        return self._batch.add_copy_energies(self, key, copy_of_vertex, sums)

    def _evaluation(self, x: np.ndarray, order: int, x_device: object = None) -> PairEvaluation:
        if self._batch is None:
            return super()._evaluation(x, order)
        key = positions_key(x)
        kept = self._kept(key, order)
        if kept is None:
            self._batch.evaluate(x, order > 0, key, x_device)
            kept = workspace_of(self).get(self, "evaluation")
        return kept


class TiVertexTriangleContact(_Batched, VertexTriangleContact):
    """:class:`~sim_core.energies.contact.reference.VertexTriangleContact` on the Taichi distance kernels
    (same arguments and errors; needs :func:`sim_core.ti_backend.init_backend`)."""

    def _distance(self, z: np.ndarray, side: np.ndarray, order: int) -> DistanceDerivatives:
        return contact_distance.point_triangle_contact_distance(z, side, order)

    def _active_distances(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self._distance(z, self.sides, 0).d
        active = np.flatnonzero(d < self.eps)
        return active, d[active]

    def contact_frames(self, x: np.ndarray) -> ContactFrames:
        """As the reference :meth:`~sim_core.energies.contact.reference.VertexTriangleContact.contact_frames`
        (weights and normals from :func:`sim_core.energies.contact.setup_kernel.contact_frames`)."""
        return _frames(self, x, True)


class TiEdgeEdgeContact(_Batched, EdgeEdgeContact):
    """:class:`~sim_core.energies.contact.reference.EdgeEdgeContact` on the Taichi distance kernels
    (same arguments and errors; needs :func:`sim_core.ti_backend.init_backend`)."""

    def _distance(self, z: np.ndarray, side: np.ndarray, order: int) -> DistanceDerivatives:
        return contact_distance.edge_edge_contact_distance(z, side, order)

    def _active_distances(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self._distance(z, self.sides, 0).d
        active = np.flatnonzero(d < self.eps)
        return active, d[active]

    def contact_frames(self, x: np.ndarray) -> ContactFrames:
        """As the reference :meth:`~sim_core.energies.contact.reference.EdgeEdgeContact.contact_frames`
        (weights and normals from :func:`sim_core.energies.contact.setup_kernel.contact_frames`)."""
        return _frames(self, x, False)
