"""The gel's deep press-slide under mesh refinement, per gel law: converged (Stable Neo-Hookean) or not (Green strain).

Issue 49 item 2: on the reference engine's two deep press-slides (stiction_s105, gel_creep_s108; 6-7.5 N) the
calibration asks for a marker depth scale of ~1.5 under the default Stable Neo-Hookean gel and 0.37-0.44 under the
Green-strain gel (Saint Venant-Kirchhoff, StVK). Forward replays of this simulator's deep press-slide (the card scene
of ``tests/sysid/simbag.py``, ``DEEP_PRESS_SLIDE`` of ``tests/sysid/test_gel_law.py``: 1.25 mm down, 7.5-10 N, then
2 mm of slip at 0.8 friction) on refined gel meshes (benchmarks log, session 55, s55-49depth) separate the two:

- The default law on the default mesh ``[8, 6, 5]``: the normal stiffness ``K = F_z / mean marker sink`` (N/m)
  pressed and at the slide's end is 5.4-5.7 % above the mesh refined 1.8x in every direction ``[14, 11, 9]``
  (2.4 % above ``[14, 11, 5]`` and ``[8, 6, 9]``: the log), the linear tets' known locking at nu = 0.45, and the
  slide / press ratio is the same on both meshes to 0.4 %. The depth scale it leaves is the law's: its K rises by
  15 % once the slide begins, the engine's falls by 27 %.
- The Green-strain law is not converged by any mesh in the slide: StVK's stress in compression has its maximum at
  the stretch ``1/sqrt(3)`` (uniaxially ``P = (lam + 2 mu) l (l^2 - 1) / 2``; Ogden, Non-linear Elastic Deformations,
  1984, sec. 4.4; Bonet and Wood, Nonlinear Continuum Mechanics for FEA, 2nd ed., sec. 6.4.1), past which an
  element collapses at finite energy. The smallest principal stretch under the sliding pad goes below that limit on
  every four-layer or finer mesh and falls further with each refinement (0.52, 0.31, 0.15 on ``[8, 6, 5]``,
  ``[8, 6, 9]``, ``[14, 11, 9]``), while the engine's two-layer mesh ``[10, 8, 3]`` locks and stays at 0.70 (on the
  stiction_s105 replay a few of its edge tets collapse too, and move its markers far less: the log). The markers
  then sink into collapsed elements: the Green-strain replay's 0.37-0.44 depth scale is StVK's material
  instability resolved, not an under-resolved mesh, so no mesh choice makes the law converge (and imitating the
  engine's locking mesh is numerics, not physics).

- The modified Saint Venant-Kirchhoff law (``modified_stvk``: StVK's shear term ``mu tr(E^2)``, its volumetric term
  written in ``J`` as ``lam / 2 (ln J)^2``; :mod:`sim_core.energies.modified_stvk`) has no stress peak in
  compression and an energy without bound as ``J -> 0``: on the three meshes where StVK's K collapses in the second,
  deeper slide (16.2 / 9.6 / 13.5 N/mm at its end, from ~30) it converges pressed and through both slides. Its
  normal stress on a sheared layer is ``mu gamma^2``, 0.18 of StVK's ``(mu + lam / 2) gamma^2`` at nu 0.45 (the
  Stable Neo-Hookean's 0.015): the three laws' slide / press ratios (1.15, 1.03-1.05, 0.72-0.74) fall in that
  order (interpolated linearly in that coefficient between the other two laws, 1.08 is the modified law's
  prediction on the default mesh; measured 1.05).

Asserted: the default law within 7 % (from above) of the refined mesh pressed and sliding and its slide / press
ratio within 1.5 %; the Green-strain law below
``1/sqrt(3)`` on the default mesh and at least 0.1 lower again on the eight-layer one, above it on the two-layer
one; the law's uniaxial stress peak at ``1/sqrt(3)`` to 1 % on a single element; the modified law on ``[10, 8, 3]``,
``[8, 6, 5]``, ``[8, 6, 9]`` through both slides: the default mesh within 5 % (from above) of the eight-layer one at
every stage, the slide / press ratio the same to 1.5 % and between 1.0 and 1.1, K in the second slide above 0.9 of
its pressed value, ``J > 0`` in every tet (all on the scene's Kuhn cut); the deep slide's mirror image in x: on the
Kuhn cut StVK's leading edge collapsed in one image (smallest stretch < 0.1) and not in the other (> 0.4), K 1.3x
apart (benchmarks log, session 58, s58-49law); on the mirrored cut (``simulation.gel_cut: mirrored``) both laws'
K the same at every stage (0.5 % / 1.5 %) with the same smallest stretch (0.01), and on an even cell count, where
the mesh is its own mirror image, to 1e-6 (session 59, 49mesh).
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.control import Control
from sim_core.energies.green_strain import GreenStrainSolid
from sim_core.scenes import load_scene
from sim_core.scenes.tactile_scene import SIMULATION_KEYS
from sim_core.simulation import Simulation
from tests.sysid.simbag import TRUE_PARAMS, scene_with, targets_from_segments
from tests.sysid.test_gel_law import DEEP_PRESS_SLIDE

PRESSED, SLID, PRESSED_AGAIN, END = 3, 11, 12, 28
"""Steps of ``DEEP_PRESS_SLIDE`` at the end of the press (1.25 mm), of the first slide (2 mm of slip), of the second
press (0.2 mm deeper) and of the second slide (4 mm)."""

LIMIT_STRETCH = 1.0 / np.sqrt(3.0)
"""StVK's stretch of largest compressive stress (uniaxial: ``d/dl [l (l^2 - 1)] = 0``)."""


