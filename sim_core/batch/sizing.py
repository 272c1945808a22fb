"""Batch size ``B`` chosen to fit the device: the memory one copy of a batch needs, measured from a
probe batch, against the memory free on the device and the host.

:func:`auto_batch_size` is the rule (largest ``B`` with ``B * per_copy <= free * (1 - reserve)``, at
most ``cap``); :func:`per_copy_from_probe` turns the memory used with no batch, a batch of one copy
and a batch of two into the per-copy figure; :func:`measure_per_copy` builds and warms the two
probe batches; :func:`free_memory` reads what is free (CUDA: ``nvidia-smi
--query-gpu=memory.free``; host: ``MemAvailable`` of ``/proc/meminfo``) and :func:`used_memory` what
this process uses (CUDA: ``nvidia-smi --query-compute-apps``; host: resident set size).
"""

from __future__ import annotations

import argparse
import gc
import os
import shutil
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from sim_core.errors import ConfigError, InsufficientMemoryError

MIB = 2**20
HOST_NOISE_BYTES = 64 * 1024
"""Host growth per copy at or below this is probe noise (page granularity, the probe's own
bookkeeping), not a copy's memory."""
DEFAULT_RESERVE = 0.2
"""Fraction of the free memory left unused by :func:`auto_batch_size` (allocator slack, JIT, other work)."""


