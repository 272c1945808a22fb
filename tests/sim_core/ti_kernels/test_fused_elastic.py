"""Fused elastic kernels (energy + gradient + exact Hessian into CSR slots) equal the NumPy reference.

Each fused kernel is checked against its reference potential (energy, gradient, and the exact
Hessian assembled through the static pattern, with fixed DoFs and repeated block vertices) at
random deformed configurations, and against central finite differences of its own energy and
gradient. A Newton step on the fused path equals the reference path.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.assembly import HessianAssembler
from sim_core.energies.hinge_bending.reference import DiscreteShellBending
from sim_core.energies.kirchhoff_bending.reference import KirchhoffBending
from sim_core.energies.membrane.reference import SpringMembrane, StVKMembrane
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.mesh.sheet import grid_sheet, sheet_topology
from sim_core.mesh.tet import tet_box
from tests.sim_core.ti_kernels.conftest import TEST_ARCH, assert_same_sums
from tests.support.fd import fd_gradient, fd_hessian, relative_error

TEST_BACKEND = f"taichi-{TEST_ARCH}"  # the solver backend of the kernels' test arch (one Taichi arch per process)


def _sheet(nx: int = 4, ny: int = 3):
    mesh = grid_sheet((0.02, 0.015), (nx, ny), (0.0, 0.0, 0.0))
    return mesh, sheet_topology(mesh.triangles)


def _deformed_sheet(x: np.ndarray, seed: int, amplitude: float = 1.5e-3) -> np.ndarray:
    """A wavy, randomly perturbed copy of a flat sheet (bent hinges, stretched and compressed edges)."""
    rng = np.random.default_rng(seed)
    y = x.copy()
    y[:, 2] += 2e-3 * np.sin(150.0 * x[:, 0]) + 1e-3 * np.cos(120.0 * x[:, 1])
    return y + amplitude * rng.standard_normal(x.shape)


def _potentials(kind: str):
    """(reference potential, rest positions, deformed positions per seed)."""
    if kind == "snh":
        mesh = tet_box((0.01, 0.01, 0.01), (3, 3, 3), (0.0, 0.0, 0.0))
        pot = StableNeoHookean(mesh.tets, mesh.x, 3e5, 0.45)
        return pot, mesh.x, lambda seed: mesh.x + 1.5e-3 * np.random.default_rng(seed).standard_normal(mesh.x.shape)
    mesh, topo = _sheet()
    if kind == "spring_membrane":
        pot = SpringMembrane(mesh.triangles, topo.edges, mesh.x, 1000.0, 800.0)
    elif kind == "kirchhoff":
        theta_bar = np.linspace(-0.3, 0.4, topo.hinges.shape[0])
        pot = KirchhoffBending(mesh.triangles, topo.hinges, mesh.x, 2e-3, 0.3, theta_bar)
    elif kind == "stvk_membrane":
        pot = StVKMembrane(mesh.triangles, mesh.x, 1e6, 0.3, 3e-4)
    elif kind == "anisotropic_bending":  # candidate term: hinge weights beta cos(2 phi) k of both signs
        from sim_core.candidates.anisotropic_bending import AnisotropicBendingCorrection

        theta_bar = np.linspace(0.2, -0.1, topo.hinges.shape[0])
        pot = AnisotropicBendingCorrection(DiscreteShellBending(topo.hinges, mesh.x, 2e-3, theta_bar), mesh.x, 0.4)
        assert pot.hinge_cos2phi.min() < -0.5 and pot.hinge_cos2phi.max() > 0.5
    else:
        theta_bar = np.linspace(0.2, -0.1, topo.hinges.shape[0])
        pot = DiscreteShellBending(topo.hinges, mesh.x, 2e-3, theta_bar)  # no fused kernel: reference part
    return pot, mesh.x, lambda seed: _deformed_sheet(mesh.x, seed)


def _fused(pot, x_rest: np.ndarray, free: np.ndarray):
    from sim_core.fused_elastic import FusedElastic

    fused = FusedElastic([pot])
    asm = HessianAssembler(x_rest.size)
    fused.bind(asm.static_pattern(fused.block_vertex_arrays(x_rest), free))
    return fused, asm


KINDS = ("snh", "spring_membrane", "kirchhoff", "stvk_membrane", "anisotropic_bending", "hinge_reference_part")


@pytest.mark.parametrize("kind", KINDS)
def test_fused_equals_reference(ti_cpu, kind):
    pot, x_rest, deformed = _potentials(kind)
    n = x_rest.shape[0]
    free = np.ones(3 * n, bool)
    free[[0, 1, 2, 7, 3 * n - 1]] = False  # fixed DoFs drop rows and columns
    fused, asm = _fused(pot, x_rest, free)
    diag = np.linspace(1.0, 2.0, 3 * n)
    for seed in (0, 1, 2):
        x = deformed(seed)
        e_ref, g_ref = pot.energy(x), pot.gradient(x)
        assert fused.energy(x) == pytest.approx(e_ref, rel=1e-12)  # energy-only kernels
        g = fused.gradient(x)
        assert relative_error(g, g_ref) < 1e-12
        assert fused.energy(x) == pytest.approx(e_ref, rel=1e-12)  # kept from the fused evaluation
        H_ref = asm.assemble_upper([pot.hessian(x, "none")], [], diag, free)
        H = asm.assemble_upper_values(fused.pattern, fused.hessian_values(x), [], diag, free)
        assert np.array_equal(H.indptr, H_ref.indptr) and np.array_equal(H.indices, H_ref.indices)
        assert relative_error(H.data, H_ref.data) < 1e-12


@pytest.mark.parametrize("kind", KINDS[:5])
def test_fused_derivatives_match_finite_differences(ti_cpu, kind):
    pot, x_rest, deformed = _potentials(kind)
    if kind == "snh":  # a smaller block keeps the dense FD Hessian cheap
        mesh = tet_box((0.01, 0.01, 0.01), (2, 2, 2), (0.0, 0.0, 0.0))
        pot, x_rest = StableNeoHookean(mesh.tets, mesh.x, 3e5, 0.45), mesh.x
        deformed = lambda seed: mesh.x + 1.5e-3 * np.random.default_rng(seed).standard_normal(mesh.x.shape)  # noqa: E731
    free = np.ones(x_rest.size, bool)
    fused, asm = _fused(pot, x_rest, free)
    x = deformed(5)
    g = fused.gradient(x)
    assert relative_error(g, fd_gradient(fused.energy, x, h=1e-7)) < 1e-5
    upper = asm.assemble_upper_values(fused.pattern, fused.hessian_values(x), [], np.zeros(x.size), free)
    H = (upper + upper.T).toarray() - np.diag(upper.diagonal())
    assert relative_error(H, fd_hessian(fused.gradient, x, h=1e-7)) < 1e-5


def test_mixed_terms_and_new_rest_angles(ti_cpu):
    """Several potentials in one FusedElastic; a step with new rest angles reuses it."""
    from sim_core.fused_elastic import FusedElastic

    mesh, topo = _sheet(5, 4)
    membrane = SpringMembrane(mesh.triangles, topo.edges, mesh.x, 1000.0, 800.0)
    bending = KirchhoffBending(mesh.triangles, topo.hinges, mesh.x, 2e-3, 0.3)
    stvk = StVKMembrane(mesh.triangles, mesh.x, 3e9, 0.3, 3e-4)
    hinge = DiscreteShellBending(topo.hinges, mesh.x, 1e-3)
    terms = [membrane, stvk, bending, hinge]
    free = np.ones(mesh.x.size, bool)
    fused = FusedElastic.for_terms(None, terms)
    asm = HessianAssembler(mesh.x.size)
    fused.bind(asm.static_pattern(fused.block_vertex_arrays(mesh.x), free))
    x = _deformed_sheet(mesh.x, 7)
    diag = np.ones(mesh.x.size)
    for theta_bar in (None, np.full(topo.hinges.shape[0], 0.2)):
        if theta_bar is not None:
            import copy

            bent = copy.copy(bending)
            bent.hinge_theta_bar = theta_bar
            terms = [membrane, stvk, bent, hinge]
            same = FusedElastic.for_terms(fused, terms)
            assert same is fused  # same elements: kernels and slot maps kept, rest angles replaced
        assert fused.energy(x) == pytest.approx(sum(p.energy(x) for p in terms), rel=1e-12)
        assert relative_error(fused.gradient(x), sum(p.gradient(x) for p in terms)) < 1e-12
        H_ref = asm.assemble_upper([p.hessian(x, "none") for p in terms], [], diag, free)
        H = asm.assemble_upper_values(fused.pattern, fused.hessian_values(x), [], diag, free)
        assert relative_error(H.data, H_ref.data) < 1e-12
    assert FusedElastic.for_terms(fused, [membrane, stvk, bending]) is not fused


def _forming_steps(backend: str, steps: int):
    """The Forming scene on solver backend ``backend`` stepped ``steps`` times along the benchmark
    trajectory; returns ``(simulation, Newton iterations of each step)``."""
    from sim_core.control import Control
    from sim_core.scenes.task_scene import load_task_scene, task_initial_state
    from sim_core.simulation import Simulation
    from sim_core.solver import SolverConfig
    from sim_core.tasks.trajectories import forming_benchmark_offsets, pose_targets
    from thinshell_ros.paths import bundled_scene

    model = load_task_scene(bundled_scene("forming"))
    sim = Simulation(model, solver_config=SolverConfig(backend=backend))
    sim.state = task_initial_state(model)
    effector = next(iter(model.effectors))
    targets = pose_targets(model.effectors[effector].initial_pose, forming_benchmark_offsets(steps))
    iterations = []
    for k in range(steps):
        control = Control()
        control.effector_pose_target[effector] = targets[k]
        iterations.append(sim.step(control).iterations)
    return sim, iterations


def test_solver_steps_equal_reference_path(ti_cpu):
    """Forming steps on the Taichi backend of the test arch (fused kernels) equal the NumPy path."""
    runs = []
    for backend in ("numpy", TEST_BACKEND):
        sim, iterations = _forming_steps(backend, 4)
        runs.append((sim.state.x.copy(), iterations, sim.solver.last_record.hessian_exact))
    (x_ref, it_ref, exact_ref), (x_fused, it_fused, exact_fused) = runs
    assert it_fused == it_ref and exact_fused == exact_ref
    assert np.max(np.abs(x_fused - x_ref)) < 1e-12


def test_compile_kernels_runs_every_fused_kernel(ti_cpu):
    from sim_core.energies.neohookean.kernel import TiStableNeoHookean
    from sim_core.kernel_compile import compile_kernels

    mesh, topo = _sheet(3, 3)
    tet = np.array([[0.0, 0.0, -0.01], [0.01, 0.0, -0.01], [0.0, 0.01, -0.01], [0.0, 0.0, 0.0]])
    x_rest = np.concatenate([mesh.x, tet])
    n = mesh.x.shape[0]
    potentials = [
        SpringMembrane(mesh.triangles, topo.edges, x_rest, 1.0, 1.0),
        TiStableNeoHookean(np.array([[n, n + 1, n + 2, n + 3]]), x_rest, 1e5, 0.3),
        KirchhoffBending(mesh.triangles, topo.hinges, x_rest, 1e-3, 0.3),
    ]
    assert compile_kernels(potentials, x_rest) >= 0.0


def test_evaluate_keeps_the_values_of_a_fresh_evaluation(ti_cpu):
    """``evaluate(x)`` keeps what ``energy``, ``gradient`` and ``hessian_values`` then read at ``x``
    (a copy of ``x`` as well): equal to a second evaluator's fresh calls, the energy to the energy-only
    kernels (bit for bit on the CPU: ``assert_same_sums``); another ``x`` is evaluated afresh."""
    mesh, topo = _sheet()
    n = mesh.x.shape[0]
    free = np.ones(3 * n, dtype=bool)
    free[:3] = False
    terms = [SpringMembrane(mesh.triangles, topo.edges, mesh.x, 1.0, 1.0),
             KirchhoffBending(mesh.triangles, topo.hinges, mesh.x, 1e-3, 0.3)]
    from sim_core.fused_elastic import FusedElastic

    pair = []
    for _ in range(2):
        fused = FusedElastic(terms)
        fused.bind(HessianAssembler(3 * n).static_pattern(fused.block_vertex_arrays(mesh.x), free))
        pair.append(fused)
    kept, fresh = pair
    x = _deformed_sheet(mesh.x, 3)
    kept.evaluate(x)
    energy_only = fresh.energy(x)  # energy-only kernels (nothing kept yet)
    assert_same_sums(kept.energy(x.copy()), energy_only)
    assert_same_sums(kept.gradient(x.copy()), fresh.gradient(x))
    assert_same_sums(kept.hessian_values(x.copy()), fresh.hessian_values(x))
    y = _deformed_sheet(mesh.x, 4)
    assert_same_sums(kept.energy(y), fresh.energy(y))
    assert abs(kept.energy(y) - energy_only) > 1e-6 * energy_only


def test_solver_prefetch_of_trial_points_changes_nothing(ti_cpu, monkeypatch):
    """Forming steps whose line searches evaluate the first trial point with the fused kernels
    (energy, gradient and Hessian: ``FusedElastic.evaluate``, ``TiLaggedFriction.keep_derivatives``) equal
    those with energy-only trial evaluations (bit for bit on the CPU: ``assert_same_sums``), with the same
    iterations, and launch fewer energy-only kernels."""
    from sim_core.energies.base import positions_key
    from sim_core.energies.friction.kernel import TiLaggedFriction
    from sim_core.fused_elastic import FusedElastic

    energy = FusedElastic.energy
    runs = []
    for prefetch in (True, False):
        calls = {"energy": 0}

        def counted(self, x, calls=calls):
            kept = self._kept
            calls["energy"] += not (kept is not None and kept[0] == positions_key(x))
            return energy(self, x)

        monkeypatch.setattr(FusedElastic, "energy", counted)
        if not prefetch:
            monkeypatch.setattr(FusedElastic, "evaluate", lambda self, x: None)
            monkeypatch.setattr(TiLaggedFriction, "keep_derivatives", lambda self, x: None)
        sim, iterations = _forming_steps(TEST_BACKEND, 6)
        runs.append((sim.state.x.copy(), iterations, calls["energy"]))
    (x_on, it_on, e_on), (x_off, it_off, e_off) = runs
    assert it_on == it_off and sum(it_on) > 6
    assert_same_sums(x_on, x_off)
    assert e_on < e_off


def _maxwell_branch(beta: float, seed: int = 5, gel=None):
    """A Maxwell branch with a random relaxed state on ``gel`` (``_potentials("snh")``, new if None)."""
    from sim_core.candidates.gel_viscoelasticity import MaxwellBranch

    pot, x_rest, deformed = _potentials("snh") if gel is None else gel
    rng = np.random.default_rng(seed)
    Fr = np.eye(3) + rng.normal(scale=0.05, size=(pot.tets.shape[0], 3, 3))
    return MaxwellBranch(pot, Fr, beta), pot, x_rest, deformed


def test_fused_anisotropic_bending_projected_blocks_are_the_candidates(ti_cpu):
    """The fallback's projected Hessian of the fused anisotropic part is the candidate's own
    (``max(c_h, 0) P(H_h)``), and the part follows a new step's term (new rest angles)."""
    import copy

    from sim_core.fused_elastic import FusedElastic

    pot, x_rest, deformed = _potentials("anisotropic_bending")
    free = np.ones(x_rest.size, bool)
    free[:4] = False
    fused, asm = _fused(pot, x_rest, free)
    x = deformed(4)
    diag = np.zeros(x_rest.size)
    for projection in ("clamp", "abs"):
        H_ref = asm.assemble_upper([pot.hessian(x, projection)], [], diag, free)
        H = asm.assemble_upper_values(fused.pattern, fused.projected_hessian_values(x, projection), [], diag, free)
        assert relative_error(H.data, H_ref.data) < 1e-12
    bending = copy.copy(pot.bending)
    bending.hinge_theta_bar = pot.bending.hinge_theta_bar + 0.05
    later = type(pot)(bending, x_rest, pot.beta)
    assert FusedElastic.for_terms(fused, [later]) is fused
    assert fused.energy(x) == pytest.approx(later.energy(x), rel=1e-12)
    assert relative_error(fused.gradient(x), later.gradient(x)) < 1e-12