def deep_press_slide(gel_element: str, resolution: tuple[int, int, int], steps: int = SLID,
                     mirror: bool = False, cut: str | None = None) -> dict[str, np.ndarray]:
    """The card scene's deep press-slide replayed to the end of its first slide (or its first ``steps`` steps) with
    the given gel law and mesh; with ``mirror`` its mirror image in x (the card clamped at its other edge, the pad
    started at the mirrored place, the slides along +x): the same problem on a gel mesh of the other handedness
    (the scene's default cut, ``kuhn``, cuts every cell along its (0,0,0)-(1,1,1) diagonal; the card's checkerboard
    and the markers are mirror-symmetric); ``cut`` overrides the scene's ``simulation.gel_cut``.

    Returns:
        per step 1..``steps``: ``stiffness`` ``F_z / mean marker sink`` (N/m; sink along the sensor's -z, the markers'
        mean), ``force`` ``|F_z|`` (N), ``stretch`` the smallest principal stretch of the gel's tets (``F = D_s
        D_m^-1``'s smallest singular value), ``volume`` the smallest volume ratio ``J = det F``.
    """
    scene = scene_with(TRUE_PARAMS)
    scene = {**scene, "simulation": {**(scene.get("simulation") or {}), "gel_element": gel_element,
                                     "gel_resolution": list(resolution),
                                     "gel_cut": cut or SIMULATION_KEYS["gel_cut"]}}
    segments = DEEP_PRESS_SLIDE
    if mirror:
        sheet = scene["sheet"]
        pose = list(scene["effectors"]["ee"]["initial_pose"])
        pose[0] = 2.0 * float(sheet["origin"][0]) + float(sheet["size"][0]) - float(pose[0])
        scene = {**scene, "sheet": {**sheet, "clamped_edge": {"x0": "x1", "x1": "x0"}[sheet["clamped_edge"]]},
                 "effectors": {**scene["effectors"], "ee": {**scene["effectors"]["ee"], "initial_pose": pose}}}
        segments = tuple(((-dx, dy, dz), n) for (dx, dy, dz), n in DEEP_PRESS_SLIDE)
    sim = Simulation(load_scene(scene), dt=scene["dt"])
    for name, value in TRUE_PARAMS.items():
        sim.set_parameter(name, value)
    tets = sim.model.bodies[sim.model.sensors["tactile"].gel_body].tets
    rest = sim.model.x_rest
    inverse_rest = np.linalg.inv(np.stack([rest[tets[:, i]] - rest[tets[:, 0]] for i in (1, 2, 3)], axis=-1))
    markers0 = sim.observe().tactile["tactile"].markers_xyz[:, 2].copy()
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), segments)[:steps]
    out = {"stiffness": [], "force": [], "stretch": [], "volume": []}
    for target in targets:
        sim.step(Control({"ee": target}))
        reading = sim.observe().tactile["tactile"]
        x = sim.state.x
        deformed = np.stack([x[tets[:, i]] - x[tets[:, 0]] for i in (1, 2, 3)], axis=-1)
        sink = float(np.mean(markers0 - reading.markers_xyz[:, 2]))
        out["force"].append(abs(float(reading.wrench[2])))
        out["stiffness"].append(out["force"][-1] / sink if sink > 0.0 else 0.0)
        out["stretch"].append(float(np.linalg.svd(deformed @ inverse_rest, compute_uv=False).min()))
        out["volume"].append(float(np.linalg.det(deformed @ inverse_rest).min()))
    return {key: np.array([np.nan] + value) for key, value in out.items()}  # index = step


