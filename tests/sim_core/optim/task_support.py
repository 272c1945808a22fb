"""Tasks of ``config/tasks`` at short horizons for the optimiser tests."""

from __future__ import annotations

from functools import lru_cache

from sim_core.optim.tasks import task_at_horizon


@lru_cache(maxsize=None)
def short_task(name: str, horizon: int):
    """``name`` at ``horizon`` steps (cached: a task's reward target is computed once)."""
    return task_at_horizon(name, horizon)


def forming_task(horizon: int = 4):
    return short_task("forming", horizon)


def folding_task(horizon: int = 4):
    return short_task("folding_u", horizon)
