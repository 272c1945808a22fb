"""Two half-batches of the Forming lockstep stepped in turn, so that one half's factorisation and CG run on the GPU
while the host does the other half's host work (issue 28, session 44, 28sync): a measurement, not an engine option.

Usage: ``python benchmarks/pipeline_lockstep.py --arch cuda --B 1024 --steps 3 [--trace-steps 1] [--b-site SITE]``

One Taichi stream: a synchronous read or upload waits for every kernel queued before it, whichever half queued
it. So the halves run in two threads of which one runs at a time (a baton handed over at the points below,
never two Taichi calls at once), and a half reads its CG's result before the other queues its own:

* ``a``: a half has queued its factorisation and CG (``BatchedPCG._run``'s read of the running copies, the one
  wait of the solve; ``_direction_pcg`` uploads the right-hand side's per-copy values before the factorisation,
  as this branch does, so the two are queued back to back);
* ``b``: a half has just synchronised at ``--b-site`` (the call site followed by the longest host work without a
  synchronisation, from ``--trace-steps``' trace), i.e. its long host stretch begins;
* ``s``: any other synchronisation (``device_copy``'s copies, ``to_numpy`` / ``from_numpy``, a launch with a
  NumPy argument, ``ti.sync``).

A half at ``a`` hands over when the other waits at ``b`` (the other's host stretch then runs beside this CG); at
``b`` when the other does not wait at ``a`` (the other then goes on to queue its CG); at ``s`` when the other
waits at ``a`` (the other reads its CG before this half queues more). Correct whatever the order (each half's
own calls keep theirs; the halves share no buffers); only the overlap depends on it.

Runs, in one process (kernels compiled once, first on one copy as ``bench batch``): ``B`` copies in one engine
(the un-split baseline), the two halves (copies ``0 .. B/2 - 1`` and ``B/2 .. B - 1`` of the same targets) one
after the other, the same halves reset and pipelined; each ``--steps`` steps after an untimed first step. Prints
the wall times, each half's Newton iterations, and the pipelined halves' positions against the sequential ones
(copy by copy). ``--trace-steps N``: first a trace of N steps of one half: per call site of a synchronisation the
host time until the next one (on the CPU arch the kernels' own time, spent inside their launches, left out), and
the time spent inside the synchronisations (the waits for the device).
"""

from __future__ import annotations

import argparse
import collections
import sys
import threading
import time

import numpy as np

_LOCAL = threading.local()  # .baton, .me (pipelined threads); .depth (nested synchronisations)
_TRACE: dict | None = None  # while tracing: {"events": [...], "launch_s": float}
_B_SITE: str | None = None
_TRACE_END = [0.0]


# ---------------------------------------------------------------------------------------------- the baton
class Baton:
    """Two threads, one running at a time: :meth:`pause` hands the turn to the other by the kinds of both points."""

    def __init__(self) -> None:
        self.cv = threading.Condition()
        self.turn = 0
        self.waiting = ["run", "start"]  # where each waits ("run": running)
        self.alive = [True, True]
        self.switches = collections.Counter()

    def start(self, me: int) -> None:
        with self.cv:
            self.cv.wait_for(lambda: self.turn == me)
            self.waiting[me] = "run"

    def pause(self, me: int, kind: str) -> None:
        with self.cv:
            other = 1 - me
            if not self.alive[other]:
                return
            w = self.waiting[other]
            hand = (w == "b") if kind == "a" else (w != "a") if kind == "b" else (w == "a")
            if not hand:
                return
            self.switches[kind + ">" + w] += 1
            self.waiting[me] = kind
            self.turn = other
            self.cv.notify_all()
            self.cv.wait_for(lambda: self.turn == me)
            self.waiting[me] = "run"

    def finish(self, me: int) -> None:
        with self.cv:
            self.alive[me] = False
            self.waiting[me] = "done"
            self.turn = 1 - me
            self.cv.notify_all()


# ---------------------------------------------------------------------------------------------- the hooks
def _site() -> str:
    """The synchronisation's caller: the innermost sim_core function outside the copy helpers, with the lockstep
    or line-search line that led there."""
    f = sys._getframe(2)
    inner = outer = None
    while f is not None:
        name = f.f_code.co_filename
        if "sim_core" in name:
            if inner is None and not any(s in name for s in ("device_copy", "transfer.py", "launch.py")):
                inner = f"{name.rsplit('sim_core/', 1)[-1]}:{f.f_code.co_name}"
            if name.endswith(("batch/lockstep.py", "batch/line_search.py")):
                outer = f"{name.rsplit('/', 1)[-1]}:{f.f_lineno}"
                break
        f = f.f_back
    return f"{inner} <- {outer}"


