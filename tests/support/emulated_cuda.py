"""The CUDA paths of ``sim_core`` emulated on Taichi's CPU arch in a test (``monkeypatch`` fixture)."""

from __future__ import annotations

import sys


def emulate_cuda(monkeypatch) -> None:
    """Every loaded sim_core module's arch query answers "cuda" (the CUDA paths, emulated on the CPU arch), the byte
    copies' excepted (they copy host memory on the CPU arch: ``benchmarks/emulated_cuda.py``); undone with
    ``monkeypatch`` at the test's end. Modules imported later keep the real query: load them first (a first run)."""
    from sim_core import ti_backend
    from sim_core.ti_kernels import device_copy

    for name, module in list(sys.modules.items()):
        if name.startswith("sim_core") and module is not device_copy \
                and getattr(module, "current_arch", None) is ti_backend.current_arch:
            monkeypatch.setattr(module, "current_arch", lambda: "cuda")
