"""A second process that evaluates one fused elastic term while the Newton loop evaluates the others.

Taichi's CPU kernel launches hold Python's GIL, and its parallel loops (atomic adds on a few cores)
ran the fused kernels about twice as slow as the serial ones on the 2-core machine
(docs/benchmarks.md), so one process uses one core. Two processes do run side by side at full
speed. :class:`ElasticWorker` starts a worker process (``python -m sim_core.elastic_worker``)
with its own Taichi runtime; :class:`sim_core.fused_elastic.FusedElastic` hands it the largest
fused term that supports it (a Stable Neo-Hookean gel: :meth:`offload_recipe`), and evaluates the
other terms in the meantime. On Forming the gel's 1125 tets (about 0.4 ms per evaluation) then
overlap the sheet's membrane and bending (about 0.45 ms).

Protocol. Positions, gradient, Hessian values and energy are exchanged through one shared memory
region (a file mapped by both processes, unlinked once both have it): ``int64`` flags
``[request, done, status, idle]`` then ``float64`` ``x (n, 3)``, ``grad (n, 3)``,
``values (nv,)``, ``energy``. Control messages (configure, wake, stop, stats) go over a socket pair
as :class:`multiprocessing.connection.Connection` messages. To evaluate, the parent writes ``x``
and increments ``request``; the worker, busy-waiting on ``request`` for :data:`SPIN_SECONDS` after
its last evaluation, zeroes ``grad`` and ``values``, runs the kernel, writes the energy and
``status`` and sets ``done``. The busy-waits need stores to become visible in program order (x86's
total store order); on other machines each request and reply is a socket message instead. After
:data:`SPIN_SECONDS` without a request the worker blocks on the socket (at most
:data:`IDLE_POLL_SECONDS` at a time), with ``idle`` set, and the parent sends a wake message.

The worker's term is always summed as the parent would sum it if it evaluated the term itself
(:class:`~sim_core.fused_elastic.FusedElastic`): gradient and values into zeroed buffers, added
after the other terms. The results therefore do not depend on whether the worker is up, busy or
gone; any failure (no start, a crash, a timeout, an error in the kernel) is logged once, the worker
is shut down, and the term is evaluated in the parent from then on.
"""

from __future__ import annotations

import importlib
import logging
import mmap
import os
import pickle
import platform
import socket
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Callable

import numpy as np

LOG = logging.getLogger(__name__)

SPIN_SECONDS = 0.005
"""The worker busy-waits this long after an evaluation for the next request (a Newton iteration
asks every few milliseconds) before it blocks on its socket."""

IDLE_POLL_SECONDS = 0.002
"""While blocked, the worker still looks at the request flag this often (a request whose wake
message it missed waits at most this long)."""

START_TIMEOUT_S = 120.0
"""Seconds :meth:`ElasticWorker.wait_ready` waits by default (import, Taichi start, kernel load)."""

REPLY_TIMEOUT_S = 60.0
"""Seconds the parent waits for a configuration or an evaluation before it gives the worker up."""

SPIN_FLAGS = (platform.machine().lower() in ("x86_64", "amd64")
              and os.environ.get("THINSHELL_WORKER_SIGNAL", "flags") != "socket")
"""Whether requests and replies are signalled by busy-waiting on the shared flags (x86: stores
are seen in program order) instead of socket messages (elsewhere, or with the environment variable
``THINSHELL_WORKER_SIGNAL=socket``, which the worker inherits)."""

_REQUEST, _DONE, _STATUS, _IDLE = range(4)
_FLAG_BYTES = 32


class WorkerError(RuntimeError):
    """The worker failed (did not start, died, timed out or reported an error); handled by falling back."""


def _layout(n: int, nv: int) -> tuple[int, int]:
    """Float count ``6 n + nv + 1`` and byte size of a region for ``n`` vertices and ``nv`` values."""
    floats = 6 * n + nv + 1
    return floats, _FLAG_BYTES + 8 * floats


class _Region:
    """The shared memory of one configuration: flags and the arrays (module docstring), over an mmap."""

    def __init__(self, buffer: mmap.mmap, n: int, nv: int) -> None:
        self.buffer = buffer
        self.n, self.nv = n, nv
        floats, _ = _layout(n, nv)
        self.flags = np.ndarray((4,), dtype=np.int64, buffer=buffer)
        data = np.ndarray((floats,), dtype=np.float64, buffer=buffer, offset=_FLAG_BYTES)
        self.x = data[: 3 * n].reshape(n, 3)
        self.grad = data[3 * n: 6 * n].reshape(n, 3)
        self.values = data[6 * n: 6 * n + nv]
        self.energy = data[6 * n + nv:]

    @classmethod
    def open(cls, path: str, n: int, nv: int) -> "_Region":
        """Map the region file ``path`` (created by the parent with the size of :func:`_layout`)."""
        _, size = _layout(n, nv)
        with open(path, "r+b") as f:
            buffer = mmap.mmap(f.fileno(), size)
        return cls(buffer, n, nv)

    def close(self) -> None:
        """Drop the arrays and unmap (later use of the arrays is an error, not a crash)."""
        self.flags = self.x = self.grad = self.values = self.energy = None
        try:
            self.buffer.close()
        except BufferError:  # an array view still exported somewhere: leave the map to the GC
            pass