def test_maxwell_branch_elastic_equivalent_equals_the_branch():
    """The branch's Stable Neo-Hookean equivalent (rest volumes beta V) has its energy, gradient and
    exact and projected Hessian blocks."""
    branch, _, _, deformed = _maxwell_branch(0.7)
    eq = branch.elastic_equivalent()
    assert eq is branch.elastic_equivalent()  # built once
    x = deformed(3)
    assert eq.energy(x) == pytest.approx(branch.energy(x), rel=1e-12)
    assert relative_error(eq.gradient(x), branch.gradient(x)) < 1e-12
    for projection in ("none", "clamp"):
        a, b = eq.hessian(x, projection), branch.hessian(x, projection)
        assert np.array_equal(a.vertices, b.vertices)
        assert relative_error(a.blocks, b.blocks) < 1e-12


def test_fused_kernel_takes_a_new_branch_each_step(ti_cpu):
    """One fused part follows the step's branch (new relaxed state, new object) through ``for_terms``:
    energy, gradient and Hessian values equal a fresh evaluator's, for the exact and projected Hessian."""
    from sim_core.fused_elastic import FusedElastic

    gel = _potentials("snh")
    first, pot, x_rest, deformed = _maxwell_branch(0.4, seed=1, gel=gel)
    second, _, _, _ = _maxwell_branch(0.9, seed=2, gel=gel)
    free = np.ones(x_rest.size, dtype=bool)
    free[:6] = False
    kept, _ = _fused(pot, x_rest, free)  # the gel alone: a different part list, rebuilt below
    kept = FusedElastic.for_terms(kept, [pot, first.elastic_equivalent()])
    kept.bind(HessianAssembler(x_rest.size).static_pattern(kept.block_vertex_arrays(x_rest), free))
    x = deformed(7)
    kept.gradient(x)
    reused = FusedElastic.for_terms(kept, [pot, second.elastic_equivalent()])
    assert reused is kept  # same elements and parameters: the parts follow the new branch
    fresh = FusedElastic([pot, second.elastic_equivalent()])
    fresh.bind(kept.pattern)
    assert kept.energy(x) == pytest.approx(fresh.energy(x), rel=1e-13)
    assert kept.energy(x) == pytest.approx(pot.energy(x) + second.energy(x), rel=1e-12)
    # bit for bit on the CPU; on CUDA the atomic sums' order varies from launch to launch (assert_same_sums)
    assert_same_sums(kept.gradient(x), fresh.gradient(x))
    assert_same_sums(kept.hessian_values(x), fresh.hessian_values(x))
    assert_same_sums(kept.projected_hessian_values(x, "clamp"), fresh.projected_hessian_values(x, "clamp"))


