"""Recordings of this project's simulator with a concealed difference from the scene they state.

The recording is simulated with parameters drawn around :data:`tests.sysid.simbag.TRUE_PARAMS` and one
concealed change of the physics that no fitted parameter can express (a finer gel mesh, another
table friction, a stiffer contact, another gel Poisson ratio); its ``scene.yaml`` states the
nominal values. A fit of the drawn parameters then meets a model error of known truth: the
coverage of its reported intervals can be counted.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from tests.sysid.simbag import (PRESS_SLIDE, TRUE_PARAMS, add_noise, scene_with, simulate_streams,
                                targets_from_segments, write_bag)

CONCEALED: dict[str, Callable[[dict], None]] = {
    "gel_mesh_fine": lambda s: s["simulation"].update(gel_resolution=[7, 5, 3]),
    "table_friction_0.5": lambda s: s["table"].update(friction=0.5),
    "gel_nu_0.40": lambda s: s["sensors"]["tactile"]["gel_material"].update(poisson_ratio=0.40),
    "contact_stiffness_x3": lambda s: s.setdefault("simulation", {}).update(contact_stiffness=6.0e4),
}
"""Concealed differences: name -> in-place change of the recording's scene dict."""

DRAWN = ("gel.youngs_modulus", "friction.gel_sheet")
"""Parameters whose true values are drawn per recording (log-uniform within +-15 % of TRUE_PARAMS)."""


def concealed_recording(out_dir: Path, concealed: str, seed: int, segments=PRESS_SLIDE) -> tuple[Path, dict]:
    """Write a noisy recording with the concealed difference ``concealed`` and true values drawn by ``seed``.

    Returns:
        ``(bag directory, true parameter values)``.
    """
    rng = np.random.default_rng(100 + seed)
    truth = dict(TRUE_PARAMS)
    for name in DRAWN:
        truth[name] *= float(np.exp(rng.uniform(-0.15, 0.15)))
    scene = scene_with(truth)
    CONCEALED[concealed](scene)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), segments)
    streams = add_noise(simulate_streams(scene, truth, targets), seed)
    return write_bag(out_dir, scene_with(TRUE_PARAMS), streams), truth
