"""The roofline of a lockstep step: bytes and flops a scene-step of each phase, from a real lockstep's data structures.

Usage: ``python benchmarks/roofline.py --arch cpu --B 2 [--at 1024] [--markdown]``. Builds ``B`` lockstep Forming
copies on the batched CG (``parts_lockstep.stepped_forming``: warmed up, two steps taken), reads the sizes of the
structures a step works on from the engine itself (:func:`lockstep_sizes`: the batched CG's device arrays after the
last factorisation, the band blocks' ``m``, ``w`` and tiles, the vertex blocks of the contact and friction terms, the
stacked model's elements) and prints, per phase, the bytes and flops of one copy's step (:func:`phase_table`) with the
counts of a step (Newton iterations, CG iterations, line-search trial points, factorisations: the ``--newton`` etc.
options, by default the figures measured on an H100 at B = 1024, docs/benchmarks_log.md, session 48) and the floor of
``--at`` copies on the device (``--device``: :data:`DEVICES`), i.e. ``max(bytes / bandwidth, flops / rate)``. The
per-copy sizes do not depend on ``B`` (every copy is the same scene), so a small ``B`` on the CPU gives them.

What is counted from the structures (exact for the code as it is): the CG iteration's passes (the both-triangle CSR
product, the vertex blocks' gather and atomic scatter, the per-copy sums, the updates, the band blocks' tiled
substitutions), the band factorisation (gather, elimination, tile inverses and couplings: the multiply-adds of the
kernels' loops summed exactly) and the vectors a Newton iteration touches. What is estimated (flops a finite
element, :data:`ELEMENT_FLOPS`, written down from the formulas' sizes, not measured): the elastic terms' energies,
gradients and Hessian blocks and their projection. Bytes are the minimal traffic (each array read or written once a
pass, no cache reuse across passes), flops count a multiply-add as two; a floor is what the design's data movement
and arithmetic cannot go below on the device, not a prediction.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict, dataclass

import numpy as np

DEVICES = {
    # bytes/s of HBM, FP64 and FP32 flop/s (vector units; FP64 tensor cores 67 TFLOP/s are unused by these kernels)
    "h100-sxm": {"name": "H100 SXM5 80 GB (HBM3 3.35 TB/s; FP64 34, FP32 67 TFLOP/s, NVIDIA datasheet)",
                 "bandwidth": 3.35e12, "fp64": 34e12, "fp32": 67e12},
    "h200": {"name": "H200 SXM 141 GB (HBM3e 4.8 TB/s; FP64 34, FP32 67 TFLOP/s, NVIDIA datasheet)",
             "bandwidth": 4.8e12, "fp64": 34e12, "fp32": 67e12},
}

ELEMENT_FLOPS = {
    # estimated flops of one element's (energy, gradient and Hessian block) and of its block's PSD projection:
    # tet: F = Ds Dm^-1 (3x3x3), the 9x9 Hessian in F, then (dF/dx)^T H (dF/dx) to 12x12: 2 (9 9 12 + 9 12 12);
    # hinge: the dihedral angle's gradient (4 vertices) and the 12x12 outer-product Hessian with its curvature terms;
    # triangle: the membrane's 9x9 block; projection: cyclic Jacobi on a 12x12 block (about 6 sweeps of 66 rotations
    # of 2 x 4 x 12 flops) or 9x9 (6 sweeps of 36 rotations of 2 x 4 x 9 flops)
    "tet": {"energy": 150, "gradient": 400, "hessian": 4536, "projection": 6 * 66 * 96},
    "hinge": {"energy": 120, "gradient": 300, "hessian": 1500, "projection": 6 * 66 * 96},
    "triangle": {"energy": 80, "gradient": 200, "hessian": 900, "projection": 6 * 36 * 72},
}

MEASURED_COUNTS = {
    # a steady Forming step at B = 1024 on an H100 (docs/benchmarks_log.md, session 48, main's profile of steps 2-5):
    # Newton iterations a step, CG iterations a step (242 / 144 / 293 / 255), line-search trial points a step (9, 4,
    # 6, 5), band factorisations a step (one a Newton iteration plus the projected retries: 2 in 4 steps), contact
    # searches a step
    "newton": 6.3592, "cg": 233.5, "trial_points": 6.0, "factorizations": 6.8592, "projected_retries": 0.5,
    "searches": 1.5,
}

MEASURED_MS = {
    # the same profile's phases, ms a step at B = 1024 (H100): the CG's solves; the factorisations; the line search;
    # the stacked gradient; the projected elastic Hessian and pair blocks; the friction set-up, end_step, the set-up's
    # rest, copy_states, garbage collection and the contact force as "host and set-up"
    "linear solve (CG iterations)": 227.1, "band factorisation": 38.3, "line search (trial points)": 206.9,
    "assembly (gradient, Hessian values)": 21.8, "projection (projected retries)": 11.4 + 28.7,
    "host and set-up (outside the Newton loop)": 63.8 + 15.7 + 15.5 + 15.2 + 14.4 + 4.6,
}


@dataclass
class LockstepSizes:
    """The per-copy sizes a lockstep step works on (one copy of a stacked scene; every copy is the same).

    Attributes:
        vertices, dofs: a copy's vertices and DoFs (``3 vertices``); free_dofs: those not fixed.
        full_nnz: entries of the both-triangle CSR of the fused elastic Hessian (the CG's operator's assembled part).
        upper_nnz: entries of its upper triangle (the fused kernels' Hessian values).
        vertex_blocks: 3x3 blocks of the contact and friction terms at the last factorisation (matrix-free part).
        band_m, band_w, band_t, band_nt: the band block's DoFs, half-bandwidth, tile rows and tiles (0: none).
        tets, hinges, triangles: elastic elements of a copy.
        value_bytes: bytes of a stored matrix entry (4 in the CG's mixed precision, 8 in double).
    """

    vertices: int
    dofs: int
    free_dofs: int
    full_nnz: int
    upper_nnz: int
    vertex_blocks: int
    band_m: int
    band_w: int
    band_t: int
    band_nt: int
    tets: int
    hinges: int
    triangles: int
    value_bytes: int


def lockstep_sizes(engine) -> LockstepSizes:
    """The per-copy sizes of a lockstep engine (:class:`~sim_core.batch.lockstep.LockstepEngine`) whose solver has
    factorised at least once on the batched CG (its device arrays' shapes are read).

    Raises:
        ValueError: the engine's solver has no batched CG, or it has not factorised yet.
    """
    solver = engine.solver
    pcg = solver.pcg
    if pcg is None or pcg.factorizations == 0:
        raise ValueError("roofline: the lockstep's solver has no batched CG that has factorised (linear_solver 'pcg')")
    scene = engine.scene
    B = scene.copies
    a = pcg._arrays
    bands = pcg.bands
    banded = bands is not None and bands.width > 0
    model = scene.model
    elements = {"tets": 0, "hinges": 0, "triangles": 0}
    for body in model.bodies.values():  # a solid's tets, a sheet's hinges and (membrane) triangles
        for key in ({"tets"} if body.kind == "solid" else {"hinges", "triangles"} if body.kind == "sheet" else set()):
            arr = getattr(body, key, None)
            elements[key] += 0 if arr is None else int(np.shape(arr)[0])
    free = np.asarray(solver.pcg._uploaded.get("free", np.ones(1)))
    return LockstepSizes(
        vertices=scene.vertex_count, dofs=3 * scene.vertex_count,
        free_dofs=int(np.count_nonzero(free)) // B if free.size > 1 else 3 * scene.vertex_count,
        full_nnz=int(pcg._full[2]) // B, upper_nnz=int(pcg._full[0][-1]) // B,
        vertex_blocks=int(pcg._nblocks) // B,
        band_m=bands.size if banded else 0, band_w=bands.width if banded else 0,
        band_t=bands.tile if banded else 0, band_nt=bands.tiles if banded else 0,
        tets=elements["tets"] // B, hinges=elements["hinges"] // B, triangles=elements["triangles"] // B,
        value_bytes=int(np.dtype(np.float32 if a["full_data"].dtype != a["x"].dtype else np.float64).itemsize)
        if "x" in a else 8)


def cg_iteration(s: LockstepSizes) -> tuple[float, float]:
    """``(bytes, flops)`` of one CG iteration of one copy (:func:`~sim_core.ti_kernels.pcg._cg_iterations`): the CSR
    product (values, column indices, row pointers, ``p`` gathered, ``ap`` written), the vertex blocks (values, row and
    column vertices, ``p`` gathered at the column, ``ap`` atomically added at the row), ``p.Ap``, the update of
    ``x``, ``r``, ``z`` with the vertex inverses and ``r.z``, ``r.r``, the band blocks' substitutions (each tile's
    ``D^-1`` read twice by halves, ``G``, ``H``; the scratch vectors), ``r.z`` again, and ``p = z + beta p``."""
    n, v, f8, fv = s.dofs, s.vertices, 8, s.value_bytes
    csr = s.full_nnz * (fv + 4) + (n + 1) * 4 + n * f8 + n * f8
    blocks = s.vertex_blocks * (9 * fv + 8 + 2 * 3 * f8)
    dot = 2 * n * f8
    update = n * (2 * f8 + f8 + 2 * f8 + f8 + f8) + 9 * v * fv  # x rw, p, r rw, ap, z w; vertex inverses
    band = 0.0
    band_flops = 0.0
    if s.band_m:
        entries = 3 * s.band_nt * s.band_t ** 2  # D^-1 (both halves), G, H
        band = entries * fv + 4 * s.band_nt * s.band_t * f8 + 2 * s.band_m * (f8 + 4)
        band_flops = 2.0 * entries
    rz = 2 * n * f8 if s.band_m else 0
    p_update = 3 * n * f8 + n * f8
    total_bytes = csr + blocks + dot + update + band + rz + p_update
    flops = 2.0 * s.full_nnz + 2 * 9 * s.vertex_blocks + 2 * n + (6 * n + 2 * 9 * v) + band_flops + 2 * n + 2 * n
    return float(total_bytes), float(flops)


def band_factorisation(s: LockstepSizes) -> tuple[float, float]:
    """``(bytes, flops)`` of one band block's factorisation (:meth:`~sim_core.ti_kernels.band_cholesky.BandBlocks.
    assemble` after the first): the band gathered (positions and values), the banded elimination (``sum_k`` of the
    updates ``(i, j)``, ``k < j <= i <= k + w``), the scaling, the tiles' ``D^-1`` (each column's forward
    substitution over the band) and ``G``, ``H`` (the kernels' loop ranges summed exactly); bytes: the band read and
    written once, the tiles written once (no re-reads counted: the minimal traffic)."""
    m, w, t, nt = s.band_m, s.band_w, s.band_t, s.band_nt
    if not m:
        return 0.0, 0.0
    band_entries = m * (w + 1)
    k = np.arange(m)
    reach = np.minimum(w, m - 1 - k)  # rows below column k in the band
    elimination = float(np.sum(reach * (reach + 1) / 2.0))  # multiply-adds (each update a multiply-add and a divide)
    a = np.arange(t)[:, None]
    c = np.arange(t)[None, :]
    inverse = float(np.sum(np.where(a >= c, np.minimum(a, w), 0))) * nt  # each column's substitution, every tile
    couple = float(np.sum(np.clip(np.minimum(a, c + w - t) + 1, 0, None))) * max(nt - 1, 0) * 2  # G and H
    flops = 2.0 * (elimination + inverse + couple) + elimination + m
    nbytes = band_entries * (4 + 8 + 8 + 8) + 3 * nt * t * t * s.value_bytes
    return float(nbytes), flops


def element_pass(s: LockstepSizes, what: str) -> tuple[float, float]:
    """``(bytes, flops)`` of one pass of the elastic elements of a copy (``what``: ``energy``, ``gradient``,
    ``hessian``, ``projection``): element indices and per-element rest data read, positions read once, the results
    written (a sum, the gradient, the Hessian values in the upper-triangle pattern, or the projected blocks read and
    written); flops :data:`ELEMENT_FLOPS` (estimates)."""
    counts = {"tet": s.tets, "hinge": s.hinges, "triangle": s.triangles}
    rest = {"tet": 4 * 4 + 9 * 8 + 8, "hinge": 4 * 4 + 3 * 8, "triangle": 3 * 4 + 4 * 8 + 8}  # indices + rest data
    block = {"tet": 144, "hinge": 144, "triangle": 81}
    nbytes = sum(k * rest[e] for e, k in counts.items()) + 3 * s.vertices * 8
    if what == "gradient":
        nbytes += 3 * s.vertices * 8
    elif what == "hessian":
        nbytes += s.upper_nnz * 8 + s.vertex_blocks * 9 * 8
    elif what == "projection":
        nbytes += sum(k * block[e] * 8 * 2 for e, k in counts.items())
    flops = sum(k * ELEMENT_FLOPS[e][what] for e, k in counts.items())
    return float(nbytes), float(flops)


def phase_table(s: LockstepSizes, counts: dict, device: dict, copies: int) -> list[dict]:
    """Per phase: what one copy moves and computes in a scene-step (bytes, flops: a pass's times the step's count of
    it, ``counts`` as :data:`MEASURED_COUNTS`), and the floor of a step of ``copies`` copies on ``device``
    (:data:`DEVICES`), ms: ``max(bytes / bandwidth, flops / FP64 rate)`` (the arithmetic is float64 but the CG's stored
    values, which only move bytes)."""
    cg_b, cg_f = cg_iteration(s)
    fac_b, fac_f = band_factorisation(s)
    grad_b, grad_f = element_pass(s, "gradient")
    hess_b, hess_f = element_pass(s, "hessian")
    energy_b, energy_f = element_pass(s, "energy")
    proj_b, proj_f = element_pass(s, "projection")
    vec = 3 * s.vertices * 8
    rows = [
        ("assembly (gradient, Hessian values)", counts["newton"], grad_b + hess_b, grad_f + hess_f),
        ("projection (projected retries)", counts["projected_retries"], proj_b, proj_f),
        ("band factorisation", counts["factorizations"], fac_b, fac_f),
        ("linear solve (CG iterations)", counts["cg"], cg_b, cg_f),
        ("line search (trial points)", counts["trial_points"], energy_b + 4 * vec + grad_b, energy_f + grad_f),
    ]
    out = []
    for name, count, nbytes, flops in rows:
        step_bytes, step_flops = count * nbytes, count * flops
        floor_s = max(copies * step_bytes / device["bandwidth"], copies * step_flops / device["fp64"])
        out.append({"phase": name, "count": count, "bytes_a_pass": nbytes, "flops_a_pass": flops,
                    "bytes_a_scene_step": step_bytes, "flops_a_scene_step": step_flops,
                    "intensity": step_flops / max(step_bytes, 1.0), "floor_ms": 1e3 * floor_s,
                    "measured_ms": MEASURED_MS.get(name)})
    return out


def markdown(rows: list[dict], copies: int, device: dict) -> str:
    """The table as Markdown, with the step's floor and the measured figures beside it."""
    lines = [f"| phase (B = {copies}, {device['name']}) | passes a step | KB a copy-step | kflop a copy-step | "
             f"flop/B | floor ms a step | measured ms a step | measured / floor |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m = r["measured_ms"]
        measured = "" if m is None else f"{m:.1f}"
        ratio = "" if m is None else f"{m / max(r['floor_ms'], 1e-9):.0f}x"
        lines.append(f"| {r['phase']} | {r['count']:.2f} | {r['bytes_a_scene_step'] / 1e3:.0f} | "
                     f"{r['flops_a_scene_step'] / 1e3:.0f} | {r['intensity']:.2f} | {r['floor_ms']:.2f} | "
                     f"{measured} | {ratio} |")
    floor = sum(r["floor_ms"] for r in rows)
    lines.append(f"| **step (these phases)** | | {sum(r['bytes_a_scene_step'] for r in rows) / 1e3:.0f} | "
                 f"{sum(r['flops_a_scene_step'] for r in rows) / 1e3:.0f} | | **{floor:.2f}** | | |")
    lines.append(f"\nfloor: {1e3 * copies / floor:,.0f} scene-steps/s at B = {copies} (these phases alone, the "
                 f"host's work outside them and the launches' latency not counted)")
    return "\n".join(lines)


def coupled_dofs(pcg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, vertex_pairs)``: the DoF pairs the batched CG's matrix of its last factorisation couples (its
    assembled upper triangle's entries and every DoF pair of its contact and friction vertex blocks), and those
    blocks' vertex pairs ``(K, 2)``."""
    indptr, indices = pcg._full[0], pcg._full[1]
    nblocks = pcg._nblocks
    vertex_pairs = np.stack([pcg._arrays["brow"].to_numpy()[:nblocks], pcg._arrays["bcol"].to_numpy()[:nblocks]], 1)
    upper_rows = np.repeat(np.arange(indptr.size - 1), np.diff(indptr))
    d = np.arange(3)
    pair_rows = (3 * vertex_pairs[:, :1] + d[None, :]).repeat(3, axis=1).ravel()
    pair_cols = np.tile(3 * vertex_pairs[:, 1:] + d[None, :], (1, 3)).ravel()
    return (np.concatenate([upper_rows, pair_rows]), np.concatenate([np.asarray(indices)[: upper_rows.size], pair_cols]),
            vertex_pairs)


def envelope(order: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Row widths of the lower envelope of a symmetric pattern in an order: ``widths[p] = p - min{q <= p : (p, q)
    coupled} + 1`` (the diagonal included) at position ``p`` of ``order`` (the DoFs in order); ``rows``, ``cols`` the
    coupled DoF pairs (either triangle or both; pairs with a DoF outside ``order`` left out). The envelope (profile)
    Cholesky factorisation fills nothing outside it (George & Liu, Computer Solution of Large Sparse Positive
    Definite Systems, 1981, Ch. 4): its factor has ``widths.sum()`` entries, row ``p`` costs ``(widths[p] - 1)
    widths[p] / 2`` multiply-adds, and a triangular solve reads each entry once.

    Returns:
        ``(len(order),)`` int64.
    """
    order = np.asarray(order, dtype=np.int64)
    pos = np.full(max(int(order.max()), int(np.max(rows, initial=0)), int(np.max(cols, initial=0))) + 1, -1)
    pos[order] = np.arange(order.size)
    pr, pc = pos[np.asarray(rows)], pos[np.asarray(cols)]
    keep = (pr >= 0) & (pc >= 0)
    hi, lo = np.maximum(pr[keep], pc[keep]), np.minimum(pr[keep], pc[keep])
    first = np.arange(order.size)
    np.minimum.at(first, hi, lo)
    return np.arange(order.size) - first + 1


def envelope_table(s: LockstepSizes, widths: np.ndarray, counts: dict, device: dict, copies: int) -> list[dict]:
    """:func:`phase_table` with the linear solve a direct envelope Cholesky of each copy's whole system (row widths
    ``widths``, :func:`envelope`; float64 factor): one factorisation a Newton iteration and projected retry (the
    envelope gathered and its factor written; ``sum (w - 1) w`` flops), one forward and one back substitution a Newton
    iteration (the factor read twice, ``4 sum w`` flops); no band block, no CG iterations."""
    rows = [r for r in phase_table(s, counts, device, copies)
            if r["phase"] not in ("band factorisation", "linear solve (CG iterations)")]
    entries = float(widths.sum())
    factor = (entries * (8 + 4 + 8), float(np.sum((widths - 1.0) * widths)) + widths.size)
    solve = (2 * entries * 8 + 4 * widths.size * 8, 4.0 * entries)
    for name, count, (nbytes, flops) in (("envelope factorisation", counts["factorizations"], factor),
                                         ("envelope solves", counts["newton"], solve)):
        step_bytes, step_flops = count * nbytes, count * flops
        floor_s = max(copies * step_bytes / device["bandwidth"], copies * step_flops / device["fp64"])
        rows.insert(-1, {"phase": name, "count": count, "bytes_a_pass": nbytes, "flops_a_pass": flops,
                         "bytes_a_scene_step": step_bytes, "flops_a_scene_step": step_flops,
                         "intensity": step_flops / max(step_bytes, 1.0), "floor_ms": 1e3 * floor_s,
                         "measured_ms": None})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=2, help="copies built to read the sizes")
    ap.add_argument("--at", type=int, default=1024, help="copies of the floor")
    ap.add_argument("--device", default="h100-sxm", choices=sorted(DEVICES))
    for key, value in MEASURED_COUNTS.items():
        ap.add_argument(f"--{key.replace('_', '-')}", type=float, default=value)
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:M:W:CG",
                    help="another band block (M DoFs, half-bandwidth W, tiles by band_cholesky.tiling) with CG CG "
                         "iterations a step: its table too (e.g. the whole copy: copy:825:131:70)")
    args = ap.parse_args()
    from parts_lockstep import stepped_forming  # (benchmarks/, the script's folder)

    from sim_core.ti_backend import init_backend

    init_backend(args.arch)
    run = stepped_forming(args.B, args.arch, pcg=True)
    sizes = lockstep_sizes(run.batch.lockstep)
    print("per-copy sizes:", asdict(sizes))
    counts = {key: getattr(args, key) for key in MEASURED_COUNTS}
    print(markdown(phase_table(sizes, counts, DEVICES[args.device], args.at), args.at, DEVICES[args.device]))
    # the whole copy's envelope in reverse Cuthill-McKee order, the contact and friction blocks' couplings included
    from sim_core.batch.sheet_bands import copy_band_dofs

    engine = run.batch.lockstep
    pcg = engine.solver.pcg
    indptr, indices = pcg._full[0], pcg._full[1]
    rows, cols, vertex_pairs = coupled_dofs(pcg)
    free = pcg._uploaded["free"]
    for label, pairs in (("elastic pattern", None), ("elastic pattern and the contact pairs", vertex_pairs)):
        order = copy_band_dofs(engine.scene, free, indptr, indices, pairs)[0]
        widths = envelope(order, rows, cols)
        print(f"\nthe whole copy as a direct envelope Cholesky, reverse Cuthill-McKee order of the {label} "
              f"(contact and friction couplings of the last factorisation inside the envelope): m {widths.size}, "
              f"half-bandwidth {int(widths.max()) - 1}, envelope {int(widths.sum())} entries, "
              f"{int(np.sum((widths - 1) * widths // 2)):,d} multiply-adds a factorisation "
              f"(a band of that width: {widths.size * (int(widths.max()) - 1) ** 2 // 2:,d})")
        print(markdown(envelope_table(sizes, widths, counts, DEVICES[args.device], args.at), args.at,
                       DEVICES[args.device]))
    for spec in args.variant:
        print(f"\nvariant {spec}:")
        print(markdown(phase_table(*variant(sizes, counts, spec), DEVICES[args.device], args.at), args.at,
                       DEVICES[args.device]))
    return 0


def variant(sizes: LockstepSizes, counts: dict, spec: str) -> tuple[LockstepSizes, dict]:
    """``(sizes, counts)`` with another band block and CG iterations a step, ``spec`` = ``NAME:M:W:CG`` (the tiles by
    :func:`~sim_core.ti_kernels.band_cholesky.tiling`; the measured figures of the phases are not the variant's)."""
    from dataclasses import replace

    from sim_core.ti_kernels.band_cholesky import tiling

    _, m, w, cg = spec.split(":")
    t, nt = tiling(int(m), int(w))
    return replace(sizes, band_m=int(m), band_w=int(w), band_t=t, band_nt=nt), {**counts, "cg": float(cg)}


if __name__ == "__main__":
    sys.exit(main())
