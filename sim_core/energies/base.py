"""The potential contract shared by every energy term, and sparse assembly of its Hessian.

Every energy in the incremental potential (inertia, gravity, membrane, bending, Stable Neo-Hookean,
contact, friction, ...) is a class in ``sim_core/energies/<energy>/reference.py`` that follows
:class:`Potential`: parameters fixed at construction, positions passed at call time (IPC Toolkit's
convention). Positions are always the *global* vertex array of the model, ``x`` of shape
``(vertex_count, 3)`` in metres; the potential holds global vertex indices of its elements. The
global degree of freedom of vertex ``i``, axis ``d`` is ``3 * i + d``.

Hessians are returned as per-element dense blocks (:class:`HessianBlocks`) which the solver
projects and assembles into one sparse matrix; nothing n x n is ever dense.
"""

from __future__ import annotations

import functools
import weakref
from typing import Literal, NamedTuple, Protocol, Sequence, runtime_checkable

import numpy as np
import scipy.sparse as sp

Projection = Literal["none", "clamp", "abs"]
"""PSD projection of element Hessians: keep as is, clamp negative eigenvalues to 0, or flip them."""


class HessianBlocks(NamedTuple):
    """Dense per-element Hessian blocks of one potential.

    Attributes:
        vertices: global vertex indices of each element, shape ``(element_count, m)``, int64.
        blocks: second derivatives, shape ``(element_count, 3 m, 3 m)``, float64, local DoF order
            vertex-major (local DoF ``3 a + d`` is axis ``d`` of ``vertices[:, a]``). Units:
            J/m^2 (= N/m).
    """

    vertices: np.ndarray
    blocks: np.ndarray

    @staticmethod
    def empty(m: int) -> "HessianBlocks":
        """An element-free block set with ``m`` vertices per element."""
        return HessianBlocks(np.zeros((0, m), dtype=np.int64), np.zeros((0, 3 * m, 3 * m)))


@runtime_checkable
class Potential(Protocol):
    """What every energy term provides.

    ``parameter_names`` lists the scalar parameters ``p`` for which
    :meth:`parameter_gradient` returns ``d(gradient)/dp`` (used by the adjoint, SYSID.md).
    """

    parameter_names: tuple[str, ...]

    def energy(self, x: np.ndarray) -> float:
        """Energy in J at positions ``x`` of shape ``(vertex_count, 3)``."""
        ...

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(vertex_count, 3)`` (zero rows for vertices not involved)."""
        ...

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-element Hessian blocks, PSD-projected per ``projection``."""
        ...

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d(parameter ``name``), shape ``(vertex_count, 3)``.

        Raises:
            KeyError: ``name`` is not in ``parameter_names``.
        """
        ...


# ---------------------------------------------------------------------------- optional capabilities
# What some potentials provide beyond :class:`Potential`. Callers test for a capability with
# ``isinstance(term, <Protocol>)``; the test ``tests/sim_core/energies/test_contract.py`` checks
# that every potential class meets :class:`Potential` and lists the capabilities each one declares.


@runtime_checkable
class ConstantDiagonalHessian(Protocol):
    """A potential whose Hessian is a constant diagonal (inertia, viscous damping): the solver adds
    :meth:`hessian_diagonal` to the Newton matrix's diagonal instead of assembling blocks."""

    def hessian_diagonal(self) -> np.ndarray:
        """The Hessian's diagonal, shape ``(3 vertex_count,)`` in N/m (global DoF order)."""
        ...


@runtime_checkable
class PenaltyContact(Protocol):
    """A penalty contact potential that switches on below its contact offset: its touching entries
    are ``vertices[active_mask(x)]`` (pairs ``(a, 4)``, or vertices ``(a,)`` against a plane or a
    sphere). The solver compares the active sets of two iterates
    (:func:`sim_core.contact_set.active_contacts`)."""

    vertices: np.ndarray

    def active_mask(self, x: np.ndarray) -> np.ndarray:
        """Whether each entry is within the contact offset at ``x`` ``(vertex_count, 3)``: ``(k,)`` bool."""
        ...


@runtime_checkable
class KeepsDerivatives(Protocol):
    """A potential that can evaluate energy, gradient and Hessian at once ahead of time: the line
    search calls :meth:`keep_derivatives` at a trial point that, once accepted, is the next
    iterate, whose gradient and Hessian are then read from the kept evaluation."""

    def keep_derivatives(self, x: np.ndarray) -> None:
        """Evaluate and keep the energy, gradient and Hessian at ``x`` ``(vertex_count, 3)`` m."""
        ...