def _fused_candidate_press(candidates: dict, route: str = "model_candidates", depth: float = 0.0004):
    """The tiny press scene of the candidate tests on the fused path, pressed ``depth`` m per step for
    4 steps with ``candidates`` set as model candidates (the diagnosis replays' route) or through
     a :class:`~sim_core.candidates.CandidateHook` given to the solver (``route="hook"``).

    Returns:
        ``(simulation, Newton iterations per step, types of the fused evaluator's parts)``.
    """
    import copy

    from sim_core.candidates import CandidateHook
    from sim_core.control import Control
    from sim_core.scenes import load_scene
    from sim_core.simulation import Simulation
    from tests.sim_core.candidates.test_hook import SCENE

    from sim_core.solver import SolverConfig

    model = load_scene(copy.deepcopy(SCENE))
    sim = Simulation(model, dt=0.01, solver_config=SolverConfig(backend=TEST_BACKEND))
    if route == "hook":
        sim.solver.set_hook(CandidateHook(candidates))
    else:
        for name, value in candidates.items():
            sim.set_parameter(f"candidate.{name}", value)
    pose = np.array(SCENE["effectors"]["ee"]["initial_pose"], dtype=float)
    iterations = []
    for k in range(1, 5):
        target = pose.copy()
        target[2] = pose[2] - depth * k
        iterations.append(sim.step(Control({"ee": target})).iterations)
    return sim, iterations, [type(part) for part in sim.solver._fused._parts]


