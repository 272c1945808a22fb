"""A second process that evaluates fused elastic terms while the Newton loop does other work.

Taichi's CPU kernel launches hold Python's GIL, and its parallel loops (atomic adds on a few cores)
ran the fused kernels about twice as slow as the serial ones on the 2-core machine
(docs/benchmarks_log.md), so one process uses one core. Two processes do run side by side at full
speed. :class:`ElasticWorker` starts a worker process (``python -m sim_core.elastic_worker``)
with its own Taichi runtime; :class:`sim_core.fused_elastic.FusedElastic` hands it the largest
fused term that supports it (a Stable Neo-Hookean gel: its ``offload_recipe()``), and evaluates the
other terms in the meantime. On Forming the gel's 1125 tets (about 0.4 ms per evaluation) then
overlap the sheet's membrane and bending (about 0.45 ms); at a step's first iterate the worker
evaluates every term while the solver sets up the contact and friction terms.

What the worker runs is a :class:`Recipe`: fused parts' ``offload_recipe()`` (a function and its
arguments each), summed in order, one of them optionally apart (into zeroed buffers added after
the others, the sums :class:`~sim_core.fused_elastic.FusedElastic` makes). The worker keeps up to
:data:`SLOTS` recipes, so that the Newton loop's usual requests (the gel's term; all terms at a
step's first iterate; the gel's projected Hessian) need no new configuration.

Protocol. Positions, gradient, Hessian values and energy are exchanged through one shared memory
region (a file mapped by both processes, unlinked once both have it): ``int64`` flags
``[request, done, status, idle, slot]`` then ``float64`` ``x (n, 3)``, ``grad (n, 3)``,
``values (nv,)``, ``energy``. Control messages (configure, wake, stop, stats) go over a socket pair
as :class:`multiprocessing.connection.Connection` messages. To evaluate, the parent writes ``x``
and the slot and increments ``request``; the worker, busy-waiting on ``request`` for
:data:`SPIN_SECONDS` after its last evaluation, zeroes ``grad`` and ``values``, runs the slot's
recipe, writes the energy and ``status`` and sets ``done``. The busy-waits need stores to become
visible in program order (x86's total store order); on other machines, or with
``ElasticWorker(signal="socket")``, each request and reply is a socket message instead. After
:data:`SPIN_SECONDS` without a request the worker blocks on the socket (at most
:data:`IDLE_POLL_SECONDS` at a time), with ``idle`` set, and the parent sends a wake message.

The worker's term is always summed as the parent would sum it if it evaluated the term itself
(:class:`~sim_core.fused_elastic.FusedElastic`): gradient and values into zeroed buffers, added
after the other terms. The results therefore do not depend on whether the worker is up, busy or
gone; any failure (no start, a crash, a timeout, an error in the kernel) is logged once, the worker
is shut down, and the term is evaluated in the parent from then on.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import mmap
import os
import pickle
import platform
import resource
import socket
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Callable

import numpy as np

from sim_core.errors import ConfigError
from sim_core.kernel_compile import compile_offload_kernels
from sim_core.worker_recipe import Recipe, part_recipe, same_recipe  # noqa: F401 (re-exported)

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

SIGNALS = ("auto", "flags", "socket")
"""How requests and replies are signalled: ``flags`` (busy-waiting on the shared flags; needs stores
seen in program order, as on x86), ``socket`` (a socket message each), ``auto`` (flags on x86, else
socket)."""

FLAGS_SAFE = platform.machine().lower() in ("x86_64", "amd64")
"""Whether this machine keeps stores in program order (x86's total store order)."""


def resolve_signal(signal: str) -> str:
    """The concrete signalling of ``signal`` (:data:`SIGNALS`): ``flags`` or ``socket``.

    Raises:
        ConfigError: unknown name, or ``flags`` on a machine without x86's store order.
    """
    if signal not in SIGNALS:
        raise ConfigError(f"ElasticWorker: unknown signal {signal!r}; use one of {SIGNALS}")
    if signal == "flags" and not FLAGS_SAFE:
        raise ConfigError(f"ElasticWorker: signal 'flags' needs x86's store order; this is {platform.machine()}")
    return ("flags" if FLAGS_SAFE else "socket") if signal == "auto" else signal


SLOTS = 4
"""Recipes a worker keeps configured (the least recently used one is replaced)."""

_REQUEST, _DONE, _STATUS, _IDLE, _SLOT = range(5)
_FLAG_BYTES = 64


def run_recipe(functions: list[Callable], args: list[tuple], apart: int | None, x: np.ndarray, grad: np.ndarray,
               values: np.ndarray, scratch: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Evaluate a recipe's parts (``functions[i](args[i], ...)``) at ``x`` into zeroed ``grad`` ``(n, 3)``
    and ``values`` ``(nv,)``: energy in J, summed in part order; part ``apart`` into ``scratch``
    (zeroed here) added after the others."""
    grad.fill(0.0)
    values.fill(0.0)
    energies = []
    for i, (function, a) in enumerate(zip(functions, args)):
        energies.append(None if i == apart else function(a, x, grad, values))
    if apart is not None:
        g, v = scratch
        g.fill(0.0)
        v.fill(0.0)
        energies[apart] = functions[apart](args[apart], x, g, v)
        grad += g
        values += v
    energy = 0.0
    for e in energies:
        energy += e
    return energy


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
        self.flags = np.ndarray((5,), dtype=np.int64, buffer=buffer)
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
        with contextlib.suppress(BufferError):  # an array view still exported somewhere: the GC unmaps it
            self.buffer.close()


def _region_file() -> tuple[int, str]:
    """A new file for a shared region, ``(fd, path)``: in ``/dev/shm`` (memory) where it can be made,
    else in the temporary directory (the page cache keeps it in memory as well)."""
    if os.path.isdir("/dev/shm"):
        with contextlib.suppress(OSError):
            return tempfile.mkstemp(prefix="thinshell-worker-", dir="/dev/shm")
    return tempfile.mkstemp(prefix="thinshell-worker-")


def _resolve(target: str) -> Callable:
    """The function ``module:name`` of a recipe."""
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


# ------------------------------------------------------------------------------------------ parent
class ElasticWorker:
    """A worker process that evaluates fused elastic terms concurrently (module docstring).

    Starting it returns at once; :attr:`ready` turns True when the worker has started Taichi and
    loaded its kernels (seconds; the parent evaluates everything itself until then). One request
    at a time (:meth:`begin` / :meth:`finish`; another thread's ``begin`` while one is out gets
    False). Several solvers may share one worker (it is configured with their recipes as they come,
    :data:`SLOTS` kept). The process ends with :meth:`close`, when the object is collected, or at
    interpreter exit.

    Attributes:
        evaluations: requests the worker completed; configurations: recipes sent to it.

    Args:
        python: interpreter of the worker (default: this one, ``sys.executable``).
        signal: how requests and replies are signalled (:data:`SIGNALS`; default ``auto``).

    Raises:
        OSError: the process cannot be started.
        ConfigError: bad ``signal`` (:func:`resolve_signal`).
    """

    def __init__(self, python: str | None = None, signal: str = "auto") -> None:
        self.signal = resolve_signal(signal)
        self._spin = self.signal == "flags"
        parent, child = socket.socketpair()
        root = str(Path(__file__).resolve().parents[1])  # the directory holding sim_core
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        try:
            self._process = subprocess.Popen(
                [python or sys.executable, "-m", "sim_core.elastic_worker", str(child.fileno()), self.signal],
                pass_fds=(child.fileno(),), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=env,
                cwd=root)  # `-m` puts the working directory first on sys.path: this sim_core, not another
        finally:
            child.close()
        parent.setblocking(True)
        self._conn = Connection(parent.detach())  # the connection owns the descriptor from now on
        self._pid = os.getpid()  # a forked child of the parent must not use the worker
        self._guard = threading.Lock()  # held while a thread starts, finishes or drains a request
        self._owner: int | None = None  # the thread whose request the worker has (begun, not finished)
        self._ready = False
        self._broken: str | None = None
        self._region: _Region | None = None
        self._slots: list[Recipe | None] = [None] * SLOTS  # the recipes the worker has, per slot
        self._slot_used = [0] * SLOTS  # request number of each slot's last use
        self._sequence = 0
        self.evaluations = 0  # evaluations done by the worker
        self.configurations = 0  # recipes sent to the worker
        self._finalizer = weakref.finalize(self, _shut_down, self._process, self._conn, self._pid)

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
        """The worker's peak resident memory in MiB (None when it is not up or busy)."""
        with self._guard:
            if self._owner is not None or not self.ready:
                return None
            try:
                self._send(("stats",))
                return float(self._reply("stats")[1])
            except WorkerError as err:
                self._fail(str(err))
                return None

    def close(self) -> None:
        """Stop the worker process and release the shared memory (idempotent)."""
        if self._broken is None:
            self._broken = "closed"
        self._finalizer()
        if self._region is not None:
            self._region.close()
            self._region = None

    # -------------------------------------------------------------------------------- evaluation
    def begin(self, recipe: Recipe, x: np.ndarray, value_count: int) -> bool:
        """Start evaluating ``recipe`` (:class:`Recipe`) at positions ``x`` ``(n, 3)`` into ``value_count``
        Hessian values; the worker is configured with it first unless one of its slots has it
        (:func:`same_recipe`). A request of this thread that was begun and never finished is
        waited for and dropped first.

        Returns:
            True when the worker took the request (call :meth:`finish`); False when it is not ready,
            failed, or has another thread's request: evaluate locally.
        """
        me = threading.get_ident()
        with self._guard:
            if os.getpid() != self._pid or (self._owner is not None and self._owner != me):
                return False
            if self._owner is not None:
                self._wait(drop=True)
            if not self.ready:
                return False
            try:
                slot = self._configure(recipe, x.shape[0], value_count)
                region = self._region
                np.copyto(region.x, x)
                self._sequence += 1
                self._slot_used[slot] = self._sequence
                region.flags[_SLOT] = slot
                if self._spin:
                    region.flags[_REQUEST] = self._sequence
                    if region.flags[_IDLE]:
                        self._send(("wake",))
                else:
                    self._send(("evaluate", self._sequence))
            except Exception as err:  # noqa: BLE001 (WorkerError; OSError: no shared memory; a recipe that does not pickle)
                self._fail(f"{type(err).__name__}: {err}")
                return False
            self._owner = me
            return True

    def finish(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        """Wait for this thread's request of :meth:`begin`: ``(energy J, grad (n, 3) N, values (nv,) N/m)``,
        the arrays views of the shared memory valid until the next :meth:`begin`; None when the
        worker failed (logged; evaluate locally) or this thread has no request."""
        with self._guard:
            if self._owner != threading.get_ident():
                return None
            return self._wait(drop=False)

    # -------------------------------------------------------------------------------- internals
    def _wait(self, drop: bool) -> tuple[float, np.ndarray, np.ndarray] | None:
        """Wait for the outstanding request (the guard held); its result, or None (failed, or ``drop``)."""
        try:
            region = self._region
            if self._spin:
                self._spin_until_done(region)
            else:
                message = self._reply("done")
                if message[1] != self._sequence:
                    raise WorkerError(f"reply to request {message[1]}, expected {self._sequence}")
            if region.flags[_STATUS] != 0:
                raise WorkerError("the worker's evaluation raised (see its stderr)")
            self.evaluations += 1
            return None if drop else (float(region.energy[0]), region.grad, region.values)
        except WorkerError as err:
            self._fail(str(err))
            return None
        finally:
            self._owner = None

    def _configure(self, recipe: Recipe, n: int, nv: int) -> int:
        """The slot holding ``recipe``, after sending it (and a new region for other sizes) if none does."""
        region = self._region
        path = None
        if region is None or region.n != n or region.nv != nv:
            _, size = _layout(n, nv)
            fd, path = _region_file()
            try:
                os.ftruncate(fd, size)
                buffer = mmap.mmap(fd, size)
            finally:
                os.close(fd)
            if region is not None:
                region.close()
            region = self._region = _Region(buffer, n, nv)
            self._slots = [None] * SLOTS  # recipes index values of a pattern: configure them again
        else:
            for slot, known in enumerate(self._slots):
                if known is not None and same_recipe(known, recipe):
                    return slot
        slot = min(range(SLOTS), key=lambda k: self._slot_used[k])
        self._slots[slot] = None
        try:
            self._send(("configure", slot, path, n, nv, [t for t, _ in recipe.parts],
                        pickle.dumps([a for _, a in recipe.parts], protocol=pickle.HIGHEST_PROTOCOL), recipe.apart,
                        int(region.flags[_REQUEST])))
            self._reply("configured")
            self.configurations += 1
        finally:
            if path is not None:
                os.unlink(path)  # both processes have it mapped (or the worker failed): no file left behind
        self._slots[slot] = recipe
        return slot

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


def _shut_down(process: subprocess.Popen, conn: Connection, owner: int) -> None:
    """Stop the worker: a stop message, then kill if it does not exit (finalizer: no self). In a forked
    child of the owner (a diagnosis replay worker) only this process's copy of the socket closes."""
    if os.getpid() == owner:
        with contextlib.suppress(OSError, ValueError):  # gone already
            conn.send(("stop",))
        try:
            process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5.0)
    with contextlib.suppress(OSError):
        conn.close()


# ------------------------------------------------------------------------------------------ worker
class _Server:
    """The worker side: up to :data:`SLOTS` configured recipes, requests from the flags or the socket."""

    def __init__(self, conn: Connection, spin: bool) -> None:
        self.conn = conn
        self.spin = spin  # requests come as flags (busy-waited), else as socket messages
        self.region: _Region | None = None
        self.slots: dict[int, tuple[list[Callable], list[tuple], int | None]] = {}
        self.scratch: tuple[np.ndarray, np.ndarray] | None = None  # the apart part's buffers
        self.seen = 0
        self.last = time.perf_counter()

    def evaluate(self, sequence: int) -> None:
        region = self.region
        try:
            functions, args, apart = self.slots[int(region.flags[_SLOT])]
            if apart is not None and (self.scratch is None or self.scratch[1].size != region.nv):
                self.scratch = (np.zeros((region.n, 3)), np.zeros(region.nv))
            region.energy[0] = run_recipe(functions, args, apart, region.x, region.grad, region.values, self.scratch)
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
            try:
                _, slot, path, n, nv, targets, args, apart, request = message
                if path is not None:
                    if self.region is not None:
                        self.region.close()
                    self.region = _Region.open(path, n, nv)
                    self.slots = {}
                self.slots[slot] = ([_resolve(t) for t in targets], pickle.loads(args), apart)
                self.seen = request
                self.conn.send(("configured",))
            except Exception as err:  # noqa: BLE001 (reported to the parent, which falls back)
                self.conn.send(("error", f"configure failed: {err!r}"))
        elif kind == "evaluate":
            self.evaluate(message[1])
            self.conn.send(("done", message[1]))
        elif kind == "stats":
            self.conn.send(("stats", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0))
        return True

    def run(self) -> None:
        """Serve until a stop message or the parent's end of the socket closes."""
        spins = 0
        while True:
            region = self.region
            if self.spin and region is not None and self.slots:
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
            self.last = time.perf_counter()  # a request usually follows: busy-wait for it again

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
    compile_offload_kernels()


def main(argv: list[str] | None = None) -> int:
    """The worker process: ``python -m sim_core.elastic_worker FD SIGNAL`` (``FD``: its end of the socket
    pair; ``SIGNAL``: ``flags`` or ``socket``, as :func:`resolve_signal` gives it)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    conn = Connection(int(argv[0]))
    spin = resolve_signal(argv[1] if len(argv) > 1 else "auto") == "flags"
    try:
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.ti_backend import init_backend

        init_backend("cpu")
        _warm_kernels()
    except Exception as err:  # noqa: BLE001 (reported to the parent, which falls back)
        conn.send(("error", f"start failed: {err!r}"))
        return 1
    conn.send(("ready",))
    try:
        _Server(conn, spin).run()
    except (EOFError, OSError):  # the parent is gone
        return 0
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    sys.exit(main())
