"""Time the parts of one lockstep Newton iteration of the Forming scene, term by term.

Usage: ``python benchmarks/parts_lockstep.py --arch cuda --B 256``. Builds ``B`` copies, takes two steps
(compilation, contacts), sets up the third step and times, at its first iterate, each term's gradient,
the fused elastic evaluation, the contact search, each dynamic term's Hessian, the projected elastic
Hessian part by part (and the bending projector's steps), the vertex blocks and the CG; median of
``--repeat`` runs each, in ms.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def _median_ms(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def stepped_forming(B: int, arch: str, horizon: int = 4, pcg: bool = False):
    """A lockstep Forming run of ``B`` copies (``sim_core.bench.batch._FormingRun``, ``horizon`` steps planned) on
    the Taichi backend of ``arch`` (initialised by the caller), warmed up and stepped twice (compilation,
    contacts); ``pcg``: the batched CG on every arch (``linear_solver="pcg"``), else the arch's default solver."""
    from sim_core.bench.batch import ARCH_BACKENDS, _FormingRun
    from sim_core.control import Control
    import sim_core.solver_config as sc

    orig = sc.SolverConfig
    if pcg:
        sc.SolverConfig = lambda **kw: orig(**kw, linear_solver="pcg")
    try:
        run = _FormingRun(B, horizon, ARCH_BACKENDS[arch], lockstep=True)
    finally:
        sc.SolverConfig = orig
    run.batch.warm_up()
    for k in range(2):
        run.batch.step([Control(effector_pose_target={run.effector: t[k]}) for t in run.targets])
    return run


def third_step(B: int, arch: str):
    """``(solver, step, x)``: ``B`` lockstep Forming copies on the batched CG (every arch; the Taichi backend of
    ``arch``, initialised by the caller) after two steps (:func:`stepped_forming`), the third step set up."""
    from sim_core.control import Control
    from sim_core.step_info import StepInfo

    run = stepped_forming(B, arch, pcg=True)
    eng = run.batch.lockstep
    solver = eng.solver
    ctrl = eng.scene.stack_controls([Control(effector_pose_target={run.effector: t[2]}) for t in run.targets])
    step, x = solver._set_up_step(eng.state, ctrl, run.batch.sims[0].dt, None, StepInfo())
    return solver, step, x


def newton_system(B: int, arch: str, projection: str):
    """``(solver, step, x, operator, dof_copy)``: :func:`third_step`, its Newton matrix as the batched solver's
    device operator (contact blocks projected by ``projection``: ``clamp`` or ``none``), and each DoF's copy
    (shape ``(3 n,)``, int32)."""
    solver, step, x = third_step(B, arch)
    contact_terms = solver.contact.potentials(x, step.x_n, step.memory)
    operator = solver._device_operator(step, x, projection, contact_terms + step.dynamic_terms)
    scene = solver.scene
    segments = np.zeros(scene.model.vertex_count, dtype=np.int32)
    segments[scene.index] = np.arange(scene.copies)[:, None]
    return solver, step, x, operator, np.repeat(segments, 3)


def newton_rhs(solver, step, x) -> np.ndarray:
    """The Newton step's right-hand side ``-g`` at ``x`` on the free DoFs, float64, shape ``(3 n,)``."""
    from sim_core.step_info import StepInfo

    g = solver._stacked_gradient(step, solver._vectors.start(x), StepInfo())[2]
    g = g if isinstance(g, np.ndarray) else g.to_numpy()
    return -np.asarray(g, dtype=np.float64).reshape(-1) * step.free


def synced_median_ms(fn, repeat: int, before=()) -> float:
    """Median ms of ``fn`` over ``repeat`` calls, the device synchronised around each (``before``'s calls made
    first, untimed, each time)."""
    from sim_core.ti_backend import ti

    times = []
    for _ in range(repeat):
        for call in before:
            call()
        ti.sync()
        t = time.perf_counter()
        fn()
        ti.sync()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    from sim_core.step_info import StepInfo
    from sim_core.ti_backend import init_backend

    init_backend(args.arch)
    solver, step, x = third_step(args.B, args.arch)
    fused = step.fused
    rows = []

    def row(name, fn):
        fn()  # compile / warm
        rows.append((name, _median_ms(fn, args.repeat)))

    def fresh_eval():
        fused._kept = None
        fused._evaluate(x)

    row("fused elastic evaluate (energy, gradient, Hessian values)", fresh_eval)
    row("fused elastic energy only", lambda: fused.energy(x + 1e-9))
    row("contact potentials (search + pairs)", lambda: solver.contact.potentials(x, step.x_n, step.memory))
    contact_terms = solver.contact.potentials(x, step.x_n, step.memory)
    shift = iter(np.arange(1, 10 ** 6) * 1e-13)  # each call at new positions: no kept evaluation is reused
    for p in step.loop_terms + contact_terms:
        if p is fused:
            continue
        row(f"gradient {type(p).__name__} (new x)", lambda p=p: p.gradient(x + next(shift)))
        row(f"energy {type(p).__name__} (new x)", lambda p=p: p.energy(x + next(shift)))
    row("stacked gradient (contact potentials + every gradient, new x)",
        lambda: solver._stacked_gradient(step, solver._vectors.start(x + next(shift)), StepInfo()))
    row("stacked energy (new x)", lambda: solver._energy(step, x + next(shift), contact_terms, solver.contact.search_position))
    for p in contact_terms + step.dynamic_terms:
        for proj in ("none", "clamp"):
            row(f"hessian {type(p).__name__} {proj}", lambda p=p, proj=proj: p.hessian(x, proj))
    for part in fused._parts:
        values = np.zeros(fused.pattern.keys.size)
        row(f"projected {type(part).__name__}", lambda part=part: part.add_projected(x, "clamp", values))
    row("projected_hessian_values (all parts)", lambda: fused.projected_hessian_values(x, "clamp"))
    for method in ("lapack", "jacobi"):
        from sim_core.ti_kernels.block_projection import project_reduced_blocks

        bend = [part for part in fused._parts if type(part).__name__ == "FusedKirchhoffBending"]
        if bend:
            red = bend[0]._projector.reduced(bend[0].triangle_hessians(x))
            red = 0.5 * (red + np.swapaxes(red, 1, 2))
            row(f"bending reduced blocks {red.shape} projected by {method}",
                lambda red=red, method=method: project_reduced_blocks(red.copy(), "clamp", method=method))
    dyn = contact_terms + step.dynamic_terms
    row("device operator (exact)", lambda: solver._device_operator(step, x, "none", dyn))
    upper, blocks, diagonal = solver._device_operator(step, x, "none", dyn)
    row("pcg factorize", lambda: solver.pcg.factorize(upper, blocks, diagonal))
    g = np.random.default_rng(0).normal(size=3 * x.shape[0]) * step.free
    row("pcg solve (random rhs)", lambda: solver.pcg.solve(g))
    print(f"B={args.B} arch={args.arch} blocks={blocks.rows.size} pattern nnz={fused.pattern.keys.size} "
          f"cg iterations={solver.pcg.iterations}")
    for name, ms in rows:
        print(f"{name:70s} {ms:10.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
