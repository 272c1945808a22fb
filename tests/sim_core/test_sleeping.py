"""``SolverConfig.sleeping``: a resting body that nothing moving can reach is held out of the Newton
system; woken in time, the scene follows the never-sleeping solver's trajectory; anything that could
change a sleeping body wakes it."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.adjoint import rollout_step
from sim_core.builder import ModelBuilder
from sim_core.bundled import config_dir
from sim_core.contact_set import ContactSet
from sim_core.energies.contact.reference import (EdgeEdgeContact, VertexTriangleContact, edge_edge_vertices,
                                                 vertex_triangle_vertices)
from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.mesh.sheet import grid_sheet
from sim_core.model import ContactSettings
from sim_core.scenes import load_scene
from sim_core.simulation import Simulation
from sim_core.sleeping import SleepSet
from sim_core.solver import SolverConfig

SCENE = config_dir() / "scenes" / "press_slide.yaml"
# the bundled scene: the card (sheet) rests on the table, clamped at x0; the tactile pad (gel,
# driven by the effector ee) hangs 3.85 mm above it. A 0.1 mm move of the pad up and back settles
# the card to its rest well within the sleep threshold (its own Newton update falls from 8e-7 m/s
# to 1e-11 m/s); the pad then descends 0.25 mm a step, comes within the contact search distance
# (eps + margin = 1.4 mm) and presses the card.
DESCENT = 0.25e-3
STEPS = 44


def _plan(z0: float) -> list[float]:
    """The pad's commanded height per step: rest, 0.1 mm up and back, rest, descent onto the card, hold."""
    z = [z0] * 8 + [z0 + 1e-4] + [z0] * 7
    while len(z) < STEPS - 4:
        z.append(z[-1] - DESCENT)
    return z + [z[-1]] * 4


def _run(sleeping: bool, sim: Simulation | None = None):
    sim = sim or Simulation.from_scene(SCENE, solver_config=SolverConfig(repeat_fixed_points=True, sleeping=sleeping))
    pose = np.array(sim.state.effector_pose["ee"])
    xs, infos, heights = [], [], _plan(float(pose[2]))
    for z in heights:
        control = Control()
        target = pose.copy()
        target[2] = z
        control.effector_pose_target["ee"] = target
        infos.append(sim.step(control))
        xs.append(sim.state.x.copy())
    return sim, np.array(xs), infos


@pytest.fixture(scope="module")
def never_sleeping():
    return _run(False)


@pytest.fixture(scope="module")
def sleeping():
    return _run(True)


def _sheet(sim: Simulation) -> slice:
    b = sim.model.bodies["sheet"]
    return slice(b.vertex_start, b.vertex_stop)


def test_a_woken_in_time_scene_follows_the_never_sleeping_trajectory(never_sleeping, sleeping):
    _, ref, ref_infos = never_sleeping
    sim, xs, infos = sleeping
    assert np.max(np.abs(xs - ref)) < 1e-9  # m, every vertex, every step
    for a, b in zip(infos, ref_infos):
        # the held card misses the never-sleeping card's sub-threshold Newton updates (~1e-13 J)
        assert a.energy == pytest.approx(b.energy, rel=1e-7)
        assert a.converged_strict and b.converged_strict
    asleep = [k for k, i in enumerate(infos) if i.sleeping]
    assert len(asleep) >= 10 and all(infos[k].sleeping == ("sheet",) for k in asleep)
    assert not any(i.sleeping or i.fell_asleep or i.woken for i in ref_infos)
    # the card fell asleep once, was held bitwise while asleep, and woke before the pad touched it
    fell = [k for k, i in enumerate(infos) if i.fell_asleep]
    woke = [k for k, i in enumerate(infos) if i.woken]
    assert len(fell) == 1 and infos[fell[0]].fell_asleep == ("sheet",) and len(woke) == 1
    assert asleep == list(range(fell[0] + 1, woke[0]))
    sheet = _sheet(sim)
    for k in asleep:
        np.testing.assert_array_equal(xs[k, sheet], xs[fell[0], sheet])
    gel = sim.model.bodies["gel"]
    touching = [k for k in range(len(infos)) if np.min(xs[k, gel.vertex_start:gel.vertex_stop, 2]) - np.max(xs[k, sheet, 2]) < sim.model.contact.eps]
    assert touching and woke[0] < touching[0]
    # a sleeping step solves the gel alone: fewer free DoFs, same iterations as the full solve
    assert all(infos[k].iterations == ref_infos[k].iterations for k in asleep)
    assert sim.step_totals.sleeping_steps == len(asleep)


