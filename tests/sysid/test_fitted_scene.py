"""The fitted scene (sysid.fitted_scene, ``thinshell sysid --write-scene``): loads and reproduces the fit."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import yaml

from sim_core.errors import ConfigError
from sim_core.scenes.scene_file import load_scene_file
from sim_core.simulation import Simulation
from sysid.cli import sysid_main
from sysid.evidence import load_evidence
from sysid.fit import fit
from sysid.fitted_scene import fitted_scene_document, fitted_scene_from_result, scene_keys_for, write_fitted_scene
from sysid.observation import ObservationModel
from tests.sysid.simbag import DT, PRESS_ONLY, make_recording


@pytest.fixture(scope="module")
def press_bag(tmp_path_factory):
    """A 4-step synthetic press whose scene.yaml states a gel modulus 2x the true one."""
    return make_recording(tmp_path_factory.mktemp("fitted") / "bag", segments=PRESS_ONLY, seed=4,
                          nominal={"gel.youngs_modulus": 6.0e5})


def test_written_scene_loads_and_reproduces_the_fitted_prediction(press_bag, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        evidence = load_evidence(press_bag)
        model = ObservationModel(evidence, dt=DT)
    names = ["gel.youngs_modulus", "friction.gel_sheet", "sensor.normal_offset"]
    result = fit(model, names, jacobian="fd", max_nfev=4)
    assert result.values["gel.youngs_modulus"] < 5.0e5  # moved from the wrong nominal 6e5 towards 3e5
    doc = fitted_scene_from_result(result, evidence)
    path = write_fitted_scene(tmp_path / "fitted.yaml", doc)
    with pytest.raises(ConfigError, match="exists"):
        write_fitted_scene(path, doc)

    sim = Simulation.from_scene(path)  # what thinshell sim and the sim node do
    assert sim.get_parameter("gel.youngs_modulus") == result.values["gel.youngs_modulus"]
    assert sim.get_parameter("friction.gel_sheet") == result.values["friction.gel_sheet"]
    parsed = load_scene_file(path)
    assert parsed.fitted["params"] == pytest.approx(result.values)
    assert set(parsed.fitted["sigma"]) == set(names) and parsed.fitted["bag"] == str(evidence.source.bag_path)
    assert parsed.fitted["effects"] == [] and parsed.fitted["status"] == result.status

    # replaying the recording in the written scene at its own (nominal) values gives the fit's prediction
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = ObservationModel(load_evidence(press_bag), scene=path, dt=DT)
    prediction = again.predict(again.simulate({}))
    model.warm_start = None  # a cold replay of the fitted values in the bag's scene (the fit's replays were warm-started)
    cold = model.predict(model.simulate(result.values))
    for ch, fitted in result.prediction_final.items():
        # same to round-off and the Newton tolerance (the mount's offset also places the gel at t0; the
        # replay shifts it from step 1): < 0.1 % of the channel's noise
        assert (np.abs(prediction[ch] - cold[ch]) / model.sigma[ch]).max() < 1e-3, ch
        # the fit's own prediction: equal to the Newton tolerance of its warm-started replays (< 5 % of the noise)
        assert (np.abs(prediction[ch] - fitted) / model.sigma[ch]).max() < 0.05, ch
    # and differs from the nominal scene's prediction (the test could fail)
    assert not np.allclose(result.prediction_initial["wrench"], result.prediction_final["wrench"],
                           atol=1e-3 * np.abs(result.prediction_final["wrench"]).max())


def test_effect_and_mapping(press_bag):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    scene = model.scene
    doc = fitted_scene_document(scene, {"candidate.stiction": 0.3, "sheet.bending_stiffness": 0.009,
                                        "contact.stiffness": 3.0e4, "friction.sheet_table": 0.25},
                                {"candidate.stiction": 0.05}, record={"bag": "b"})
    assert doc["simulation"]["candidates"] == {"stiction": 0.3} and doc["fitted"]["effects"] == ["stiction"]
    assert doc["fitted"]["sigma"] == {"candidate.stiction": 0.05, "sheet.bending_stiffness": None,
                                      "contact.stiffness": None, "friction.sheet_table": None}
    assert doc["table"]["friction"] == 0.25 and doc["sheet"]["material"]["bending_stiffness"] == 0.009
    sim = Simulation.from_scene(yaml.safe_load(yaml.safe_dump(doc)))
    assert sim.model.candidates == {"stiction": 0.3} and sim.get_parameter("candidate.stiction") == 0.3
    assert "fitted" not in scene  # input untouched
    assert scene_keys_for(scene, "gel.density") == [("sensors", "tactile", "gel_material", "density")]
    # the stick speed (the calibration's secant stage) has its scene key, read back by the built scene
    eps_doc = fitted_scene_document(scene, {"contact.eps_v": 3e-3})
    assert eps_doc["simulation"]["contact_eps_v"] == 3e-3
    assert Simulation.from_scene(yaml.safe_load(yaml.safe_dump(eps_doc))).get_parameter("contact.eps_v") == 3e-3
    with pytest.raises(ConfigError, match="'contact.warp' has no scene key"):
        fitted_scene_document(scene, {"contact.warp": 1e-4})
    with pytest.raises(ConfigError, match="not finite"):
        fitted_scene_document(scene, {"gel.youngs_modulus": float("nan")})
    with pytest.raises(ConfigError, match="simulation.candidates"):
        Simulation.from_scene({**doc, "simulation": {"candidates": {"warp_drive": 1.0}}})


def test_cli_scene_with_the_sensor_calibration_reproduces_the_fit_in_compare(press_bag, tmp_path, capsys):
    """thinshell sysid (sensor calibration on, its default) -> fitted scene -> thinshell compare on the same
    recording: the fitted scene's RMS per channel is the fit's final RMS."""
    import json

    from sysid.compare import compare_main
    from sysid.results import load_fit_json

    scene = tmp_path / "fitted.yaml"
    assert sysid_main([str(press_bag), "--out", str(tmp_path / "fit"), "--params", "gel.youngs_modulus",
                       "--max-nfev", "1", "--quiet", "--dt", str(DT), "--write-scene", str(scene)]) == 0
    fitted = load_scene_file(scene).fitted
    assert set(fitted["sensor_calibration"]) >= {"force_gain", "marker_scale_z", "fx"}
    fit_rms = load_fit_json(tmp_path / "fit" / "fit.json")["metrics"]["rms_final"]
    assert compare_main([str(press_bag), "--scene", str(scene), "--label", "fitted", "--out", str(tmp_path / "cmp"),
                         "--dt", str(DT), "--arch", "numpy"]) == 0
    cmp = json.loads((tmp_path / "cmp" / "compare.json").read_text())["rms"]
    for ch, entry in fit_rms.items():
        assert cmp["fitted"][ch]["rms"] == pytest.approx(entry["rms"], rel=0.02), ch
    capsys.readouterr()


def test_cli_writes_the_scene_and_refuses_to_overwrite(press_bag, tmp_path, capsys):
    scene = tmp_path / "fitted.yaml"
    args = [str(press_bag), "--out", str(tmp_path / "fit"), "--params", "gel.youngs_modulus", "--max-nfev", "1",
            "--quiet", "--write-scene", str(scene)]
    assert sysid_main(args) == 0, capsys.readouterr().err
    assert f"fitted scene: {scene}" in capsys.readouterr().out
    fitted = load_scene_file(scene).fitted
    assert Simulation.from_scene(scene).get_parameter("gel.youngs_modulus") == fitted["params"]["gel.youngs_modulus"]
    assert sysid_main([*args[:2], str(tmp_path / "fit2"), *args[3:]]) == 2
    assert f"scene file {scene} exists" in capsys.readouterr().err


def test_task_scene_values_go_into_the_task_scene_keys():
    """A ``kind: task`` scene (Forming): every fitted parameter lands in its own key and reads back."""
    from sim_core.optim.tasks import task_at_horizon
    from sim_core.scenes import load_scene
    from sysid.fitted_scene import scene_with_values

    scene = task_at_horizon("forming").scene
    values = {"sheet.bending_stiffness": 2.5e-3, "dome.youngs_modulus": 4.2e5, "dome.poisson_ratio": 0.3,
              "friction.sheet_dome": 3.5, "contact.stiffness": 1.5e4, "damping": 0.2, "sheet.yield_angle": 1.0}
    doc = fitted_scene_document(scene, values, record={"status": "converged"})
    assert doc["sheets"]["sheet"]["bending"] == {"bending_stiffness": 2.5e-3}          # replaces k_bend_thinshelllab
    assert doc["effectors"]["dome"]["material"]["youngs_modulus"] == 4.2e5
    assert {tuple(f["pair"]): f["mu"] for f in doc["friction"]} == {("dome", "sheet"): 3.5, ("table", "sheet"): 5.0}
    assert doc["fitted"]["params"] == values and doc["fitted"]["status"] == "converged"
    model = load_scene(doc)                       # the fitted: record is accepted by the task-scene builder
    for name, value in values.items():
        assert model.get_parameter(name) == pytest.approx(value, rel=1e-12)
    assert scene["sheets"]["sheet"]["bending"] == {"k_bend_thinshelllab": 200.0}      # input untouched
    with pytest.raises(ConfigError, match="sheet 'sheet' has a spring membrane"):
        scene_with_values(scene, {"sheet.youngs_modulus": 1e6})
    with pytest.raises(ConfigError, match="sheet 'sheet' gives areal_density"):
        scene_with_values(scene, {"sheet.density": 1e3})
    with pytest.raises(ConfigError, match="'contact.eps' has no key in a task scene"):
        scene_with_values(scene, {"contact.eps": 1e-4})
    with pytest.raises(ConfigError, match="friction list has no such pair"):
        scene_with_values(scene, {"friction.dome_table": 1.0})
    with pytest.raises(ConfigError, match="not finite"):
        scene_with_values(scene, {"damping": float("nan")})