@pytest.fixture(scope="module")
def default_law():
    return {res: deep_press_slide("stable_neohookean", res) for res in ((8, 6, 5), (14, 11, 9))}


@pytest.fixture(scope="module")
def green_strain():
    return {res: deep_press_slide("green_strain", res) for res in ((10, 8, 3), (8, 6, 5), (8, 6, 9))}


def test_the_default_gel_is_within_the_linear_tets_error_and_its_slide_trend_is_the_laws(default_law):
    """Measured K pressed 35.56 / 33.75 N/mm, at the slide's end 41.00 / 38.78 (``[8, 6, 5]`` / ``[14, 11, 9]``):
    the default mesh 5.4-5.7 % stiffer (the linear tets' locking at nu = 0.45, from above: see
    test_known_answers_gel_compression.py), and the slide / press ratio 1.153 / 1.149."""
    base, fine = default_law[(8, 6, 5)], default_law[(14, 11, 9)]
    assert base["force"][PRESSED] > 6.0  # the deep presses' load (6-7.5 N) or more
    for step in (PRESSED, SLID):
        assert 1.0 < base["stiffness"][step] / fine["stiffness"][step] < 1.07, step
    trend = [run["stiffness"][SLID] / run["stiffness"][PRESSED] for run in (base, fine)]
    assert trend[0] == pytest.approx(trend[1], rel=0.015)
    # the law's own trend, which the engine's recording does not share (it softens by 27 % in the slide)
    assert trend[0] > 1.1


def test_the_green_strain_gel_collapses_past_its_limit_stretch_and_refinement_does_not_converge(green_strain):
    """Measured smallest stretch at the slide's end: 0.697 (``[10, 8, 3]``), 0.516 (``[8, 6, 5]``), 0.307
    (``[8, 6, 9]``); pressed, before the slide, all above the limit (0.87 / 0.83 / 0.78) and K within 3.0 %. The
    first slide's softening is the law's on every mesh (slide / press 0.719 / 0.743 / 0.741; the engine's recording
    of stiction_s105 0.734); the collapse shows in the force only further on (the log: K at the second slide's end
    16.2 / 9.6 / 13.5 N/mm, and Newton fails on ``[14, 11, 5]`` and ``[20, 15, 9]``)."""
    two_layer, default, eight_layer = (green_strain[res] for res in ((10, 8, 3), (8, 6, 5), (8, 6, 9)))
    runs = (two_layer, default, eight_layer)
    assert min(run["stretch"][PRESSED] for run in runs) > LIMIT_STRETCH
    assert default["stiffness"][PRESSED] == pytest.approx(eight_layer["stiffness"][PRESSED], rel=0.05)
    for run in runs:
        assert 0.68 < run["stiffness"][SLID] / run["stiffness"][PRESSED] < 0.78
    assert two_layer["stretch"][SLID] > LIMIT_STRETCH > default["stretch"][SLID]
    assert eight_layer["stretch"][SLID] < default["stretch"][SLID] - 0.1


