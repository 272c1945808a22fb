"""The elastic terms of a lockstep batch's stacked model, with the bending plasticity after a step computed by one
Taichi kernel over every hinge of every copy
(:class:`sim_core.energies.hinge_bending.plasticity_kernel.HingePlasticity`) instead of NumPy over the stacked
hinges: 104 ms a step at 1024 Forming copies on the H200 host (docs/benchmarks_log.md, session 40, 28lock). With the
batched CG the step's accepted positions are already on the device (the Newton loop's iterate,
:mod:`sim_core.batch.device_iterates`): the kernel reads them there (:attr:`StackedElasticTerms.device_positions`), with
no upload of the stacked positions (14 MB at B = 1024)."""

from __future__ import annotations

import numpy as np

from sim_core.elastic import ElasticTerms
from sim_core.errors import ConfigError


class StackedElasticTerms(ElasticTerms):
    """:class:`~sim_core.elastic.ElasticTerms` whose :meth:`plastic_update` runs on the Taichi backend initialised
    in this process (the lockstep solver makes it on a Taichi backend only). Same arguments.

    Attributes:
        device_positions: ``(x, x_device)``: host positions ``(N, 3)`` and the same values as a float64 Taichi ndarray
            ``(N, 3)``, set by the lockstep solver before a step's finish; :meth:`plastic_update` of that very ``x``
            (identity) reads ``x_device`` instead of uploading ``x``. None: always uploaded.
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._plasticity: dict = {}  # sheet name -> HingePlasticity, made at its first finite yield angle
        self.device_positions: tuple | None = None

    def plastic_update(self, x: np.ndarray, hinge_theta_bar: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Bending plasticity after a step ending at positions ``x`` ``(N, 3)`` (m): the new rest angles (rad) per
        sheet, those of :meth:`ElasticTerms.plastic_update` to round-off (a sheet of infinite yield angle keeps a
        copy of its rest angles).

        Raises:
            ConfigError: a negative or NaN yield angle.
        """
        # Taichi kernels: a Taichi backend only
        from sim_core.energies.hinge_bending.plasticity_kernel import HingePlasticity

        kept = self.device_positions
        x_device = kept[1] if kept is not None and kept[0] is x else None
        out = {}
        for name, hinges in self.hinges.items():
            yield_angle = float(self.model.bodies[name].material.get("yield_angle", np.inf))
            if not yield_angle >= 0:
                raise ConfigError(f"sheet {name!r}: yield_angle must be >= 0 rad (inf = elastic), got {yield_angle}")
            tb = hinge_theta_bar.get(name)
            tb = np.zeros(hinges.shape[0]) if tb is None else np.asarray(tb, dtype=float)
            if not np.isfinite(yield_angle):
                out[name] = np.array(tb)
                continue
            kernel = self._plasticity.get(name)
            if kernel is None:
                kernel = self._plasticity[name] = HingePlasticity(hinges)
            out[name] = kernel.update(x, tb, yield_angle) if x_device is None else _update_on_device(
                kernel, x_device, tb, yield_angle)
        return out


def _update_on_device(kernel, x_device, theta_bar: np.ndarray, yield_angle: float) -> np.ndarray:
    """:meth:`HingePlasticity.update <sim_core.energies.hinge_bending.plasticity_kernel.HingePlasticity.update>` of
    ``kernel`` with the positions already on the device: ``x_device``, a float64 Taichi ndarray ``(N, 3)`` (m); the
    same kernel on the same values, so the same rest angles (rad, a new array ``(h,)``)."""
    from sim_core.energies.hinge_bending.plasticity_kernel import hinge_plastic_update
    from sim_core.ti_kernels.transfer import download, upload

    theta_bar = np.ascontiguousarray(theta_bar, dtype=np.float64)
    if theta_bar.shape != (kernel.hinge_count,):
        raise ValueError(f"HingePlasticity: rest angles of shape {theta_bar.shape}, expected ({kernel.hinge_count},)")
    tb = upload(kernel._theta_bar.ensure(theta_bar.shape), theta_bar)
    if kernel.hinge_count:
        hinge_plastic_update(x_device, kernel._hinges, tb, float(yield_angle))
    return download(tb)
