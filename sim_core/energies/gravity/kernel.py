"""Gravity on a Taichi backend: the energy at positions in device memory and the constant gradient added there.

The Taichi twin of :class:`sim_core.energies.gravity.reference.GravityPotential` (the reference and test oracle,
DESIGN.md's incremental potential)::

    E = - sum_i m_i g . x_i = sum_i c_i . x_i,    dE/dx_i = c_i = - m_i g,

``c`` the reference's kept constant gradient ``(n, 3)`` (N), copied to the device once
(:func:`sim_core.ti_kernels.buffers.on_device`) and added from there into a device-resident gradient sum
(capability :class:`~sim_core.energies.base.DeviceGradient`) by one launch that sums the energy along. The loop is
serial on the CPU (the energy summed in vertex order), parallel on CUDA.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np

from sim_core.energies.gravity.reference import GravityPotential
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import on_device
from sim_core.ti_kernels.launch import summing_kernel
from sim_core.ti_kernels.transfer import same_shapes

_F64_1, _F64_2 = linalg.F64_1, linalg.F64_2


@summing_kernel
def gravity_energy_add_gradient(x: _F64_2, constant: _F64_2, gradient: _F64_2, energy: _F64_1):
    """Energy ``sum_i c_i . x_i`` (J, returned) at ``x`` ``(n, 3)`` (m); ``gradient`` ``(n, 3)`` ``+= c`` (N)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(x.shape[0]):
        for d in ti.static(range(3)):
            energy[i % energy.shape[0]] += constant[i, d] * x[i, d]
            gradient[i, d] += constant[i, d]


class TiGravityPotential(GravityPotential):
    """:class:`~sim_core.energies.gravity.reference.GravityPotential` that also adds its gradient into a device
    array (module docstring); the same arguments, errors, energy, gradient and parameter derivative.

    Raises:
        ConfigError: non-finite gravity, or the Taichi backend is not initialised
            (:func:`sim_core.ti_backend.init_backend`).
    """

    def __init__(self, vertex_mass: np.ndarray, gravity: np.ndarray) -> None:
        super().__init__(vertex_mass, gravity)
        require_backend("TiGravityPotential")
        self._device: dict = {}  # on CUDA: the device copy of the constant gradient (buffers.on_device)

    def add_gradient_on_device(self, x: np.ndarray, x_device, gradient_device) -> float:
        """Add ``-m g`` (N) into the Taichi ndarray ``gradient_device`` ``(n, 3)`` and return the energy (J) at the
        device positions ``x_device`` ``(n, 3)`` (m) (capability :class:`~sim_core.energies.base.DeviceGradient`);
        ``x`` (the same positions on the host) gives the shape and dtype of the kept constant.

        Raises:
            ValueError: ``x_device`` or ``gradient_device`` is not of ``x``'s shape.
        """
        same_shapes("TiGravityPotential.add_gradient_on_device", x, x_device, gradient_device)
        constant = np.ascontiguousarray(self._constant_gradient(x), dtype=np.float64)
        if not constant.size:
            return 0.0
        return float(gravity_energy_add_gradient(x_device, on_device(self._device, "gradient", constant),
                                                 gradient_device))