@runtime_checkable
class HingeBending(Protocol):
    """A bending energy of the dihedral angles of hinges, ``E = d^T K_h d`` with
    ``d = theta - theta_bar`` (diagonal ``K_h`` for discrete-shell bending, coupled for Kirchhoff
    plates); the adjoint differentiates through the rest angles ``theta_bar`` (bending plasticity)."""

    hinges: np.ndarray
    hinge_theta_bar: np.ndarray

    def theta(self, x: np.ndarray) -> np.ndarray:
        """Signed dihedral angle of every hinge in rad, shape ``(h,)``."""
        ...

    def theta_gradient(self, x: np.ndarray) -> np.ndarray:
        """``dtheta/dx`` of every hinge, shape ``(h, 4, 3)`` in 1/m."""
        ...

    def theta_stiffness(self) -> sp.csr_matrix:
        """``A = dE/dtheta dtheta`` = ``2 K_h`` in J/rad^2, sparse ``(h, h)``."""
        ...

    def theta_stiffness_product(self, v: np.ndarray) -> np.ndarray:
        """``A v`` for ``v`` of shape ``(h, r)``, equal to ``theta_stiffness() @ v`` bit for bit."""
        ...


@runtime_checkable
class ElasticEquivalent(Protocol):
    """A term equal to an elastic potential on another rest state (the gel's Maxwell branch: a
    Stable Neo-Hookean on its relaxed rest shape), which the fused elastic kernels evaluate
    through :meth:`elastic_equivalent` (:mod:`sim_core.fused_elastic`)."""

    def elastic_equivalent(self) -> Potential:
        """The elastic potential this term equals now."""
        ...


@runtime_checkable
class SubsetHessian(Protocol):
    """A potential whose Hessian blocks can be evaluated for the entries of some vertices only: the
    lockstep batch's projected retry projects the blocks of the copies it retries, not every copy's
    (:mod:`sim_core.batch.lockstep`)."""

    def hessian_of_vertices(self, x: np.ndarray, projection: Projection, vertices: np.ndarray) -> HessianBlocks:
        """The blocks of :meth:`Potential.hessian` whose first vertex is marked in ``vertices`` (bool
        ``(vertex_count,)``; a mask closed under the entries, e.g. one stacked copy's vertices)."""
        ...


@runtime_checkable
class DeviceHessian(Protocol):
    """A potential whose exact Hessian blocks can stay in the device memory a kernel wrote them to: the
    lockstep batch's CG expands them there (:mod:`sim_core.batch.lockstep`) instead of taking them through
    the host."""

    def hessian_on_device(self, x: np.ndarray) -> object | None:
        """The unprojected blocks of :meth:`Potential.hessian` at ``x`` ``(vertex_count, 3)`` as
        :class:`~sim_core.ti_kernels.buffers.DeviceHessianBlocks`, or None where they are not on the device
        (the caller then asks :meth:`Potential.hessian`)."""
        ...


