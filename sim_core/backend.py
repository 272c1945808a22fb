"""The compute backend of a solver: one declared name (``SolverConfig.backend``), resolved once.

Backends:

- ``"numpy"``: the NumPy reference potentials and contact set (no Taichi).
- ``"taichi-cpu"``: the fused Taichi elastic kernels of the Newton loop
  (:class:`sim_core.fused_elastic.FusedElastic`) and the Taichi contact, friction and broad-phase
  kernels of :class:`sim_core.contact_set.ContactSet`, on Taichi's CPU backend (serial element loops:
  results reproducible bit for bit, and safe in forked replay workers). The elastic potentials
  themselves stay the NumPy reference (the adjoint and sensitivities use them); their Taichi twins
  (:func:`sim_core.energies.registry.use_taichi_kernels`) are not part of a backend (their loops are parallel,
  which a forked worker cannot run).
- ``"taichi-cuda"``: the same kernels on CUDA (parallel element loops: sums in a varying order). The
  kernels of one environment keep their arrays in device memory and copy only their outputs back
  (:mod:`sim_core.ti_kernels.device_copy`), but the Newton system is still solved on the host (the
  symmetric solver of ``SolverConfig.linear_solver``), so one environment of a scene this small is still
  slower here than on ``taichi-cpu``: Forming (1,698 DoF) at 24.8-25.2 steps/s on an H200 host against
  28.6-31.1 with ``taichi-cpu`` on the same host's CPU (SciPy SuperLU, no MKL; docs/benchmarks_log.md,
  session 39, 28single). The GPU pays off for batches of copies (:mod:`sim_core.batch`).
- ``"auto"``: the fastest available, resolved by :func:`resolve_backend`: ``taichi-cuda`` when
  Taichi starts on CUDA, else ``taichi-cpu`` when Taichi imports, else ``numpy``; in a process whose
  Taichi runtime is already initialised, the Taichi backend of that arch.

Batches of scene copies (:mod:`sim_core.batch`) run on any of these backends: every copy's solver
resolves the same name, and the copies share the process's Taichi runtime.

Taichi keeps one runtime per process (:mod:`sim_core.ti_backend`): :func:`resolve_backend` initialises
it (:func:`sim_core.ti_backend.init_backend`, idempotent) for a Taichi backend, and a second backend
of another arch in the same process is a :class:`~sim_core.errors.ConfigError`.
"""

from __future__ import annotations

from sim_core.errors import ConfigError

BACKENDS: tuple[str, ...] = ("numpy", "taichi-cpu", "taichi-cuda")
"""The concrete backends (what :func:`resolve_backend` returns)."""

BACKEND_CHOICES: tuple[str, ...] = BACKENDS + ("auto",)
"""Accepted values of ``SolverConfig.backend``."""

_ARCH = {"numpy": None, "taichi-cpu": "cpu", "taichi-cuda": "cuda"}


def check_backend(name: object, what: str = "solver backend") -> str:
    """``name`` when it is one of :data:`BACKEND_CHOICES`.

    Raises:
        ConfigError: anything else, naming ``what`` and the allowed values.
    """
    if not isinstance(name, str) or name not in BACKEND_CHOICES:
        raise ConfigError(f"{what} must be one of {', '.join(BACKEND_CHOICES)}; got {name!r}")
    return name


def backend_arch(backend: str) -> str | None:
    """The Taichi arch of a concrete backend (``"cpu"``, ``"cuda"``), None for ``"numpy"``.

    Raises:
        ConfigError: not one of :data:`BACKENDS`.
    """
    if backend not in _ARCH:
        raise ConfigError(f"backend must be one of {', '.join(BACKENDS)}; got {backend!r}")
    return _ARCH[backend]


def uses_taichi(backend: str) -> bool:
    """Whether a concrete backend runs the Taichi kernels."""
    return backend_arch(backend) is not None


def backend_of_arch(arch: str) -> str:
    """The backend of an arch name of the command-line tools (``numpy``, ``cpu``, ``cuda``).

    Raises:
        ConfigError: another name.
    """
    for backend, a in _ARCH.items():
        if arch == (a or "numpy"):
            return backend
    raise ConfigError(f"arch must be one of numpy, cpu, cuda; got {arch!r}")


def resolve_backend(name: str) -> str:
    """The concrete backend for ``name`` (:data:`BACKEND_CHOICES`), with Taichi initialised for it.

    Raises:
        ConfigError: an unknown name; a Taichi backend whose arch is not available here, or whose
            arch differs from the one this process already initialised Taichi with.
    """
    check_backend(name)
    if name == "numpy":
        return name
    if name == "auto":
        return _fastest_available()
    from sim_core.ti_backend import init_backend  # Taichi only for a Taichi backend

    init_backend(_ARCH[name])
    return name


def _fastest_available() -> str:
    """``"auto"``: the backend of an already initialised Taichi runtime, else ``taichi-cuda``, else
    ``taichi-cpu``, else ``numpy`` (Taichi not installed)."""
    try:
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.ti_backend import current_arch, init_backend
    except ImportError:
        return "numpy"
    arch = current_arch()
    if arch is None:
        try:
            arch = init_backend("cuda")
        except ConfigError:
            arch = init_backend("cpu")
    return "taichi-cuda" if arch == "cuda" else "taichi-cpu"