def test_an_approaching_pad_wakes_the_sleeping_card_before_its_step(sleeping):
    sim, xs, infos = sleeping
    woke = next(k for k, i in enumerate(infos) if i.woken)
    assert infos[woke].woken == ("sheet",) and infos[woke].wake_redos == 0 and not infos[woke].sleeping
    # the gap between the pad at its commanded height and the card's box when it woke: within the search
    # distance plus the pad's reach in a step (2 x its commanded move), and not the step before
    gel, sheet = sim.model.bodies["gel"], _sheet(sim)
    radius = sim.model.contact.eps + sim.model.contact.candidate_margin

    def gap(k):
        return np.min(xs[k, gel.vertex_start:gel.vertex_stop, 2]) - np.max(xs[k, sheet, 2])

    assert gap(woke - 1) - DESCENT < radius + 2 * DESCENT
    assert gap(woke - 2) - DESCENT >= radius + 2 * DESCENT - 1e-6


def test_a_pair_reached_during_the_solve_wakes_the_body_and_solves_again(never_sleeping, monkeypatch):
    # without the reach test before the step, the contact candidate pairs of the solve find the card
    monkeypatch.setattr(SleepSet, "_within_reach", lambda self, *args: False)
    _, ref, _ = never_sleeping
    sim, xs, infos = _run(True)
    redone = [k for k, i in enumerate(infos) if i.wake_redos]
    assert len(redone) == 1 and infos[redone[0]].woken == ("sheet",) and infos[redone[0]].wake_redos == 1
    assert infos[redone[0] - 1].sleeping == ("sheet",) and not infos[redone[0]].sleeping
    assert np.max(np.abs(xs - ref)) < 1e-9
    assert sim.step_totals.wake_redos == 1


def _asleep_sim() -> Simulation:
    """The bundled scene with the card asleep (after the pad's move up and back)."""
    sim = Simulation.from_scene(SCENE, solver_config=SolverConfig(repeat_fixed_points=True, sleeping=True))
    pose = np.array(sim.state.effector_pose["ee"])
    for k in range(16):
        target = pose.copy()
        target[2] += 1e-4 if k == 8 else 0.0
        control = Control()
        control.effector_pose_target["ee"] = target
        sim.step(control)
    assert sim.last_info.sleeping == ("sheet",)
    return sim


def test_changed_inputs_or_state_wake_the_card_and_a_guess_keeps_it_held():
    sim = _asleep_sim()
    assert sim.step().sleeping == ("sheet",)
    sim.set_parameter("sheet.bending_stiffness", sim.get_parameter("sheet.bending_stiffness") * 1.01)
    info = sim.step()
    assert info.woken == ("sheet",) and not info.sleeping

    sim = _asleep_sim()
    sim.model.gravity = np.array([0.0, 0.0, -9.0])
    assert sim.step().woken == ("sheet",)

    sim = _asleep_sim()
    sim.state.x = sim.state.x.copy()
    sim.state.x[_sheet(sim).start + 20, 2] += 1e-6  # the state is not the held one
    assert sim.step().woken == ("sheet",)

    sim = _asleep_sim()
    held = sim.state.x.copy()
    guess = held.copy()
    guess[_sheet(sim).start + 20, 2] += 1e-6  # a guess elsewhere for the sleeping card: its held positions stand
    info = sim.step(Control(position_guess=guess))
    assert info.sleeping == ("sheet",) and not info.woken
    assert np.array_equal(sim.state.x[_sheet(sim)], held[_sheet(sim)])

    sim = _asleep_sim()
    sim.reset()
    assert not sim.step().sleeping


def test_sleeping_is_refused_for_gradients_and_bad_settings():
    sim = _asleep_sim()
    with pytest.raises(ConfigError, match=r"rollout step 3: bodies \['sheet'\] slept through the step"):
        rollout_step(sim, None, 3)
    with pytest.raises(ConfigError, match="sleep_velocity must be a finite number > 0"):
        SolverConfig(sleeping=True, sleep_velocity=0.0)
    with pytest.raises(ConfigError, match="sleeping is not available with lockstep"):
        SolverConfig(sleeping=True, lockstep=True)


