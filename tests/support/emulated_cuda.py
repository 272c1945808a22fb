"""The CUDA paths of ``sim_core`` emulated on Taichi's CPU arch in a test (``monkeypatch`` fixture)."""

from __future__ import annotations

import importlib
import pkgutil
import sys

_LOADED_FIRST = ("sim_core.energies", "sim_core.candidates", "sim_core.ti_kernels", "sim_core.batch")
"""Packages whose modules are all imported before the queries change: a module that a CUDA path imports lazily
(``sides_kernel``, ``rows_kernel``) and that were first imported while the query answers "cuda" would bind the changed
``ti_backend.current_arch`` as its own and keep it in every later test."""


def emulate_cuda(monkeypatch) -> None:
    """Every loaded sim_core module's arch query answers "cuda" (the CUDA paths, emulated on the CPU arch), the byte
    copies' excepted (they copy host memory on the CPU arch: ``benchmarks/emulated_cuda.py``); undone with
    ``monkeypatch`` at the test's end. The modules of :data:`_LOADED_FIRST` are imported first, so that none binds the
    changed query; a module of another package first imported inside the test keeps the real query."""
    from sim_core import ti_backend

    for package_name in _LOADED_FIRST:
        package = importlib.import_module(package_name)
        for info in pkgutil.walk_packages(package.__path__, package_name + "."):
            importlib.import_module(info.name)
    from sim_core.ti_kernels import device_copy

    query = ti_backend.current_arch  # (taken before the loop changes ti_backend's own)
    for name, module in list(sys.modules.items()):
        if name.startswith("sim_core") and module is not device_copy \
                and getattr(module, "current_arch", None) is query:
            monkeypatch.setattr(module, "current_arch", lambda: "cuda")
