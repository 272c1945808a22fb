"""No tunnelling (issue: simulator core, "A sheet pressed and dragged between a gel and a table must
never tunnel"): sheet on sheet, a sheet folded onto itself, and a sheet on a tet-box table.

Every step of each rollout is checked by :class:`tests.support.contact_audit.CrossingAudit`, which
keeps its own sides (never the solver's side memory): the contact distance (m) of every pair that
has a side at the step's start stays > 0 at its end, and no edge pierces a triangle. Each scenario
also proves that the surfaces actually touched (pairs within the contact offset eps = 0.4 mm), or
the check would prove nothing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim_core.builder import ModelBuilder
from sim_core.control import Control
from sim_core.mesh.sheet import TriMesh
from sim_core.scenes.task_scene import build_task_scene, load_task_scene, task_initial_state
from sim_core.simulation import Simulation
from tests.support.contact_audit import CrossingAudit
from tests.support.press_scenes import EPS, pad_scene, paper_sheet, press_and_drag

SCENES = Path(__file__).resolve().parents[2] / "config" / "scenes"


def _forces(sim: Simulation, body: str) -> np.ndarray:
    """Net contact + friction force on ``body`` at the end of the last step, N, ``(3,)``."""
    b = sim.model.bodies[body]
    return sim.state.contact_force[b.vertex_start:b.vertex_stop].sum(axis=0)


def test_the_audit_sees_a_vertex_pass_through_a_triangle():
    """The audit itself can fail: a vertex 0.2 mm above a triangle that ends 0.1 mm below it has
    signed distance -0.1 mm, and the triangle's edges pierced by a crossing sheet are counted."""
    b = ModelBuilder()
    mat = {"youngs_modulus": 1e8, "poisson_ratio": 0.3, "thickness": 1e-4, "density": 1000.0, "bending_stiffness": 1e-4}
    b.add_sheet("a", TriMesh(np.array([[0.0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]]), np.array([[0, 1, 2]])), mat)
    b.add_sheet("b", TriMesh(np.array([[0.002, 0.002, 2e-4], [0.012, 0.002, 2e-4], [0.002, 0.012, 2e-4]]),
                             np.array([[0, 1, 2]])), mat)
    model = b.finalize()
    audit = CrossingAudit(model, [("a", "b")])
    x_n = model.x_rest
    x = x_n.copy()
    x[3, 2] = -1e-4  # b's first vertex goes through a
    step = audit.step(x_n, x)
    assert step.min_signed_distance == pytest.approx(-1e-4)
    assert step.intersections == 2  # b's two edges at that vertex pierce a
    assert step.active_pairs > 0


@pytest.fixture(scope="module")
def stacked_sheets_run():
    """Two paper sheets stacked on the table plane (lower 60 x 30 mm, 9 x 5 vertices; upper
    30 x 20 mm, 6 x 5 vertices, grids not aligned, 0.35 mm apart), pressed 1.5 mm by the pad in
    10 steps and dragged 20 mm along +x in 20 steps. Coulomb coefficients: pad-upper 0.8,
    upper-lower 0.3, lower-table 0.8, so the upper sheet slides over the lower one under load."""
    pad_z = 0.0007 + 0.00015 + EPS + 0.0006  # 0.6 mm gap above the upper sheet's contact offset
    scene = pad_scene(
        {"lower": paper_sheet((0.06, 0.03), (9, 5), (-0.01, -0.015, 0.00035)),
         "upper": paper_sheet((0.03, 0.02), (6, 5), (-0.0125, -0.0105, 0.0007))},
        pad_z, [{"pair": ["pad", "upper"], "mu": 0.8}, {"pair": ["upper", "lower"], "mu": 0.3},
                {"pair": ["lower", "table"], "mu": 0.8}], pad_x=0.0025)
    model = build_task_scene(scene)
    sim = Simulation(model)
    sim.state = task_initial_state(model)
    sheets, gel = CrossingAudit(model, [("upper", "lower")]), CrossingAudit(model, [("pad", "upper")])
    lower = model.bodies["lower"]
    lower_z, pad_force = [], []

    def on_step(x_n, sim):
        sheets.step(x_n, sim.state.x)
        gel.step(x_n, sim.state.x)
        lower_z.append(sim.state.x[lower.vertex_start:lower.vertex_stop, 2].min())
        pad_force.append(_forces(sim, "pad"))

    upper = model.bodies["upper"]
    x0 = sim.state.x.copy()
    press_and_drag(sim, "pad", 0.0015, 0.02, 10, 20, on_step)
    slid = (sim.state.x[upper.vertex_start:upper.vertex_stop, 0].mean() - x0[upper.vertex_start:upper.vertex_stop, 0].mean()
            - (sim.state.x[lower.vertex_start:lower.vertex_stop, 0].mean() - x0[lower.vertex_start:lower.vertex_stop, 0].mean()))
    return sheets, gel, np.array(lower_z), np.array(pad_force), slid


