"""The gel's law chosen by the data (:mod:`sysid.gel_law`): one replay per law, the smaller whitened sum of squares.

- This simulator's own press-slides of the card scene (pressed 1.45 mm by a kinematic arm, slid 6 mm), one made with
  the Green-strain gel and one with the default Stable Neo-Hookean gel, noise at the reference bags' levels, each
  written with a ``scene.yaml`` that does not name its law (concealed): the choice finds the law that made each.
  Measured: the two laws' noise-free streams differ by 3.2 / 12.7 / 62 noise levels (markers z / xy, F_z; peak load
  26 N against 14 N); the true law's replay reads whitened RMS markers / pixels / wrench 0.85 / 0.75 / 0.74 (Green
  strain) and 0.92 / 0.94 / 1.19 (default), the other 6.0 / 6.5 / 13.1 and 7.3 / 10.5 / 37.3; delta-BIC 9.6e4 and
  3.7e5.
- The bundled reference recording nominal_s101 (MuJoCo 4.0, whose flex solids are Saint Venant-Kirchhoff): the
  choice is the Green-strain law (at the scene's values whitened RMS markers / pixels / wrench 5.28 / 7.63 / 3.72
  against 6.33 / 9.14 / 3.88 for the default law; delta-BIC 2.0e6).

Four replays of the card scene (about 1.5 CPU s each) and two of nominal_s101 (about 12 each): 35 CPU s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sysid.evidence import load_evidence
from sysid.gel_law import choose_gel_law
from tests.sysid.simbag import TRUE_PARAMS, add_noise, scene_with, simulate_streams, targets_from_segments, write_bag

DEEP_PRESS_SLIDE = (((0.0, 0.0, -0.00125), 3), ((-0.002, 0.0, 0.0), 8), ((0.0, 0.0, -0.0002), 1),
                    ((-0.004, 0.0, 0.0), 16))
"""Segments ``(displacement (m), steps)``: the card press-slide of :data:`tests.sysid.simbag.PRESS_SLIDE` pressed
0.2 mm deeper (strains at which the laws part)."""

REFERENCE = Path(__file__).resolve().parents[2] / "bags" / "nominal_s101"


@pytest.fixture(scope="module", params=["green_strain", "stable_neohookean"])
def concealed(request, tmp_path_factory):
    """``(law, bag)``: this simulator's press-slide made with ``law``; its ``scene.yaml`` names no law."""
    law = request.param
    scene = scene_with(TRUE_PARAMS)
    made_with = {**scene, "simulation": {**scene.get("simulation", {}), "gel_element": law}}
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), DEEP_PRESS_SLIDE)
    streams = add_noise(simulate_streams(made_with, TRUE_PARAMS, targets), seed=11)
    return law, write_bag(tmp_path_factory.mktemp(law) / "bag", scene, streams)


def test_the_data_choose_the_law_that_made_the_recording(concealed):
    law, bag = concealed
    choice = choose_gel_law(load_evidence(bag))
    assert choice.chosen == law, choice.summary()
    # the true law follows the recording at its noise; the other is far off (a delta-BIC of thousands)
    assert max(choice.rms[law].values()) < 1.3, choice.summary()
    assert choice.margin > 1000.0, choice.summary()


def test_diagnose_with_gel_element_auto_replays_the_law_the_recording_chooses(concealed):
    """``thinshell diagnose --gel-element auto``: before either stage the pipeline puts the chosen law in both stages'
    replays (with the other ``simulation`` overrides kept) and reports the choice."""
    from sysid.diagnose.cli import build_parser, options_from_args
    from sysid.diagnose.pipeline import with_gel_law

    law, bag = concealed
    options = options_from_args(build_parser().parse_args([str(bag), "--gel-element", "auto",
                                                           "--gel-resolution", "5", "4", "2"]))  # the scene's own
    chosen, choice = with_gel_law(bag, options)
    expected = {"gel_resolution": [5, 4, 2], "gel_element": law}
    assert chosen.signatures.simulation == chosen.score.simulation == expected
    assert choice.summary()["chosen"] == law
    plain = options_from_args(build_parser().parse_args([str(bag)]))
    assert with_gel_law(bag, plain) == (plain, None)


def test_the_reference_engines_recording_chooses_the_green_strain_law():
    choice = choose_gel_law(load_evidence(REFERENCE, include_image="auto"))
    assert choice.chosen == "green_strain", choice.summary()
    rms = choice.rms
    assert all(rms["green_strain"][ch] < rms["stable_neohookean"][ch] for ch in choice.channels), choice.summary()


def test_one_law_is_no_choice():
    with pytest.raises(ValueError, match="at least two"):
        choose_gel_law(None, ("green_strain",))


def test_sysid_with_gel_element_auto_fits_with_the_law_the_recording_chooses(concealed, tmp_path, capsys):
    """``thinshell sysid --gel-element auto``: the fit's replays take the law that made the recording (its first
    replay, sensor calibrated, follows the recording at the noise; the other law's misses it by 6-37 noise levels) and
    fit.json's ``diagnostics.gel_law`` reports the choice."""
    from sysid.cli import sysid_main
    from sysid.results import load_fit_json

    law, bag = concealed
    out = tmp_path / "fit"
    rc = sysid_main([str(bag), "--out", str(out), "--gel-element", "auto", "--params", "gel.youngs_modulus",
                     "--max-nfev", "1", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    doc = load_fit_json(out / "fit.json")
    reported = doc["diagnostics"]["gel_law"]
    assert reported["element"] == reported["choice"]["chosen"] == law and reported["requested"] == "auto"
    assert reported["choice"]["delta_bic"] > 1000.0
    first = doc["metrics"]["rms_initial"]
    assert max(first[ch]["whitened_rms"] for ch in ("markers_xyz", "wrench")) < 1.5, first
