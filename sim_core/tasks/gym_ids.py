"""Gymnasium registration of the ten ThinShellLab task environments (ids ``thinshell/<Task>-v0``).

Importing :mod:`sim_core.tasks` registers them (string entry points: nothing heavy is imported until an
environment is made), so the usual Gymnasium forms work::

    import gymnasium as gym
    import sim_core.tasks
    gym.register_envs(sim_core.tasks)          # optional: says which import registered them
    env = gym.make("thinshell/Forming-v0")
    env = gym.make("sim_core.tasks:thinshell/Forming-v0")   # no explicit import needed

The environment class is :class:`sim_core.tasks.env.ThinShellTaskEnv`.
"""

from __future__ import annotations

import importlib.util

from sim_core.tasks.registry import TASK_NAMES

ENV_NAMESPACE = "thinshell"
ENV_ENTRY_POINT = "sim_core.tasks.env:ThinShellTaskEnv"
_DISPLAY_NAMES = {"folding_l": "Folding-L", "folding_u": "Folding-U", "pick_folding": "Pick-Folding"}


def env_id(task_name: str) -> str:
    """Gymnasium id of a task: ``thinshell/<Name>-v0`` (``"folding_l"`` -> ``thinshell/Folding-L-v0``)."""
    return f"{ENV_NAMESPACE}/{_DISPLAY_NAMES.get(task_name, task_name.capitalize())}-v0"


def gymnasium_installed() -> bool:
    """Whether Gymnasium can be imported (a requirement of thinshell; a minimal install for the
    simulator alone, such as the GPU machine's, may lack it)."""
    return importlib.util.find_spec("gymnasium") is not None


def register_envs() -> list[str]:
    """Register the ten task environments with Gymnasium (idempotent); returns their ids.

    Raises:
        ModuleNotFoundError: Gymnasium is not installed.
    """
    import gymnasium as gym  # optional heavy dependency: Gymnasium, for the environments only

    ids = []
    for name in TASK_NAMES:
        eid = env_id(name)
        if eid not in gym.registry:
            gym.register(id=eid, entry_point=ENV_ENTRY_POINT, kwargs={"task": name})
        ids.append(eid)
    return ids
