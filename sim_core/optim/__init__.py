"""Trajectory and parameter optimisation on the simulator: CMA-ES, gradient ascent through the
adjoint, the hybrid, and parallel rollouts on Ray.

Why in sim_core (DESIGN.md puts the differentiable simulator and its consumers' numerical core
here): the optimisers need nothing but a task (scene + reward), the simulation and its adjoint -
all sim_core - and no recording, sensor model or ROS. Keeping them here lets sysid and the ROS
nodes use them along the one-way dependency thinshell_ros -> sysid -> sim_core. The inverse tasks
(:mod:`sim_core.optim.inverse_task`) search the parameters in the coordinates ``thinshell sysid`` fits
in (:mod:`sim_core.parameter_coordinates`); the command line (``thinshell optimise``) is
:mod:`sim_core.optim.cli` and its benchmark (``thinshell bench optimise``) :mod:`sim_core.optim.bench`.

Modules: :mod:`~sim_core.optim.actions` (action layout, control points, targets, chain rule),
:mod:`~sim_core.optim.episode` (one episode, its score and its reward gradient),
:mod:`~sim_core.optim.evaluators` (serial and Ray batches), :mod:`~sim_core.optim.search`
(CMA-ES / Adam / hybrid with checkpoints), :mod:`~sim_core.optim.inverse_task` (inverse tasks'
parameter space), :mod:`~sim_core.optim.cli` and :mod:`~sim_core.optim.bench`.
"""
