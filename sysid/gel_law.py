"""The gel's constitutive law chosen by the data: one replay of a recording per law, compared by an information criterion.

The laws (:data:`GEL_LAWS`, ``simulation.gel_element``) share the small-strain response (``E``, ``nu``) and part at
second order in the strain: Stable Neo-Hookean (the default) keeps a sheared layer's thickness, the Green-strain
law (Saint Venant-Kirchhoff, :mod:`sim_core.energies.green_strain`) thins it and softens in compression, so a pressed
gel sinks further once it slides (docs/known_answers.md, "The slide's depth gap is the gel's law"). Each law is
replayed at the same parameter values (the scene's, or ``values``), through the effector's drive fitted from the
recording (:func:`sysid.drive_calibration.fit_drive`) and the scene's sensor calibration. The laws have the same
number of parameters, so the difference of their Bayesian information criteria is the difference of their
whitened sums of squares over the tactile channels (``-2 log L`` up to a constant shared by both); the law with the
smaller is the data's choice, and ``margin`` says by how much.

This module reads a recording only through :mod:`sysid.evidence` and replays it through
:class:`sysid.observation.ObservationModel`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from sysid.calibration import whitened_rms
from sysid.drive_calibration import fit_drive
from sysid.observation import ObservationModel

GEL_LAWS: tuple[str, ...] = ("stable_neohookean", "green_strain")
"""The gel laws compared by default (:data:`sim_core.elastic.SOLID_ELEMENTS` names)."""

AUTO_LAW = "auto"
"""``simulation.gel_element`` (``thinshell diagnose`` / ``thinshell sysid --gel-element``) that asks for the law the
recording chooses (:func:`choose_gel_law`) instead of a named one."""

TACTILE = ("markers_xyz", "markers_uv", "wrench")
"""Channels whose whitened sums of squares are compared."""


@dataclass(frozen=True)
class GelLawChoice:
    """What :func:`choose_gel_law` found.

    Attributes:
        chosen: the law of the smallest whitened sum of squares.
        cost: law -> whitened sum of squares over :attr:`channels` (noise units squared, summed over samples).
        rms: law -> channel -> whitened RMS.
        margin: the runner-up's cost minus the chosen law's (the delta-BIC in its favour; equal parameter counts).
        channels: the compared channels.
    """

    chosen: str
    cost: dict[str, float]
    rms: dict[str, dict[str, float]]
    margin: float
    channels: tuple[str, ...]

    def summary(self) -> dict[str, Any]:
        """JSON-ready: the chosen law, the margin, each law's cost and whitened RMS per channel."""
        return {"chosen": self.chosen, "delta_bic": self.margin, "cost": dict(self.cost),
                "whitened_rms": {law: dict(r) for law, r in self.rms.items()}, "channels": list(self.channels)}


def choose_gel_law(evidence, laws: Sequence[str] = GEL_LAWS, *, dt: float = 0.01, t_max: float | None = None,
                   values: Mapping[str, float] | None = None, channels: Sequence[str] = TACTILE,
                   arch: str = "cpu", simulation: Mapping[str, Any] | None = None) -> GelLawChoice:
    """Replay ``evidence`` once per gel law and choose the law by the whitened sum of squares (module docstring).

    Args:
        evidence: a loaded recording (:func:`sysid.evidence.load_evidence`) of a tactile scene.
        laws: ``simulation.gel_element`` names to compare (at least two).
        dt, t_max, arch: the replays' step (s), end (s; None: the recording's) and elastic backend.
        values: parameter values of every replay (None: the scene's).
        channels: the compared channels; those the recording lacks are skipped.
        simulation: other overrides of the scene's ``simulation:`` block for every replay (e.g. ``gel_resolution``).

    Returns:
        :class:`GelLawChoice`.

    Raises:
        ValueError: fewer than two laws, or none of ``channels`` in the recording.
        ConfigError: an unknown law (the scene's check names it).
    """
    if len(laws) < 2:
        raise ValueError(f"choose_gel_law: compare at least two gel laws, got {list(laws)}")
    cost: dict[str, float] = {}
    rms: dict[str, dict[str, float]] = {}
    for law in laws:
        model = ObservationModel(evidence, dt=dt, t_max=t_max, arch=arch,
                                 simulation={**dict(simulation or {}), "gel_element": law})
        drive = fit_drive(model)
        model.set_drive_stiffness(drive.replay_stiffness, drive.replay_damping)
        prediction = model.predict(model.simulate(dict(values or {})))
        rms[law] = whitened_rms(model, prediction, channels)
        if not rms[law]:
            raise ValueError(f"choose_gel_law: the recording has none of the channels {list(channels)}")
        cost[law] = float(sum(r**2 * np.asarray(prediction[ch]).size for ch, r in rms[law].items()))
    ranked = sorted(cost, key=cost.get)
    return GelLawChoice(chosen=ranked[0], cost=cost, rms=rms, margin=cost[ranked[1]] - cost[ranked[0]],
                        channels=tuple(next(iter(rms.values()))))
