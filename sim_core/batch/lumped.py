"""The step's lumped-mass terms (inertia, gravity, viscous damping) as one diagonal quadratic for the lockstep loop.

The three terms of the incremental potential that act on each vertex alone (DESIGN.md "Time stepping"),

    E_inertia = sum_v m_v / (2 dt^2) |x_v - x_hat_v|^2        (sim_core.energies.inertia.reference)
    E_gravity = - sum_v m_g,v g . x_v                          (sim_core.energies.gravity.reference)
    E_damping = sum_v c m_v / (2 dt) |x_v - x^n_v|^2           (sim_core.energies.damping.reference),

sum to one quadratic with a diagonal Hessian, completed to a square:

    E(x) = sum_v w_v / 2 |x_v - y_v|^2 + E_0,   w_v = m_v / dt^2 + c m_v / dt,
    w_v y_v = m_v / dt^2 x_hat_v + c m_v / dt x^n_v + m_g,v g,
    E_0 = E_inertia(y) + E_gravity(y) + E_damping(y)   (the sum's minimum, at x = y)

(a vertex without mass has ``w_v = 0`` and no term). Its energy and gradient read the stacked positions once each,
where the three terms read them five times for the energy and build three ``(N, 3)`` arrays for the gradient.
The values are the three terms' sums to round-off (not bit for bit: other operations). The lockstep solver evaluates
it in the Newton loop in place of the three terms (:func:`lumped_loop_terms`); the step's record keeps the terms
themselves (``StepTerms.fixed_terms``).
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.damping.reference import ViscousDamping
from sim_core.energies.gravity.reference import GravityPotential
from sim_core.energies.inertia.reference import InertiaPotential
from sim_core.errors import ConfigError


class LumpedQuadratic:
    """The sum of a step's inertia, gravity and damping terms (module docstring for the formula).

    Args:
        inertia: the step's :class:`InertiaPotential` (masses ``m`` kg ``(n,)``, ``x_hat`` m ``(n, 3)``, ``dt`` s).
        gravity: its :class:`GravityPotential` (masses ``m_g`` kg ``(n,)``, ``g`` m/s^2 ``(3,)``), or None.
        damping: its :class:`ViscousDamping` (``c`` 1/s, ``x^n`` m ``(n, 3)``, the same masses and ``dt``), or None.

    Raises:
        ConfigError: the terms are over different vertex counts, or the damping's time step is not the inertia's.

    Attributes:
        weight: ``w`` per vertex, kg/s^2, shape ``(n,)``.
        center: ``y`` per vertex, m, shape ``(n, 3)`` (``x_hat`` where ``w = 0``; the inertia's own array when it is
            the only term).
        offset: ``E_0``, J.
        predicted: whether ``y`` is the inertia's ``x_hat`` itself (no gravity, no damping): then the device may make
            ``y`` from the state it keeps (:meth:`use_device_center`).
    """

    def __init__(self, inertia: InertiaPotential, gravity: GravityPotential | None = None,
                 damping: ViscousDamping | None = None) -> None:
        m = inertia.vertex_mass
        n = m.shape[0]
        weight = m / inertia.dt ** 2
        if gravity is not None and gravity.vertex_mass.shape != (n,):
            raise ConfigError(f"LumpedQuadratic: gravity over {gravity.vertex_mass.shape[0]} vertices, not {n}")
        k_damping = None
        if damping is not None:
            if damping.vertex_mass.shape != (n,) or damping.dt != inertia.dt:
                raise ConfigError("LumpedQuadratic: damping over other vertices or another time step than the inertia")
            k_damping = damping.damping / damping.dt * damping.vertex_mass
            weight = weight + k_damping
        vertex_offset = np.zeros(n)  # E_0 per vertex (copy_energies)
        if gravity is None and damping is None:  # the inertia alone: y = x_hat, E_0 = 0
            center, offset = inertia.x_hat, 0.0
        else:  # y = x_hat + (c m / dt (x^n - x_hat) + m_g g) / w, a vertex without mass at x_hat
            inverse = np.divide(1.0, weight, out=np.zeros(n), where=weight > 0)
            shift = np.zeros((n, 3))
            if gravity is not None:
                shift += (gravity.vertex_mass * inverse)[:, None] * gravity.gravity[None, :]
            if damping is not None:
                shift += (k_damping * inverse)[:, None] * (damping.x_prev - inertia.x_hat)
            center = inertia.x_hat + shift
            # the terms' energies at the minimum from y - x_hat (the shift) and y - x^n: no cancellation of the large
            # |x_hat|^2 sums, and one pass each (the terms' own energy methods: 3-4 passes and temporaries each)
            offset = 0.5 / inertia.dt ** 2 * float(np.einsum("i,ij,ij->", m, shift, shift))
            if gravity is not None:
                offset -= float(np.einsum("i,ij,j->", gravity.vertex_mass, center, gravity.gravity))
            if damping is not None:
                pull = np.subtract(center, damping.x_prev)
                offset += 0.5 * damping.damping / damping.dt * float(np.einsum("i,ij,ij->", damping.vertex_mass, pull,
                                                                                   pull))
            vertex_offset = 0.5 / inertia.dt ** 2 * m * np.einsum("ij,ij->i", shift, shift)
            if gravity is not None:
                vertex_offset -= gravity.vertex_mass * (center @ gravity.gravity)
            if damping is not None:
                vertex_offset += 0.5 * damping.damping / damping.dt * damping.vertex_mass * np.einsum("ij,ij->i", pull,
                                                                                                      pull)
        self.weight = weight
        self.center = center
        self.predicted = gravity is None and damping is None
        self.offset = offset
        self._weight3 = weight[:, None]
        self._root3 = np.sqrt(weight)[:, None]
        self._device: tuple | None = None  # (center, weight) on the device: add_gradient_on_device
        self._device_energy: tuple | None = None  # (x, partial sums) of the last add_gradient_on_device
        self._vertex_offset = vertex_offset
        self._copy_offset: tuple | None = None  # (copy_of_vertex, E_0 per copy, w / 2) of copy_energies

    def energy(self, x: np.ndarray) -> float:
        """Energy in J at ``x`` ``(n, 3)``: ``sum_v w_v / 2 |x_v - y_v|^2 + E_0``, as the squared norm of
        ``sqrt(w_v) (x_v - y_v)`` (one temporary; NumPy's own dot product, not BLAS's threads, which contend on a
        busy host); where ``x`` is the array object of the last :meth:`add_gradient_on_device`, the partial sums that
        kernel left on the device, read back and added in order (the same value to round-off)."""
        kept = self._device_energy
        if kept is not None and kept[0] is x:
            from sim_core.ti_kernels.transfer import download  # Taichi only on a Taichi backend

            return float(np.sum(download(kept[1]))) + self.offset
        d = np.subtract(x, self.center)
        d *= self._root3
        flat = d.reshape(-1)
        return 0.5 * float(np.einsum("i,i->", flat, flat)) + self.offset

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each vertex, J ``(copy_count,)`` (capability
        :class:`~sim_core.energies.base.CopyEnergies`): ``sum_v w_v / 2 |x_v - y_v|^2`` and ``E_0`` per copy, the
        latter as the three terms' energies at ``y`` per vertex (made at the first call for ``copy_of_vertex``). The
        squares' row sums by columns (``(d_x + d_y) + d_z``, the order of NumPy's sum over a row of three) into one
        temporary, times ``w_v / 2`` kept from the first call: the same values as ``0.5 w d.sum(axis=1)`` in two
        passes fewer (4.2 against 10.9 ms at 580,000 vertices on the VM)."""
        kept = self._copy_offsets(copy_of_vertex, copy_count)
        d = np.subtract(x, self.center)
        d *= d
        rows = np.add(d[:, 0], d[:, 1])
        rows += d[:, 2]
        rows *= kept[2]
        return np.bincount(copy_of_vertex, weights=rows, minlength=copy_count) + kept[1]

    def _copy_offsets(self, copy_of_vertex: np.ndarray, copy_count: int) -> tuple:
        """``(copy_of_vertex, E_0 per copy (J, (copy_count,)), w / 2 (kg/s^2, (n,)))``, made at the first call for
        ``copy_of_vertex`` and kept."""
        kept = self._copy_offset
        if kept is None or kept[0] is not copy_of_vertex:
            kept = self._copy_offset = (copy_of_vertex, np.bincount(copy_of_vertex, weights=self._vertex_offset,
                                                                    minlength=copy_count), 0.5 * self.weight)
        return kept

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """Gradient ``w_v (x_v - y_v)`` in J/m, shape ``(n, 3)`` (a new array)."""
        g = np.subtract(x, self.center)
        g *= self._weight3
        return g


    def add_gradient_on_device(self, x: np.ndarray, x_device, gradient_device) -> None:
        """Add :meth:`gradient` at ``x`` into ``gradient_device`` on the device (capability
        :class:`~sim_core.energies.base.DeviceGradient`;
        :func:`~sim_core.ti_kernels.copy_vectors.add_diagonal_quadratic`, with ``y`` and ``w`` uploaded at the first
        call), the energy's partial sums left there for :meth:`energy` at ``x``.

        Args:
            x: the positions ``(n, 3)`` (m) on the host (the key of the energy kept).
            x_device: the same positions, a Taichi float64 ndarray ``(n, 3)``.
            gradient_device: a Taichi float64 ndarray ``(n, 3)``, J/m, added into.

        Returns:
            None (the energy stays on the device until :meth:`energy` asks for it).
        """
        from sim_core.ti_backend import ti  # Taichi kernels: a Taichi backend only
        from sim_core.ti_kernels import copy_vectors, device_copy

        n = self.weight.shape[0]
        if not n:
            return None
        center, weight = self._device_arrays()
        partial = device_copy.new_ndarray(ti.f64, (copy_vectors.energy_chunks(n),))
        copy_vectors.add_diagonal_quadratic(x_device, center, weight, gradient_device, partial)
        self._device_energy = (x, partial)
        return None

    def use_device_center(self, center_device) -> None:
        """Take ``center_device``, a float64 Taichi ndarray ``(n, 3)`` (m) holding :attr:`center`'s values (made on the
        device from the state kept there, :meth:`~sim_core.ti_kernels.copy_vectors.CopyVectors.advanced`), as the
        device's ``y`` in place of an upload of :attr:`center` (``3 n`` float64 values a step)."""
        weight = None if self._device is None else self._device[1]
        self._device = (center_device, weight)

    def _device_arrays(self) -> tuple:
        """``(center, weight)`` as float64 Taichi ndarrays ``(n, 3)`` and ``(n,)`` (at least one row), uploaded at the
        first call (the center where :meth:`use_device_center` has not given it)."""
        center, weight = (None, None) if self._device is None else self._device
        if center is None or weight is None:
            from sim_core.ti_backend import ti  # Taichi kernels: a Taichi backend only
            from sim_core.ti_kernels import copy_vectors, device_copy, transfer

            n = self.weight.shape[0]
            if weight is None:
                weight = device_copy.new_ndarray(ti.f64, (max(n, 1),))
                transfer.upload(weight, self.weight if n else np.zeros(1))
            if center is None:
                center = transfer.upload(copy_vectors.new_vectors(n), self.center if n else np.zeros((1, 3)))
            self._device = (center, weight)
        return self._device

    def add_copy_energies_on_device(self, x: np.ndarray, x_device, copy_of_vertex: np.ndarray, sums) -> bool:
        """:meth:`copy_energies` at ``x`` added into ``sums`` (a :class:`~sim_core.ti_kernels.copy_vectors.CopySums`
        over ``copy_of_vertex``; capability :class:`~sim_core.energies.base.DeviceCopyEnergies`): the squares
        ``w_v / 2 |x_v - y_v|^2`` of ``x_device`` summed by copy in one launch
        (:meth:`~sim_core.ti_kernels.copy_vectors.CopySums.add_diagonal_quadratic`), ``E_0`` per copy added on the
        host. Always True."""
        kept = self._copy_offsets(copy_of_vertex, sums.copy_count)
        if self.weight.shape[0]:
            sums.add_diagonal_quadratic(x_device, *self._device_arrays())
        sums.add(kept[1])
        return True


def lumped_loop_terms(loop_terms: list) -> list:
    """``loop_terms`` (a step's Newton-loop terms, ``StepTerms.loop_terms``) with its inertia, gravity and damping
    terms replaced by one :class:`LumpedQuadratic` at the inertia's place; unchanged when it has no inertia term,
    or more than one of a kind."""
    kinds = (InertiaPotential, GravityPotential, ViscousDamping)
    found = {k: [p for p in loop_terms if type(p) is k] for k in kinds}
    if len(found[InertiaPotential]) != 1 or any(len(v) > 1 for v in found.values()):
        return loop_terms
    lumped = LumpedQuadratic(found[InertiaPotential][0], *(found[k][0] if found[k] else None for k in kinds[1:]))
    out = []
    for p in loop_terms:
        if type(p) is InertiaPotential:
            out.append(lumped)
        elif type(p) not in kinds:
            out.append(p)
    return out