def auto_batch_size(per_copy_bytes: float, free_bytes: float, cap: int | None = None,
                    reserve_fraction: float = DEFAULT_RESERVE, what: str = "device") -> int:
    """Largest batch size ``B`` whose copies fit in the free memory less a reserve.

    ``B = floor(free_bytes * (1 - reserve_fraction) / per_copy_bytes)``, at most ``cap``.

    Args:
        per_copy_bytes: memory one copy adds, bytes (> 0; :func:`per_copy_from_probe`).
        free_bytes: memory free now, bytes (>= 0; :func:`free_memory`).
        cap: upper bound on ``B`` (>= 1; e.g. the population size), or None.
        reserve_fraction: fraction of ``free_bytes`` kept free, in ``[0, 1)``.
        what: the memory's name in error messages (``"GPU"``, ``"host"``).

    Returns:
        ``B >= 1``.

    Raises:
        ConfigError: ``per_copy_bytes <= 0`` or not finite, ``free_bytes < 0``, ``cap < 1``, or
            ``reserve_fraction`` outside ``[0, 1)``.
        InsufficientMemoryError: not even one copy fits.
    """
    per_copy, free = float(per_copy_bytes), float(free_bytes)
    if not per_copy > 0.0 or per_copy == float("inf"):
        raise ConfigError(f"batch sizing: memory per copy must be a positive number of bytes, got {per_copy_bytes}")
    if not free >= 0.0:
        raise ConfigError(f"batch sizing: free {what} memory must be >= 0 bytes, got {free_bytes}")
    if cap is not None and int(cap) < 1:
        raise ConfigError(f"batch sizing: cap must be >= 1, got {cap}")
    if not 0.0 <= float(reserve_fraction) < 1.0:
        raise ConfigError(f"batch sizing: reserve_fraction must be in [0, 1), got {reserve_fraction}")
    usable = free * (1.0 - float(reserve_fraction))
    B = int(usable // per_copy) if usable < per_copy * 2.0**62 else 2**62
    if B < 1:
        raise InsufficientMemoryError(
            f"batch sizing: not even one copy fits in {what} memory: one copy needs {per_copy / MIB:.1f} MiB, "
            f"{free / MIB:.1f} MiB free of which {usable / MIB:.1f} MiB usable "
            f"(reserve {100 * float(reserve_fraction):.0f} %)")
    return B if cap is None else min(B, int(cap))


def per_copy_from_probe(used_0: float, used_1: float, used_2: float) -> float:
    """Memory one copy adds, from the memory used with no batch, a batch of one copy and of two.

    The larger of the second copy's increment ``used_2 - used_1`` and the mean ``(used_2 - used_0)
    / 2`` (a first copy may carry shared set-up, a second may land in memory the allocator already
    held: the larger figure does not under-count).

    Args:
        used_0, used_1, used_2: memory used, bytes, with no batch, ``B = 1``, ``B = 2``.

    Returns:
        bytes per copy (> 0).

    Raises:
        ConfigError: no growth measured (both figures <= 0): the probe cannot size a batch.
    """
    per_copy = max(float(used_2) - float(used_1), (float(used_2) - float(used_0)) / 2.0)
    if not per_copy > 0.0:
        raise ConfigError(f"batch sizing: the probe measured no memory growth per copy (used {used_0:.0f}, "
                          f"{used_1:.0f}, {used_2:.0f} bytes with 0, 1, 2 copies)")
    return per_copy


def _nvidia_smi(args: list[str]) -> str | None:
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return None
    try:
        return subprocess.run([exe, *args, "--format=csv,noheader,nounits"], capture_output=True, text=True,
                              timeout=20, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None


def host_available_bytes(meminfo: Path = Path("/proc/meminfo")) -> float | None:
    """``MemAvailable`` of ``meminfo``, bytes; None where the file or the field is missing."""
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) * 1024.0  # kB
    except (OSError, ValueError, IndexError):
        return None
    return None


def host_used_bytes() -> float | None:
    """Resident set size of this process, bytes (``/proc/self/statm``); None where unavailable."""
    try:
        return float(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def gpu_free_bytes(device: int = 0) -> float | None:
    """Free memory of CUDA device ``device``, bytes (``nvidia-smi --query-gpu=memory.free``); None where
    ``nvidia-smi`` is missing or fails."""
    out = _nvidia_smi(["--query-gpu=memory.free"])
    if out is None:
        return None
    rows = [line.strip() for line in out.splitlines() if line.strip()]
    try:
        return float(rows[device]) * MIB
    except (IndexError, ValueError):
        return None


def gpu_used_bytes() -> float | None:
    """GPU memory used by this process, bytes (``nvidia-smi --query-compute-apps``); None where
    ``nvidia-smi`` is missing or lists no memory for this process."""
    out = _nvidia_smi(["--query-compute-apps=pid,used_memory"])
    if out is None:
        return None
    used = [float(mem) for pid, mem in (line.split(",", 1) for line in out.splitlines() if "," in line)
            if pid.strip() == str(os.getpid())]
    return sum(used) * MIB if used else None


def free_memory(resource: str) -> float | None:
    """Free memory of ``resource`` (``"gpu"``: CUDA device 0; ``"host"``), bytes; None if unknown."""
    return gpu_free_bytes() if resource == "gpu" else host_available_bytes()


def used_memory(resource: str) -> float | None:
    """Memory this process uses on ``resource`` (``"gpu"`` or ``"host"``), bytes; None if unknown."""
    return gpu_used_bytes() if resource == "gpu" else host_used_bytes()


def resources_of(backend: str) -> tuple[str, ...]:
    """Memories a batch of ``backend`` fills: ``("host", "gpu")`` for ``taichi-cuda``, else ``("host",)``."""
    return ("host", "gpu") if backend == "taichi-cuda" else ("host",)


@dataclass(frozen=True)
class BatchSizing:
    """A batch size chosen to fit, with the figures it came from.

    Attributes:
        B: the batch size (>= 1).
        per_copy_bytes: memory per copy, bytes, per resource (``"host"``, ``"gpu"``).
        free_bytes: memory free at the probe, bytes, per resource.
        limit: the resource that bounds ``B`` (``"cap"`` when the cap does).
    """

    B: int
    per_copy_bytes: dict
    free_bytes: dict
    limit: str

    def as_record(self) -> dict:
        """The figures in MiB for a JSON record (``auto_B``, ``auto_limit``, ``{res}_mib_per_copy_probe``,
        ``{res}_mib_free``)."""
        rec = {"auto_B": self.B, "auto_limit": self.limit}
        for res, v in self.per_copy_bytes.items():
            rec[f"{res}_mib_per_copy_probe"] = v / MIB
        for res, v in self.free_bytes.items():
            rec[f"{res}_mib_free"] = v / MIB
        return rec


def measure_per_copy(build: Callable[[int], object], resources: tuple[str, ...],
                     used: Callable[[str], float | None] | None = None) -> dict:
    """Memory per copy on each resource, from probe batches of one and two copies.

    Host memory is measured two ways and the larger figure is kept (one at or below
    :data:`HOST_NOISE_BYTES` counts as no growth): the growth of ``used("host")``
    (resident set size by default; it misses memory that the allocator reuses after earlier work was
    freed) and the growth of the Python heap as :mod:`tracemalloc` traces it (NumPy and SciPy arrays
    included; it misses memory that native libraries such as Taichi or PARDISO allocate themselves).

    Args:
        build: ``build(B)`` builds and warms a batch of ``B`` copies (it is kept alive while the memory
            is read, then dropped).
        resources: ``"host"`` and/or ``"gpu"``.
        used: ``used(resource)``: memory this process uses, bytes, or None (default :func:`used_memory`).

    A GPU's use that does not grow with the probe (the copies fit in memory that Taichi's pool
    already holds: under 1 MiB a copy on an H100, ``docs/benchmarks.md``) leaves the GPU out: the
    host, at some 15 MiB a copy, bounds ``B`` first.

    Returns:
        ``{resource: bytes per copy}`` for the resources whose use could be read and grew.

    Raises:
        ConfigError: the host probe measured no growth either way.
    """
    import tracemalloc

    used = used or used_memory
    tracing = tracemalloc.is_tracing()
    if not tracing:
        tracemalloc.start()
    try:
        gc.collect()
        readings = [{**{r: used(r) for r in resources}, "traced": float(tracemalloc.get_traced_memory()[0])}]
        for B in (1, 2):
            batch = build(B)
            readings.append({**{r: used(r) for r in resources}, "traced": float(tracemalloc.get_traced_memory()[0])})
            del batch
            gc.collect()
    finally:
        if not tracing:
            tracemalloc.stop()
    out = {}
    for r in resources:
        vals = [rd[r] for rd in readings]
        if r == "host":
            figures = [max(vals[2] - vals[1], (vals[2] - vals[0]) / 2.0)] if all(v is not None for v in vals) else []
            figures.append(max(readings[2]["traced"] - readings[1]["traced"],
                               (readings[2]["traced"] - readings[0]["traced"]) / 2.0))
            if max(figures) <= HOST_NOISE_BYTES:
                raise ConfigError(f"batch sizing: the probe measured no host memory growth per copy (resident set "
                                  f"{vals} bytes, traced heap {[rd['traced'] for rd in readings]} bytes with 0, 1, 2 copies)")
            out[r] = max(figures)
        elif all(v is not None for v in vals) and max(vals[2] - vals[1], (vals[2] - vals[0]) / 2.0) > 0.0:
            out[r] = per_copy_from_probe(*vals)
    return out


def choose_batch_size(per_copy_bytes: dict, cap: int | None = None, reserve_fraction: float = DEFAULT_RESERVE,
                      free: Callable[[str], float | None] | None = None) -> BatchSizing:
    """The largest ``B`` that fits every resource of ``per_copy_bytes`` (:func:`auto_batch_size` on each).

    Args:
        per_copy_bytes: ``{resource: bytes per copy}`` (:func:`measure_per_copy`).
        cap: upper bound on ``B``, or None.
        reserve_fraction: as :func:`auto_batch_size`.
        free: ``free(resource)``: free memory, bytes, or None (default :func:`free_memory`).

    Returns:
        the :class:`BatchSizing`.

    Raises:
        ConfigError: no resource's free memory or per-copy memory could be read and no cap bounds ``B``.
        InsufficientMemoryError: not even one copy fits one of the resources.
    """
    free = free or free_memory
    names = {"gpu": "GPU", "host": "host"}
    sizes, frees = {}, {}
    for r, per in per_copy_bytes.items():
        f = free(r)
        if f is None:
            continue
        frees[r] = f
        sizes[r] = auto_batch_size(per, f, None, reserve_fraction, what=names.get(r, r))
    if not sizes:
        if cap is None:
            raise ConfigError("batch sizing: neither the free memory nor the memory per copy could be read")
        return BatchSizing(int(cap), dict(per_copy_bytes), frees, "cap")
    limit = min(sizes, key=sizes.get)
    B = sizes[limit]
    if cap is not None and int(cap) < B:
        B, limit = int(cap), "cap"
    return BatchSizing(B, dict(per_copy_bytes), frees, limit)


def batch_size_arg(text: str) -> int | str:
    """A ``--batch-size`` command-line value (an ``argparse`` type): an integer >= 1 or ``auto``.

    Raises:
        argparse.ArgumentTypeError: anything else.
    """
    if text == "auto":
        return text
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"an integer >= 1 or auto, got {text!r}")
    return value
