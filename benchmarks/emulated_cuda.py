"""The CUDA paths of ``sim_core`` emulated on Taichi's CPU arch, for the benchmark scripts of this folder.

:func:`gpu_sum_cells` gives the summing kernels a GPU's sum arrays (device arrays of ``launch.SUM_CELLS`` cells: the
sums then equal the CPU arch's to round-off only); :func:`answer_cuda`, called once the modules in question are
imported (after a first run: the kernels compiled), makes the arch query of every loaded ``sim_core`` module but the
byte copies' (:mod:`sim_core.ti_kernels.device_copy`, which must copy host memory on the CPU arch) answer "cuda", as
``tests/sim_core/ti_kernels/test_device_paths.py`` does (:func:`import_kernel_modules` imports them all first, for a
script without a compilation run). :func:`add_emulation_flag` and :func:`init_arch` are the scripts' flag and its
check. The Taichi program still runs on the CPU arch, so the
kernels' loops stay serial where a single environment asks for it.
"""

from __future__ import annotations

import sys


def add_emulation_flag(ap) -> None:
    """A benchmark script's ``--emulate-cuda`` flag (``argparse`` parser ``ap``; :func:`init_arch` checks it)."""
    ap.add_argument("--emulate-cuda", action="store_true",
                    help="on the CPU arch: every sim_core arch query answers cuda (the CUDA paths, emulated)")


def init_arch(ap, args, kernel_profiler: bool = False, offline_cache_dir: str | None = None) -> None:
    """Refuse ``--emulate-cuda`` off the CPU arch (``ap.error``), initialise the Taichi backend of ``args.arch``
    (:func:`sim_core.ti_backend.init_backend`'s ``kernel_profiler`` and ``offline_cache_dir``: None, Taichi's own)
    and, emulating, give the sums a GPU's cells (:func:`gpu_sum_cells`; :func:`answer_cuda` comes after the kernels'
    compilation run, or after :func:`import_kernel_modules`)."""
    if args.emulate_cuda and args.arch != "cpu":
        ap.error("--emulate-cuda emulates the CUDA paths on the CPU arch: --arch cpu")
    from sim_core.ti_backend import init_backend

    init_backend(args.arch, offline_cache_dir=offline_cache_dir, kernel_profiler=kernel_profiler)
    if args.emulate_cuda:
        gpu_sum_cells()


def gpu_sum_cells() -> None:
    """The summing kernels' sum arrays with a GPU's ``SUM_CELLS`` cells (before the first sum is made), and the byte
    copies' own arch query kept on the CPU arch (:func:`answer_cuda` leaves it)."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import device_copy, launch

    launch._new_cells = lambda runtime: device_copy.new_ndarray(ti.f64, (launch.SUM_CELLS,))
    device_copy.current_arch = lambda: "cpu"


def import_kernel_modules() -> None:
    """Import every module of the kernel packages (``sim_core.energies``, ``.candidates``, ``.ti_kernels``,
    ``.batch``), so that :func:`answer_cuda` reaches them before any kernel is compiled: for a script that emulates
    from its first kernel on (no compilation run before)."""
    import importlib
    import pkgutil

    for package_name in ("sim_core.energies", "sim_core.candidates", "sim_core.ti_kernels", "sim_core.batch"):
        package = importlib.import_module(package_name)
        for info in pkgutil.walk_packages(package.__path__, package_name + "."):
            importlib.import_module(info.name)


def answer_cuda() -> int:
    """Every loaded ``sim_core`` module whose ``current_arch`` is :func:`sim_core.ti_backend.current_arch` answers
    "cuda" from now on (:mod:`sim_core.ti_kernels.device_copy` excepted); returns how many modules were changed."""
    import sim_core.ti_backend as ti_backend
    from sim_core.ti_kernels import device_copy

    query = ti_backend.current_arch
    changed = 0
    for module in list(sys.modules.values()):
        if getattr(module, "__name__", "").startswith("sim_core") and module is not device_copy \
                and getattr(module, "current_arch", None) is query:
            module.current_arch = lambda: "cuda"
            changed += 1
    return changed