def _resolve(target: str) -> Callable:
    """The function ``module:name`` of a recipe."""
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


# ------------------------------------------------------------------------------------------ parent
class ElasticWorker:
    """A worker process that evaluates one fused elastic term concurrently (module docstring).

    Starting it returns at once; :attr:`ready` turns True when the worker has started Taichi and
    loaded its kernel (seconds; the parent evaluates the term itself until then). Use it from one
    thread at a time per evaluation (:meth:`begin` / :meth:`finish`; another thread's ``begin``
    during an evaluation gets False). Several solvers may share one worker (it reconfigures when
    the term changes). The process ends with :meth:`close`, when the object is collected, or at
    interpreter exit.

    Args:
        python: interpreter of the worker (default: this one, ``sys.executable``).

    Raises:
        OSError: the process cannot be started.
    """

    def __init__(self, python: str | None = None) -> None:
        parent, child = socket.socketpair()
        root = str(Path(__file__).resolve().parents[1])  # the directory holding sim_core
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        try:
            self._process = subprocess.Popen(
                [python or sys.executable, "-m", "sim_core.elastic_worker", str(child.fileno())],
                pass_fds=(child.fileno(),), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=env)
        finally:
            child.close()
        parent.setblocking(True)
        self._socket = parent
        self._conn = Connection(os.dup(parent.fileno()))
        self._pid = os.getpid()  # a forked child of the parent must not use the worker
        self._lock = threading.Lock()
        self._ready = False
        self._broken: str | None = None
        self._region: _Region | None = None
        self._recipe: tuple | None = None  # (target, args) of the configuration
        self._sequence = 0
        self.evaluations = 0  # evaluations done by the worker
        self._finalizer = weakref.finalize(self, _shut_down, self._process, self._conn, parent, self._pid)

    # -------------------------------------------------------------------------------- state
    @property
    def ready(self) -> bool:
        """Whether the worker is up (non-blocking; False for good once it failed or was closed)."""
        if self._ready or self._broken is not None:
            return self._ready and self._broken is None
        try:
            if self._conn.poll():
                message = self._conn.recv()
                if message[0] != "ready":
                    raise WorkerError(str(message[1]) if message[0] == "error" else f"unexpected message {message[0]!r}")
                self._ready = True
            elif self._process.poll() is not None:
                raise WorkerError(f"the worker process exited with code {self._process.returncode} before it was ready")
        except (OSError, EOFError) as err:  # the socket closed: the process ended
            try:
                code = self._process.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                code = None
            self._fail(f"the worker process exited (code {code}) before it was ready ({err!r})")
        except WorkerError as err:
            self._fail(str(err))
        return self._ready and self._broken is None

    @property
    def failure(self) -> str | None:
        """Why the worker was given up (None while it is usable)."""
        return self._broken

    @property
    def pid(self) -> int:
        """Process id of the worker."""
        return self._process.pid

    def wait_ready(self, timeout: float = START_TIMEOUT_S) -> bool:
        """Block until :attr:`ready` (True) or ``timeout`` seconds (False; the worker may still come up)."""
        end = time.monotonic() + timeout
        while not self.ready and self._broken is None:
            remaining = end - time.monotonic()
            if remaining <= 0:
                return False
            self._conn.poll(min(remaining, 0.05))
        return self.ready

    def peak_rss_mib(self) -> float | None:
        """The worker's peak resident memory in MiB (None when it is not up)."""
        if not self.ready or not self._lock.acquire(blocking=False):
            return None
        try:
            self._send(("stats",))
            message = self._reply("stats")
            return float(message[1])
        except WorkerError as err:
            self._fail(str(err))
            return None
        finally:
            self._lock.release()

    def close(self) -> None:
        """Stop the worker process and release the shared memory (idempotent)."""
        if self._broken is None:
            self._broken = "closed"
        self._finalizer()
        if self._region is not None:
            self._region.close()
            self._region = None

    # -------------------------------------------------------------------------------- evaluation
    def begin(self, recipe: tuple[str, tuple], x: np.ndarray, value_count: int) -> bool:
        """Start evaluating ``recipe`` at positions ``x`` ``(n, 3)`` into ``value_count`` Hessian values.

        ``recipe``: ``(target, args)``, ``target`` a ``"module:function"`` called in the worker as
        ``function(args, x, grad, values) -> energy`` on zeroed ``grad`` and ``values`` (a fused
        part's :meth:`offload_recipe`); the worker is reconfigured (``args`` sent) when ``target``
        or any of ``args`` differs from the last call's (arrays compared by identity: a recipe's
        arrays must not be changed in place).

        Returns:
            True when the worker took the request (call :meth:`finish`); False when it is not ready,
            failed, or busy with another thread's request: evaluate locally.
        """
        if os.getpid() != self._pid or not self._lock.acquire(blocking=False):
            return False
        if not self.ready:
            self._lock.release()
            return False
        try:
            self._configure(recipe, x.shape[0], value_count)
            region = self._region
            np.copyto(region.x, x)
            self._sequence += 1
            if SPIN_FLAGS:
                region.flags[_REQUEST] = self._sequence
                if region.flags[_IDLE]:
                    self._send(("wake",))
            else:
                self._send(("evaluate", self._sequence))
            return True
        except Exception as err:  # noqa: BLE001 (WorkerError; OSError: no shared memory; a recipe that does not pickle)
            self._fail(f"{type(err).__name__}: {err}")
            self._lock.release()
            return False

    def finish(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        """Wait for the request of :meth:`begin`: ``(energy J, grad (n, 3) N, values (nv,) N/m)``, the
        arrays views of the shared memory valid until the next :meth:`begin`; None when the worker
        failed (logged; evaluate locally)."""
        try:
            region = self._region
            if SPIN_FLAGS:
                self._spin_until_done(region)
            else:
                message = self._reply("done")
                if message[1] != self._sequence:
                    raise WorkerError(f"reply to request {message[1]}, expected {self._sequence}")
            if region.flags[_STATUS] != 0:
                raise WorkerError("the worker's kernel raised (see its stderr)")
            self.evaluations += 1
            return float(region.energy[0]), region.grad, region.values
        except WorkerError as err:
            self._fail(str(err))
            return None
        finally:
            self._lock.release()

    # -------------------------------------------------------------------------------- internals
    def _configure(self, recipe: tuple[str, tuple], n: int, nv: int) -> None:
        """Send ``recipe`` (and a new region for other sizes) unless it is the configured one."""
        known = self._recipe
        region = self._region
        if known is not None and region is not None and region.n == n and region.nv == nv and (
                known is recipe or (known[0] == recipe[0] and len(known[1]) == len(recipe[1]) and all(
                    a is b or (not isinstance(a, np.ndarray) and a == b) for a, b in zip(known[1], recipe[1])))):
            return
        path = None
        if region is None or region.n != n or region.nv != nv:
            _, size = _layout(n, nv)
            fd, path = tempfile.mkstemp(prefix="thinshell-worker-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None)
            try:
                os.ftruncate(fd, size)
                buffer = mmap.mmap(fd, size)
            finally:
                os.close(fd)
            if region is not None:
                region.close()
            region = self._region = _Region(buffer, n, nv)
            self._recipe = None
        try:
            self._send(("configure", path, n, nv, recipe[0], pickle.dumps(recipe[1], protocol=pickle.HIGHEST_PROTOCOL),
                        int(region.flags[_REQUEST])))
            self._reply("configured")
        finally:
            if path is not None:
                os.unlink(path)  # both processes have it mapped (or the worker failed): no file left behind
        self._recipe = recipe

    def _spin_until_done(self, region: _Region) -> None:
        sequence = self._sequence
        flags = region.flags
        count = 0
        start = time.monotonic()
        while flags[_DONE] != sequence:
            count += 1
            if count & 0x3FFF == 0:
                if self._process.poll() is not None:
                    raise WorkerError(f"the worker process exited with code {self._process.returncode}")
                if time.monotonic() - start > REPLY_TIMEOUT_S:
                    raise WorkerError(f"no reply within {REPLY_TIMEOUT_S:g} s")

    def _send(self, message: tuple) -> None:
        try:
            self._conn.send(message)
        except (OSError, ValueError) as err:
            raise WorkerError(f"cannot reach the worker ({err})") from err

    def _reply(self, kind: str) -> tuple:
        try:
            if not self._conn.poll(REPLY_TIMEOUT_S):
                raise WorkerError(f"no {kind!r} reply within {REPLY_TIMEOUT_S:g} s")
            message = self._conn.recv()
        except (OSError, EOFError) as err:
            raise WorkerError(f"the worker is gone ({err})") from err
        if message[0] == "error":
            raise WorkerError(f"the worker reported: {message[1]}")
        if message[0] != kind:
            raise WorkerError(f"expected a {kind!r} reply, got {message[0]!r}")
        return message

    def _fail(self, reason: str) -> None:
        if self._broken is None:
            LOG.warning("elastic worker (pid %s) given up, evaluating in this process from now on: %s",
                        self._process.pid, reason)
            self._broken = reason
        self._finalizer()


def _shut_down(process: subprocess.Popen, conn: Connection, sock: socket.socket, owner: int) -> None:
    """Stop the worker: a stop message, then kill if it does not exit (finalizer: no self). In a forked
    child of the owner (a diagnosis replay worker) only this process's copies of the sockets close."""
    if os.getpid() != owner:
        for closable in (conn, sock):
            try:
                closable.close()
            except OSError:
                pass
        return
    try:
        conn.send(("stop",))
    except (OSError, ValueError):
        pass
    try:
        process.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(timeout=5.0)
    for closable in (conn, sock):
        try:
            closable.close()
        except OSError:
            pass


# ------------------------------------------------------------------------------------------ worker
class _Server:
    """The worker side: one configuration at a time, requests from the flags or the socket."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.region: _Region | None = None
        self.function: Callable | None = None
        self.args: Any = None
        self.seen = 0
        self.last = time.perf_counter()

    def evaluate(self, sequence: int) -> None:
        region = self.region
        try:
            region.grad.fill(0.0)
            region.values.fill(0.0)
            region.energy[0] = self.function(self.args, region.x, region.grad, region.values)
            region.flags[_STATUS] = 0
        except Exception:  # reported through the status flag; the parent falls back
            LOG.exception("elastic worker: evaluation failed")
            region.flags[_STATUS] = 1
        region.flags[_DONE] = sequence
        self.seen = sequence
        self.last = time.perf_counter()

    def handle(self, message: tuple) -> bool:
        """Act on a control message; False on stop."""
        kind = message[0]
        if kind == "stop":
            return False
        if kind == "configure":
            _, path, n, nv, target, args, request = message
            try:
                if path is not None:
                    if self.region is not None:
                        self.region.close()
                    self.region = _Region.open(path, n, nv)
                self.function = _resolve(target)
                self.args = pickle.loads(args)
                self.seen = request
                self.conn.send(("configured",))
            except Exception as err:  # noqa: BLE001 (reported to the parent, which falls back)
                self.conn.send(("error", f"configure failed: {err!r}"))
        elif kind == "evaluate":
            self.evaluate(message[1])
            self.conn.send(("done", message[1]))
        elif kind == "stats":
            import resource

            self.conn.send(("stats", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0))
        return True

    def run(self) -> None:
        """Serve until a stop message or the parent's end of the socket closes."""
        spins = 0
        while True:
            region = self.region
            if SPIN_FLAGS and region is not None and self.function is not None:
                request = int(region.flags[_REQUEST])
                if request != self.seen:
                    self.evaluate(request)
                    continue
                spins += 1
                if time.perf_counter() - self.last < SPIN_SECONDS:
                    if spins & 0xFF or not self.conn.poll():  # a control message now and then
                        continue
                elif not self._wait_idle(region):
                    continue
            message = self.conn.recv()
            if message[0] != "wake" and not self.handle(message):
                return

    def _wait_idle(self, region: _Region) -> bool:
        """Block on the socket for at most :data:`IDLE_POLL_SECONDS` with the idle flag set; whether a
        message is pending (False also when a request came in)."""
        region.flags[_IDLE] = 1
        if int(region.flags[_REQUEST]) != self.seen:
            region.flags[_IDLE] = 0
            return False
        pending = self.conn.poll(IDLE_POLL_SECONDS)
        region.flags[_IDLE] = 0
        return pending


def _warm_kernels() -> None:
    """Load (or compile) the kernels a worker may run, on a single tet."""
    from sim_core.ti_kernels.fused_neohookean import compile_remote_kernel

    compile_remote_kernel()


def main(argv: list[str] | None = None) -> int:
    """The worker process: ``python -m sim_core.elastic_worker FD`` (``FD``: its end of the socket pair)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    conn = Connection(int(argv[0]))
    try:
        from sim_core.ti_backend import init_backend

        init_backend("cpu")
        _warm_kernels()
    except Exception as err:  # noqa: BLE001 (reported to the parent, which falls back)
        conn.send(("error", f"start failed: {err!r}"))
        return 1
    conn.send(("ready",))
    try:
        _Server(conn).run()
    except (EOFError, OSError):  # the parent is gone
        return 0
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    sys.exit(main())
