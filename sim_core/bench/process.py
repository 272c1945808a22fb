"""Process figures of the benchmarks: when this process started, its peak resident memory."""

from __future__ import annotations

import os
import resource
import sys
import time
from pathlib import Path

_IMPORT_TIME = time.time()


def process_start_time() -> float:
    """Wall-clock time (s since the epoch) at which this process started.

    Read from ``/proc/self/stat`` (start time in clock ticks after boot) and ``/proc/stat`` (boot
    time); falls back to the time this module was imported where ``/proc`` is unavailable.
    """
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        start_ticks = int(fields[19])  # field 22 of stat(5); fields[0] is field 3
        btime = next(int(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines() if line.startswith("btime"))
        return btime + start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return _IMPORT_TIME


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far, MiB (``getrusage``; KiB on Linux)."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024.0 if sys.platform != "darwin" else kib / 2**20