@pytest.mark.parametrize("route", ["model_candidates", "hook"])
def test_solver_fuses_the_maxwell_branch(ti_cpu, monkeypatch, route):
    """A press with the gel viscoelasticity candidate on the fused path (branch in the fused Stable
    Neo-Hookean kernel) equals the same steps with the branch evaluated by its NumPy methods (a
    dynamic Hessian term), whether set as model candidates (as the diagnosis replays do) or given as
    a hook, and the relaxation state follows."""
    import sim_core.fused_elastic as fused_elastic
    from sim_core.energies.neohookean.fused_kernel import FusedStableNeoHookean

    params = {"gel_viscoelasticity": 1.5, "gel_viscoelasticity.tau": 0.03}
    fused, it_fused, parts_fused = _fused_candidate_press(params, route)
    monkeypatch.setattr(fused_elastic, "_fused_form", lambda potential: potential)  # no elastic equivalent
    plain, it_plain, parts_plain = _fused_candidate_press(params, route)
    assert parts_fused.count(FusedStableNeoHookean) == 2  # the gel and its branch
    assert parts_plain.count(FusedStableNeoHookean) == 1
    assert it_fused == it_plain
    assert np.max(np.abs(fused.state.x - plain.state.x)) < 1e-12
    Fr_f = fused.state.candidate_state["gel_viscoelasticity"]
    Fr_p = plain.state.candidate_state["gel_viscoelasticity"]
    for name in Fr_f:
        assert np.max(np.abs(Fr_f[name] - Fr_p[name])) < 1e-10
        assert np.max(np.abs(Fr_f[name] - np.eye(3))) > 1e-4  # the branch did relax: it was active