@runtime_checkable
class SparseGradient(Protocol):
    """A potential whose gradient is non-zero on few vertices and can be given as those vertices' rows: the
    lockstep batch adds the rows into its stacked gradient (:mod:`sim_core.batch.lockstep`) instead of an
    ``(n, 3)`` array a term (14 MB a term at 1024 stacked Forming copies)."""

    def gradient_rows(self, x: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """:meth:`Potential.gradient` at ``x`` ``(vertex_count, 3)`` as ``(vertices, rows)``: the gradient is
        ``rows`` ``(u, 3)`` (N) at the distinct ``vertices`` ``(u,)`` (int) and zero elsewhere; or ``(None, g)``
        with ``g`` the whole ``(vertex_count, 3)`` gradient (gravity's kept constant, given without a copy). The
        caller only reads the arrays."""
        ...


@runtime_checkable
class DeviceGradient(Protocol):
    """A potential that evaluates at positions already in device memory and adds its gradient into a device
    array: the lockstep batch keeps its iterates and stacked gradient on the device on a Taichi backend
    (:mod:`sim_core.batch.lockstep`) and reads back per-copy scalars only."""

    def add_gradient_on_device(self, x: np.ndarray, x_device: object, gradient_device: object) -> float | None:
        """Add :meth:`Potential.gradient` at ``x`` (N) into ``gradient_device``.

        Args:
            x: the positions ``(vertex_count, 3)`` (m) on the host: the caches' key and the host-side set-up's input
                (a read-only iterate, :func:`~sim_core.batch.iterates.frozen`).
            x_device: the same positions as a Taichi float64 ndarray ``(vertex_count, 3)`` (m), only read.
            gradient_device: a Taichi float64 ndarray ``(vertex_count, 3)`` the gradient is added into.

        Returns:
            the energy at ``x`` (J) where the kernels computed it along, else None.
        """
        ...


@runtime_checkable
class CopyEnergies(Protocol):
    """A potential whose energy on a stacked model of disconnected copies (:mod:`sim_core.batch.stacked`) can be
    given per copy: each element's energy added to the copy of its first vertex (an element never joins two
    copies). The lockstep batch tests each copy's line-search step on its own energy
    (:mod:`sim_core.batch.line_search`)."""

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray | None:
        """:meth:`Potential.energy` at ``x`` ``(vertex_count, 3)`` split by copy (J), shape ``(copy_count,)``:
        its sum is the energy to round-off. ``copy_of_vertex``: the copy of each vertex, int ``(vertex_count,)``.
        None where the term cannot split its energy (e.g. a part without element energies)."""
        ...


@runtime_checkable
class DeviceCopyEnergies(Protocol):
    """A :class:`CopyEnergies` term whose per-copy energies can be added where its kernels run, into sums shared by
    the terms and read back once (:class:`~sim_core.ti_kernels.copy_vectors.CopySums`): the lockstep line search's
    trial points on the device (:mod:`sim_core.batch.line_search`)."""

    def add_copy_energies_on_device(self, x: np.ndarray, x_device: object, copy_of_vertex: np.ndarray,
                                    sums: object) -> bool:
        """Add :meth:`CopyEnergies.copy_energies` at ``x`` ``(vertex_count, 3)`` (J by copy) into ``sums`` (a
        :class:`~sim_core.ti_kernels.copy_vectors.CopySums` over ``copy_of_vertex``), reading the positions from
        ``x_device`` (the same positions, a Taichi float64 ndarray); False where it cannot (nothing added: the caller
        asks :meth:`CopyEnergies.copy_energies`)."""
        ...


@runtime_checkable
class SplitPotential(Protocol):
    """A potential that the solver evaluates as the sum of other potentials (the nodal-pressure gel: a Stable
    Neo-Hookean shear part, which a fused kernel takes, and its nodal volumetric term,
    :mod:`sim_core.energies.nodal_pressure`); energy, gradient and exact Hessian are the parts' sums."""

    def parts(self) -> tuple:
        """The potentials whose sum this one is."""
        ...


CAPABILITIES: tuple[type, ...] = (
    ConstantDiagonalHessian, PenaltyContact, KeepsDerivatives, HingeBending, ElasticEquivalent, SubsetHessian,
    DeviceHessian, SparseGradient, DeviceGradient, CopyEnergies, DeviceCopyEnergies, SplitPotential)
"""The optional capabilities a potential may declare (each a ``runtime_checkable`` Protocol)."""


def declares(obj: object, capability: type) -> bool:
    """``isinstance(obj, capability)`` for a capability Protocol of :data:`CAPABILITIES`, at the cost of a
    dictionary look-up: its methods are looked up once per class of ``obj``, its data members (e.g.
    :attr:`PenaltyContact.vertices`) on ``obj`` itself. (A ``runtime_checkable`` ``isinstance`` walks the
    Protocol's members on every call, about 80 us: the Newton loop asks several times per iteration.)"""
    methods, data = _capability_members(type(obj), capability)
    return methods and all(hasattr(obj, name) for name in data)


@functools.cache
def _capability_members(cls: type, capability: type) -> tuple[bool, tuple[str, ...]]:
    """Whether class ``cls`` has every method of ``capability`` (callable), and the Protocol's data members."""
    data = tuple(getattr(capability, "__annotations__", {}))
    methods = [name for name, value in vars(capability).items() if callable(value) and not name.startswith("_")]
    return all(callable(getattr(cls, name, None)) for name in methods), data


def sum_by_copy(copy_of_vertex: np.ndarray, vertices: np.ndarray, values: np.ndarray, copy_count: int) -> np.ndarray:
    """Per-element ``values`` ``(k,)`` summed by the copy of each element's vertex ``vertices`` ``(k,)`` (int; its
    first vertex: :class:`CopyEnergies`), shape ``(copy_count,)`` (one ``np.bincount``, in element order)."""
    if not len(values):
        return np.zeros(copy_count)
    return np.bincount(np.take(copy_of_vertex, vertices), weights=values, minlength=copy_count)


class BorrowedWorkspace:
    """Mixin of a potential built on a Stable Neo-Hookean whose ``dF/dx`` and deformation memo it reads (the attribute
    named by ``_host``): its ``workspace`` (:mod:`sim_core.workspace`) is the host's, so both share one memo."""

    _host = "shear"

    @property
    def workspace(self):
        """The host's workspace, or None before one is given."""
        return getattr(self, self._host).__dict__.get("workspace")

    @workspace.setter
    def workspace(self, value) -> None:
        getattr(self, self._host).workspace = value


def project_psd(blocks: np.ndarray, projection: Projection = "clamp") -> np.ndarray:
    """Project symmetric element Hessians onto the positive semi-definite cone.

    Args:
        blocks: shape ``(k, n, n)``, symmetric.
        projection: ``"none"`` returns the input, ``"clamp"`` sets negative eigenvalues to 0
            (Teran et al. 2005), ``"abs"`` replaces them by their absolute value.

    Returns:
        Array of shape ``(k, n, n)``.

    Raises:
        ValueError: unknown projection name.
    """
    if projection == "none" or blocks.shape[0] == 0:
        return blocks
    if projection not in ("clamp", "abs"):
        raise ValueError(f"unknown PSD projection {projection!r}; use 'none', 'clamp' or 'abs'")
    sym = 0.5 * (blocks + np.swapaxes(blocks, 1, 2))
    w, q = np.linalg.eigh(sym)
    if np.all(w >= 0.0):
        return sym
    w = np.maximum(w, 0.0) if projection == "clamp" else np.abs(w)
    return np.einsum("kij,kj,klj->kil", q, w, q, optimize=True)


def block_dof_indices(vertices: np.ndarray) -> np.ndarray:
    """Global DoF indices of element vertex lists.

    Args:
        vertices: shape ``(k, m)`` global vertex indices.

    Returns:
        shape ``(k, 3 m)``: ``3 * vertices[:, a] + d`` in vertex-major order.
    """
    vertices = np.asarray(vertices, dtype=np.int64)
    return (3 * vertices[:, :, None] + np.arange(3)[None, None, :]).reshape(vertices.shape[0], 3 * vertices.shape[1])


def scatter_gradient(vertex_count: int, vertices: np.ndarray, element_grad: np.ndarray) -> np.ndarray:
    """Sum per-element gradients into the global gradient.

    Args:
        vertex_count: number of vertices of the model.
        vertices: shape ``(k, m)`` global vertex indices.
        element_grad: shape ``(k, m, 3)`` or ``(k, 3 m)``.

    Returns:
        shape ``(vertex_count, 3)``.

    One ``np.bincount`` over the flattened DoF indices (the sums of ``np.add.at`` in the same
    order, bit for bit, at a third of its cost for the few hundred rows of a contact potential).
    """
    k, m = vertices.shape
    if not k:
        return np.zeros((vertex_count, 3))
    dofs = (np.asarray(vertices, dtype=np.int64).reshape(-1, 1) * 3 + np.arange(3)).reshape(-1)
    weights = np.asarray(element_grad, dtype=float).reshape(-1)
    return np.bincount(dofs, weights=weights, minlength=3 * vertex_count).reshape(vertex_count, 3)


def assemble_hessian(
    parts: Sequence[HessianBlocks], dof_count: int, diagonal: np.ndarray | None = None
) -> sp.csr_matrix:
    """Assemble element blocks into one sparse symmetric matrix (COO -> CSR, duplicates summed).

    Args:
        parts: block sets of several potentials.
        dof_count: ``3 * vertex_count``.
        diagonal: optional extra diagonal, shape ``(dof_count,)`` (e.g. the mass term m / dt^2).

    Returns:
        CSR matrix of shape ``(dof_count, dof_count)``.
    """
    rows, cols, vals = [], [], []
    for part in parts:
        if part.blocks.shape[0] == 0:
            continue
        dofs = block_dof_indices(part.vertices)
        n = dofs.shape[1]
        rows.append(np.repeat(dofs, n, axis=1).reshape(-1))
        cols.append(np.tile(dofs, (1, n)).reshape(-1))
        vals.append(part.blocks.reshape(-1))
    if diagonal is not None:
        idx = np.arange(dof_count)
        rows.append(idx)
        cols.append(idx)
        vals.append(np.asarray(diagonal, dtype=float))
    if not rows:
        return sp.csr_matrix((dof_count, dof_count))
    mat = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(dof_count, dof_count)
    )
    return mat.tocsr()


