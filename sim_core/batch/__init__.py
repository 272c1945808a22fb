"""Batched simulation: ``B`` independent copies of one scene stepped together.

Modules: :mod:`~sim_core.batch.simulation` (``BatchedSimulation``: per-copy models, solvers, states,
controls; per-copy convergence and failure), :mod:`~sim_core.batch.stacked` (the copies as one
stacked model of disconnected copies), :mod:`~sim_core.batch.lockstep` (one Newton solve of all copies
per step, ``SolverConfig.lockstep``; its batched conjugate gradient is
:mod:`sim_core.ti_kernels.pcg`), :mod:`~sim_core.batch.sizing` (the batch size that fits the
device's free memory, from the memory per copy of a probe), :mod:`~sim_core.bench.batch` (``thinshell bench batch``: scene-steps
per second and memory per copy against ``B``). Task populations roll out through
:func:`sim_core.tasks.population.rollout_population`.
"""

from __future__ import annotations

from sim_core.batch.simulation import BatchedSimulation, BatchStep, same_topology

__all__ = ["BatchedSimulation", "BatchStep", "same_topology"]
