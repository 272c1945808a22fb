"""Tack bond logic of the MuJoCo generator (pure numpy; MuJoCo is not imported)."""

import numpy as np
import pytest

from benchmarks.mujoco_world import tack
from benchmarks.mujoco_world.mjcf import GEL_COUNT, gel_bottom_rest, gel_vertex_body

SCENE = {"sheet": {"size": [0.1, 0.06], "resolution": [21, 13], "origin": [0.0, -0.03, 0.00015]},
         "sensors": {"tactile": {"gel_size": [0.0186, 0.0143, 0.004]}}}


def test_candidates_are_the_card_vertices_under_the_gel_and_their_nearest_gel_vertex():
    rest = gel_bottom_rest(SCENE)
    cands = tack.tack_candidates(SCENE, (0.0879, 0.0029), rest)
    # card pitch 5 mm: x in {80, 85, 90, 95} (|x - 87.9| <= 9.3 mm), y in {0, 5, 10} (|y - 2.9| <= 7.15 mm)
    assert [(c.card_ix, c.card_iy) for c in cands] == [(ix, iy) for ix in (16, 17, 18, 19) for iy in (6, 7, 8)]
    for c in cands:
        p = np.array([c.card_ix * 0.005, -0.03 + c.card_iy * 0.005]) - (0.0879, 0.0029)
        d = np.linalg.norm(rest - p, axis=1)
        assert d[c.gel_bottom] == pytest.approx(d.min())
        assert d.min() <= 0.5 * np.hypot(0.0186 / (GEL_COUNT[0] - 1), 0.0143 / (GEL_COUNT[1] - 1)) + 1e-12


def test_gel_vertex_body_names_the_bottom_layer_vertex_of_the_flexcomp_grid():
    gnx, gny, gnz = GEL_COUNT
    # bottom index k is y outer, x inner; the flexcomp grid index is (ix * gny + iy) * gnz + iz, iz = 0 at the bottom
    assert gel_vertex_body(tack.TackCandidate(0, 0, 0)) == "gel_0"
    assert gel_vertex_body(tack.TackCandidate(0, 0, 1)) == f"gel_{gny * gnz}"
    assert gel_vertex_body(tack.TackCandidate(0, 0, gnx)) == f"gel_{gnz}"
    assert gel_vertex_body(tack.TackCandidate(0, 0, gnx * gny - 1)) == f"gel_{((gnx - 1) * gny + gny - 1) * gnz}"
    rest = gel_bottom_rest(SCENE)
    assert rest[gnx + 2, 0] == pytest.approx(rest[2, 0]) and rest[gnx + 2, 1] > rest[2, 1]


def test_bonds_break_on_the_norm_of_their_force_above_the_strength_and_only_when_active():
    f = np.array([[0.0, 0.0, 0.26], [0.2, 0.0, 0.1], [0.15, 0.15, 0.15], [0.0, 0.0, -0.3], [0.0, 0.0, 0.5]])
    active = np.array([True, True, True, True, False])
    brk = tack.bonds_to_break(f, active, 0.25)
    # |f| = 0.26, 0.224, 0.260, 0.3, (0.5 inactive)
    np.testing.assert_array_equal(brk, [True, False, True, True, False])
    with pytest.raises(ValueError, match="must be positive"):
        tack.bonds_to_break(f, active, 0.0)
    with pytest.raises(ValueError, match="expected \\(5, 3\\)"):
        tack.bonds_to_break(f[:, :2], active, 0.25)