def _wrap_sync(owner, name: str, kind_of=None) -> None:
    """Wrap ``owner.name`` as a synchronisation point (the outermost of nested ones counts)."""
    raw = getattr(owner, name)

    def wrapped(*args, **kwargs):
        depth = getattr(_LOCAL, "depth", 0)
        if depth:
            return raw(*args, **kwargs)
        kind = kind_of(args) if kind_of else "s"
        if kind is None:
            return raw(*args, **kwargs)
        baton = getattr(_LOCAL, "baton", None)
        site = _site() if (_TRACE is not None or (baton is not None and _B_SITE is not None)) else None
        if baton is not None:
            baton.pause(_LOCAL.me, kind)
        _LOCAL.depth = 1
        l0 = _TRACE["launch_s"] if _TRACE is not None else 0.0
        t0 = time.perf_counter()
        try:
            return raw(*args, **kwargs)
        finally:
            t1 = time.perf_counter()
            _LOCAL.depth = 0
            if _TRACE is not None:
                _TRACE["events"].append((t0, t1, kind, site, l0, _TRACE["launch_s"]))
            if baton is not None and site is not None and _B_SITE in site:
                baton.pause(_LOCAL.me, "b")

    setattr(owner, name, wrapped)


def _has_numpy(args) -> str | None:
    return "s" if any(isinstance(a, np.ndarray) for a in args) else None


def install_hooks() -> None:
    from taichi.lang import kernel_impl
    from taichi.lang._ndarray import Ndarray

    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import device_copy, launch, pcg

    # on the CPU arch a launch runs the kernel: its time (inside the synchronisation hooks) is left out of the host
    # time
    for owner, name in ((launch._Plan, "launch"), (kernel_impl.Kernel, "__call__")):
        _time_launches(owner, name)
    _wrap_sync(device_copy, "_copy")
    _wrap_sync(pcg, "_copy_out", lambda args: "a" if tuple(args[0].shape) == (1,) else "s")
    for name in ("_ndarray_to_numpy", "_ndarray_matrix_to_numpy", "_ndarray_from_numpy", "_ndarray_matrix_from_numpy"):
        _wrap_sync(Ndarray, name)
    _wrap_sync(ti, "sync")
    _wrap_sync(launch._Plan, "launch", lambda args: _has_numpy(args[2]))
    _wrap_sync(kernel_impl.Kernel, "__call__", lambda args: _has_numpy(args[1:]))


def _time_launches(owner, name: str) -> None:
    raw = getattr(owner, name)

    def timed(*args, **kwargs):
        if _TRACE is None or getattr(_LOCAL, "timing", False):
            return raw(*args, **kwargs)
        _LOCAL.timing = True
        t0 = time.perf_counter()
        try:
            return raw(*args, **kwargs)
        finally:
            _TRACE["launch_s"] += time.perf_counter() - t0
            _LOCAL.timing = False

    setattr(owner, name, timed)


# ---------------------------------------------------------------------------------------------- runs
def _forming(B: int, steps: int, backend: str, targets=None):
    from sim_core.bench.batch import _FormingRun

    run = _FormingRun(B, steps, backend, lockstep=True)
    if targets is not None:
        run.targets = targets
    return run


def _step(run, k: int):
    from sim_core.control import Control

    res = run.batch.step([Control(effector_pose_target={run.effector: t[k]}) for t in run.targets])
    return [i.iterations if i is not None else -1 for i in res.infos]


def _steps(run, first: int, last: int) -> tuple[float, list]:
    t0 = time.perf_counter()
    its = [_step(run, k) for k in range(first, last)]
    return time.perf_counter() - t0, its