def test_solver_fuses_the_anisotropic_bending_candidate(ti_cpu, monkeypatch):
    """A press with the anisotropic bending candidate set as model candidates (the diagnosis replays'
    route): the fused hinge part equals the candidate's NumPy blocks merged as a dynamic term."""
    import sim_core.solver as solver_module
    from sim_core.energies.hinge_bending.fused_kernel import FusedAnisotropicBending

    params = {"anisotropic_bending": -0.6}
    fused, it_fused, parts_fused = _fused_candidate_press(params, depth=0.0005)
    off, _, _ = _fused_candidate_press({}, depth=0.0005)
    monkeypatch.setattr(solver_module, "fusable", lambda p: False)
    plain, it_plain, parts_plain = _fused_candidate_press(params, depth=0.0005)
    assert parts_fused.count(FusedAnisotropicBending) == 1 and FusedAnisotropicBending not in parts_plain
    assert it_fused == it_plain
    assert np.max(np.abs(fused.state.x - plain.state.x)) < 1e-12
    assert np.max(np.abs(off.state.x - fused.state.x)) > 1e-9  # the candidate acts


def test_device_array_evaluation_equals_the_host_one(ti_cpu, monkeypatch):
    """The CUDA evaluation path (constant arrays, positions, gradient and Hessian values as Taichi
    ndarrays, sim_core.ti_kernels.buffers.on_device), run here on the CPU arch with the arch query
    answering "cuda": the same energy, gradient and values as the NumPy-argument path."""
    import sim_core.ti_backend as backend
    from sim_core.fused_elastic import FusedElastic

    if ti_cpu == "cuda":
        pytest.skip("the reference is the NumPy-argument path, which runs on the CPU arch only")
    terms = []
    xs = []
    offset = 0
    for kind in ("snh", "spring_membrane", "kirchhoff"):
        pot, x_rest, deformed = _potentials(kind)
        xs.append((x_rest, deformed(3)))
        terms.append((kind, pot, offset))
        offset += x_rest.shape[0]
    # one model of three disjoint bodies: each term's element indices moved to its body's rows
    pots = [_potentials(kind)[0] for kind, _, _ in terms]
    pots = [StableNeoHookean(pots[0].tets, xs[0][0], 3e5, 0.45),
            SpringMembrane(pots[1].triangles + terms[1][2], pots[1].edges + terms[1][2], np.concatenate([x for x, _ in xs]),
                           1000.0, 800.0),
            KirchhoffBending(pots[2].triangles + terms[2][2], pots[2].hinges + terms[2][2],
                             np.concatenate([x for x, _ in xs]), 2e-3, 0.3, np.linspace(-0.3, 0.4, pots[2].hinges.shape[0]))]
    x_rest = np.concatenate([x for x, _ in xs])
    x = np.concatenate([y for _, y in xs])
    free = np.ones(x.size, bool)
    free[:6] = False

    def evaluate():
        fused = FusedElastic(pots)
        asm = HessianAssembler(x.size)
        fused.bind(asm.static_pattern(fused.block_vertex_arrays(x_rest), free))
        return fused.energy(x), fused.gradient(x), fused.hessian_values(x).copy(), fused

    e_host, g_host, v_host, fused_host = evaluate()
    p_host = fused_host.projected_hessian_values(x, "clamp")
    assert not fused_host._on_device()
    assert fused_host.projected_hessian_values_device(x, "clamp") is None  # host arrays: no device values
    import sim_core.energies.kirchhoff_bending.fused_kernel as kirchhoff_kernel
    import sim_core.energies.membrane.fused_spring_kernel as spring_kernel

    for module in (backend, kirchhoff_kernel, spring_kernel):
        monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    e_dev, g_dev, v_dev, fused_dev = evaluate()
    assert fused_dev._on_device() and fused_dev._device_kept is not None
    assert e_dev == pytest.approx(e_host, rel=1e-13)
    assert relative_error(g_dev, g_host) < 1e-13
    assert relative_error(v_dev, v_host) < 1e-13
    assert abs(v_host).max() > 0
    # a GPU's sum arrays of several cells (here 4, in host memory): every part's energy added into one array, read
    # once an evaluation (the energy-only kernels), the fused evaluation's only when its energy is asked for
    from sim_core.ti_kernels import launch

    monkeypatch.setattr(launch, "_new_cells", lambda runtime: np.zeros(4))
    reads = []
    cells_sum = launch._cells_sum
    monkeypatch.setattr(launch, "_cells_sum", lambda array: (reads.append(array), cells_sum(array))[1])
    e_shared, g_shared, v_shared, fused_shared = evaluate()
    assert fused_shared._sums.sharing and len(reads) == 1
    assert e_shared == pytest.approx(e_host, rel=1e-13)
    assert fused_shared.energy(x) == pytest.approx(e_host, rel=1e-13) and len(reads) == 2  # the evaluation's, once
    assert fused_shared.energy(x) == pytest.approx(e_host, rel=1e-13) and len(reads) == 2
    np.testing.assert_array_equal(g_shared, g_dev)
    np.testing.assert_array_equal(v_shared, v_dev)
    # the projected Hessian: positions uploaded once, every part's blocks made, reduced and scattered by kernels on
    # device arrays, the reduced blocks projected by LAPACK on the host (few blocks): the host path's values
    p_dev = fused_dev.projected_hessian_values(x, "clamp")
    assert relative_error(p_dev, p_host) < 1e-12
    assert relative_error(p_host, v_host) > 1e-6  # the projection changed the matrix
    # the values left on the device, the reduced blocks projected there by the Jacobi kernel (as a lockstep batch's
    # many blocks), of every element and of the elements touching the marked vertices (the last body's)
    from sim_core.ti_kernels import block_projection

    monkeypatch.setattr(block_projection, "HOST_PROJECTION_MAX_BLOCKS", 0)
    marked = np.zeros(x.shape[0], dtype=bool)
    marked[terms[2][2]:] = True
    for vertices in (None, marked):
        want = fused_host.projected_hessian_values(x, "abs", vertices)
        device = fused_dev.projected_hessian_values_device(x, "abs", vertices)
        assert not isinstance(device, np.ndarray) and device.shape == want.shape
        assert relative_error(device.to_numpy(), want) < 1e-12
    assert relative_error(want, p_host) > 1e-6  # the marked body's blocks only
    # a new mask (a lockstep batch's next projected retry): every part's element rows are sent before the
    # projection's first kernel (the fill of the sums), so that no synchronous copy waits for a queued kernel
    from sim_core.ti_kernels import device_copy, transfer

    events = []
    to_device, fill = device_copy.to_device, transfer.fill
    monkeypatch.setattr(device_copy, "to_device", lambda *args: (events.append("copy"), to_device(*args))[1])
    monkeypatch.setattr(transfer, "fill", lambda *args: (events.append("fill"), fill(*args))[1])
    device = fused_dev.projected_hessian_values_device(x, "abs", marked.copy())
    assert relative_error(device.to_numpy(), want) < 1e-12
    assert events.count("fill") == 1 and events.count("copy") >= 1, events  # the marked body's rows
    assert events[-1] == "fill", events  # every copy before it
    with pytest.raises(ValueError, match="projection"):
        fused_dev.projected_hessian_values_device(x, "flip")