def test_bond_wrench_is_the_reaction_on_the_gel_with_its_moment_about_the_origin():
    f_card = np.array([[0.0, 0.0, 0.1], [0.05, 0.0, 0.1], [1.0, 1.0, 1.0]])
    at = np.array([[0.01, 0.0, 0.0], [-0.01, 0.002, 0.0], [0.0, 0.0, 0.0]])
    active = np.array([True, True, False])
    origin = np.array([0.0, 0.0, 0.001])
    w = tack.bond_wrench(f_card, at, active, origin)
    f_gel = -f_card[:2]
    np.testing.assert_allclose(w[:3], f_gel.sum(axis=0))
    np.testing.assert_allclose(w[3:], sum(np.cross(a - origin, f) for a, f in zip(at[:2], f_gel)))
    # a pure couple: equal and opposite forces give zero net force and a moment independent of the origin
    couple = np.array([[0.0, 0.0, 0.2], [0.0, 0.0, -0.2]])
    pts = np.array([[0.005, 0.0, 0.0], [-0.005, 0.0, 0.0]])
    w1 = tack.bond_wrench(couple, pts, np.array([True, True]), [0.0, 0.0, 0.0])
    w2 = tack.bond_wrench(couple, pts, np.array([True, True]), [0.3, -0.1, 0.2])
    np.testing.assert_allclose(w1[:3], 0.0, atol=1e-15)
    np.testing.assert_allclose(w1[3:], w2[3:], atol=1e-15)
    np.testing.assert_allclose(w1[3:], [0.0, 0.002, 0.0], atol=1e-15)


def test_under_footprint_is_the_gel_rectangle_around_the_effector():
    xy = np.array([[0.0, 0.0], [0.009, 0.007], [0.0095, 0.0], [0.0, -0.0072]])
    np.testing.assert_array_equal(tack.under_footprint(xy, (0.0, 0.0), (0.0186, 0.0143)), [True, True, False, False])


def test_reference_convention_records_the_force_on_the_card():
    f_card = np.array([[0.02, 0.0, 0.05], [0.01, 0.01, 0.04]])
    at = np.array([[0.01, 0.0, 0.0], [-0.01, 0.002, 0.0]])
    active = np.array([True, True])
    phys = tack.bond_wrench(f_card, at, active, [0.0, 0.0, 0.0], "physical")
    ref = tack.bond_wrench(f_card, at, active, [0.0, 0.0, 0.0], "reference")
    np.testing.assert_allclose(ref, -phys)
    np.testing.assert_allclose(ref[:3], f_card.sum(axis=0))
    with pytest.raises(ValueError, match="unknown bond wrench convention 'gel'"):
        tack.bond_wrench(f_card, at, active, [0.0, 0.0, 0.0], "gel")


def _steady_spring(d, m_card, m_gel, solref):
    """Stiffness of a soft equality row at rest from MuJoCo's equations, step by step (not the closed form):
    a1 = a0 + A f with f = (a_ref - a0) / (A + R), R = (1 - d) / d * A_hat, a_ref = -k r, k = d / (d^2 tau^2 zeta^2);
    a1 = 0 at rest, so f = -k r / R; the spring's stiffness is -f / r."""
    tau, zeta = solref
    a_hat = 1.0 / m_card + 1.0 / m_gel
    k = d / (d * d * tau * tau * zeta * zeta)
    r = 1.0e-3
    for a_true in (a_hat, 0.01 * a_hat):            # the true A (effective inertia) does not matter at rest
        R = (1.0 - d) / d * a_hat
        a0 = k * r * a_true / R                     # the a0 at which a1 = a0 + A f vanishes
        f = (-k * r - a0) / (a_true + R)
        assert a0 + a_true * f == pytest.approx(0.0, abs=1e-9 * a0)
    return -f / r


def test_bond_impedance_makes_a_spring_of_the_asked_stiffness_and_the_default_is_far_softer():
    m_card, m_gel, solref = 4.615e-6, 4.876e-6, (0.005, 1.0)
    d = tack.bond_impedance(m_card, m_gel, tack.BOND_STIFFNESS_N_PER_M, solref)
    assert 0.98 < d < 0.999
    assert _steady_spring(d, m_card, m_gel, solref) == pytest.approx(tack.BOND_STIFFNESS_N_PER_M, rel=1e-9)
    assert tack.bond_stiffness(m_card, m_gel, d, solref) == pytest.approx(tack.BOND_STIFFNESS_N_PER_M, rel=1e-12)
    # MuJoCo's default solimp (d 0.9 to 0.95): 1-2 N/m, the card slides out of the bonds
    assert 0.9 < _steady_spring(0.95, m_card, m_gel, solref) < 2.0
    assert tack.bond_solimp(d)[:2] == (d, d)
    with pytest.raises(ValueError, match="softer than any impedance"):
        tack.bond_impedance(m_card, m_gel, 0.05, solref)
    with pytest.raises(ValueError, match="must be positive"):
        tack.bond_impedance(m_card, 0.0, 8.0, solref)
