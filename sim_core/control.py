"""Control: what the user commands for one step (Newton-style ``model.control()``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from sim_core.drive_compression import CompressionUnknown


@dataclass
class Control:
    """Effector commands for one step.

    Attributes:
        effector_pose_target: effector name -> target pose ``[x y z qx qy qz qw]`` in ``world``
            (m, unit quaternion). A missing name holds the current pose.
        gripper_target: effector name -> finger opening target in m (two-finger effectors only).
        position_guess: optional solver hint, not a command: positions ``(n, 3)`` in m to start the
            step's Newton iterations from (free vertices; fixed and driven vertices still start
            at their targets), e.g. the same step of a replay at nearby parameters. The step
            converges to the same tolerance from any start, and takes at least one Newton
            correction from the guess (the result is never the guess itself); a start close to the
            solution saves iterations. None: start from the step's initial positions.
        compression: a series spring on one effector whose compression the step solves for with its
            positions (:mod:`sim_core.drive_compression`; the effector then ends the step ``b`` behind its
            target along the spring's axis), or None (every effector at its target).
    """

    effector_pose_target: dict[str, np.ndarray] = field(default_factory=dict)
    gripper_target: dict[str, float] = field(default_factory=dict)
    position_guess: np.ndarray | None = None
    compression: "CompressionUnknown | None" = None

    def copy(self) -> "Control":
        """Deep copy (the position guess is shared: it is read, never written)."""
        return Control(
            {k: np.array(v, dtype=float) for k, v in self.effector_pose_target.items()},
            dict(self.gripper_target),
            self.position_guess,
            self.compression,
        )