def test_a_nodal_pressure_gel_steps_alike_on_the_fused_path(ti_cpu):
    """A nodal-pressure gel (:mod:`sim_core.energies.nodal_pressure`) pressed by a plate: its shear part goes to
    the fused Stable Neo-Hookean kernel and its nodal term to a reference part, and the steps equal the NumPy
    path's."""
    from sim_core.control import Control
    from sim_core.fused_elastic import _ReferencePart
    from sim_core.indentation import build_indentation
    from sim_core.mesh.sheet import TriMesh
    from sim_core.mesh.tet import TetMesh
    from sim_core.model import ContactSettings
    from sim_core.simulation import Simulation
    from sim_core.solver import SolverConfig

    gel = tet_box((0.01, 0.008, 0.004), (5, 4, 3), (-0.005, -0.004, -0.004))
    plate = TriMesh(np.array([[-0.02, -0.02, 0.0], [0.02, -0.02, 0.0], [0.02, 0.02, 0.0], [-0.02, 0.02, 0.0]]),
                    np.array([[0, 1, 2], [0, 2, 3]]))
    setup = build_indentation(TetMesh(gel.x, gel.tets), np.flatnonzero(np.isclose(gel.x[:, 2], -0.004)), plate,
                              3e5, 0.45, ContactSettings(stiffness=2e5, eps=4e-4, eps_v=1e-6, self_contact=False),
                              indenter_lift=None, indenter_vertices_vs_gel=False, gel_element="nodal_pressure_neohookean")
    runs = []
    for backend in ("numpy", TEST_BACKEND):
        sim = Simulation(setup.model, dt=1.0, solver_config=SolverConfig(tol_velocity=1e-9, max_iterations=50,
                                                                         projection="abs", backend=backend))
        pose = sim.state.effector_pose[setup.effector].copy()
        for k in range(1, 3):
            control = Control()
            control.effector_pose_target[setup.effector] = pose - np.array([0, 0, 3e-5 * k, 0, 0, 0, 0])
            sim.step(control)
        runs.append(sim.state.x.copy())
        if backend != "numpy":
            parts = [type(p).__name__ for p in sim.solver._fused._parts]
            assert "FusedStableNeoHookean" in parts and any(isinstance(p, _ReferencePart) for p in sim.solver._fused._parts)
    assert np.max(np.abs(runs[1] - runs[0])) < 1e-10
    assert np.abs(runs[0][: len(gel.x)] - setup.model.x_rest[: len(gel.x)]).max() > 2e-5  # the gel was pressed
