"""The kernels a process compiles reach Taichi's offline cache even when the process froze its
long-lived objects (``gc.freeze``, as the ROS nodes do), so the next process loads them instead of
compiling again; a forked child does not finalise its parent's runtime."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]

PROBE = textwrap.dedent("""
    import gc, os, sys
    from sim_core.ti_backend import init_backend, write_offline_cache
    init_backend("cpu", offline_cache_dir=sys.argv[1])
    from sim_core.ti_kernels import compaction
    compaction.compile_kernels()
    pid = os.fork()
    if pid == 0:  # a forked child running its parent's exit handlers finalises nothing
        os._exit(0 if write_offline_cache(os.getppid()) is False else 3)
    assert os.waitpid(pid, 0)[1] == 0
    if sys.argv[2] == "freeze":
        keep = [gc]
        keep.append(keep)  # a cycle among the frozen objects, as a node's start-up state has
        gc.collect()
        gc.freeze()
""")


def _cache_files(tmp_path: Path, mode: str) -> list[Path]:
    cache = tmp_path / f"cache_{mode}"
    run = subprocess.run([sys.executable, "-c", PROBE, str(cache), mode], cwd=REPO, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    return sorted(p for p in cache.rglob("*") if p.is_file())


def test_a_frozen_process_still_writes_its_kernels_to_the_offline_cache(tmp_path):
    frozen = _cache_files(tmp_path, "freeze")
    plain = _cache_files(tmp_path, "plain")
    assert frozen, "a process with gc.freeze left nothing in the offline cache"
    assert [p.name for p in frozen] == [p.name for p in plain]
