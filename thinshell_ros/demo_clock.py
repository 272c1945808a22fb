"""Wall and CPU seconds of ``thinshell demo``'s stages, and its stages that run beside others.

The demo measures each stage's wall time and the CPU time spent while it ran, so that a run on a
loaded machine still says where the work goes (the load stretches wall time, not CPU time).

- :func:`cpu_seconds`: CPU s (user + system) of this process and its reaped children so far.
- :class:`Phase`: wall and CPU s of a stretch of the demo (one stage, or stages running side by side).
- :class:`BackgroundTool`: a ``thinshell`` command (``diagnose``, ``compare``) run as a subprocess beside
  the demo's own work, its output in a log file; :meth:`BackgroundTool.wait` gives its exit code,
  wall s to its exit and CPU s (the child's and its own children's, read from ``/proc`` when it exits, before
  it is reaped).
"""

from __future__ import annotations

import contextlib
import os
import resource
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def cpu_seconds() -> float:
    """CPU seconds (user + system) of this process (all threads) and of its children reaped so far."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


@dataclass
class Phase:
    """Wall and CPU seconds of a stretch of the demo, from construction to :meth:`stop`.

    Attributes:
        name: the phase's name (``demo.json``'s ``phases``).
        stages: the stages that ran in it (several when they ran side by side).
        wall_s, cpu_s: s, set by :meth:`stop` (CPU: this process and its children reaped in the phase).
    """

    name: str
    stages: tuple[str, ...]
    wall_s: float | None = None
    cpu_s: float | None = None
    _t0: float = field(default_factory=time.monotonic, repr=False)
    _c0: float = field(default_factory=cpu_seconds, repr=False)

    def stop(self) -> "Phase":
        self.wall_s = time.monotonic() - self._t0
        self.cpu_s = cpu_seconds() - self._c0
        return self

    def as_dict(self) -> dict:
        return {"stages": list(self.stages), "wall_s": round(self.wall_s or 0.0, 2), "cpu_s": round(self.cpu_s or 0.0, 2)}


def _proc_cpu(pid: int) -> float | None:
    """CPU s of a process and its reaped children (``/proc/<pid>/stat`` fields 14-17), None if unreadable."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()   # after "pid (comm) ": field 3 is fields[0]
    return sum(int(v) for v in fields[11:15]) / _TICK


class BackgroundTool:
    """``thinshell <tool> <args>`` as a subprocess of this checkout (``python -m thinshell_ros.cli``),
    stdout and stderr into ``log``.

    Args:
        tool: the ``thinshell`` command (``diagnose``, ``compare``, ...).
        args: its arguments.
        log: the log file (written).
    """

    def __init__(self, tool: str, args: Sequence[str], log: Path):
        self.tool, self.args, self.log = tool, [str(a) for a in args], Path(log)
        env = dict(os.environ)
        repo = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = repo + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self._t0 = time.monotonic()
        with open(self.log, "w") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "thinshell_ros.cli", tool, *self.args], env=env,
                                         stdout=out, stderr=subprocess.STDOUT)
        self.wall_s: float | None = None
        self.cpu_s: float | None = None
        self._watch = threading.Thread(target=self._on_exit, name=f"thinshell {tool} watch", daemon=True)
        self._watch.start()

    @property
    def command(self) -> str:
        return f"thinshell {self.tool} {' '.join(self.args)}"

    def _on_exit(self) -> None:
        """Wait for the child's exit without reaping it; then its wall and CPU s (readable until reaped)."""
        with contextlib.suppress(ChildProcessError):   # reaped already (a wait elsewhere): only the wall time
            os.waitid(os.P_PID, self.proc.pid, os.WEXITED | os.WNOWAIT)
            self.cpu_s = _proc_cpu(self.proc.pid)
        self.wall_s = time.monotonic() - self._t0

    def wait(self) -> int:
        """Wait for the tool to end; returns its exit code (:attr:`wall_s`: s from its start to its exit and
        :attr:`cpu_s`: its CPU s, are then set)."""
        self._watch.join()
        return self.proc.wait()

    def stop(self) -> None:
        """End the tool if it still runs (SIGTERM, then SIGKILL)."""
        if self.proc.poll() is None:
            self.proc.terminate()
            self._watch.join(timeout=10.0)
            try:
                self.proc.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def log_tail(self, n: int = 3000) -> str:
        """The last ``n`` characters of the tool's log."""
        try:
            return self.log.read_text(errors="replace")[-n:]
        except OSError:
            return ""
