"""Bending plasticity after a step in one Taichi kernel: the rest angles of every hinge of a sheet moved where the
dihedral angle exceeds them by more than the yield angle.

The kernel counterpart of :func:`sim_core.energies.hinge_bending.reference.plastic_update` applied to the
hinges' dihedral angles (:func:`sim_core.energies.hinge_bending.reference.dihedral_angle`; ThinShellLab, Wang
et al. 2024; DESIGN.md): with ``d = theta - theta_bar``, ``theta_bar <- theta - y sign(d)`` where ``|d| > y``.
For a lockstep batch's stacked sheet (1024 Forming copies: 300,032 hinges) NumPy's gather of the hinges'
positions and its temporaries took 104 ms a step on the H200 host (docs/benchmarks_log.md, session 40, 28lock);
here one launch reads the positions once. The angles are those of the NumPy reference to round-off (the
kernel divides the triple product by ``|e|`` after the dot product, the reference normalises ``e`` first).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np

from sim_core.energies.hinge_bending.kernel import _dihedral_angle, _hinge_positions
from sim_core.ti_backend import ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import DeviceArray, upload_constant
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.transfer import download, upload


@fast_kernel
def hinge_plastic_update(x: linalg.F64_2, hinges: linalg.I32_2, theta_bar: linalg.F64_1, yield_angle: ti.f64):
    """``theta_bar[h] <- theta_h - y sign(theta_h - theta_bar[h])`` where ``|theta_h - theta_bar[h]| > y``
    (``theta_h`` the signed dihedral angle of hinge ``h`` at ``x``, rad), in place."""
    for h in range(hinges.shape[0]):
        x0, x1, x2, x3 = _hinge_positions(x, hinges, h)
        theta = _dihedral_angle(x0, x1, x2, x3)
        d = theta - theta_bar[h]
        if ti.abs(d) > yield_angle:
            theta_bar[h] = theta - yield_angle * ti.select(d > 0.0, 1.0, -1.0)


class HingePlasticity:
    """The plastic update of one sheet's hinges on the device (module docstring).

    Args:
        hinges: global vertex indices ``[e0, e1, opp0, opp1]`` of the sheet's hinges, shape ``(h, 4)``
            (uploaded once).
    """

    def __init__(self, hinges: np.ndarray) -> None:
        self.hinge_count = int(len(hinges))
        self._hinges = upload_constant(np.asarray(hinges, dtype=np.int32), ti.i32)
        self._x = DeviceArray(ti.f64)
        self._theta_bar = DeviceArray(ti.f64)

    def update(self, x: np.ndarray, theta_bar: np.ndarray, yield_angle: float) -> np.ndarray:
        """The new rest angles (rad, a new array of shape ``(h,)``) after a step ending at positions ``x``
        ``(n, 3)`` (m) from ``theta_bar`` ``(h,)`` (rad), with the yield angle ``yield_angle`` (rad, >= 0)."""
        theta_bar = np.ascontiguousarray(theta_bar, dtype=np.float64)
        if theta_bar.shape != (self.hinge_count,):
            raise ValueError(f"HingePlasticity: rest angles of shape {theta_bar.shape}, expected ({self.hinge_count},)")
        xd = upload(self._x.ensure(np.shape(x)), x)
        tb = upload(self._theta_bar.ensure(theta_bar.shape), theta_bar)
        if self.hinge_count:
            hinge_plastic_update(xd, self._hinges, tb, float(yield_angle))
        return download(tb)
