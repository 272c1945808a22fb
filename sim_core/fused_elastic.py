"""All elastic terms of a Newton iteration in one call: energy, gradient and exact Hessian values.

The Newton loop needs, per iteration, the elastic energy, its gradient and its exact Hessian
assembled into the upper triangle of the Newton matrix. Through the reference potentials that is
three calls per potential, per-element blocks ``(k, 3m, 3m)`` and a ``bincount`` over every block
entry (:meth:`sim_core.assembly.HessianAssembler.assemble_upper`). :class:`FusedElastic` instead
launches one Taichi kernel per potential (``sim_core/energies/<energy>/fused_*kernel.py``) that computes energy,
gradient and exact Hessian together and adds the Hessian entries straight into the values of the
assembler's static pattern through precomputed slot maps
(:meth:`sim_core.assembly.StaticPattern.slot_map`); the line search calls energy-only kernels,
or the fused ones (:meth:`FusedElastic.evaluate`) at a first trial point that, once accepted, is the
next iterate (its gradient and Hessian are then read from the kept evaluation).

Potentials without a fused kernel (hinge bending) are evaluated through their
reference methods and added through the same slot maps, so any mix of elastic terms works. The
PSD-projected Hessian, which the solver needs in the iterations where PARDISO's Cholesky refuses
the exact matrix, goes into the same slots (:meth:`FusedElastic.projected_hessian_values`):
Kirchhoff bending computes its exact per-triangle blocks in Taichi and eigen-decomposes only the
blocks a Cholesky test does not prove definite (:mod:`sim_core.ti_kernels.block_projection`);
Stable Neo-Hookean and StVK membranes use the analytic / Jacobi projections of their Taichi twins
(:mod:`sim_core.energies.neohookean.kernel`, :mod:`sim_core.energies.membrane.kernel`).

On CUDA every array argument of a launch that is a NumPy array is copied to the device and back;
there the fused parts keep their constant arrays (elements, rest shapes, slot tables) on the device
(:func:`sim_core.ti_kernels.buffers.on_device`), and an evaluation uploads the positions once for all parts
and leaves the gradient and Hessian values in device memory, copied to the host once each when asked for
(:meth:`FusedElastic._on_device`); the parts' kernels are launched one after another and their energy sums read
after the last (:class:`sim_core.ti_kernels.launch.DeferredSums`), so the host does not wait for each part's kernel.
A caller that keeps its positions and gradient in device memory (the lockstep batch) evaluates through
:meth:`FusedElastic.add_gradient_on_device` (capability :class:`~sim_core.energies.base.DeviceGradient`): the
kernels read its positions and the gradient is added into its array there, with no transfer.

Needs :func:`sim_core.ti_backend.init_backend` (``--arch cpu|cuda``).
"""

from __future__ import annotations

import importlib
from typing import Protocol, Sequence, runtime_checkable

import numpy as np

from sim_core.assembly import StaticPattern
from sim_core.energies import green_strain, kirchhoff_bending, membrane, neohookean
from sim_core.energies.base import CopyEnergies, ElasticEquivalent, declares, positions_key
from sim_core.worker_recipe import Recipe


OFFLOAD_MIN_ELEMENTS = 256
"""A part with fewer elements is not worth a worker's round trip (tens of microseconds)."""


FUSED_KERNELS: dict[tuple[str, str], tuple[str, str]] = {
    **neohookean.FUSED_KERNELS, **green_strain.FUSED_KERNELS, **membrane.FUSED_KERNELS,
    **kirchhoff_bending.FUSED_KERNELS,
    ("sim_core.candidates.anisotropic_bending", "AnisotropicBendingCorrection"):
        ("sim_core.energies.hinge_bending.fused_kernel", "FusedAnisotropicBending"),
}
"""The registry of fused kernels: potential class -> fused part class, both as (module, name), from
the energy folders' registrations (``FUSED_KERNELS`` in ``sim_core/energies/<energy>/__init__.py``)
and the candidate terms'.
A potential's class or its nearest registered base class selects the part; the Taichi modules
are imported on first use (importing Taichi is optional and heavy)."""


@runtime_checkable
class Offloadable(Protocol):
    """A fused part that :class:`~sim_core.elastic_worker.ElasticWorker` can evaluate."""

    element_count: int

    def offload_recipe(self) -> tuple[str, tuple]:
        """``(kernel name, arguments)`` of its fused evaluation, for the worker."""
        ...


@runtime_checkable
class OffloadableProjected(Protocol):
    """A fused part whose PSD-projected Hessian the worker can evaluate."""

    def offload_projected_recipe(self, projection: str) -> tuple[str, tuple]:
        """``(kernel name, arguments)`` of its projected-Hessian evaluation, for the worker."""
        ...