def test_held_pairs_apart_and_unremembered_leave_the_candidates_others_stay():
    model = load_scene(SCENE)
    contact = ContactSet(model)
    sheet = model.bodies["sheet"]
    x = model.state().x.copy()
    # fold one vertex of the card onto a triangle of it that is not its neighbour: an active held pair
    x_search, vt, ee = contact._candidate_pairs(x)
    p, t = vt[len(vt) // 2]
    x[p] = x[contact.triangles[t]].mean(axis=0) + np.array([0.0, 0.0, 0.5 * model.contact.eps])
    contact = ContactSet(model)
    memory = contact.begin_step(x, None)
    candidates = contact._candidate_pairs(x)
    remembered = candidates[2][:3]  # three edge-edge pairs in the memory
    memory.edge_edge.update(remembered, np.ones(len(remembered)))
    held = np.zeros(model.vertex_count, dtype=bool)
    held[sheet.vertex_start:sheet.vertex_stop] = True
    contact.held = held
    _, vt_kept, ee_kept = contact._without_held_pairs(candidates, x, memory)
    assert len(vt_kept) < len(candidates[1]) and len(ee_kept) < len(candidates[2])
    # exactly the pairs with a vertex not held, active at x or remembered (their vertices gathered whole here), with
    # the whole card held and with the card's first half held (pairs of held and free elements too)
    some = held.copy()
    some[(sheet.vertex_start + sheet.vertex_stop) // 2:sheet.vertex_stop] = False
    for mask in (held, some):
        contact.held = mask
        found = contact._without_held_pairs(candidates, x, memory)
        for pairs, kept, vertices, kind, mem in (
                (candidates[1], found[1], vertex_triangle_vertices(candidates[1], contact.triangles),
                 VertexTriangleContact, memory.vertex_triangle),
                (candidates[2], found[2], edge_edge_vertices(candidates[2], contact.edges), EdgeEdgeContact,
                 memory.edge_edge)):
            elements = contact.triangles if kind is VertexTriangleContact else contact.edges
            stays = ~mask[vertices].all(axis=1) | kind(pairs, elements, np.zeros(len(pairs)), contact.stiffness,
                                                       contact.eps).active_mask(x) | mem.lookup(pairs)[1]
            assert not stays.all()
            np.testing.assert_array_equal(kept, pairs[stays])
    contact.held = held
    assert any(np.array_equal(row, [p, t]) for row in vt_kept)  # active: kept
    for row in remembered:
        assert any(np.array_equal(r, row) for r in ee_kept)  # remembered: kept
    # every pair left out is apart: the full and the kept potentials agree at x
    full = contact._vertex_triangle(candidates[1], np.zeros(len(candidates[1])))
    kept = contact._vertex_triangle(vt_kept, np.zeros(len(vt_kept)))
    assert full.energy(x) == pytest.approx(kept.energy(x), rel=1e-12) and full.energy(x) > 0
    assert contact._without_held_pairs(candidates, x, memory) is contact._without_held_pairs(candidates, x, memory)
    contact.held = None
    assert contact._without_held_pairs(candidates, x, memory) is candidates


def _sheet_under_a_sphere(sleeping: bool) -> Simulation:
    """A 4 x 4 sheet on the table z = 0 and an 8 mm sphere driven 12 mm above it (Newton to 1e-8 m/s, a
    tenth of the sleep velocity, so that the sheet settles within the sleep threshold; at 1e-9 m/s the
    contact step stalls at 1.5-1.9e-8 m/s with either linear solver under NumPy 2.4.6 / SciPy 1.17.1)."""
    b = ModelBuilder()
    material = {"youngs_modulus": 1e7, "poisson_ratio": 0.3, "thickness": 5e-4, "density": 500.0,
                "bending_stiffness": 1e-4}
    b.add_sheet("sheet", grid_sheet((0.03, 0.03), (4, 4), (-0.015, -0.015, 2e-4)), material)
    b.add_plane("table", [0.0, 0.0, 1.0], 0.0)
    b.set_friction("sheet", "table", 0.3)
    b.add_sphere("ball", [0.0, 0.0, 0.02], 0.008)
    b.add_effector("ee", "ball", [0], [0.0, 0.0, 0.02, 0.0, 0.0, 0.0, 1.0], max_translation_per_step=2e-3)
    config = SolverConfig(tol_velocity=1e-8, repeat_fixed_points=True, sleeping=sleeping)
    return Simulation(b.finalize(contact=ContactSettings(stiffness=1e4, eps=4e-4)), dt=0.005, solver_config=config)


def _sphere_run(sleeping: bool):
    sim = _sheet_under_a_sphere(sleeping)
    xs, infos = [], []
    for k in range(40):
        control = Control()
        control.effector_pose_target["ee"] = np.array([0.0, 0.0, 0.02 - 1e-3 * max(0, k - 14), 0.0, 0.0, 0.0, 1.0])
        infos.append(sim.step(control))
        xs.append(sim.state.x.copy())
    return np.array(xs), infos


def test_a_sphere_coming_down_wakes_the_sheet_and_the_trajectories_agree(monkeypatch):
    ref, _ = _sphere_run(False)
    xs, infos = _sphere_run(True)
    assert np.max(np.abs(xs - ref)) < 1e-9
    asleep = [k for k, i in enumerate(infos) if i.sleeping]
    woke = [k for k, i in enumerate(infos) if i.woken]
    assert len(asleep) >= 5 and len(woke) == 1 and infos[woke[0]].woken == ("sheet",)
    # woken (by the reach test, before its step) before the sphere came within the contact offset of a vertex
    gap = [float(np.min(np.linalg.norm(x[:-1] - x[-1], axis=1))) - 0.008 for x in ref]
    touch = next(k for k, g in enumerate(gap) if g < 4e-4)
    assert woke[0] < touch and infos[woke[0]].wake_redos == 0
    # without the reach test (also the one that keeps a body near a moving one from falling asleep), the
    # solve's own check finds the sphere near the sleeping sheet, at every step it falls asleep again
    monkeypatch.setattr(SleepSet, "_within_reach", lambda self, *args: False)
    xs, infos = _sphere_run(True)
    redone = [k for k, i in enumerate(infos) if i.wake_redos]
    assert redone and redone[0] <= touch and all(infos[k].woken == ("sheet",) for k in redone)
    assert np.max(np.abs(xs - ref)) < 1e-9
