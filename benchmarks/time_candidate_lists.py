"""Time a lockstep Forming batch's new candidate lists, built again at its converged positions: host and device.

Usage: ``python benchmarks/time_candidate_lists.py --arch cuda --B 256,1024 --repeat 5``; ``--arch cpu
--emulate-cuda`` runs the CUDA paths on the CPU arch (:mod:`emulated_cuda`). Builds ``B`` Forming copies
(``sim_core.bench.batch._FormingRun``; the kernels compiled first on one copy, as ``thinshell bench batch``), steps them
``--steps`` times (the steady scene-steps/s of the steps after the
first reported: ``thinshell bench batch``'s rate), then ``--repeat`` times drops the contact set's lists (the
search, its sides, vertices and pair batch: what a trial point outside the last search's cover costs) and builds them
again with :meth:`~sim_core.contact_set.ContactSet.potentials` at the batch's positions, the step's memory, then
``--repeat`` times makes a step's potentials over the kept lists (a new step's memory: sides measured and placed again,
new potentials and pair batch: what every step's start costs), then ``--repeat`` times a steady step's contact and
friction set-up at ``x^n`` over the kept lists (``ContactSet.friction``: potentials, sides from the last end's codes,
the pair batch's evaluation of ``x^n``, friction rows; wall, inside launches and copies, host, copies, MB). Reports a
build's wall time (ms, median), the part of it
inside Taichi launches and synchronous copies (cProfile, the launch calls' cumulative time), the host's rest, the
synchronous copies (count, MB) and new device arrays a build, the lists' lengths, and the step's potentials' wall time
(ms, median). The candidate lists' host work is the host's rest: on a GPU the launches are asynchronous and a copy
waits for them, so the launches' and copies' time is the device's share plus the transfers.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import sys
import time

from emulated_cuda import add_emulation_flag, init_arch  # (benchmarks/, the script's folder)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--B", default="8", help="copies; a comma-separated list times each size in turn")
    ap.add_argument("--repeat", type=int, default=3, help="builds a size (the median is reported)")
    ap.add_argument("--steps", type=int, default=2, help="steps before the builds (at least 2)")
    ap.add_argument("--top", type=int, default=0, help="also the last build's N functions of most own time")
    add_emulation_flag(ap)
    args = ap.parse_args()
    init_arch(ap, args)
    from sim_core.bench.batch import ARCH_BACKENDS, _FormingRun

    backend = ARCH_BACKENDS[args.arch]
    # every kernel compiled or loaded first, the projected Hessian's too (as bench batch): no kernel's per-process
    # preparation inside the timed steps
    from sim_core.kernel_compile import compile_kernels

    warm = _FormingRun(1, 2, backend, lockstep=True)
    warm.run()
    sim0 = warm.batch.sims[0]
    compile_kernels(sim0.solver.elastic.potentials(sim0.state.hinge_theta_bar), sim0.model.x_rest)
    del warm, sim0
    if args.emulate_cuda:  # after the compilation run: the modules the steps call are imported
        from emulated_cuda import answer_cuda

        answer_cuda()
    counts = _count_device_traffic()
    for B in (int(b) for b in str(args.B).split(",")):
        run = _FormingRun(B, max(args.steps, 2), backend, lockstep=True)
        per_step = run.run()[3][1:]
        print(f"B={B}: steady {sum(n for n, _ in per_step) / sum(w for _, w in per_step):.0f} scene-steps/s (steps "
              f"2-{len(per_step) + 1}, {1e3 * sum(w for _, w in per_step) / len(per_step):.1f} ms a step)", flush=True)
        engine = run.batch.lockstep
        solver = engine.solver
        contact, x = solver.contact, engine.state.x
        memory = contact.begin_step(x, engine.state.contact_memory)
        contact.potentials(x, x, memory)  # the kernels of this size's lists compiled and bound
        walls, inside, copies, megabytes, arrays = [], [], [], [], []
        for _ in range(args.repeat):
            memory = contact.begin_step(x, engine.state.contact_memory)
            _forget_lists(contact)
            counts.clear()
            prof = cProfile.Profile()
            t = time.perf_counter()
            prof.enable()
            pots = contact.potentials(x, x, memory)
            prof.disable()
            walls.append(1e3 * (time.perf_counter() - t))
            stats = pstats.Stats(prof)
            inside.append(1e3 * _device_time(stats))
            copies.append(counts["copies"])
            megabytes.append(counts["bytes"] / 1e6)
            arrays.append(counts["arrays"])
        vt, ee = contact._candidates[1:]
        end_geometry = contact._end_geometry  # (the codes the last step's end measured: the next start's sides)
        again = []  # a step's potentials over the kept lists (new sides: what every step's start costs)
        for _ in range(args.repeat):
            memory = contact.begin_step(x, engine.state.contact_memory)
            contact._end_geometry = None  # (the sides measured again, as a step whose start is not the last end)
            t = time.perf_counter()
            contact.potentials(x, x, memory)
            again.append(1e3 * (time.perf_counter() - t))
        setup = _time_setup(contact, x, engine.state.contact_memory, run.batch.sims[0].dt, end_geometry, args.repeat,
                            counts)
        med = statistics.median
        print(f"B={B}: candidate lists {len(vt)} vertex-triangle + {len(ee)} edge-edge pairs "
              f"({len(pots)} potentials); a build (median of {args.repeat}): {med(walls):.1f} ms, launches and "
              f"copies {med(inside):.1f} ms, host {med(walls) - med(inside):.1f} ms; synchronous copies "
              f"{med(copies):.0f}, {med(megabytes):.1f} MB; new device arrays {med(arrays):.0f}; a step's potentials "
              f"over the kept lists {med(again):.1f} ms", flush=True)
        print(f"B={B}: a step's contact and friction set-up at x^n over the kept lists (median of {args.repeat}): "
              f"{med(setup[0]):.1f} ms, launches and copies {med(setup[1]):.1f} ms, host "
              f"{med([w - i for w, i in zip(*setup[:2])]):.1f} ms; synchronous copies {med(setup[2]):.0f}, "
              f"{med(setup[3]):.1f} MB", flush=True)
        if args.top:
            stats.sort_stats("tottime").print_stats(args.top)
        del run, engine, solver, contact, pots
    return 0


def _time_setup(contact, x, state_memory, dt: float, end_geometry, repeat: int, counts: dict) -> tuple[list, ...]:
    """``repeat`` times a steady step's contact and friction set-up at ``x^n = x`` over the kept lists
    (:meth:`~sim_core.contact_set.ContactSet.friction` after ``begin_step``: the step's pair potentials, their sides from
    the codes the last step's end measured, ``end_geometry``, and the friction rows; no evaluation handed on from the
    last potentials, so the pair batch measures ``x^n``, as at a step whose sides changed); returns lists of the wall ms,
    the ms inside launches and synchronous copies (cProfile), the copies and their MB."""
    walls, inside, copies, megabytes = [], [], [], []
    for _ in range(repeat):
        memory = contact.begin_step(x, state_memory)
        contact._end_geometry, contact._last_pots = end_geometry, ()
        counts.clear()
        prof = cProfile.Profile()
        t = time.perf_counter()
        prof.enable()
        contact.friction(x, dt, memory)
        prof.disable()
        walls.append(1e3 * (time.perf_counter() - t))
        inside.append(1e3 * _device_time(pstats.Stats(prof)))
        copies.append(counts["copies"])
        megabytes.append(counts["bytes"] / 1e6)
    return walls, inside, copies, megabytes


def _forget_lists(contact) -> None:
    """Drop what a contact set keeps of its candidate lists (the search, its sides, vertices, geometry and pair
    potentials), so that its next :meth:`~sim_core.contact_set.ContactSet.potentials` builds them again."""
    for name in ("_candidates", "_cache", "_step_table", "_end_geometry", "_vertices_kept", "_held_kept",
                 "_list_keys"):
        setattr(contact, name, None)
    contact._last_pots = ()


def _count_device_traffic() -> dict:
    """Count the synchronous byte copies (``device_copy._copy``: calls and bytes) and the new device arrays
    (``device_copy.new_ndarray``) into the dict returned (``copies``, ``bytes``, ``arrays``; cleared by the caller)."""
    import collections

    from sim_core.ti_kernels import device_copy

    counts: dict = collections.Counter()
    copy, new = device_copy._copy, device_copy.new_ndarray

    def counted_copy(array, host, upload, rows=None):
        counts["copies"] += 1
        counts["bytes"] += host.nbytes if rows is None else host[:rows].nbytes
        return copy(array, host, upload, rows)

    def counted_new(dtype, shape):
        counts["arrays"] += 1
        return new(dtype, shape)

    device_copy._copy, device_copy.new_ndarray = counted_copy, counted_new
    for module in list(sys.modules.values()):  # the modules that bound new_ndarray by name
        if getattr(module, "new_ndarray", None) is new and module is not device_copy:
            module.new_ndarray = counted_new
    return counts


def _device_time(stats: pstats.Stats) -> float:
    """Seconds inside Taichi kernel launches and synchronous copies (their outermost calls' cumulative time)."""
    total = 0.0
    for (path, _, name), (_, _, _, cumulative, callers) in stats.stats.items():
        launch = (path.endswith("sim_core/ti_kernels/launch.py") and name == "__call__") or \
                 (path.endswith("sim_core/ti_kernels/device_copy.py") and name == "_copy") or \
                 ("/taichi/" in path and name == "__call__" and "kernel_impl" in path)
        if launch and not any(_is_launch(c) for c in callers):
            total += cumulative
    return total


def _is_launch(caller: tuple) -> bool:
    path, _, name = caller
    return (path.endswith("sim_core/ti_kernels/launch.py") and name == "__call__") or "/taichi/" in path


if __name__ == "__main__":
    sys.exit(main())
