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


def test_bond_solimp_leaves_a_drift_under_a_millimetre_where_the_default_leaves_centimetres():
    # steady state of a soft equality row (MuJoCo: a1 = (1 - d) a0 + d a_ref, a_ref = -k r, a1 = 0):
    # r = (1 - d) a0 / (d k), k = 1 / (d_max^2 tau^2) (zeta = 1); a0 = 0.23 N on a 4.6 mg vertex
    a0, tau = 0.23 / 4.6e-6, 0.005

    def drift(d):
        return (1 - d) * a0 / (d * (1 / (d * d * tau * tau)))

    assert drift(0.9) > 0.01
    d = tack.BOND_SOLIMP[0]
    assert tack.BOND_SOLIMP[0] == tack.BOND_SOLIMP[1]
    assert drift(d) < 2e-4
