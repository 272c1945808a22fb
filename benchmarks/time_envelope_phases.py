"""One envelope factorisation (``schedule="dots"``, the CUDA default) timed by its parts on one real Newton matrix: the
column's dot products, its pivot and write-back, the block synchronisation a column (issue 52, docs/gpu_roofline.md).

Usage: ``python benchmarks/time_envelope_phases.py --arch cuda --B 1024 --repeat 5``. Builds ``B`` lockstep Forming
copies (``parts_lockstep.newton_system``: two steps taken, the third set up; its Newton matrix with the contact blocks
projected), factorises it once with :class:`~sim_core.ti_kernels.envelope_cholesky.BatchedEnvelope` (the solver's
lanes and group), then times (medians of ``--repeat``, the device synchronised around each) the gather and
factorisation (``_eliminate``) and variants of the factorisation kernel over the same envelope with parts left out:
``full`` (the solver's kernel's work: :func:`~sim_core.ti_kernels.envelope_cholesky._factor_dots` copied with switches),
``no_dots`` (each entry's dot product not taken: the pivot, the write-back, the column loop and its synchronisation),
``no_sync`` (no block synchronisation a column), ``loop_only`` (neither dots nor writes: the column loop, the tasks'
index reads and the synchronisation). The variants run on an envelope already factorised (values change, the loads,
arithmetic and control flow do not: the loops depend on the envelope's structure only), so their difference is each
part's time; a part's share = ``full`` less the variant without it. Prints one JSON line: the envelope's size
(``m`` columns, entries a copy, the mean front), and the ms of each variant.
"""

import argparse
import json
import sys
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    from parts_lockstep import newton_system, synced_median_ms  # (benchmarks/, the script's folder)

    from sim_core.ti_backend import init_backend, ti

    init_backend(args.arch)
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope
    from sim_core.ti_kernels.envelope_funcs import _F64, _I32, _group_sum, _pivot
    from sim_core.ti_kernels.precision import VALUES, stored

    @ti.kernel
    def factor_parts(env: VALUES, off: _I32, first: _I32, fptr: _I32, frows: _I32, todo: _I32, bad: _I32, inv: _F64,
                     m: ti.i32, size: ti.i32, copies: ti.i32, lanes: ti.template(), group: ti.template(),
                     dots: ti.template(), writes: ti.template(), sync: ti.template()):
        # _factor_dots of sim_core.ti_kernels.envelope_cholesky, its parts switched: dots (the entries' dot products),
        # writes (the pivot and the write-back), sync (the block synchronisation a column)
        ti.loop_config(block_dim=lanes)
        for t in range(copies * lanes):
            c = t // lanes
            lane = t % lanes
            sub = lane % group
            groups = lanes // group
            if lane == 0:
                bad[c] = 0
            if todo[c] != 0:
                base = c * size
                vb = c * m
                for j in range(m):
                    fj = first[j]
                    rowj = base + off[j] - fj
                    start = fptr[j]
                    front = fptr[j + 1] - start
                    task = lane // group
                    while task <= front:
                        i = j
                        if task > 0:
                            i = frows[start + task - 1]
                        fi = first[i]
                        rowi = base + off[i] - fi
                        acc = 0.0
                        other = 0.0
                        if ti.static(dots):
                            k = ti.max(fi, fj) + sub
                            while k + group < j:
                                acc += ti.cast(env[rowi + k], ti.f64) * ti.cast(env[rowj + k], ti.f64) * inv[vb + k]
                                other += (ti.cast(env[rowi + k + group], ti.f64)
                                          * ti.cast(env[rowj + k + group], ti.f64) * inv[vb + k + group])
                                k += 2 * group
                            if k < j:
                                acc += ti.cast(env[rowi + k], ti.f64) * ti.cast(env[rowj + k], ti.f64) * inv[vb + k]
                            acc = _group_sum(acc + other, lane, group)
                        if ti.static(writes):
                            if sub == 0:
                                v = ti.cast(env[rowi + j], ti.f64) - acc
                                env[rowi + j] = stored(v, env)
                                if task == 0:
                                    stored_v = ti.cast(env[rowi + j], ti.f64)
                                    inv[vb + j] = 1.0 / _pivot(stored_v)
                                    if not stored_v > 0.0:
                                        bad[c] = 1
                        elif ti.static(dots):  # the sum kept live without a write-back of the envelope
                            if sub == 0 and acc != acc:
                                bad[c] = 2
                        task += groups
                    if ti.static(sync and lanes > 1):
                        ti.simt.block.sync()

    t0 = time.perf_counter()
    solver, step, x, operator, dof_copy = newton_system(args.B, args.arch, "clamp")
    set_up_s = time.perf_counter() - t0
    envelope = BatchedEnvelope(dof_copy, precision="double")
    envelope.factorize(*operator)
    envelope.solve(np.zeros(dof_copy.size))  # (compilation; the envelope's flags read)
    a, B, m, size = envelope._arrays, envelope._copies, envelope._m, envelope.entries
    lanes, group = envelope._lane_count(), envelope.group
    env = envelope._array("env", max(B * size, 1), envelope._env_dtype)
    inv = envelope._array("env_inv", max(B * m, 1))
    todo = envelope._array("env_todo", max(B, 1), ti.i32)
    bad = envelope._array("env_scratch_flags", B + 1, ti.i32)
    fptr = a["env_fptr"].to_numpy()

    def variant(dots: bool, writes: bool, sync: bool):
        return lambda: factor_parts(env, a["env_off"], a["env_first"], a["env_fptr"], a["env_frows"], todo, bad, inv,
                                    m, size, B, lanes, group, dots, writes, sync)

    record = {"bench": "envelope_phases", "arch": args.arch, "B": B, "m": m, "entries": size, "lanes": lanes,
              "group": group, "schedule": envelope.schedule, "mean_front": float(np.mean(np.diff(fptr[:m + 1]))),
              "set_up_s": round(set_up_s, 1),
              "eliminate_ms": synced_median_ms(envelope._eliminate, args.repeat)}
    for name, switches in (("full", (True, True, True)), ("no_dots", (False, True, True)),
                           ("no_sync", (True, True, False)), ("no_writes", (True, False, True)),
                           ("loop_only", (False, False, True))):
        run = variant(*switches)
        run()  # compilation
        record[f"{name}_ms"] = synced_median_ms(run, args.repeat)
    print(json.dumps(record), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
