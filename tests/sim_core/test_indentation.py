"""Indentation of a gel by a rigid sphere (sim_core.indentation): geometry helpers and Hertz contact."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim_core import indentation as ind
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh import io
from sim_core.mesh.tet import box_face_vertices
from sim_core.mesh.validate import tet_signed_volumes
from sim_core.model import ContactSettings

FEATS = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "feats" / "calculix_templates"


def test_hertz_force_matches_hand_value_and_scales_with_depth_to_the_three_halves():
    # E* = 3e5 / (1 - 0.25) = 4e5; F = 4/3 * 4e5 * sqrt(4e-3) * (1e-4)^1.5 = 0.033733 N
    assert ind.hertz_force(1e-4, 4e-3, 3e5, 0.5) == pytest.approx(4 / 3 * 4e5 * np.sqrt(4e-3) * 1e-6, rel=1e-12)
    f = ind.hertz_force([1e-4, 4e-4], 5e-3, 3e5, 0.45)
    assert f[1] / f[0] == pytest.approx(8.0, rel=1e-12)


def test_graded_axis_is_fine_then_geometric_and_ends_at_the_extent():
    z = ind.graded_axis(5.0, 0.1, 1.0, 1.5)
    h = np.diff(z)
    assert z[0] == 0.0 and z[-1] == 5.0
    assert np.allclose(h[:10], 0.1)
    assert np.all(h[10:-2] / h[9:-3] == pytest.approx(1.5))
    with pytest.raises(ConfigError, match="growth >= 1"):
        ind.graded_axis(1.0, 0.1, 0.5, 0.9)


def test_graded_gel_block_is_positively_oriented_with_top_face_at_zero():
    gel = ind.graded_gel_block(3e-3, 2e-3, 2e-4, 6e-4, 4e-4, 1.5)
    assert np.all(tet_signed_volumes(gel.x, gel.tets) > 0)
    assert np.allclose(gel.x.min(axis=0), [-3e-3, -3e-3, -2e-3]) and np.allclose(gel.x.max(axis=0), [3e-3, 3e-3, 0])
    assert np.sum(tet_signed_volumes(gel.x, gel.tets)) == pytest.approx(6e-3 * 6e-3 * 2e-3, rel=1e-12)


def test_sphere_cap_lies_on_the_sphere_with_outward_normals():
    cap = ind.sphere_cap(5e-3, 2e-3, 2e-4)
    centre = np.array([0.0, 0.0, 5e-3])
    assert np.allclose(np.linalg.norm(cap.x - centre, axis=1), 5e-3, rtol=1e-12)
    assert cap.x[:, 2].min() == 0.0
    t = cap.triangles
    n = np.cross(cap.x[t[:, 1]] - cap.x[t[:, 0]], cap.x[t[:, 2]] - cap.x[t[:, 0]])
    assert np.all(n[:, 2] < 0)


@pytest.mark.skipif(not (FEATS / "all.msh").is_file(), reason="FEATS data not present")
def test_feats_mesh_splits_into_a_domed_gel_and_a_hemispherical_indenter():
    m = io.read_mesh(FEATS / "all.msh", scale=1e-3)
    sets = {**io.load_node_sets(FEATS / "gelsight_miniVolume.nam", m.node_ids),
            **io.load_node_sets(FEATS / "indenterVolume.nam", m.node_ids)}
    parts = ind.split_by_node_sets(m.mesh, sets)
    gel, _ = parts["Ngelsight_miniVolume"]
    indenter = ind.surface_of(parts["NindenterVolume"][0])
    assert np.allclose(np.ptp(gel.x, axis=0), [20.75e-3, 25.25e-3, 4e-3], rtol=1e-5)
    lower = indenter.x[indenter.x[:, 2] < 7.4e-3]  # everything below the flat top: a sphere R 7.5 mm
    assert np.allclose(np.linalg.norm(lower - [0, 0, 7.5e-3], axis=1), 7.5e-3, rtol=1e-6)


def _sphere_on_block(half_width, depth, h, nu, growth=1.6, radius=5e-3, d_max=1e-4, steps=2, exact=False):
    a = np.sqrt(radius * d_max)
    gel = ind.graded_gel_block(half_width, depth, h, 1.3 * a, 0.6 * a, growth)
    cap = ind.RigidSphere(np.array([0.0, 0.0, radius]), radius) if exact else ind.sphere_cap(radius, 2.0 * a, h)
    eps = 1e-2 * d_max
    contact = ContactSettings(stiffness=1e4, eps=eps, eps_v=1e-3, self_contact=False,
                              candidate_margin=2 * d_max / steps + eps)
    setup = ind.build_indentation(gel, box_face_vertices(gel, 2, "min"), cap, 3e5, nu, contact, indenter_lift=eps)
    depths = d_max * np.arange(1, steps + 1) / steps
    return ind.run_depth_sweep(setup, depths, d_max / steps), radius + eps


@pytest.mark.parametrize("exact", [False, True], ids=["meshed_cap", "exact_sphere"])
def test_coarse_sphere_indentation_follows_the_hertz_three_halves_power(exact):
    """F ~ d^(3/2) within 10 % on a coarse 3 x 3 x 3 mm block (a = 0.5-0.7 mm, h = 0.2 mm).

    The force level itself is 30 % above Hertz here: the block is only ~4 a deep and bonded at its
    base (finite-layer stiffening, Dimitriadis et al. 2002) and the linear tets are coarse; the
    level is checked in the slow test on a larger, finer block.
    """
    res, radius = _sphere_on_block(3e-3, 3e-3, 2e-4, 0.3, exact=exact)
    exponent = np.log(res.force[1] / res.force[0]) / np.log(res.depth[1] / res.depth[0])
    assert exponent == pytest.approx(1.5, rel=0.10)
    ratio = res.force / ind.hertz_force(res.depth, radius, 3e5, 0.3)
    assert np.all((ratio > 1.0) & (ratio < 1.45)), ratio
    assert np.allclose(res.force_vector[:, :2], 0.0, atol=0.01 * res.force[-1])  # frictionless, symmetric


def test_fit_sphere_recovers_centre_and_radius_and_rejects_non_spheres():
    rng = np.random.default_rng(3)
    d = rng.normal(size=(40, 3))
    d[:, 2] = -np.abs(d[:, 2])  # lower half only, as cut from a hemispherical indenter
    pts = [0.001, -0.002, 7.5e-3] + 7.5e-3 * d / np.linalg.norm(d, axis=1, keepdims=True)
    s = ind.fit_sphere(pts)
    assert np.allclose(s.center, [0.001, -0.002, 7.5e-3], atol=1e-12) and s.radius == pytest.approx(7.5e-3, rel=1e-12)
    assert np.allclose(s.lowest_point, [0.001, -0.002, 0.0], atol=1e-12)
    with pytest.raises(MeshError, match="coplanar"):
        ind.fit_sphere(np.column_stack([rng.normal(size=(10, 2)), np.zeros(10)]))
    with pytest.raises(MeshError, match="deviate"):
        ind.fit_sphere(rng.normal(size=(30, 3)))
    with pytest.raises(MeshError, match="at least 4"):
        ind.fit_sphere(pts[:3])


def test_exact_sphere_indenter_is_one_kinematic_centre_vertex_carrying_the_reaction():
    gel = ind.graded_gel_block(1.5e-3, 1e-3, 2.5e-4, 0.0, 0.0, 1.0)
    sphere = ind.RigidSphere(np.array([0.0, 0.0, 2e-3]), 2e-3)
    setup = ind.build_indentation(gel, box_face_vertices(gel, 2, "min"), sphere, 3e5, 0.3,
                                  ContactSettings(eps=1e-5, self_contact=False), indenter_lift=None)
    body = setup.model.bodies[setup.indenter_body]
    assert body.kind == "sphere" and body.vertex_stop - body.vertex_start == 1
    assert setup.model.vertex_fixed[body.vertex_start]
    assert setup.initial_gap == pytest.approx(0.0, abs=1e-15)  # lifted to first touch
    res = ind.run_depth_sweep(setup, [2e-5, 4e-5], 2e-5)
    assert np.all(res.force > 0) and res.force[1] > res.force[0]
    assert "indenter.radius" not in setup.model.parameter_names


def test_sphere_indentation_force_within_ten_percent_of_hertz():
    """Exact rigid sphere (R 5 mm) into a 30 x 30 x 30 mm block bonded at its base, nu = 0.3, depths
    0.05 / 0.1 mm (contact radius a = 0.5-0.7 mm), h = 0.15 mm near the contact, graded away (45.7k
    DoF). Measured: F / F_Hertz = 1.059 / 1.051 (at h = 0.1 mm, 85.7k DoF: 1.037 / 1.040); the
    block is ~40 a deep so the bonded-layer stiffening (Dimitriadis et al. 2002) is ~2 %, the rest
    is linear-tet discretisation. An 8 mm block gives ~1.14: ~8 % of it is the finite layer."""
    res, radius = _sphere_on_block(15e-3, 30e-3, 1.5e-4, 0.3, growth=1.5, exact=True)
    ratio = res.force / ind.hertz_force(res.depth, radius, 3e5, 0.3)
    assert np.all(np.abs(ratio - 1.0) < 0.10), ratio
    exponent = np.log(res.force[1] / res.force[0]) / np.log(res.depth[1] / res.depth[0])
    assert exponent == pytest.approx(1.5, abs=0.05)


def test_depth_sweep_rejects_non_increasing_depths():
    gel = ind.graded_gel_block(1e-3, 1e-3, 5e-4, 0.0, 0.0, 1.0)
    cap = ind.sphere_cap(2e-3, 5e-4, 2.5e-4)
    setup = ind.build_indentation(gel, box_face_vertices(gel, 2, "min"), cap, 3e5, 0.3,
                                  ContactSettings(eps=1e-5, self_contact=False), indenter_lift=1e-5)
    with pytest.raises(ConfigError, match="positive and increasing"):
        ind.run_depth_sweep(setup, [2e-5, 1e-5], 1e-5)
    with pytest.raises(ConfigError, match="self_contact must be False"):
        ind.build_indentation(gel, box_face_vertices(gel, 2, "min"), cap, 3e5, 0.3, ContactSettings())


def test_add_sphere_validates_its_inputs():
    from sim_core.builder import ModelBuilder

    b = ModelBuilder()
    b.add_sphere("ball", [0.0, 0.0, 1.0], 0.1)
    with pytest.raises(ConfigError, match="duplicate"):
        b.add_sphere("ball", [0.0, 0.0, 1.0], 0.1)
    with pytest.raises(ConfigError, match="radius"):
        b.add_sphere("b2", [0.0, 0.0, 1.0], 0.0)
    with pytest.raises(ConfigError, match="center"):
        b.add_sphere("b3", [0.0, np.nan, 1.0], 0.1)