def trace(run, steps: int, host_arch: bool) -> str:
    """Step ``run`` ``steps`` times with the synchronisations recorded; print per call site the host time to the
    next one and the waits; return the site (of kind ``s``, at least every other iteration) whose following host
    stretch is the longest in the median."""
    global _TRACE
    _TRACE = {"events": [], "launch_s": 0.0}
    t0 = time.perf_counter()
    solver = run.batch.lockstep.solver
    iterations = 0
    for k in range(1, steps + 1):
        _step(run, k)
        iterations += solver.last_stacked_info.iterations
    wall = time.perf_counter() - t0
    ev, _TRACE_END[0], _TRACE = _TRACE["events"], _TRACE["launch_s"], None
    after = collections.defaultdict(list)  # site -> host seconds from its end to the next synchronisation
    inside = collections.defaultdict(float)
    end = t0 + wall
    for (s0, s1, kind, site, _, l1), nxt in zip(ev, ev[1:] + [(end, None, None, "end", _TRACE_END[0], None)]):
        inside[f"{kind} {site}"] += s1 - s0
        host = nxt[0] - s1 - ((nxt[4] - l1) if host_arch else 0.0)
        after[f"{kind} {site}"].append(host)
    host_total = sum(sum(v) for v in after.values())
    print(f"trace: {steps} steps, {iterations} Newton iterations, {wall * 1e3:.1f} ms, {len(ev)} synchronisations "
          f"({len(ev) / max(iterations, 1):.1f} an iteration); host between them {1e3 * host_total / iterations:.1f} "
          f"ms an iteration, inside them {1e3 * sum(inside.values()) / iterations:.1f}")
    print(f"{'site (kind, caller <- lockstep line)':<100} {'n/it':>5} {'host ms/it':>10} {'max ms':>7} "
          f"{'wait ms/it':>10}")
    for key in sorted(after, key=lambda k: -sum(after[k]))[:25]:
        v = after[key]
        print(f"{key[:100]:<100} {len(v) / iterations:5.2f} {1e3 * sum(v) / iterations:10.2f} {1e3 * max(v):7.2f} "
              f"{1e3 * inside[key] / iterations:10.2f}")
    waits = collections.defaultdict(float)
    for key, v in inside.items():
        waits[key.split()[0]] += v
    print("inside the synchronisations by kind (ms an iteration): "
          + ", ".join(f"{k} {1e3 * v / iterations:.1f}" for k, v in sorted(waits.items())))
    longest = sorted(((h, key) for key, v in after.items() for h in v), reverse=True)[:8]
    print("longest host stretches (ms):", ", ".join(f"{1e3 * h:.1f} after {key}" for h, key in longest))
    often = [k for k, v in after.items() if k.startswith("s ") and len(v) >= 0.5 * iterations]
    best = max(often, key=lambda k: float(np.median(after[k])))
    print(f"b site: {best} (median {1e3 * float(np.median(after[best])):.2f} ms after it)", flush=True)
    return best.split(" ", 1)[1]


