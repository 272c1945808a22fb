"""Adhesion candidate: pairs, FD derivatives, tensile force up to the bond strength on lift-off."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.candidates.adhesion import LaggedAdhesion, adhesion_pairs
from sim_core.errors import ConfigError
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

EPS, DELTA = 4e-4, 2.5e-4


def _one_pair(height):
    """Gel vertex 0 above the sheet triangle (1, 2, 3) in z = 0, at ``height``."""
    x = np.array([[0.2e-2, 0.2e-2, height], [0, 0, 0], [1e-2, 0, 0], [0, 1e-2, 0]], dtype=float)
    v, w, n = adhesion_pairs(x, np.array([0]), np.array([[1, 2, 3]]), EPS, 5 * DELTA)
    return x, v, w, n


def test_pairs_take_the_nearest_triangle_within_reach():
    x, v, w, n = _one_pair(EPS + 2 * DELTA)
    assert v.tolist() == [[0, 1, 2, 3]]
    assert np.allclose(n, [[0, 0, 1]]) and np.allclose(w.sum(axis=1), 0.0)
    assert _one_pair(EPS + 6 * DELTA)[1].shape == (0, 4)  # out of reach


@pytest.mark.parametrize("opening", [0.5, 1.0, 3.0])
def test_gradient_and_hessian_match_finite_differences(opening):
    x, v, w, n = _one_pair(EPS + DELTA)
    ad = LaggedAdhesion(v, w, n, EPS, beta=0.2, delta=DELTA)
    rng = np.random.default_rng(3)
    x = x.copy()
    x[0, 2] = EPS + opening * DELTA
    x += rng.normal(scale=1e-6, size=x.shape)
    assert relative_error(ad.gradient(x), fd_gradient(ad.energy, x, h=1e-9)) < 1e-5
    H = dense_hessian(ad.hessian(x, "none"), 4)
    assert relative_error(H, fd_hessian(ad.gradient, x, h=1e-9)) < 1e-5
    blocks = ad.hessian(x, "clamp").blocks
    assert np.linalg.eigvalsh(blocks).min() > -1e-9 * max(np.abs(blocks).max(), 1.0)
    h = 1e-6
    fd = (LaggedAdhesion(v, w, n, EPS, 0.2 + h, DELTA).gradient(x) - LaggedAdhesion(v, w, n, EPS, 0.2 - h, DELTA).gradient(x)) / (2 * h)
    assert relative_error(LaggedAdhesion(v, w, n, EPS, 0.0, DELTA).parameter_gradient(x, "beta"), fd) < 1e-8


def test_tensile_force_on_lift_off_peaks_at_the_bond_strength():
    x0, v, w, n = _one_pair(EPS)
    beta = 0.25
    ad = LaggedAdhesion(v, w, n, EPS, beta, DELTA)
    heights = EPS + np.linspace(-1e-4, 8 * DELTA, 2001)
    pull = []
    for z in heights:
        x = x0.copy()
        x[0, 2] = z
        pull.append(ad.gradient(x)[0, 2])  # dE/dz > 0: the bond pulls the gel vertex down, toward the sheet
    pull = np.array(pull)
    assert np.all(pull[heights <= EPS] == 0.0)  # pressed: no adhesion force
    assert pull.max() == pytest.approx(beta, rel=1e-4)
    assert heights[np.argmax(pull)] - EPS == pytest.approx(DELTA, rel=0.01)
    assert pull[-1] < 0.02 * beta  # the bond has broken
    # the sheet triangle feels the opposite force (momentum balance)
    x = x0.copy()
    x[0, 2] = EPS + DELTA
    assert np.allclose(ad.gradient(x).sum(axis=0), 0.0, atol=1e-15)


def test_rejects_negative_bond_strength():
    _, v, w, n = _one_pair(EPS)
    with pytest.raises(ConfigError, match="bond strength beta"):
        LaggedAdhesion(v, w, n, EPS, -1.0, DELTA)
    with pytest.raises(ConfigError, match="delta"):
        LaggedAdhesion(v, w, n, EPS, 1.0, 0.0)


def test_default_reach_forms_bonds_only_in_contact():
    """With the hook's default reach a gel vertex bonds only where it touches the sheet (within the
    contact offset), not across a gap of a fraction of delta (the card buckled away from the gel)."""
    from sim_core.candidates.hook import CandidateHook

    reach = CandidateHook({"adhesion": 0.1}).setting("adhesion.reach")
    for height, pairs in ((0.9 * EPS, 1), (EPS + 0.5 * DELTA, 0), (EPS + 2 * DELTA, 0)):
        x = np.array([[0.2e-2, 0.2e-2, height], [0, 0, 0], [1e-2, 0, 0], [0, 1e-2, 0]], dtype=float)
        assert adhesion_pairs(x, np.array([0]), np.array([[1, 2, 3]]), EPS, reach)[0].shape[0] == pairs, height


def test_bond_memory_keeps_a_touched_vertex_bonded_up_to_the_release_opening():
    """A gel vertex that touched the sheet stays bonded (and keeps its lagged pair) while its opening
    is below the release opening; one that never touched forms no pair across the same gap, and a
    released one bonds again only on contact."""
    from sim_core.candidates.adhesion import bonded_after, bonded_pairs

    reach, release = 0.01 * DELTA, 5 * DELTA
    gel, tri = np.array([0]), np.array([[1, 2, 3]])

    def at(height):
        return np.array([[0.2e-2, 0.2e-2, height], [0, 0, 0], [1e-2, 0, 0], [0, 1e-2, 0]], dtype=float)

    none = np.zeros(0, np.int64)
    bonded = bonded_after(at(0.9 * EPS), gel, tri, EPS, reach, release, none)  # in contact: bonds
    assert bonded.tolist() == [0]
    for opening in (0.5, 2.0, 4.9):
        x = at(EPS + opening * DELTA)
        assert bonded_pairs(x, gel, tri, EPS, reach, release, bonded)[0].tolist() == [[0, 1, 2, 3]]
        assert bonded_pairs(x, gel, tri, EPS, reach, release, none)[0].shape == (0, 4)  # never touched
        assert bonded_after(x, gel, tri, EPS, reach, release, bonded).tolist() == [0]
    far = at(EPS + 5.1 * DELTA)
    released = bonded_after(far, gel, tri, EPS, reach, release, bonded)
    assert released.size == 0 and bonded_pairs(far, gel, tri, EPS, reach, release, bonded)[0].shape == (0, 4)
    assert bonded_after(at(EPS + 2 * DELTA), gel, tri, EPS, reach, release, released).size == 0
    assert bonded_after(at(0.95 * EPS), gel, tri, EPS, reach, release, released).tolist() == [0]


def _anchored_pair(shift):
    """Gel vertex 0 at the contact offset above the sheet triangle (1, 2, 3) in z = 0, moved by ``shift`` (m)."""
    x = np.array([[0.2e-2, 0.2e-2, EPS], [0, 0, 0], [1e-2, 0, 0], [0, 1e-2, 0]], dtype=float)
    v, w, n = adhesion_pairs(x, np.array([0]), np.array([[1, 2, 3]]), EPS, 5 * DELTA)
    x = x.copy()
    x[0] += shift
    return x, v, w, n


@pytest.mark.parametrize("shift", [(0.3, 0.2, 0.5), (1.0, -0.4, 0.0), (0.2, 0.1, 2.0), (0.5, 0.5, -0.2)])
def test_shear_gradient_and_hessian_match_finite_differences(shift):
    x, v, w, n = _anchored_pair(np.asarray(shift) * DELTA)
    ad = LaggedAdhesion(v, w, n, EPS, beta=0.2, delta=DELTA, delta_t=1.5 * DELTA)
    x = x + np.random.default_rng(5).normal(scale=1e-7, size=x.shape)
    assert relative_error(ad.gradient(x), fd_gradient(ad.energy, x, h=1e-9)) < 1e-5
    H = dense_hessian(ad.hessian(x, "none"), 4)
    assert relative_error(H, fd_hessian(ad.gradient, x, h=1e-9)) < 1e-5
    assert np.linalg.eigvalsh(dense_hessian(ad.hessian(x, "clamp"), 4)).min() > -1e-9 * np.abs(H).max()


def test_shear_force_of_a_closed_bond_is_the_coupled_cohesive_law():
    """Known answer: Xu & Needleman (1994, J. Mech. Phys. Solids 42(9)) with q = 1 at zero normal opening,
    E = beta delta e (1 - exp(-t^2/delta_t^2)), so the shear force is 2 e beta delta t / delta_t^2 exp(-t^2 / delta_t^2): stiffness 2 e beta delta / delta_t^2 at
    rest and the peak sqrt(2 e) beta delta / delta_t at t = delta_t / sqrt(2). The normal-only law (delta_t None)
    has no shear force at all."""
    beta, delta_t = 0.2, 1.5 * DELTA
    for t in np.array([0.01, 0.5, 1.0, 2.0]) * delta_t:
        x, v, w, n = _anchored_pair(np.array([t, 0.0, 0.0]))
        ad = LaggedAdhesion(v, w, n, EPS, beta=beta, delta=DELTA, delta_t=delta_t)
        force_on_gel = -ad.gradient(x)[0]
        expected = 2 * np.e * beta * DELTA * t / delta_t ** 2 * np.exp(-(t / delta_t) ** 2)
        assert force_on_gel[0] == pytest.approx(-expected, rel=1e-9)  # pulls the gel back over its anchor
        assert abs(force_on_gel[2]) < 1e-12 * expected
        assert not LaggedAdhesion(v, w, n, EPS, beta=beta, delta=DELTA).gradient(x).any()
    peak = np.sqrt(2 * np.e) * beta * DELTA / delta_t
    x, v, w, n = _anchored_pair(np.array([delta_t / np.sqrt(2), 0.0, 0.0]))
    assert -LaggedAdhesion(v, w, n, EPS, beta, DELTA, delta_t).gradient(x)[0, 0] == pytest.approx(-peak, rel=1e-9)


def test_anchored_bonds_hold_their_sheet_point_until_the_shear_release():
    """A bond keeps the sheet point it formed on while the gel slides (the nearest point would follow the gel),
    and breaks once the tangential opening passes the shear release."""
    from sim_core.candidates.adhesion import anchored_after, anchored_pairs, no_anchors

    gel, tri = np.array([0]), np.array([[1, 2, 3]])
    x0, _, _, _ = _anchored_pair(np.zeros(3))
    reach, release, release_t = 0.01 * DELTA, 5 * DELTA, 5 * DELTA
    anchors = anchored_after(x0, gel, tri, EPS, reach, release, release_t, no_anchors())
    assert anchors[0].tolist() == [0] and np.allclose(anchors[2], [[0.6, 0.2, 0.2]])
    slid = x0.copy()
    slid[0] += [3 * DELTA, 0.0, 2 * DELTA]  # off the table and sideways: out of reach of a new bond
    kept = anchored_after(slid, gel, tri, EPS, reach, release, release_t, anchors)
    assert np.allclose(kept[2], anchors[2])  # the same sheet point, not the one now nearest
    v, w, n = anchored_pairs(slid, gel, tri, EPS, reach, kept)
    assert np.allclose(w, [[1.0, -0.6, -0.2, -0.2]]) and np.allclose(n, [[0, 0, 1]])
    far = x0.copy()
    far[0] += [6 * DELTA, 0.0, 2 * DELTA]
    assert anchored_after(far, gel, tri, EPS, reach, release, release_t, anchors)[0].size == 0


@pytest.mark.parametrize("ratio", [None, 0.5, 1.0, 4.0])
@pytest.mark.parametrize("shift", [(0.3, 0.2, 0.5), (1.0, -0.4, 0.0), (0.2, 0.1, 2.0), (0.5, 0.5, -0.2),
                                   (1.0, -0.4, 3.0)])
def test_compliant_layer_gradient_hessian_and_stiffness_derivative_match_finite_differences(shift, ratio):
    """The compliant layer (normal law + k_t |P d|^2 / 2; with ``ratio`` the normal spring ``ratio k_t max(s, 0)^2 /
    2`` in place of the cohesive law): gradient and Hessian against central differences of the energy / gradient,
    the projected Hessian PSD, and d(grad E)/d k_t (both springs scale with it) against a central difference in k_t;
    with the normal spring the bond strength has no column."""
    x, v, w, n = _anchored_pair(np.asarray(shift) * DELTA)
    k = 3.0

    def bonds(k_t):
        return LaggedAdhesion(v, w, n, EPS, beta=0.2, delta=DELTA, k_shear=k_t, normal_ratio=ratio)

    ad = bonds(k)
    x = x + np.random.default_rng(7).normal(scale=1e-7, size=x.shape)
    assert relative_error(ad.gradient(x), fd_gradient(ad.energy, x, h=1e-9)) < 1e-5
    H = dense_hessian(ad.hessian(x, "none"), 4)
    assert relative_error(H, fd_hessian(ad.gradient, x, h=1e-9)) < 1e-5
    assert np.linalg.eigvalsh(dense_hessian(ad.hessian(x, "clamp"), 4)).min() > -1e-9 * np.abs(H).max()
    h = 1e-4
    fd = (bonds(k + h).gradient(x) - bonds(k - h).gradient(x)) / (2 * h)
    assert relative_error(ad.parameter_gradient(x, "k_shear"), fd) < 1e-8
    assert ratio is None or not ad.parameter_gradient(x, "beta").any()


def test_compliant_layer_is_a_linear_shear_spring_beside_the_normal_law():
    """Known answer: a bond at zero normal opening slid by t along the sheet pulls the gel back with k_t t (any t:
    the layer does not soften), and its normal force is the normal law's; k_t = 0 is the normal-only law."""
    k_t = 2.5
    for t in np.array([0.01, 1.0, 10.0, 40.0]) * DELTA:
        x, v, w, n = _anchored_pair(np.array([t, 0.0, 0.0]))
        force_on_gel = -LaggedAdhesion(v, w, n, EPS, 0.2, DELTA, k_shear=k_t).gradient(x)[0]
        assert force_on_gel[0] == pytest.approx(-k_t * t, rel=1e-12) and abs(force_on_gel[2]) < 1e-15
    x, v, w, n = _anchored_pair(np.array([3 * DELTA, 0.0, DELTA]))
    normal_only = LaggedAdhesion(v, w, n, EPS, 0.2, DELTA).gradient(x)
    layered = LaggedAdhesion(v, w, n, EPS, 0.2, DELTA, k_shear=k_t).gradient(x)
    assert layered[0, 2] == pytest.approx(normal_only[0, 2], rel=1e-12)
    assert np.array_equal(LaggedAdhesion(v, w, n, EPS, 0.2, DELTA, k_shear=0.0).gradient(x), normal_only)
    with pytest.raises(ConfigError, match="not both"):
        LaggedAdhesion(v, w, n, EPS, 0.2, DELTA, delta_t=DELTA, k_shear=k_t)
    with pytest.raises(ConfigError, match="k_shear"):
        LaggedAdhesion(v, w, n, EPS, 0.2, DELTA, k_shear=-1.0)


