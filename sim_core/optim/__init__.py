"""Trajectory and parameter optimisation on the simulator: CMA-ES, gradient ascent through the
adjoint, the hybrid, and parallel rollouts on Ray.

Why in sim_core (DESIGN.md puts the differentiable simulator and its consumers' numerical core
here): the optimisers need nothing but a task (scene + reward), the simulation and its adjoint -
all sim_core - and no recording, sensor model or ROS. Keeping them here lets sysid (the inverse
tasks share its parameter coordinates and drive them through :mod:`sim_core.optim.inverse_task`) and the
ROS nodes use them along the one-way dependency thinshell_ros -> sysid -> sim_core. The command
line (``thinshell optimise``) lives in :mod:`sim_core.optim.cli`, which can dispatch an inverse
task to sysid's parameter coordinates.

Modules: :mod:`~sim_core.optim.actions` (action layout, control points, targets, chain rule),
:mod:`~sim_core.optim.episode` (one episode, its score and its reward gradient),
:mod:`~sim_core.optim.evaluators` (serial and Ray batches), :mod:`~sim_core.optim.search`
(CMA-ES / Adam / hybrid with checkpoints).
"""
