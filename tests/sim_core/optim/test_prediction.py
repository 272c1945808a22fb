"""The predicted contact summary of trajectory.yaml (sim_core.optim.prediction): a gel pressed onto a
card reads a normal force and shifted markers; the effector's net force and the tactile sensor's agree
(two code paths, one in world axes, one in the sensor frame: the norm is frame-independent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.optim.prediction import contact_summary
from sim_core.scenes.scene_file import load_yaml
from sim_core.simulation import Simulation

SCENE = Path(__file__).resolve().parents[3] / "config" / "scenes" / "press_slide.yaml"
DEPTH = 0.0012  # m of commanded press; the contact face starts 0.45 mm above the card


@pytest.fixture(scope="module")
def pressed():
    scene = load_yaml(SCENE.read_text())
    scene["sheet"]["clamped_edge"] = "none"
    scene["effectors"]["ee"]["initial_pose"] = [0.05, 0.0, 0.0009, 1.0, 0.0, 0.0, 0.0]
    scene["simulation"] = {"gel_resolution": [6, 5, 2]}
    sim = Simulation.from_scene(scene)
    pose0 = sim.state.effector_pose["ee"].copy()
    control = sim.model.control()
    states = [sim.state.copy()]
    for i in range(6):
        target = pose0.copy()
        target[2] -= DEPTH * (i + 1) / 6
        control.effector_pose_target["ee"] = target
        sim.step(control)
        states.append(sim.state.copy())
    return sim, states


def test_no_contact_reads_zero(pressed):
    sim, states = pressed
    s = contact_summary(sim, states[:1])
    assert s["wrench_peak_N.ee"] == 0.0 and s["torque_peak_Nm.ee"] == 0.0
    assert s["tactile_normal_peak_N.tactile"] == 0.0 and s["tactile_shear_peak_N.tactile"] == 0.0
    assert s["tactile_marker_shift_peak_m.tactile"] == 0.0


def test_a_press_reads_a_normal_force_shifted_markers_and_the_same_force_on_both_paths(pressed):
    sim, states = pressed
    s = contact_summary(sim, states)
    normal, shear = s["tactile_normal_peak_N.tactile"], s["tactile_shear_peak_N.tactile"]
    assert normal > 1e-3  # the gel pushes the card onto the table
    assert shear < 0.2 * normal  # a straight press: little tangential force
    # the effector wrench (world axes) and the tactile wrench (sensor frame) are the same force
    assert normal * (1 - 1e-9) <= s["wrench_peak_N.ee"] <= np.hypot(normal, shear) * (1 + 1e-9)
    assert len(s["wrench_final.ee"]) == 6 and s["wrench_final.ee"][2] > 0  # the card pushes the gel up (+z)
    # markers move with the gel's surface: by more than nothing, by less than the press itself
    assert 0.0 < s["tactile_marker_shift_peak_m.tactile"] < DEPTH
    with pytest.raises(ConfigError, match="no states"):
        contact_summary(sim, [])
