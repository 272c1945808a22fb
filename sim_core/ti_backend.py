"""The Taichi runtime of the element kernels: one explicit, idempotent initialisation per process.

Taichi keeps its runtime (arch, default float type, compiled kernels, allocated ndarrays) in
process-global state, and ``ti.init`` may run only once before kernels are used. This module is the
ONE place in thinshell that holds that state: :data:`_STATE` records the arch this process
initialised Taichi with (``None`` until :func:`init_backend` is called). Nothing here calls
``ti.init`` at import time; importing this module only imports ``taichi``. Machine-readable stdout
(``bench --json``) stays clean: the import-time version banner is switched off through Taichi's
``ENABLE_TAICHI_HEADER_PRINT`` variable (only when the user has not set it) and ``ti.init``'s
start-up line is sent to stderr.

Usage::

    from sim_core.ti_backend import init_backend
    arch = init_backend("cpu")          # or "cuda"; once per process, before any Taichi potential

Kernels run in float64 (``default_fp=ti.f64``). The offline cache (compiled kernels kept on disk,
Taichi's ``offline_cache`` option) makes the second process start without LLVM work; the Python
frontend (the AST walk that builds each kernel's IR and cache key) still runs, made cheaper by
:func:`sim_core.ti_frontend.memoize_source_positions` and
:func:`~sim_core.ti_frontend.memoize_function_sources`, which :func:`init_backend` installs.

Taichi writes the kernels a process compiled into the offline cache only when its program is
finalised (``ti.reset()``, or the program object's destruction at exit). A process that moved its
long-lived objects to the collector's permanent generation (``gc.freeze``, as the ROS nodes do) never
destroys the program, so it would compile every kernel again on each start and leave nothing for
the next process: :func:`init_backend` therefore registers :func:`write_offline_cache` to run at
the initialising process's exit.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import sys
from dataclasses import dataclass

from sim_core.errors import ConfigError
from sim_core.ti_frontend import memoize_function_sources, memoize_source_positions

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
import taichi as ti  # noqa: E402  (after the banner switch above)

SUPPORTED_ARCHS: tuple[str, ...] = ("cpu", "cuda")
"""Arch names accepted by :func:`init_backend`."""


@dataclass
class _BackendState:
    """Process-global Taichi state (Taichi itself is process-global; see the module docstring).

    Attributes:
        arch: the arch Taichi was initialised with (``"cpu"`` or ``"cuda"``), ``None`` before.
        offline_cache: whether the offline kernel cache is on.
    """

    arch: str | None = None
    offline_cache: bool = True


_STATE = _BackendState()
"""The only module-level mutable state of the Taichi backend (one Taichi runtime per process)."""


def init_backend(arch: str = "cpu", offline_cache: bool = True, offline_cache_dir: str | None = None,
                 kernel_profiler: bool = False) -> str:
    """Initialise Taichi once for this process (float64 kernels) and return the arch in use.

    Also memoises Taichi's per-node source-position messages and function sources
    (:mod:`sim_core.ti_frontend`; the same IR and messages, less frontend time).
    Idempotent: a second call with the same arch returns at once. Taichi cannot switch arch while
    kernels and ndarrays of the first arch are alive, so a call with another arch raises.

    Args:
        arch: ``"cpu"`` (LLVM x64/arm64, the default) or ``"cuda"``.
        offline_cache: keep compiled kernels on disk between processes (Taichi ``offline_cache``).
        offline_cache_dir: directory of the offline cache; ``None`` uses Taichi's default
            (``~/.cache/taichi/ticache``).
        kernel_profiler: record each kernel task's device time (Taichi ``kernel_profiler``, read with
            ``ti.profiler.print_kernel_profiler_info``; benchmarks only: it synchronises every launch).

    Returns:
        the arch actually used, ``"cpu"`` or ``"cuda"`` (Taichi never silently falls back here).

    Raises:
        ConfigError: unknown arch name; CUDA requested but not available on this machine (no
            driver or no GPU); Taichi already initialised with a different arch.
    """
    if arch not in SUPPORTED_ARCHS:
        raise ConfigError(f"init_backend: unknown Taichi arch {arch!r}; use one of {SUPPORTED_ARCHS}")
    if _STATE.arch is not None:
        if _STATE.arch != arch:
            raise ConfigError(
                f"init_backend: Taichi is already initialised with arch {_STATE.arch!r} in this process; "
                f"cannot switch to {arch!r} (start a new process)"
            )
        return _STATE.arch
    # fast_math off: LLVM fast-math may reassociate sums and assume no inf/NaN, which breaks the
    # 1e-10 agreement with the NumPy reference and the inf-safe Jacobi rotations.
    options = {"offline_cache": bool(offline_cache), "fast_math": False, "kernel_profiler": bool(kernel_profiler)}
    if offline_cache_dir is not None:
        options["offline_cache_file_path"] = str(offline_cache_dir)
    ti_arch = ti.cpu if arch == "cpu" else ti.cuda
    try:
        with contextlib.redirect_stdout(sys.stderr):
            ti.init(arch=ti_arch, default_fp=ti.f64, default_ip=ti.i32, enable_fallback=False,
                    log_level=ti.WARN, **options)
    except RuntimeError as err:
        raise ConfigError(f"init_backend: Taichi arch {arch!r} is not available on this machine ({err})") from err
    _STATE.arch = arch
    _STATE.offline_cache = bool(offline_cache)
    if offline_cache:
        atexit.register(write_offline_cache, os.getpid())
    memoize_source_positions()
    memoize_function_sources()
    return arch


def write_offline_cache(owner_pid: int | None = None) -> bool:
    """Finalise the Taichi program, which writes the kernels compiled in this process into the offline
    cache (module docstring); registered at exit by :func:`init_backend`. After it Taichi is
    uninitialised in this process.

    Args:
        owner_pid: the process that initialised Taichi; in any other process (a forked child that runs
            its parent's exit handlers) nothing is done, since a child's copy of the runtime has no
            worker threads to finalise with.

    Returns:
        whether the program was finalised.
    """
    if _STATE.arch is None or not _STATE.offline_cache or (owner_pid is not None and os.getpid() != owner_pid):
        return False
    ti.reset()
    _STATE.arch = None
    return True


def current_arch() -> str | None:
    """The arch Taichi was initialised with in this process, or ``None`` before :func:`init_backend`."""
    return _STATE.arch


def serial_loops() -> bool:
    """Whether element loops that sum into shared entries run serially (the fused kernels).

    On the CPU they do: the sums are then in element order, so results are bitwise reproducible run
    to run, and on a few cores parallel atomics were slower (see docs/benchmarks_log.md). On CUDA they
    run in parallel (Taichi makes ``+=`` on global memory atomic there). Called at kernel
    compile time (``ti.loop_config(serialize=ti.static(serial_loops()))``), after :func:`init_backend`.
    """
    return _STATE.arch != "cuda"


def require_backend(who: str) -> str:
    """The current arch; raises if :func:`init_backend` has not been called.

    Args:
        who: name of the caller, used in the error message.

    Raises:
        ConfigError: Taichi not initialised yet.
    """
    if _STATE.arch is None:
        raise ConfigError(
            f"{who}: the Taichi backend is not initialised; call sim_core.ti_backend.init_backend(arch) first"
        )
    return _STATE.arch