_F64 = np.dtype(np.float64)


class FrozenPositionsKey:
    """The :func:`positions_key` of a frozen positions array: equal to another only for the same array object,
    which it keeps alive (so that its ``id`` is not reused while a cache holds the key).

    A frozen array is a read-only float64 ``np.ndarray`` whose values cannot change while it exists: one that owns its
    memory (whoever freezes an array never makes it writeable again), or one :meth:`register` was given (an array over
    memory of another owner, e.g. a reused page-locked block of
    :class:`~sim_core.ti_kernels.device_copy.PinnedBlocks`, that no writeable array shares while it exists).
    """

    __slots__ = ("x",)

    _registered: dict = {}  # id(array) -> weakref.ref of the arrays given to register() that still exist

    def __init__(self, x: np.ndarray) -> None:
        self.x = x

    def __eq__(self, other: object) -> bool:
        return isinstance(other, FrozenPositionsKey) and other.x is self.x

    def __hash__(self) -> int:
        return id(self.x)

    @classmethod
    def register(cls, x: np.ndarray) -> np.ndarray:
        """Make ``x`` read-only and key it by identity from now on (:meth:`holds`); returns ``x``. The caller
        promises that no writeable array over ``x``'s memory exists, or will, while ``x`` exists.

        Raises:
            ValueError: ``x`` is not a float64 ``np.ndarray``.
        """
        if type(x) is not np.ndarray or x.dtype is not _F64:
            raise ValueError(f"FrozenPositionsKey.register: a float64 np.ndarray is needed, got "
                             f"{type(x).__name__} {getattr(x, 'dtype', '')}")
        x.flags.writeable = False
        key, registered = id(x), cls._registered

        def forget(ref, key=key, registered=registered) -> None:
            if registered.get(key) is ref:
                del registered[key]

        registered[key] = weakref.ref(x, forget)
        return x

    @classmethod
    def holds(cls, x) -> bool:
        """Whether ``x`` is frozen (class docstring): a read-only float64 ``np.ndarray`` that owns its memory or was
        given to :meth:`register`."""
        if type(x) is not np.ndarray or x.dtype is not _F64 or x.flags.writeable:
            return False
        if x.base is None:
            return True
        ref = cls._registered.get(id(x))
        return ref is not None and ref() is x


