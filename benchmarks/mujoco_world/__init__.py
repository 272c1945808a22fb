"""An independent-engine (MuJoCo 4.0.0) generator of labelled recordings of the reference world.

Benchmark-only: nothing in sim_core, sysid or thinshell_ros imports it, and MuJoCo is not a
dependency of the project (``benchmarks/mujoco_world/requirements.txt``). See README.md.
"""