def test_the_green_strain_law_has_its_compressive_stress_peak_at_the_limit_stretch():
    """One tet compressed along z with its base held (uniaxial strain): the force on the apex, ``-dW/dz``, is
    ``V (lam + 2 mu) l (l^2 - 1) / 2 / h`` and largest in magnitude at ``l = 1/sqrt(3)``."""
    h = 1.0e-3
    rest = np.array([[0.0, 0.0, 0.0], [h, 0.0, 0.0], [0.0, h, 0.0], [0.0, 0.0, h]])
    solid = GreenStrainSolid(np.array([[0, 1, 2, 3]]), rest, 3.0e5, 0.45)
    stretches = np.linspace(0.3, 0.95, 1301)
    force = []
    for stretch in stretches:
        x = rest.copy()
        x[3, 2] = stretch * h
        force.append(solid.gradient(x)[3, 2])
    force = np.array(force)
    assert stretches[np.argmin(force)] == pytest.approx(LIMIT_STRETCH, rel=0.01)
    lam_2mu = 3.0e5 * (1 - 0.45) / ((1 + 0.45) * (1 - 2 * 0.45))
    expected = h**3 / 6 * lam_2mu * stretches * (stretches**2 - 1) / 2 / h
    assert force == pytest.approx(expected, rel=1e-6)



@pytest.fixture(scope="module")
def modified_stvk():
    return {res: deep_press_slide("modified_stvk", res, steps=END) for res in ((10, 8, 3), (8, 6, 5), (8, 6, 9))}


def test_the_modified_stvk_gel_converges_through_both_slides_where_stvk_collapses(modified_stvk):
    """Measured K pressed 36.80 / 33.37 / 32.46 N/mm, at the first slide's end 37.90 / 35.05 / 34.12, pressed again
    0.2 mm deeper 44.69 / 40.89 / 39.70 and at the second slide's end 44.57 / 41.09 / 40.07 (``[10, 8, 3]`` /
    ``[8, 6, 5]`` / ``[8, 6, 9]``): the default mesh 2.5-2.8 % above the eight-layer one at every stage; in the
    second slide K stays within 8 % of its pressed value (StVK's falls to 0.3-0.5 of it). Slide / press ratio 1.030 /
    1.050 / 1.051: between StVK's (0.72-0.74) and Stable Neo-Hookean's (1.15), as the laws' normal stress under
    shear orders them. Every tet keeps ``J > 0`` by the law; the smallest stretch at the pad's edge is
    a strain concentration the finer mesh resolves (0.52 / 0.45 / 0.39 at the end), not a collapse: the force does
    not follow it."""
    two_layer, default, eight_layer = (modified_stvk[res] for res in ((10, 8, 3), (8, 6, 5), (8, 6, 9)))
    assert default["force"][PRESSED] > 6.0  # the deep presses' load (6-7.5 N) or more
    for step in (PRESSED, SLID, PRESSED_AGAIN, END):
        assert 1.0 < default["stiffness"][step] / eight_layer["stiffness"][step] < 1.05, step
    trend = [run["stiffness"][SLID] / run["stiffness"][PRESSED] for run in (two_layer, default, eight_layer)]
    assert trend[1] == pytest.approx(trend[2], rel=0.015)
    assert all(1.0 < ratio < 1.1 for ratio in trend), trend
    for run in (two_layer, default, eight_layer):
        second = run["stiffness"][PRESSED_AGAIN:END + 1]
        assert second.min() > 0.9 * second[0]
        assert run["stiffness"][END] > 0.95 * second[0]
        assert np.nanmin(run["volume"]) > 0.0


STAGES = (PRESSED, SLID, PRESSED_AGAIN, END)


@pytest.fixture(scope="module")
def mirror_images():
    """The deep slide and its mirror image through both slides: both laws on the default mesh cut ``mirrored``, StVK
    on the Kuhn cut (the scene's default) of the same mesh and on ``[7, 7, 5]`` cut ``mirrored`` (6 x 6 x 4 cells:
    the mesh its own mirror image)."""
    runs = {(law, "default", mirror): deep_press_slide(law, (8, 6, 5), steps=END, mirror=mirror, cut="mirrored")
            for law in ("stable_neohookean", "green_strain") for mirror in (False, True)}
    runs.update({("green_strain", "kuhn", mirror): deep_press_slide("green_strain", (8, 6, 5), steps=END,
                                                                    mirror=mirror, cut="kuhn")
                 for mirror in (False, True)})
    runs.update({("green_strain", "even", mirror): deep_press_slide("green_strain", (7, 7, 5), steps=END,
                                                                    mirror=mirror, cut="mirrored")
                 for mirror in (False, True)})
    return runs


