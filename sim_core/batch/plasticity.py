"""The elastic terms of a lockstep batch's stacked model, with the bending plasticity after a step computed by one
Taichi kernel over every hinge of every copy
(:class:`sim_core.energies.hinge_bending.plasticity_kernel.HingePlasticity`) instead of NumPy over the stacked
hinges: 104 ms a step at 1024 Forming copies on the H200 host (docs/benchmarks_log.md, session 40, 28lock)."""

from __future__ import annotations

import numpy as np

from sim_core.elastic import ElasticTerms
from sim_core.errors import ConfigError


class StackedElasticTerms(ElasticTerms):
    """:class:`~sim_core.elastic.ElasticTerms` whose :meth:`plastic_update` runs on the Taichi backend initialised
    in this process (the lockstep solver makes it on a Taichi backend only). Same arguments."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._plasticity: dict = {}  # sheet name -> HingePlasticity, made at its first finite yield angle

    def plastic_update(self, x: np.ndarray, hinge_theta_bar: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Bending plasticity after a step ending at positions ``x`` ``(N, 3)`` (m): the new rest angles (rad) per
        sheet, those of :meth:`ElasticTerms.plastic_update` to round-off (a sheet of infinite yield angle keeps a
        copy of its rest angles).

        Raises:
            ConfigError: a negative or NaN yield angle.
        """
        # Taichi kernels: a Taichi backend only
        from sim_core.energies.hinge_bending.plasticity_kernel import HingePlasticity

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
            out[name] = kernel.update(x, tb, yield_angle)
        return out