def test_stacked_sheets_pressed_and_dragged_never_cross(stacked_sheets_run):
    """Upper vs lower sheet: min signed distance > 0 at every step (measured: ~0.34 mm, pushed from
    eps = 0.4 mm by ~36 N), no edge-triangle piercing, the sheets touch at every step (pairs < eps)
    and the upper sheet slid > 15 mm over the lower one; the lower sheet's vertices stay above the
    table plane z = 0 (signed distance of a vertex to the plane: its z) while the pad pushes with
    > 20 N; the pad does not cross the upper sheet either."""
    sheets, gel, lower_z, pad_force, slid = stacked_sheets_run
    s = sheets.summary()
    assert s["min_signed_distance"] > 0.0, s
    assert s["intersections"] == 0, s
    assert s["active_steps"] == len(sheets.history), s
    assert slid > 0.015, slid
    assert np.all(lower_z > 0.0), lower_z.min()
    assert pad_force[10:, 2].min() > 20.0, pad_force[:, 2]
    g = gel.summary()
    assert g["min_signed_distance"] > 0.0 and g["intersections"] == 0 and g["max_active_pairs"] > 0, g


def test_sheet_on_a_tet_box_table_pressed_and_dragged_never_crosses_the_box():
    """A paper sheet (40 x 30 mm, 7 x 5 vertices) resting on a frozen 9 x 9 x 2 tet box (top face
    z = 0, not a plane) is pressed 1.5 mm by the pad and dragged 20 mm (pad-sheet mu 0.8,
    sheet-box 0.3: the sheet slides on the box). Sheet vs box surface: min signed distance > 0
    at every step, no piercing, contact active at every step; the box carries the pad's load
    (vertical contact force on the box = -(force on the pad) within 2 % + the sheet's weight),
    and the sheet really slid (> 15 mm)."""
    scene = pad_scene({"sheet": paper_sheet((0.04, 0.03), (7, 5), (-0.02, -0.015, 0.00035))},
                      0.00035 + 0.00015 + EPS + 0.0005,
                      [{"pair": ["pad", "sheet"], "mu": 0.8}, {"pair": ["sheet", "table"], "mu": 0.3}],
                      table="box", pad_x=-0.005)
    model = build_task_scene(scene)
    sim = Simulation(model)
    sim.state = task_initial_state(model)
    audit = CrossingAudit(model, [("sheet", "table")])
    sheet = model.bodies["sheet"]
    x0 = sim.state.x[sheet.vertex_start:sheet.vertex_stop].copy()
    balance = []

    def on_step(x_n, sim):
        audit.step(x_n, sim.state.x)
        balance.append((_forces(sim, "pad")[2], _forces(sim, "table")[2]))

    press_and_drag(sim, "pad", 0.0015, 0.02, 8, 20, on_step)
    s = audit.summary()
    assert s["min_signed_distance"] > 0.0, s
    assert s["intersections"] == 0, s
    assert s["active_steps"] == len(audit.history), s
    pad_z, box_z = np.array(balance)[8:].T
    weight = sheet.material["density"] * sheet.material["thickness"] * 0.04 * 0.03 * 9.81
    assert pad_z.min() > 20.0
    np.testing.assert_allclose(-box_z, pad_z + weight, rtol=0.02)
    slid = (sim.state.x[sheet.vertex_start:sheet.vertex_stop, 0] - x0[:, 0]).mean()
    assert slid > 0.015, slid


def _fold_onto_itself(sim: Simulation, steps: int, on_step, depth: float = 0.0125, ramp: int = 25,
                      drag: float = 0.0) -> None:
    """Folding scene: the dome over the hairpin's bend moves down ``depth`` (default 12.5 mm) in
    ``ramp`` steps (the top layer starts 13.3 mm above the bottom one and sags under the dome),
    then holds, or drags the fold ``drag`` m along +x over the remaining steps."""
    pose0 = sim.state.effector_pose["dome"].copy()
    control = Control()
    for i in range(steps):
        target = pose0.copy()
        target[0] += drag * max(0.0, (i + 1 - ramp) / (steps - ramp))
        target[2] -= depth * min(1.0, (i + 1) / ramp)
        control.effector_pose_target["dome"] = target
        x_n = sim.state.x.copy()
        sim.step(control)
        on_step(x_n, sim)


