"""Maintained benchmarks and test-set tooling of a thinshell checkout (README.md lists each one).

Not part of the installed package: nothing in sim_core, sysid or thinshell_ros imports it (an
import-linter contract, ``.importlinter``); run a benchmark from the checkout's root as
``python -m benchmarks.<name>``.
"""
