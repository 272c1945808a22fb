"""A task at a shorter horizon (quick optimisations, tests, benchmarks at reduced cost).

The task file is read again with ``horizon: H`` and its reference trajectory cut to its first H
steps, so that every part of the task that depends on the horizon follows: a reward whose target is
the end of the reference trajectory (``sheet_target``, ``observed_motion``) then targets the state
after H reference steps.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from sim_core.errors import ConfigError


def task_at_horizon(name_or_path: str | Path, horizon: int | None = None):
    """Load a task (:func:`sim_core.tasks.registry.load_task`), optionally at a shorter horizon.

    Args:
        name_or_path: task name (``"forming"``) or task file.
        horizon: steps per episode, 1 <= H <= the file's horizon; None keeps the file's.

    Returns:
        the :class:`~sim_core.tasks.spec.TaskSpec`.

    Raises:
        ConfigError: unknown task, bad file, or a horizon out of range (naming the file).
    """
    from sim_core.tasks.registry import build_task, default_tasks_dir, load_task

    task = load_task(name_or_path)
    if horizon is None or int(horizon) == task.horizon:
        return task
    path = Path(task.path) if task.path else default_tasks_dir() / f"{name_or_path}.yaml"
    h = int(horizon)
    if not 1 <= h <= task.horizon:
        raise ConfigError(f"{path}: horizon must be in 1..{task.horizon}, got {horizon}")
    doc = yaml.safe_load(path.read_text())
    doc["horizon"] = h
    if doc.get("reference") is not None:
        left, cut = h, []
        for block in doc["reference"]:
            if left <= 0:
                break
            steps = int(block["steps"])
            cut.append({**block, "steps": min(steps, left)})
            left -= steps
        doc["reference"] = cut
    try:
        return build_task(doc, path)
    except ConfigError as err:
        raise ConfigError(f"{path} (horizon {h}): {err}") from err