def _self_contact_pairs_active(sim: Simulation) -> int:
    """Vertex-triangle and edge-edge pairs of the sheet with itself in the solver's contact set whose
    contact distance is below eps at the current state."""
    body = sim.model.body_of_vertex()
    x = sim.state.x
    count = 0
    for pot in sim.solver.contact._pairs(x, sim.state.contact_memory):
        v = pot.vertices
        same = body[v[:, 0]] == body[v[:, -1]]
        count += int(np.count_nonzero(same & (pot.distance(x) < sim.model.contact.eps)))
    return count


def test_sheet_folded_onto_itself_never_crosses():
    """``config/scenes/folding.yaml`` (16 x 4 strip folded into a hairpin, self-contact on): the
    dome presses the top layer down onto the bottom layer (27 steps). Self pairs (the contact set's
    rest-distance exclusion, 2 (eps + margin) = 2.8 mm, applied): min signed distance > 0 at every
    step and no edge of the sheet pierces one of its triangles; the layers do come within eps of
    each other (audit: pairs < eps; solver: self-contact pairs < eps in its contact set) on the last
    steps. Without self-contact the same motion makes the layers cross (checked here, so the audit
    is shown to catch it on this scene)."""
    model = load_task_scene(SCENES / "folding.yaml")
    sim = Simulation(model)
    sim.state = task_initial_state(model)
    audit = CrossingAudit(model, [("sheet", "sheet")])
    solver_active = []
    _fold_onto_itself(sim, 27, lambda x_n, sim: (audit.step(x_n, sim.state.x),
                                                  solver_active.append(_self_contact_pairs_active(sim))))
    s = audit.summary()
    assert s["min_signed_distance"] > 0.0, s
    assert s["intersections"] == 0, s
    assert s["max_active_pairs"] >= 5 and s["active_steps"] >= 4, s
    assert max(solver_active) >= 3, solver_active


def test_without_self_contact_the_same_fold_crosses():
    """Control of the previous test: the folding scene with ``self_contact: false`` and the same
    dome motion lets the top layer pass through the bottom one, and the audit reports it
    (negative signed distance and piercing edges)."""
    import yaml

    scene = yaml.safe_load((SCENES / "folding.yaml").read_text())
    scene["contact"]["self_contact"] = False
    model = build_task_scene(scene)
    sim = Simulation(model)
    sim.state = task_initial_state(model)
    audit = CrossingAudit(model, [("sheet", "sheet")])
    _fold_onto_itself(sim, 27, lambda x_n, sim: audit.step(x_n, sim.state.x))
    s = audit.summary()
    assert s["min_signed_distance"] < 0.0 and s["intersections"] > 0, s


@pytest.mark.parametrize("depth, ramp, steps, drag", [(0.0125, 25, 40, 0.0), (0.0135, 20, 40, 0.0),
                                                      (0.0125, 25, 65, 0.015)])
def test_sheet_held_folded_onto_itself_keeps_converging(depth, ramp, steps, drag):
    """The dome pressed into the folded sheet (12.5 mm in 25 steps, or 13.5 mm in 20) and held
    for the rest of 40 steps, or pressed 12.5 mm and then dragging the fold 15 mm along +x over 40
    more steps: every Newton step converges, within 40 iterations, and no self pair crosses.

    Regression: all three motions failed before with "line search failed ... (no decrease along the
    Newton direction)" (steps 27, 18-20 and 27), dt halvings or not. A dome edge and a sheet edge
    0.81 mm apart at the step's start kept the side of their line-line normal; within the step the
    lines crossed beyond an end of the sheet edge, and the pair's contact distance would have
    jumped from +0.61 to -0.61 mm on re-entering the interior region: an energy step of 5.1 mJ at
    the iterate, which no line search crosses. The solver now releases such stale sides when its
    line search fails (:meth:`sim_core.contact_set.ContactSet.release_stale_sides`); the test
    checks that this happened (so the scenario still exercises it)."""
    model = load_task_scene(SCENES / "folding.yaml")
    sim = Simulation(model)
    sim.state = task_initial_state(model)
    audit = CrossingAudit(model, [("sheet", "sheet")])
    released, iterations = [], []

    def on_step(x_n, sim):
        audit.step(x_n, sim.state.x)
        released.append(sim.last_info.released_sides)
        iterations.append(sim.last_info.iterations)

    _fold_onto_itself(sim, steps, on_step, depth, ramp, drag)
    s = audit.summary()
    assert s["min_signed_distance"] > 0.0 and s["intersections"] == 0, s
    assert s["max_active_pairs"] > 0, s
    assert sum(released) > 0, released
    assert max(iterations) <= 40, iterations  # stale sides released early (SolverConfig.stale_side_backtracks)