def pipelined(runs, first: int, last: int, ctx) -> tuple[float, list, Baton]:
    """Step the two half runs over steps ``first .. last - 1`` in two threads handing a baton."""
    baton = Baton()
    its = [None, None]
    errors = []

    def body(me):
        if ctx is not None:  # Taichi's CUDA context current on this thread too (device_copy's driver copies)
            from sim_core.ti_kernels import device_copy

            device_copy._driver().cuCtxSetCurrent(ctx)
        _LOCAL.baton, _LOCAL.me = baton, me
        baton.start(me)
        try:
            its[me] = [_step(runs[me], k) for k in range(first, last)]
        except BaseException as err:  # noqa: BLE001 - reported after the join
            errors.append(err)
        finally:
            _LOCAL.baton = None
            baton.finish(me)

    threads = [threading.Thread(target=body, args=(me,)) for me in (0, 1)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    if errors:
        raise errors[0]
    return wall, its, baton


def main() -> int:
    global _B_SITE
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=16)
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--trace-steps", type=int, default=0)
    ap.add_argument("--b-site", default="auto",
                    help="the call site that starts the long host stretch (a substring of the trace's), or auto: the "
                         "trace's")
    ap.add_argument("--skip-full", action="store_true")
    ap.add_argument("--again", action="store_true", help="the sequential halves again after the pipelined ones")
    args = ap.parse_args()
    _B_SITE = args.b_site or None

    from sim_core.bench.batch import ARCH_BACKENDS
    from sim_core.ti_backend import init_backend

    backend = ARCH_BACKENDS[args.arch]
    init_backend(args.arch)
    import sim_core.solver_config as sc

    orig = sc.SolverConfig
    sc.SolverConfig = lambda **kw: orig(**kw, **({"linear_solver": "pcg"} if kw.get("lockstep") else {}))
    t0 = time.perf_counter()
    from sim_core.kernel_compile import compile_kernels

    warm = _forming(1, 2, backend)
    warm.run()
    sim0 = warm.batch.sims[0]
    compile_kernels(sim0.solver.elastic.potentials(sim0.state.hinge_theta_bar), sim0.model.x_rest)
    del warm, sim0
    print(f"compiled in {time.perf_counter() - t0:.1f} s", flush=True)
    install_hooks()
    B, half, S = args.B, args.B // 2, args.steps
    steps = S + 1 + max(args.trace_steps, 0)
    t0 = time.perf_counter()
    full = _forming(B, steps, backend)
    targets = full.targets
    runs = [_forming(half, steps, backend, targets[:half]), _forming(B - half, steps, backend, targets[half:])]
    for run in runs:
        run.batch.warm_up()
    print(f"built in {time.perf_counter() - t0:.1f} s", flush=True)
    host_arch = args.arch == "cpu"
    if args.trace_steps:
        _step(runs[0], 0)
        best = trace(runs[0], args.trace_steps, host_arch)
        if args.b_site == "auto":
            _B_SITE = best
        runs[0].batch.reset()
        sys.stdout.flush()
    ctx = None
    if not host_arch:
        import ctypes

        from sim_core.ti_kernels import device_copy

        lib = device_copy._driver()
        lib.cuCtxSetCurrent.argtypes = (ctypes.c_void_p,)
        c = ctypes.c_void_p()
        lib.cuCtxGetCurrent(ctypes.byref(c))
        ctx = c.value
    results = {}
    if not args.skip_full:
        full.batch.warm_up()
        _step(full, 0)
        wall, its = _steps(full, 1, S + 1)
        results["full"] = (wall, its)
        print(f"one engine, B = {B}: {S} steps in {wall:.3f} s, {B * S / wall:.1f} scene-steps/s, Newton iterations a "
              f"step {[max(i) for i in its]}", flush=True)
        del full
    for run in runs:
        _step(run, 0)
    t0 = time.perf_counter()
    seq_its = [[], []]
    seq_x = []
    for k in range(1, S + 1):
        for me in (0, 1):
            seq_its[me].append(_step(runs[me], k))
    wall_seq = time.perf_counter() - t0
    seq_x = [run.batch.lockstep.state.x.copy() for run in runs]
    print(f"two halves one after the other: {S} steps in {wall_seq:.3f} s, {B * S / wall_seq:.1f} scene-steps/s, "
          f"Newton iterations a step {[max(i) for i in seq_its[0]]} / {[max(i) for i in seq_its[1]]}", flush=True)
    for run in runs:
        run.batch.reset()
        run.batch.warm_up()
        _step(run, 0)
    wall_pipe, pipe_its, baton = pipelined(runs, 1, S + 1, ctx)
    print(f"two halves pipelined: {S} steps in {wall_pipe:.3f} s, {B * S / wall_pipe:.1f} scene-steps/s, Newton "
          f"iterations a step {[max(i) for i in pipe_its[0]]} / {[max(i) for i in pipe_its[1]]}; hand-overs "
          f"{dict(baton.switches)}", flush=True)
    same_its = all(np.array_equal(np.array(seq_its[m]), np.array(pipe_its[m])) for m in (0, 1))
    dx = max(float(np.abs(run.batch.lockstep.state.x - x).max()) for run, x in zip(runs, seq_x))
    print(f"pipelined against one after the other: iterations copy by copy equal {same_its}, positions max |dx| "
          f"{dx:.3g} m; wall {wall_seq:.3f} -> {wall_pipe:.3f} s ({100 * (wall_pipe / wall_seq - 1):+.1f} %)"
          + (f"; one engine {results['full'][0]:.3f} s" if "full" in results else ""))
    if args.again:  # the order's effect: the sequential halves once more, after the pipelined ones
        for run in runs:
            run.batch.reset()
            run.batch.warm_up()
            _step(run, 0)
        def sequential():
            if ctx is not None:
                from sim_core.ti_kernels import device_copy

                device_copy._driver().cuCtxSetCurrent(ctx)
            for k in range(1, S + 1):
                for me in (0, 1):
                    _step(runs[me], k)

        t0 = time.perf_counter()
        worker = threading.Thread(target=sequential)  # on a thread of its own, as the pipelined halves
        worker.start()
        worker.join()
        wall = time.perf_counter() - t0
        print(f"two halves one after the other again, on another thread: {S} steps in {wall:.3f} s, "
              f"{B * S / wall:.1f} scene-steps/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
