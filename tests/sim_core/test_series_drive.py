"""A gel pad pressed onto a rigid table through a series spring (sim_core.series_drive).

Known answers: at rest the spring's force equals the contact's load (``F = k_s b``); the load is the
one the kinematic drive gives with the pad at the spring's end (``F = F_kin(d - b)``); for a contact of
secant stiffness ``k_c`` the load is the series spring's ``k_s k_c / (k_s + k_c) d``; an infinitely
stiff spring is the kinematic drive, bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.scenes import load_scene
from sim_core.series_drive import CompressionLoad, SeriesSpringDrive
from sim_core.simulation import Simulation
from tests.sim_core.test_sliding_normal_force import _scene

DOWN = np.array([0.0, 0.0, -1.0])  # the sensor normal into the table (the gel faces down)
START_Z = 0.001  # m: the pad's start height above the table


def _simulation() -> Simulation:
    return Simulation(load_scene(_scene(0.8)), dt=0.01)


def _gel_vertices(sim: Simulation) -> np.ndarray:
    sensor = sim.model.sensors["tactile"]
    return np.asarray(sim.model.bodies[sensor.gel_body].vertices)


def _pose(z: float) -> np.ndarray:
    return np.array([0.0, 0.0, z, 1.0, 0.0, 0.0, 0.0])


def _anchor_path(depth: float) -> list[float]:
    """Approach in 12 steps to ``depth`` (m) past first contact, then 8 steps of dwell."""
    return [START_Z - (START_Z + depth) * k / 12 for k in range(1, 13)] + [-depth] * 8


def _kinematic_load(depth: float) -> float:
    sim = _simulation()
    for z in _anchor_path(depth):
        sim.step(Control({"ee": _pose(z)}))
    return -float(sim.observe().tactile["tactile"].wrench[2])


def _spring_press(depth: float, stiffness: float):
    sim = _simulation()
    drive = SeriesSpringDrive("ee", stiffness, _gel_vertices(sim), force_tolerance=1.0e-4)
    b, slope, result = 0.0, 0.0, None
    for z in _anchor_path(depth):
        result = drive.step(sim, Control({"ee": _pose(z)}), DOWN, start=b, contact_slope=slope)
        assert result.converged and result.evaluations <= drive.max_evaluations
        b, slope = result.compression, result.contact_slope
    return sim, result


def test_spring_load_equals_the_kinematic_load_at_the_spring_end():
    depth = 4.0e-4
    f_kin = _kinematic_load(depth)
    k_c = f_kin / depth  # the contact's secant stiffness at this depth
    sim, end = _spring_press(depth, k_c)
    # at rest: the spring's force is the contact's load
    assert end.load == pytest.approx(end.compression * k_c, abs=2.0e-4)
    assert end.load == pytest.approx(-sim.observe().tactile["tactile"].wrench[2], rel=1e-9)
    # the pad sits b behind its anchor, and the load is the kinematic one there
    assert sim.state.effector_pose["ee"][2] == pytest.approx(-depth + end.compression, abs=1e-12)
    assert end.load == pytest.approx(_kinematic_load(depth - end.compression), rel=2e-3)
    # two equal springs in series: about half the load (exactly half for a linear contact)
    assert end.load == pytest.approx(0.5 * f_kin, rel=0.15)
    assert 0.3 * depth < end.compression < 0.7 * depth


def test_infinitely_stiff_spring_is_the_kinematic_drive_bit_for_bit():
    kinematic, driven = _simulation(), _simulation()
    drive = SeriesSpringDrive("ee", math.inf, _gel_vertices(driven))
    for z in _anchor_path(3.0e-4):
        kinematic.step(Control({"ee": _pose(z)}))
        result = drive.step(driven, Control({"ee": _pose(z)}), DOWN)
        assert result.evaluations == 1 and result.compression == 0.0
    assert np.array_equal(kinematic.state.x, driven.state.x)
    assert np.array_equal(kinematic.state.contact_force, driven.state.contact_force)


def test_the_step_totals_count_the_accepted_step_only():
    sim, _ = _spring_press(2.0e-4, 2.0e4)
    assert sim.step_totals.steps == len(_anchor_path(2.0e-4))


@pytest.mark.parametrize("stiffness, axis, match", [
    (0.0, DOWN, "stiffness must be > 0"),
    (-5.0, DOWN, "stiffness must be > 0"),
    (1.0e3, np.array([0.0, 0.0, -2.0]), "axis must be a unit 3-vector"),
])
def test_invalid_drives_are_refused(stiffness, axis, match):
    sim = _simulation()
    with pytest.raises(ConfigError, match=match):
        drive = SeriesSpringDrive("ee", stiffness, _gel_vertices(sim))
        drive.step(sim, Control({"ee": _pose(START_Z)}), axis)


def test_a_damper_holds_the_moving_tool_back_by_c_v_over_k_s_in_free_motion():
    """An anchor lowered at v = 5 mm/s above the table (no contact): with a damper c on the tool's velocity
    the tool settles ``c v / k_s`` behind it (the implicit step's steady state is exact, ``k_s b = c (v dt
    + b - b) / dt``, reached geometrically by the factor ``(c / dt) / (k_s + c / dt)``, a half here, per
    step), here 3000 N/m and 30 N s/m: 50 um, a 10 ms delay; without the damper it sits at its anchor."""
    k_s, c, v, dt = 3000.0, 30.0, 0.005, 0.01
    lag = {}
    for damping in (0.0, c):
        sim = _simulation()
        drive = SeriesSpringDrive("ee", k_s, _gel_vertices(sim), damping=damping)
        z0 = float(sim.state.effector_pose["ee"][2])
        for k in range(1, 16):
            anchor = z0 - v * dt * k
            result = drive.step(sim, Control({"ee": _pose(anchor)}), DOWN)
            assert result.converged and result.load == 0.0
        lag[damping] = float(sim.state.effector_pose["ee"][2]) - anchor
    assert lag[0.0] == 0.0
    assert lag[c] == pytest.approx(c * v / k_s, rel=0.5 ** 15 * 1.01)


@pytest.mark.parametrize("damping", [-1.0, math.inf, math.nan])
def test_an_invalid_damper_is_refused(damping):
    with pytest.raises(ConfigError, match="damping must be finite and >= 0"):
        SeriesSpringDrive("ee", 3000.0, _gel_vertices(_simulation()), damping=damping)


def test_the_load_at_a_compression_does_not_depend_on_the_order_of_the_evaluations():
    """``F(b)`` of one step (:class:`~sim_core.series_drive.CompressionLoad`, ``starts="line"``) is the same
    whichever compressions were evaluated before it: each evaluation's Newton start is a function of its own
    ``b``. At the solver's default 1e-4 m/s, with ``starts="chained"`` (each from the previous evaluation's
    solution) the load at ``b_0 + 5 um`` moves by 3.2 mN with the order (measured, session 57), 32 times this
    drive's force tolerance."""
    sim = _simulation()
    drive = SeriesSpringDrive("ee", 2000.0, _gel_vertices(sim), force_tolerance=1.0e-4, starts="line")
    path = _anchor_path(0.0004)
    b, slope = 0.0, 0.0
    for z in path[:14]:
        result = drive.step(sim, Control({"ee": _pose(z)}), DOWN, start=b, contact_slope=slope)
        b, slope = result.compression, result.contact_slope
    assert result.load > 0.5  # pressed
    state, control = sim.state, Control({"ee": _pose(path[14])})
    first_two, later = [b, b + 2.0e-5], [b + 5.0e-6, b + 1.2e-5]

    def loads(order):
        sim.state = state
        load = CompressionLoad(drive, sim, control, DOWN)
        return {c: load(c) for c in first_two + order}

    forward, backward = loads(later), loads(later[::-1])
    assert forward[later[0]] > forward[later[1]] + 0.1  # the load falls as the tool backs off
    for c in first_two + later:
        assert forward[c] == pytest.approx(backward[c], abs=1.0e-9)


def test_unknown_evaluation_starts_are_refused():
    with pytest.raises(ConfigError, match="starts must be one of"):
        SeriesSpringDrive("ee", 2000.0, np.arange(3), starts="previous")
