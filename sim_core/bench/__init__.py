"""Speed benchmarks of the simulator (no ROS needed): ``thinshell bench forming`` and ``thinshell bench scale``.

* :mod:`sim_core.bench.forming`: ThinShellLab's Forming scene (1698 DoF) driven by the benchmark
  trajectory of DESIGN.md (49 steps): DoF, steps/s, Newton iterations per step, the shares of
  assembly and linear solve, the cold start (process start to the end of the first step).
* :mod:`sim_core.bench.scale`: flat sheets of about 1k, 10k and 100k DoF under gravity, one edge
  clamped: time per step and peak resident memory.
* :mod:`sim_core.bench.cli`: their command lines (``thinshell bench`` dispatches to them,
  ``thinshell_ros.bench``).

Both run the solver on the backend the sim node runs (``SolverConfig.backend``, :mod:`sim_core.backend`):
``--arch numpy`` (the NumPy reference), ``cpu`` or ``cuda`` (``taichi-cpu`` / ``taichi-cuda``: the fused
elastic kernels of :mod:`sim_core.fused_elastic` in the Newton loop, compiled before the timed steps).
"""
