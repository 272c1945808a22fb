"""Net wrench on the gel: force and torque about the sensor origin, in the sensor frame."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.sensors.wrench import net_wrench
from sim_core.transforms import quat_from_rotvec, quat_to_matrix

FLIPPED = np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0])  # 180 deg about x: sensor z = world -z


def test_single_force_at_identity_pose() -> None:
    w = net_wrench(np.array([[1.0, 2.0, 3.0]]), np.array([[0.1, 0.0, 0.0]]), np.array([0, 0, 0, 0, 0, 0, 1.0]))
    # tau = r x f = (0.1, 0, 0) x (1, 2, 3) = (0, -0.3, 0.2)
    np.testing.assert_allclose(w, [1.0, 2.0, 3.0, 0.0, -0.3, 0.2], atol=1e-15)


def test_single_force_in_a_rotated_translated_frame() -> None:
    rng = np.random.default_rng(0)
    q = quat_from_rotvec(rng.normal(size=3))
    R = quat_to_matrix(q)
    t = rng.normal(size=3)
    f_s, r_s = rng.normal(size=3), rng.normal(size=3)  # force and its point, given in the sensor frame
    w = net_wrench((R @ f_s)[None], (R @ r_s + t)[None], np.concatenate([t, q]))
    np.testing.assert_allclose(w[:3], f_s, atol=1e-12)
    np.testing.assert_allclose(w[3:], np.cross(r_s, f_s), atol=1e-12)


def test_pure_couple_has_no_force_and_a_position_independent_torque() -> None:
    f = np.array([[0.0, 2.0, 0.0], [0.0, -2.0, 0.0]])
    for shift in (np.zeros(3), np.array([0.3, -0.7, 0.2])):
        p = np.array([[0.05, 0.0, 0.0], [-0.05, 0.0, 0.0]]) + shift
        w = net_wrench(f, p, np.array([0, 0, 0, 0, 0, 0, 1.0]))
        np.testing.assert_allclose(w, [0, 0, 0, 0, 0, 0.2], atol=1e-14)  # 2 N * 0.1 m about +z


def test_pressing_onto_an_object_below_gives_negative_fz() -> None:
    # gel faces down (sensor z = world -z) and presses on a table: the table pushes the gel up (world +z)
    points = np.array([[x, y, 0.1] for x in (-0.005, 0.005) for y in (-0.005, 0.005)])
    forces = np.tile([0.0, 0.0, 0.5], (4, 1))
    w = net_wrench(forces, points, FLIPPED)
    assert w[2] == pytest.approx(-2.0)
    np.testing.assert_allclose(w[[0, 1, 3, 4, 5]], 0.0, atol=1e-15)


def test_shape_mismatch_is_rejected() -> None:
    with pytest.raises(ValueError, match="same shape"):
        net_wrench(np.zeros((2, 3)), np.zeros((3, 3)), FLIPPED)
