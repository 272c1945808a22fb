"""Control: what the user commands for one step (Newton-style ``model.control()``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Control:
    """Effector commands for one step.

    Attributes:
        effector_pose_target: effector name -> target pose ``[x y z qx qy qz qw]`` in ``world``
            (m, unit quaternion). A missing name holds the current pose.
        gripper_target: effector name -> finger opening target in m (two-finger effectors only).
    """

    effector_pose_target: dict[str, np.ndarray] = field(default_factory=dict)
    gripper_target: dict[str, float] = field(default_factory=dict)

    def copy(self) -> "Control":
        """Deep copy."""
        return Control(
            {k: np.array(v, dtype=float) for k, v in self.effector_pose_target.items()},
            dict(self.gripper_target),
        )