def positions_key(x: np.ndarray) -> tuple | FrozenPositionsKey:
    """``(shape, bytes)`` of positions ``x`` as float64 in C order: equal keys are bitwise equal positions.

    A frozen array (:meth:`FrozenPositionsKey.holds`: read-only float64 that owns its memory, as the lockstep solver's
    iterates are, :mod:`sim_core.batch.lockstep`, or that was registered, as its trial points downloaded into
    page-locked memory on CUDA are) is keyed by identity instead (:class:`FrozenPositionsKey`): its contents cannot
    change while it exists. Reading the bytes of a stacked batch's positions (14 MB at 1024 Forming copies) took 28 ms
    a Newton iteration on the H200 host (docs/benchmarks_log.md, session 40, 28lock).

    Kept evaluations are matched by this key: the pair potentials' (:mod:`sim_core.energies.contact.reference`)
    and the fused elastic terms' (:mod:`sim_core.fused_elastic`); a copy of ``x`` compared with
    ``np.array_equal`` cost four times as much, and bitwise equality is the stricter test.
    """
    if type(x) is not np.ndarray or x.dtype is not _F64:
        x = np.asarray(x, dtype=np.float64)
    elif FrozenPositionsKey.holds(x):
        return FrozenPositionsKey(x)
    return x.shape, x.tobytes()