def test_isotropic_layer_bond_is_a_linear_spring_to_its_anchor_in_every_direction():
    """Known answer: with ``normal_ratio`` 1 an open bond (gel vertex lifted by s past the contact offset and slid by
    t) pulls the gel back toward its anchored point held off by the offset with ``k_t (t, 0, s)`` (Hooke, any
    opening: no softening), and a pressed one (s < 0) only in shear; the release opening is where that spring's
    force reaches the bond strength (``beta / k_n``)."""
    from sim_core.candidates.hook import CandidateHook

    k_t = 2.5
    for s, t in [(0.1, 0.0), (4.0, 1.0), (40.0, 10.0), (-0.5, 2.0)]:
        x, v, w, n = _anchored_pair(np.array([t, 0.0, s]) * DELTA)
        force_on_gel = -LaggedAdhesion(v, w, n, EPS, 0.2, DELTA, k_shear=k_t, normal_ratio=1.0).gradient(x)[0]
        expected = -k_t * np.array([t, 0.0, max(s, 0.0)]) * DELTA
        np.testing.assert_allclose(force_on_gel, expected, rtol=1e-12, atol=1e-18)
    with pytest.raises(ConfigError, match="normal_ratio"):
        LaggedAdhesion(v, w, n, EPS, 0.2, DELTA, normal_ratio=1.0)
    hook = CandidateHook({"adhesion": 0.1, "adhesion.shear_stiffness": k_t, "adhesion.normal_ratio": 2.0})
    assert hook.setting("adhesion.release") == pytest.approx(0.1 / (2.0 * k_t))