def test_the_mirrored_cut_gives_the_deep_slides_mirror_image_the_same_answer_under_both_laws(mirror_images):
    """The deep press-slide and its mirror image in x are one problem. On the default mesh, cut ``mirrored`` (every
    cell's cut the mirror image of its partner's but the middle column's, :func:`sim_core.mesh.tet.mirrored_cut_flags`),
    measured (image / mirror image, K in N/mm pressed, at the first slide's end, pressed again, at the second slide's
    end): Stable Neo-Hookean 34.33 / 34.26, 39.49 / 39.51, 43.30 / 43.33, 44.90 / 44.93 (0.2 % at most); StVK 25.01 /
    25.24, 19.02 / 19.04, 20.75 / 20.72, 14.45 / 14.42 (0.9 % pressed, 0.2 % after), smallest stretch at the second
    slide's end 0.470 / 0.470 in both (no leading edge collapsed in either image). With an even cell count along x
    (``[7, 7, 5]``) the mesh is its own mirror image and the two answers agree to the solver's tolerance."""
    for law, rel in (("stable_neohookean", 0.005), ("green_strain", 0.015)):
        image, mirror = (mirror_images[(law, "default", m)] for m in (False, True))
        for step in STAGES:
            assert image["stiffness"][step] == pytest.approx(mirror["stiffness"][step], rel=rel), (law, step)
        for step in (SLID, END):
            assert image["stretch"][step] == pytest.approx(mirror["stretch"][step], abs=0.01), (law, step)
    stvk = [mirror_images[("green_strain", "default", m)] for m in (False, True)]
    for run in stvk:
        assert 0.68 < run["stiffness"][SLID] / run["stiffness"][PRESSED] < 0.78  # the law's softening, as on any cut
    image, mirror = (mirror_images[("green_strain", "even", m)] for m in (False, True))
    for key in ("stiffness", "stretch", "volume"):
        assert image[key][1:] == pytest.approx(mirror[key][1:], rel=1e-6), key


def test_on_the_kuhn_cut_the_mesh_handedness_decides_stvks_collapse(mirror_images):
    """The Kuhn cut (every cell along its (0,0,0)-(1,1,1) diagonal) has one handedness; measured on ``[8, 6, 5]``
    (image / mirror image): StVK K 25.88 / 25.91 N/mm pressed, 19.22 / 19.10 at the first slide's end (the law's
    softening the same, 0.74), but at the second slide's end 9.63 / 14.59 with the smallest stretch 0.026 / 0.493:
    which image's leading edge collapses past ``1/sqrt(3)`` is decided by the cells' handedness (the default law on
    this cut: 35.56 / 35.51, 41.00 / 40.16, 47.17 / 45.47, 2-4 % apart). The reference engine's deep press-slides
    show it too (benchmarks log, session 58, s58-49law: its recordings' leading edge followed at depth RMS 3.4-3.7
    only on the engine's two-layer mesh cut along the other diagonal)."""
    stvk = [mirror_images[("green_strain", "kuhn", m)] for m in (False, True)]
    assert stvk[0]["stiffness"][PRESSED] == pytest.approx(stvk[1]["stiffness"][PRESSED], rel=0.005)
    assert stvk[0]["stiffness"][SLID] == pytest.approx(stvk[1]["stiffness"][SLID], rel=0.03)
    end_stretch = sorted(run["stretch"][END] for run in stvk)
    assert end_stretch[0] < 0.1 < 0.4 < end_stretch[1]  # one image collapsed, the other not
    end_k = sorted(run["stiffness"][END] for run in stvk)
    assert end_k[1] > 1.3 * end_k[0]
