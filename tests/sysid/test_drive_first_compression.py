"""The drive step's first compression (sysid.replay_drive.first_compression): the root of the spring's balance
with the load linear in the tool's advance, so that a step in free motion, where the load is zero and the
balance ``-K b + c d / dt = 0`` is linear, lands on its root at the first evaluation, and a step in contact
starts where a linear contact of the last secant's slope would balance.

The scene: tests/sim_core/test_sliding_normal_force's gel pad over a rigid table, driven down through a
3,000 N/m spring with a 30 N s/m damper (the reference engine's arm: 3,000 N/m, 34 N s/m).
"""

from __future__ import annotations

import numpy as np
import pytest

import sysid.replay_drive as replay_drive
from sim_core.control import Control
from sim_core.series_drive import SeriesSpringDrive
from sysid.drive_calibration import fit_drive
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel
from sysid.replay_drive import first_compression
from tests.sim_core.test_series_drive import DOWN, START_Z, _gel_vertices, _pose, _simulation
from tests.sysid.conftest import reference_bag

K_S, C = 3000.0, 30.0


def _press(anchors: list[float]):
    """Drive the pad through ``anchors`` (z of the spring's anchor, m) with the first compression of each step
    from :func:`first_compression`; each step's :class:`~sim_core.series_drive.SeriesDriveStep` and the reach."""
    sim = _simulation()
    drive = SeriesSpringDrive("ee", K_S, _gel_vertices(sim), damping=C, force_tolerance=1.0e-4)
    load, slope, steps = 0.0, 0.0, []
    for z in anchors:
        tool = float(np.dot(np.asarray(sim.state.effector_pose["ee"], dtype=float)[:3], DOWN))
        reach = float(np.dot(_pose(z)[:3], DOWN)) - tool
        start = first_compression(load, slope, reach, K_S, C / sim.dt)
        result = drive.step(sim, Control({"ee": _pose(z)}), DOWN, start=start, contact_slope=slope)
        assert result.converged
        steps.append((result, start, reach))
        load, slope = result.load, result.contact_slope
    return sim, steps


def test_a_step_in_free_motion_lands_on_the_dampers_lag_at_once():
    """An anchor accelerated from rest above the table (no contact): every step's first compression is the
    damper's exact lag ``c d / (dt K)`` (the tool's position solves a linear balance), one evaluation a step,
    where the last step's compression, off by the change of the damper's pull, takes two."""
    v, dt = 0.005, 0.01
    anchors = [START_Z - v * dt * k * min(k, 5) / 5 for k in range(1, 13)]  # speeding up over five steps
    sim, steps = _press(anchors)
    rate = C / dt
    for result, start, reach in steps:
        assert result.load == 0.0 and result.evaluations == 1
        assert result.compression == pytest.approx(rate * reach / (K_S + rate), rel=1e-12)
    # the lag settles at c v / k_s once the anchor's speed is steady (the damper's steady state)
    assert steps[-1][0].compression == pytest.approx(C * v / K_S, rel=0.5 ** 6)
    # the last compression would be off by the damper's change at every step of the speed-up
    moved = [abs(steps[k][0].compression - steps[k - 1][0].compression) * (K_S + rate) for k in range(1, 5)]
    assert min(moved) > 1.0e-4


def test_a_pressed_step_starts_at_a_linear_contacts_balance_and_ends_on_the_springs():
    """The anchor pressed 0.3 mm past first contact and held: at rest the spring's force is the contact's load
    (``k_s b = F``), and once held every step's first compression balances the last load (the contact at rest
    changes by less than the tolerance), one evaluation a step."""
    depth = 3.0e-4
    anchors = [START_Z - (START_Z + depth) * k / 12 for k in range(1, 13)] + [-depth] * 10
    sim, steps = _press(anchors)
    end = steps[-1][0]
    assert end.load > 0.5 and end.load == pytest.approx(K_S * end.compression, abs=2.0e-4)
    held = steps[-4:]
    assert all(r.evaluations == 1 for r, _, _ in held)
    assert all(abs(start - r.compression) * (K_S + C / 0.01 + r.contact_slope) < 1.0e-4 for r, start, _ in held)


def test_a_replay_through_the_reference_arm_takes_one_evaluation_a_step_out_of_contact_and_the_converged_load(
        monkeypatch):
    """nominal_s101's first 1.2 s (approach to ~0.7 s, press, dwell from ~0.8 s at ~4.2 N; coarse gel) through its
    fitted arm (3,000 N/m, 34 N s/m): every step without load on the gel takes one evaluation (the damper's lag at
    once), and the replayed load is the one of the same replay with every drive step solved 100x tighter, within the
    drive's force tolerance (0.005 noise levels, 1 mN): the first guesses move no answer. (The slide begins at
    1.55 s: 1.2 s holds every kind of step the claim is about, free, pressing and held.) The secant's claim: the
    replay's drive solved by the secant whatever ``DRIVE_SOLVE`` says (a joint step is one Newton solve from any
    first compression, tests/sim_core/test_drive_compression.py)."""
    monkeypatch.setattr(replay_drive, "DRIVE_SOLVE", "secant")
    model = ObservationModel(load_evidence(reference_bag("nominal_s101")), dt=0.01, t_max=1.2,
                             simulation={"gel_resolution": [5, 4, 2]}, arch="cpu")
    fit = fit_drive(model)
    assert fit.compliant
    model.set_drive_stiffness(fit.replay_stiffness, fit.replay_damping)
    steps = []
    step = SeriesSpringDrive.step

    def kept(self, *args, **kwargs):
        result = step(self, *args, **kwargs)
        steps.append(result)
        return result

    monkeypatch.setattr(SeriesSpringDrive, "step", kept)
    trace = model.simulate({})
    free = [r for r in steps if r.load == 0.0]
    assert len(steps) == model.step_count and len(free) > 50 and len(free) < len(steps)
    assert all(r.evaluations == 1 for r in free) and all(r.converged for r in steps)
    tolerance = replay_drive.DRIVE_FORCE_TOLERANCE * float(model.sigma["wrench"][2])
    monkeypatch.setattr(replay_drive, "DRIVE_FORCE_TOLERANCE", replay_drive.DRIVE_FORCE_TOLERANCE * 1e-2)
    tight = model.simulate({})
    difference = np.abs(np.asarray(trace.wrench)[:, 2] - np.asarray(tight.wrench)[:, 2])
    assert float(difference.max()) < 2.0 * tolerance