def _fused_class(potential) -> type | None:
    """The fused part class registered (:data:`FUSED_KERNELS`) for ``potential``'s class or its
    nearest registered base class, or None."""
    for cls in type(potential).__mro__:
        entry = FUSED_KERNELS.get((cls.__module__, cls.__qualname__))
        if entry is not None:
            return getattr(importlib.import_module(entry[0]), entry[1])
    return None


def fusable(potential) -> bool:
    """Whether a fused part evaluates ``potential`` (an elastic potential with a fused kernel, or a
    candidate term with one or with an ``elastic_equivalent()`` that has one)."""
    return _fused_class(_fused_form(potential)) is not None


def _fused_form(potential):
    """The potential a part evaluates for ``potential``: its ``elastic_equivalent()`` when it is an
    :class:`~sim_core.energies.base.ElasticEquivalent` (a candidate term equal to an elastic
    potential, e.g. the gel's Maxwell branch, a Stable Neo-Hookean on its relaxed rest state:
    :mod:`sim_core.candidates.gel_viscoelasticity`), else itself."""
    return potential.elastic_equivalent() if isinstance(potential, ElasticEquivalent) else potential


class _ReferencePart:
    """A potential without a fused kernel: its reference energy, gradient and exact Hessian blocks,
    added to the static values through a slot map of its block vertices."""

    ELEMENT_ARRAYS = ("triangles", "edges", "hinges", "tets")
    """Element arrays a replacement potential must share (same objects) to reuse the slot map."""

    def __init__(self, potential) -> None:
        self.potential = potential
        self.vertices: np.ndarray | None = None  # block vertices: set by FusedElastic.block_vertex_arrays
        self._slots: np.ndarray | None = None
        self._pattern: StaticPattern | None = None

    def accepts(self, potential) -> bool:
        """Same type and the same element arrays (rest angles and other parameters may differ)."""
        p = self.potential
        return type(potential) is type(p) and all(
            getattr(potential, k, None) is getattr(p, k, None) for k in self.ELEMENT_ARRAYS)

    def update(self, potential) -> None:
        """Evaluate ``potential`` from now on."""
        self.potential = potential

    def bind(self, pattern: StaticPattern) -> None:
        """Use ``pattern``'s slots (the map is built at the next evaluation)."""
        self._pattern = pattern
        self._slots = None

    def energy(self, x: np.ndarray) -> float:
        """The reference energy in J."""
        return float(self.potential.energy(x))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray | None:
        """The reference potential's energy split by copy (J, ``(copy_count,)``) where it declares
        :class:`~sim_core.energies.base.CopyEnergies`, else None."""
        if not declares(self.potential, CopyEnergies):
            return None
        return self.potential.copy_energies(x, copy_of_vertex, copy_count)

    def evaluate(self, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
        """Energy (returned); adds the reference gradient to ``grad`` and the exact blocks to ``values``.

        Raises:
            RuntimeError: the potential's Hessian blocks are over another vertex array than the one
                the pattern was built from.
        """
        grad += self.potential.gradient(x)
        blocks = self.potential.hessian(x, "none")
        self._add_blocks(blocks, values)
        return float(self.potential.energy(x))

    def _add_blocks(self, blocks, values: np.ndarray) -> None:
        """Sum ``blocks`` (the potential's ``HessianBlocks``) into the pattern's slot ``values``."""
        if blocks.vertices is not self.vertices:
            raise RuntimeError(f"FusedElastic: {type(self.potential).__name__} changed its Hessian-block vertex array")
        if self._slots is None:
            self._slots = self._pattern.slot_map(blocks.vertices)
        keep = self._slots >= 0
        values += np.bincount(self._slots[keep], weights=blocks.blocks[keep], minlength=values.size)

    def add_projected(self, x: np.ndarray, projection: str, values: np.ndarray) -> None:
        """Add the reference ``projection`` Hessian blocks into ``values`` (slot map of :meth:`evaluate`).

        Raises:
            ValueError: unknown projection.
            RuntimeError: the potential's Hessian blocks are over another vertex array than the one
                the pattern was built from.
        """
        blocks = self.potential.hessian(x, projection)
        self._add_blocks(blocks, values)


class FusedElastic:
    """Energy, gradient and exact Hessian values of a list of elastic potentials, fused per potential.

    Build with :meth:`for_terms` once per step (cheap when the terms are those of the last step);
    then per Newton iterate ``x``: :meth:`gradient` or :meth:`add_gradient_on_device` (runs the fused
    kernels, keeps energy and Hessian values of ``x``), :meth:`hessian_values`, and :meth:`energy` for
    line-search points.
    Follows the energy/gradient half of the potential contract (``sim_core.energies.base``), so
    the solver can sum it with the other terms.

    Args:
        potentials: the step's elastic potentials (:meth:`sim_core.elastic.ElasticTerms.potentials`),
            and candidate terms with an ``elastic_equivalent()`` (evaluated as that potential).

    Attributes:
        vertex_arrays: the Hessian-block vertex array of each potential, in order (the static
            pattern of the solver's assembler is built from these arrays).
        pattern: the bound :class:`~sim_core.assembly.StaticPattern` (see :meth:`bind`).
    """

    parameter_names: tuple[str, ...] = ()

    def __init__(self, potentials: Sequence) -> None:
        self._parts = []
        for p in potentials:
            q = _fused_form(p)
            cls = _fused_class(q)
            self._parts.append(cls(q) if cls is not None else _ReferencePart(q))
        self._offloadable = [isinstance(p, Offloadable) for p in self._parts]
        self.potentials = list(potentials)
        self.vertex_arrays: list[np.ndarray] | None = None
        self.pattern: StaticPattern | None = None
        self._kept: tuple | None = None  # (positions_key(x), energy, gradient, values): the evaluation buffers
        self._buffers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.offload = None  # an ElasticWorker (sim_core.elastic_worker), set by the solver; None: all here
        self._offload_buffers: tuple[np.ndarray, np.ndarray] | None = None  # the offloaded part's, when local
        self._recipes: dict[str, Recipe] = {}  # the last worker recipes ("part", "all", "projected")
        self._pending: tuple | None = None  # positions_key of a start() whose result is not taken yet
        self._device_kept: tuple | None = None  # on CUDA: device positions, gradient, values (_device_buffers)
        self._values_on_device = False  # the kept evaluation's Hessian values are on the device only
        self._gradient_on_host = False  # the kept evaluation's gradient is in its host array (_kept[2])
        self._gradient_on_device = False  # ... in the device gradient array (_device_kept[1], CUDA)
        self._sums = None  # on CUDA: the DeferredSums of the device evaluations (its cells kept)
        self._device_x_key = None  # on CUDA: positions_key of the positions in the device positions array
        self._projected_device = None  # on CUDA: the projected Hessian values (projected_hessian_values_device)

    @classmethod
    def for_terms(cls, current: "FusedElastic | None", potentials: Sequence) -> "FusedElastic":
        """``current`` updated to ``potentials`` (new rest angles) when it has the same elements, else a new one."""
        forms = [_fused_form(p) for p in potentials]
        if current is not None and len(current._parts) == len(potentials) and all(
                part.accepts(q) for part, q in zip(current._parts, forms)):
            current._drop_pending()
            for part, q in zip(current._parts, forms):
                part.update(q)
            current.potentials = list(potentials)
            current._kept = None
            return current
        return cls(potentials)

    def block_vertex_arrays(self, x: np.ndarray) -> list[np.ndarray]:
        """The Hessian-block vertex arrays of the potentials (reference parts: from one Hessian at ``x``)."""
        if self.vertex_arrays is None:
            for part in self._parts:
                if isinstance(part, _ReferencePart):
                    part.vertices = part.potential.hessian(x, "none").vertices
            self.vertex_arrays = [part.vertices for part in self._parts]
        return self.vertex_arrays

    def bind(self, pattern: StaticPattern) -> None:
        """Use ``pattern`` (built from :meth:`block_vertex_arrays` and the step's free mask) from now on."""
        if pattern is not self.pattern:
            self._drop_pending()
            for part in self._parts:
                part.bind(pattern)
            self.pattern = pattern
            self._kept = None

    def _evaluate(self, x: np.ndarray) -> tuple:
        kept = self._kept
        key = positions_key(x)
        if kept is not None and kept[0] == key:
            return kept
        if self.pattern is None:
            raise RuntimeError("FusedElastic: bind(pattern) before evaluating")
        self._forget()
        xc, grad, values = self._evaluation_buffers(np.shape(x))
        pending, self._pending = self._pending, None
        if pending is not None:  # every part evaluated in the worker since start()
            result = self.offload.finish()
            if pending == key and result is not None:
                energy, remote_grad, remote_values = result
                np.copyto(xc, x)
                np.copyto(grad, remote_grad)
                np.copyto(values, remote_values)
                return self._keep(key, energy, grad, values)
        np.copyto(xc, x)
        remote = self.offloaded_part()
        if remote is None and self._on_device():
            # CUDA: positions up once per evaluation, not per part; the gradient and Hessian values stay there
            # until asked for (gradient, hessian_values)
            xd = self._upload_positions(xc, key, values.size)
            return self._evaluate_on_device(key, xd, grad, values)
        grad.fill(0.0)
        values.fill(0.0)
        if remote is None:
            energy = 0.0
            for part in self._parts:
                energy += part.evaluate(xc, grad, values)
        else:
            energy = self._evaluate_offloaded(remote, xc, grad, values)
        return self._keep(key, energy, grad, values)

    def _forget(self) -> None:
        """Drop the kept evaluation (its arrays are about to be overwritten)."""
        self._kept = None
        self._values_on_device = self._gradient_on_device = self._gradient_on_host = False

    def _keep(self, key, energy: float, grad: np.ndarray, values: np.ndarray, on_device: bool = False) -> tuple:
        """Keep the evaluation of positions ``key``: energy (J; or a callable reading it, :meth:`_deferred_sum`'s
        ``read=False``), the gradient and Hessian values in the host arrays ``grad`` and ``values``, or, ``on_device``,
        in the device arrays of :meth:`_device_buffers` (CUDA)."""
        self._kept = (key, energy if callable(energy) else float(energy), grad, values)
        self._gradient_on_host = not on_device
        self._gradient_on_device = self._values_on_device = on_device
        return self._kept

    def _evaluate_on_device(self, key, x_device, grad: np.ndarray, values: np.ndarray) -> tuple:
        """The parts' kernels at the device positions ``x_device`` ``(n, 3)`` (m) into the zeroed device gradient and
        Hessian values of :meth:`_device_buffers` (CUDA, every part a device part), kept for positions ``key``; the
        host arrays ``grad`` and ``values`` are filled from them when asked for. The parts' energy sums are read
        when first asked for (:meth:`_kept_energy`: one copy back, after the last launch; :meth:`_deferred_sum`), so
        that the host goes on launching while the device runs them."""
        from sim_core.ti_kernels.transfer import fill  # Taichi only on a Taichi backend

        _, gd, vd = self._device_buffers(grad.shape, values.size)
        fill(gd, 0.0)
        fill(vd, 0.0)
        energy = self._deferred_sum(lambda part: part.evaluate(x_device, gd, vd), 0.0, read=False)
        return self._keep(key, energy, grad, values, on_device=True)

    def add_gradient_on_device(self, x: np.ndarray, x_device, gradient_device) -> float:
        """Add the elastic gradient at ``x`` (N) into the device array ``gradient_device``; the energy (J) returned
        (capability :class:`~sim_core.energies.base.DeviceGradient`).

        The parts' kernels read the positions from ``x_device`` (no upload) and the evaluation is kept for ``x``
        (:func:`~sim_core.energies.base.positions_key`) as :meth:`evaluate` keeps it: the next :meth:`energy`,
        :meth:`gradient`, :meth:`hessian_values` and :meth:`hessian_values_device` at ``x`` read it; an evaluation
        already kept for ``x`` is added without running the kernels again. On CUDA, with every part a device part,
        the gradient and Hessian values stay in device memory (the gradient added there by one launch); elsewhere
        (the CPU arch: ``x_device`` is host memory; parts without a fused kernel read ``x``; an offloaded part or a
        :meth:`start` pending) the gradient is formed in host memory as :meth:`gradient` forms it and added into
        ``gradient_device`` by one launch.

        Args:
            x: positions ``(n, 3)`` (m), the key of the kept evaluation.
            x_device: the same positions, a float64 Taichi ndarray ``(n, 3)``, only read.
            gradient_device: a float64 Taichi ndarray ``(n, 3)``, the gradient added into it.

        Returns:
            the elastic energy at ``x`` (J), or None where the device evaluation's energy was not read yet (on CUDA:
            :meth:`energy` at ``x`` reads it).

        Raises:
            RuntimeError: :meth:`bind` was not called.
            ValueError: ``x_device`` or ``gradient_device`` is not of ``x``'s shape.
        """
        from sim_core.ti_backend import current_arch
        from sim_core.ti_kernels.transfer import add_into, same_shapes, upload  # Taichi only on a Taichi backend

        shape = same_shapes("FusedElastic.add_gradient_on_device", x, x_device, gradient_device)
        key = positions_key(x)
        kept = self._kept
        if kept is None or kept[0] != key:
            if self.pattern is None:
                raise RuntimeError("FusedElastic: bind(pattern) before evaluating")
            if self._pending is not None or self.offloaded_part() is not None:
                kept = self._evaluate(x)
            elif self._on_device():
                self._forget()
                _, grad, values = self._evaluation_buffers(shape)
                kept = self._evaluate_on_device(key, x_device, grad, values)
            elif current_arch() == "cuda":  # a part without a device kernel: the host evaluation
                kept = self._evaluate(x)
            else:  # the CPU arch: the kernels read the device (host-memory) positions, into the host arrays
                kept = self._evaluate_at(key, x, x_device)
        if self._gradient_on_device:
            add_into(gradient_device, self._device_kept[1])
        elif current_arch() == "cuda":  # the host gradient up once into the device gradient array, kept there
            add_into(gradient_device, upload(self._device_buffers(shape, kept[3].size)[1], kept[2]))
            self._gradient_on_device = True
        else:
            add_into(gradient_device, kept[2])
        return None if callable(kept[1]) else kept[1]

    def _kept_energy(self) -> float:
        """The kept evaluation's energy (J), read from the device where it is still there (one copy back)."""
        kept = self._kept
        if callable(kept[1]):
            kept = self._kept = (kept[0], float(kept[1]()), kept[2], kept[3])
        return kept[1]

    def _evaluate_at(self, key, x: np.ndarray, x_device) -> tuple:
        """:meth:`_evaluate`'s host loop with the fused parts' kernels reading ``x_device`` (a Taichi ndarray in host
        memory: the CPU arch) and the other parts ``x``: the same kernels on the same values, the same sums."""
        self._forget()
        _, grad, values = self._evaluation_buffers(np.shape(x))
        grad.fill(0.0)
        values.fill(0.0)
        energy = 0.0
        for part in self._parts:
            energy += part.evaluate(x if isinstance(part, _ReferencePart) else x_device, grad, values)
        return self._keep(key, energy, grad, values)

    def offloaded_part(self):
        """The part evaluated apart (in :attr:`offload`'s worker when it is up): with a worker set, the
        part with an ``offload_recipe`` and the most elements (at least :data:`OFFLOAD_MIN_ELEMENTS`),
        when there are other parts to evaluate meanwhile; else None. Depends on the configuration
        only, not on the worker's state, so results do not either (:meth:`_evaluate_offloaded`)."""
        if self.offload is None or len(self._parts) < 2:
            return None
        parts = [p for p, able in zip(self._parts, self._offloadable)
                 if able and p.element_count >= OFFLOAD_MIN_ELEMENTS]
        return max(parts, key=lambda p: p.element_count) if parts else None

    def start(self, x: np.ndarray) -> None:
        """Begin evaluating every part at ``x`` ``(n, 3)`` in :attr:`offload`'s worker, when it is up
        and every part has an ``offload_recipe`` (else nothing happens); the next evaluation at equal
        positions takes the result. The solver calls this with a step's first iterate, whose
        evaluation then runs while it sets up the step's contact and friction terms. The sums are
        those of :meth:`_evaluate` (the offloaded part apart, added after the others), so results do
        not depend on whether it ran.

        Raises:
            RuntimeError: :meth:`bind` was not called.
        """
        if self.offload is None or self._pending is not None:
            return
        if self.pattern is None:
            raise RuntimeError("FusedElastic: bind(pattern) before evaluating")
        if not all(self._offloadable):
            return
        key = positions_key(x)
        if self._kept is not None and self._kept[0] == key:
            return
        remote = self.offloaded_part()
        apart = None if remote is None else next(i for i, p in enumerate(self._parts) if p is remote)
        recipe = self._recipe("all", tuple(p.offload_recipe() for p in self._parts), apart)
        xc, _, values = self._evaluation_buffers(np.shape(x))
        np.copyto(xc, x)
        if self.offload.begin(recipe, xc, values.size):
            self._pending = key

    def _drop_pending(self) -> None:
        """Wait for and drop the result of a :meth:`start` not taken."""
        if self._pending is not None:
            self._pending = None
            self.offload.finish()

    def _recipe(self, name: str, parts: tuple, apart: int | None) -> Recipe:
        """The kept :class:`~sim_core.elastic_worker.Recipe` ``name`` when its parts are the same objects
        (the parts keep theirs while nothing changes), else a new one: the worker recognises it by identity."""
        kept = self._recipes.get(name)
        if kept is None or kept.apart != apart or len(kept.parts) != len(parts) or any(
                a is not b for a, b in zip(kept.parts, parts)):
            kept = self._recipes[name] = Recipe(parts, apart)
        return kept

    def _evaluate_offloaded(self, remote, xc: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
        """Energy (J); the gradient and Hessian values of all parts added into ``grad`` and ``values``
        (zeroed), with ``remote`` evaluated into separate zeroed buffers, by the worker while this
        process evaluates the other parts, or here when the worker is not up (or fails), and added
        after them; the energies summed in part order. Where no other part touches ``remote``'s
        vertices (a gel beside a sheet) the sums are those of :meth:`_evaluate`'s loop bit for bit."""
        started = self.offload.begin(self._recipe("part", (remote.offload_recipe(),), None), xc, values.size)
        energies = []
        try:
            for part in self._parts:
                energies.append(None if part is remote else part.evaluate(xc, grad, values))
        finally:
            result = self.offload.finish() if started else None
        if result is None:
            buffers = self._offload_buffers
            if buffers is None or buffers[0].shape != grad.shape or buffers[1].size != values.size:
                buffers = self._offload_buffers = (np.zeros(grad.shape), np.zeros(values.size))
            remote_grad, remote_values = buffers
            remote_grad.fill(0.0)
            remote_values.fill(0.0)
            remote_energy = remote.evaluate(xc, remote_grad, remote_values)
        else:
            remote_energy, remote_grad, remote_values = result
        grad += remote_grad
        values += remote_values
        energy = 0.0
        for e in energies:
            energy += remote_energy if e is None else e
        return energy

    def _on_device(self) -> bool:
        """Whether the evaluation runs on device arrays: Taichi on CUDA and every part a fused kernel
        part whose constant arrays live on the device (``_device``, :func:`~sim_core.ti_kernels.buffers.on_device`)."""
        from sim_core.ti_backend import current_arch

        return current_arch() == "cuda" and all(getattr(p, "_device", None) is not None for p in self._parts)

    def _upload_positions(self, xc: np.ndarray, key, nnz: int):
        """``xc`` ``(n, 3)`` (m) copied into the device positions array of :meth:`_device_buffers` (``nnz`` Hessian
        values), kept as the positions of ``key`` (:meth:`device_positions`); the array returned."""
        from sim_core.ti_kernels.transfer import upload  # Taichi only on a Taichi backend

        xd = self._device_buffers(xc.shape, nnz)[0]
        self._device_x_key = None
        upload(xd, xc)
        self._device_x_key = key
        return xd

    def device_positions(self, x: np.ndarray):
        """The device array (a float64 Taichi ndarray ``(n, 3)``, only to be read) that holds the positions ``x``
        (m) where the last evaluation here copied them (CUDA), or None: other terms' kernels may read them there
        instead of copying them again (:func:`~sim_core.ti_kernels.transfer.positions_on_device`)."""
        kept = self._device_kept
        if kept is None or self._device_x_key is None or self._device_x_key != positions_key(x):
            return None
        return kept[0]

    def offer_positions(self, workspace) -> None:
        """On CUDA, let the terms sharing ``workspace`` (:class:`~sim_core.workspace.Workspace`) read the positions this
        evaluator copies to the device (:meth:`device_positions`,
        :func:`~sim_core.ti_kernels.transfer.offer_positions`); elsewhere nothing is done."""
        if self._on_device():
            from sim_core.ti_kernels.transfer import offer_positions  # Taichi only on a Taichi backend

            offer_positions(workspace, self)

    def _device_buffers(self, shape: tuple, nnz: int) -> tuple:
        """Device arrays (Taichi ndarrays) for positions ``shape``, gradient ``shape`` and ``nnz`` Hessian values."""
        from sim_core.ti_backend import ti

        kept = self._device_kept
        if kept is None or tuple(kept[0].shape) != tuple(shape) or kept[2].shape != (max(nnz, 1),):
            self._device_x_key = None
            kept = self._device_kept = (ti.ndarray(ti.f64, shape=tuple(shape)), ti.ndarray(ti.f64, shape=tuple(shape)),
                                        ti.ndarray(ti.f64, shape=(max(nnz, 1),)))
        return kept

    def _evaluation_buffers(self, shape: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The positions ``shape``, gradient ``shape`` and Hessian-value ``(pattern.keys.size,)`` arrays
        the kernels read and add into, float64, kept from one evaluation to the next (the kernels'
        launches then bind no new arrays: :mod:`sim_core.ti_kernels.launch`); new ones when the
        shapes change."""
        buffers = self._buffers
        if buffers is None or buffers[0].shape != shape or buffers[2].size != self.pattern.keys.size:
            zeros = np.zeros
            from sim_core.ti_backend import current_arch

            if current_arch() == "cuda":  # the positions and gradient cross at every evaluation: page-locked memory
                from sim_core.ti_kernels.device_copy import pinned_zeros as zeros  # Taichi only on a Taichi backend
            buffers = self._buffers = (zeros(shape), zeros(shape), np.zeros(self.pattern.keys.size))
        return buffers

    def evaluate(self, x: np.ndarray) -> None:
        """Run the fused kernels at ``x`` ``(n, 3)`` (m) and keep energy, gradient and Hessian values:
        the next :meth:`energy`, :meth:`gradient` and :meth:`hessian_values` at equal positions read
        them (the Newton line search evaluates a trial point this way when, once accepted, it is the
        next iterate, whose gradient and Hessian are needed).

        Raises:
            RuntimeError: :meth:`bind` was not called.
        """
        self._evaluate(x)

    def energy(self, x: np.ndarray) -> float:
        """Elastic energy in J at ``x`` ``(n, 3)`` (energy-only kernels unless ``x`` was evaluated; on
        CUDA the positions travel to the device once for all parts)."""
        kept = self._kept
        if kept is not None and kept[0] == positions_key(x):
            return self._kept_energy()
        xc = np.ascontiguousarray(x, dtype=np.float64)
        if self.pattern is not None and self.offloaded_part() is None and self._on_device():
            xd = self._upload_positions(xc, positions_key(x), self.pattern.keys.size)
            return float(self._deferred_sum(lambda part: part.energy(xd), 0))
        return float(sum(part.energy(xc) for part in self._parts))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray | None:
        """:meth:`energy` at ``x`` ``(n, 3)`` split by copy, J ``(copy_count,)`` (capability
        :class:`~sim_core.energies.base.CopyEnergies`): each part's energy kernel with one sum cell an element, its
        cells summed by the copy of the element's first vertex (on CUDA the positions travel to the device once for
        all parts); None when a part cannot split its energy. Raises RuntimeError: :meth:`bind` not called (CUDA)."""
        xc = np.ascontiguousarray(x, dtype=np.float64)
        if self.pattern is not None and self._on_device():
            from sim_core.ti_kernels.transfer import upload  # Taichi only on a Taichi backend

            xc = upload(self._device_buffers(xc.shape, self.pattern.keys.size)[0], xc)
        total = np.zeros(copy_count)
        for part in self._parts:
            part_energies = part.copy_energies(xc if not isinstance(part, _ReferencePart) else x, copy_of_vertex,
                                               copy_count)
            if part_energies is None:
                return None
            total += part_energies
        return total

    def add_copy_energies_on_device(self, x: np.ndarray, x_device, copy_of_vertex: np.ndarray, sums) -> bool:
        """:meth:`copy_energies` at ``x`` added into ``sums`` (a :class:`~sim_core.ti_kernels.copy_vectors.CopySums`;
        capability :class:`~sim_core.energies.base.DeviceCopyEnergies`): the parts' kernels reading ``x_device``, their
        cells added where they are; False (nothing added) with a part that has no fused kernel."""
        if any(isinstance(part, _ReferencePart) for part in self._parts):
            return False
        with sums:
            for part in self._parts:
                part.copy_energies(x_device, copy_of_vertex, sums.copy_count)
        return True

    def _deferred_sum(self, run, start: float, read: bool = True):
        """:meth:`~sim_core.ti_kernels.launch.DeferredSums.sum_of` the parts (``run(part)`` each, in one block of
        this term's sums, added to ``start``; ``read`` False: a callable reading the sum, valid until the next block):
        a kept evaluation's energy still on the device (:meth:`_kept_energy`) is read first.

        Raises:
            RuntimeError: a part launched more than one summing kernel.
        """
        from sim_core.ti_kernels.launch import DeferredSums  # Taichi only on a Taichi backend

        if self._kept is not None and callable(self._kept[1]):
            self._kept_energy()
        if self._sums is None:
            self._sums = DeferredSums(shared=True)
        return self._sums.sum_of(self._parts, run, start, read)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)`` (a new array; evaluates energy and Hessian of ``x`` too; on CUDA the
        gradient of a device evaluation is copied to the host when first asked for)."""
        kept = self._evaluate(x)
        if not self._gradient_on_host:
            from sim_core.ti_kernels.transfer import download  # Taichi only on a Taichi backend

            download(self._device_kept[1], kept[2])
            self._gradient_on_host = True
        return kept[2].copy()

    def hessian_values(self, x: np.ndarray) -> np.ndarray:
        """Exact Hessian entries in N/m summed per slot of :attr:`pattern`, shape ``(pattern.keys.size,)``
        (the kept array: the next evaluation at other positions overwrites it). On CUDA the values stay
        on the device after an evaluation and are copied here only when asked for."""
        kept = self._evaluate(x)
        if self._values_on_device:
            from sim_core.ti_kernels.transfer import download  # Taichi only on a Taichi backend

            device = self._device_kept[2]
            if tuple(device.shape) == kept[3].shape:  # (the device array has one entry at least) straight into it
                download(device, kept[3])
            else:
                kept[3][:] = download(device)[: kept[3].size]
            self._values_on_device = False
        return kept[3]

    def hessian_values_device(self, x: np.ndarray):
        """The exact Hessian values of :meth:`hessian_values` as the Taichi ndarray the fused kernels wrote on
        the device (CUDA, every part a device part: at least ``pattern.keys.size`` entries, the kept
        array), or None where the evaluation runs on host arrays."""
        self._evaluate(x)
        return self._device_kept[2] if self._values_on_device else None

    def projected_hessian_values_device(self, x: np.ndarray, projection: str, vertices: np.ndarray | None = None,
                                        closed: bool = False):
        """The values of :meth:`projected_hessian_values` summed on the device, as a float64 Taichi ndarray of
        ``max(pattern.keys.size, 1)`` entries kept here (the next call overwrites it; the exact values of
        :meth:`hessian_values_device` are kept apart), or None where the parts do not all run on device arrays
        (:meth:`_on_device`: CUDA, every part a fused kernel part, none offloaded). The positions go up once; each
        part adds its projected blocks there (``add_projected_on_device``), through the packed upper slot tables of
        the exact Hessian, with no block and no partial sum crossing to the host; every part's element rows are sent
        first (``stage_projected_rows``), so that no synchronous copy between the kernels waits for them. ``closed``:
        the caller's promise that ``vertices`` is closed under every part's elements (whole copies of a stacked scene),
        so that each part finds its marked elements by their first vertex
        (:func:`~sim_core.ti_kernels.block_projection.marked_rows`).

        Raises:
            RuntimeError: :meth:`bind` was not called.
            ValueError: unknown projection.
        """
        if self.pattern is None:
            raise RuntimeError("FusedElastic: bind(pattern) before evaluating")
        if self.offloaded_part() is not None or not self._on_device() or not all(
                hasattr(part, "add_projected_on_device") and hasattr(part, "stage_projected_rows")
                for part in self._parts):
            return None
        from sim_core.ti_backend import ti  # Taichi only on a Taichi backend
        from sim_core.ti_kernels.linalg import projection_code
        from sim_core.ti_kernels.transfer import fill

        projection_code(projection)
        nnz = self.pattern.keys.size
        xd = self._upload_positions(np.ascontiguousarray(x, dtype=np.float64), positions_key(x), nnz)
        if self._projected_device is None or tuple(self._projected_device.shape) != (max(nnz, 1),):
            self._projected_device = ti.ndarray(ti.f64, shape=(max(nnz, 1),))
        for part in self._parts:  # every part's rows sent before the first kernel: no copy waits for one
            subset = getattr(part, "projects_subsets", False)
            part.stage_projected_rows(vertices if subset else None, closed if subset else False)
        values = fill(self._projected_device, 0.0)
        for part in self._parts:
            if getattr(part, "projects_subsets", False):
                part.add_projected_on_device(xd, projection, values, vertices, closed)
            else:
                part.add_projected_on_device(xd, projection, values, None)
        return values

    def projected_hessian_values(self, x: np.ndarray, projection: str,
                                 vertices: np.ndarray | None = None) -> np.ndarray:
        """Hessian entries in N/m with PSD-projected element blocks, summed per slot of :attr:`pattern`.

        Each potential's blocks are projected as its reference ``hessian(x, projection)`` does (the
        same blocks to round-off): Kirchhoff bending through its per-triangle blocks and
        :class:`~sim_core.ti_kernels.block_projection.TranslationFreeProjector`, Stable Neo-Hookean
        and StVK membranes through their Taichi twins, the others through the reference potential.

        Args:
            x: positions ``(n, 3)`` in m.
            projection: "clamp" or "abs" ("none" gives the exact Hessian, element by element).
            vertices: None, or a bool mask ``(n,)`` closed under the elements (every element touching a
                marked vertex has all its vertices marked, as the copies of a stacked scene): then the
                rows and columns of the marked vertices hold the projected Hessian's entries, and those of
                the others only part of them (parts with ``projects_subsets`` project only the elements
                touching marked vertices; a lockstep batch needs the projected matrix of a few copies).

        Returns:
            a new array of shape ``(pattern.keys.size,)``.

        Raises:
            RuntimeError: :meth:`bind` was not called.
            ValueError: unknown projection.
        """
        if self.pattern is None:
            raise RuntimeError("FusedElastic: bind(pattern) before evaluating")
        device = self.projected_hessian_values_device(x, projection, vertices)
        if device is not None:  # CUDA: every part's blocks summed on the device, the sums downloaded once
            from sim_core.ti_kernels.transfer import download  # Taichi only on a Taichi backend

            values = download(device)
            return values if values.size == self.pattern.keys.size else values[: self.pattern.keys.size].copy()
        xc = np.ascontiguousarray(x, dtype=np.float64)
        values = np.zeros(self.pattern.keys.size)
        remote = self.offloaded_part()
        if remote is None or not isinstance(remote, OffloadableProjected):
            for part in self._parts:
                if vertices is not None and getattr(part, "projects_subsets", False):
                    part.add_projected(xc, projection, values, vertices=vertices)
                else:
                    part.add_projected(xc, projection, values)
            return values
        # the offloaded part's projected blocks apart (in the worker meanwhile), added after the others'
        recipe = self._recipe("projected", (remote.offload_projected_recipe(projection),), None)
        self._drop_pending()
        started = self.offload.begin(recipe, xc, values.size)
        try:
            for part in self._parts:
                if part is not remote:
                    part.add_projected(xc, projection, values)
        finally:
            result = self.offload.finish() if started else None
        if result is None:
            remote_values = np.zeros(values.size)
            remote.add_projected(xc, projection, remote_values)
        else:
            remote_values = result[2]
        values += remote_values
        return values
