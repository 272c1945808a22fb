"""sim_core.scenes.scene_file: scene.yaml v1 loading, validation messages, round trip."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from sim_core.errors import ConfigError
from sim_core.scenes.scene_file import SceneFile, load_scene_file, load_yaml

REPO = Path(__file__).resolve().parents[3]
REFERENCE_SCENE = REPO / ".." / "shared" / "data" / "reference_bags" / "nominal_s101" / "scene.yaml"

# The example of INTERFACES.md, verbatim (note the YAML 1.2 float 3.0e9, which PyYAML alone reads as a string).
INTERFACES_EXAMPLE = """\
version: 1
name: card_press_slide          # free text
dt: 0.005
gravity: [0.0, 0.0, -9.81]
table: {height: 0.0, friction: 0.3}
sheet:
  size: [0.10, 0.06]
  resolution: [21, 13]
  thickness: 0.0003
  density: 700.0
  origin: [0.0, -0.03, 0.0003]
  clamped_edge: x0
  material: {youngs_modulus: 3.0e9, poisson_ratio: 0.3, bending_stiffness: 8.0e-3}
sensors:
  tactile:
    effector: ee
    gel_size: [0.0186, 0.0143, 0.004]
    gel_material: {youngs_modulus: 3.0e5, poisson_ratio: 0.45, density: 1100.0}
    friction: 0.8
    marker_grid: [9, 7]
    marker_pitch: 0.0020
    camera: {fx: 300.0, fy: 300.0, cx: 160.0, cy: 120.0, width: 320, height: 240, distance: 0.025}
    mount: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
effectors:
  ee: {initial_pose: [0.07, 0.0, 0.03, 0.0, 0.0, 0.0, 1.0]}
"""


@pytest.fixture
def example(tmp_path) -> Path:
    path = tmp_path / "scene.yaml"
    path.write_text(INTERFACES_EXAMPLE)
    return path


def _edited(tmp_path: Path, edit) -> Path:
    data = load_yaml(INTERFACES_EXAMPLE)
    edit(data)
    path = tmp_path / "edited.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_interfaces_example_loads_with_si_values(example):
    scene = load_scene_file(example)
    assert isinstance(scene, SceneFile) and scene.source == str(example)
    assert scene.sheet.material.youngs_modulus == 3.0e9 and scene.sheet.material.bending_stiffness == 8.0e-3
    assert scene.sheet.resolution == (21, 13) and scene.sheet.clamped_edge == "x0"
    tactile = scene.sensors["tactile"]
    assert tactile.marker_count == 63 and tactile.camera.distance == 0.025
    assert tactile.camera.k1 is None and tactile.camera.k2 is None
    assert tactile.mount == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    assert scene.effectors["ee"].initial_pose[:3] == (0.07, 0.0, 0.03)


def test_round_trip_through_to_dict(example, tmp_path):
    scene = load_scene_file(example)
    assert load_scene_file(scene.to_dict()) == scene
    dumped = tmp_path / "dumped.yaml"
    dumped.write_text(yaml.safe_dump(scene.to_dict(), sort_keys=False))
    assert load_scene_file(dumped) == scene
    assert load_scene_file(scene) is scene


@pytest.mark.parametrize("path", [REFERENCE_SCENE, REPO / "config" / "scenes" / "press_slide.yaml"])
def test_shipped_and_reference_scenes_load(path):
    if not path.is_file():
        pytest.skip(f"{path} not present")
    scene = load_scene_file(path)
    assert scene.version == 1 and scene.sheet.resolution == (21, 13)
    assert scene.sensors["tactile"].mount is None  # optional, left unset rather than defaulted
    assert "mount" not in scene.to_dict()["sensors"]["tactile"]


def test_optional_distortion_and_simulation_block(tmp_path):
    def edit(d):
        d["sensors"]["tactile"]["camera"].update(k1=-0.1, k2=0.02)
        del d["sensors"]["tactile"]["mount"]
        d["simulation"] = {"contact_stiffness": 1.0e4}

    scene = load_scene_file(_edited(tmp_path, edit))
    assert (scene.sensors["tactile"].camera.k1, scene.sensors["tactile"].camera.k2) == (-0.1, 0.02)
    assert scene.sensors["tactile"].mount is None and scene.simulation == {"contact_stiffness": 1.0e4}
    assert scene.to_dict()["sensors"]["tactile"]["camera"]["k1"] == -0.1
    assert scene.to_dict()["simulation"] == {"contact_stiffness": 1.0e4}


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(extra=1), "unknown key extra"),
    (lambda d: d["sheet"].update(thicknes=1e-3), "unknown key sheet.thicknes"),
    (lambda d: d["sheet"]["material"].update(E=1.0), "unknown key sheet.material.E"),
    (lambda d: d["sensors"]["tactile"]["camera"].update(fxx=1.0), "unknown key sensors.tactile.camera.fxx"),
    (lambda d: d["effectors"]["ee"].update(pose=[0] * 7), "unknown key effectors.ee.pose"),
])
def test_unknown_keys_are_rejected_with_dotted_name_and_file(tmp_path, edit, message):
    path = _edited(tmp_path, edit)
    with pytest.raises(ConfigError, match=f"^{path}: {message}"):
        load_scene_file(path)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["sheet"]["material"].pop("bending_stiffness"), "missing required key sheet.material.bending_stiffness"),
    (lambda d: d.pop("dt"), "missing required key dt"),
    (lambda d: d.pop("table"), "missing required key table"),
    (lambda d: d["sensors"]["tactile"]["camera"].pop("distance"), "missing required key sensors.tactile.camera.distance"),
    (lambda d: d["sheet"].update(thickness=-1e-3), "sheet.thickness must be > 0.0"),
    (lambda d: d["sheet"]["material"].update(poisson_ratio=0.5), "sheet.material.poisson_ratio must be < 0.5"),
    (lambda d: d["sheet"].update(resolution=[21.0, 13]), r"sheet.resolution\[0\] must be an integer"),
    (lambda d: d["sheet"].update(size=[0.1]), "sheet.size must be a list of 2 numbers"),
    (lambda d: d["sheet"].update(clamped_edge="left"), "sheet.clamped_edge must be one of none"),
    (lambda d: d["sheet"]["material"].update(youngs_modulus="3.0e9x"), "sheet.material.youngs_modulus must be a number"),
    (lambda d: d["effectors"]["ee"].update(initial_pose=[0, 0, 0, 0, 0, 0, 2.0]), "effectors.ee.initial_pose quaternion"),
    (lambda d: d["sensors"]["tactile"].update(effector="arm"), "sensors.tactile.effector names unknown effector 'arm'"),
    (lambda d: d["sensors"]["tactile"].update(friction=float("nan")), "sensors.tactile.friction must be finite"),
    (lambda d: d.update(simulation=[1]), "simulation must be a mapping"),
])
def test_missing_and_invalid_values(tmp_path, edit, message):
    path = _edited(tmp_path, edit)
    with pytest.raises(ConfigError, match=f"^{path}: {message}"):
        load_scene_file(path)


def test_wrong_or_missing_version(tmp_path):
    with pytest.raises(ConfigError, match="version is 2; this reader understands version 1"):
        load_scene_file(_edited(tmp_path, lambda d: d.update(version=2)))
    with pytest.raises(ConfigError, match="missing required key version"):
        load_scene_file(_edited(tmp_path, lambda d: d.pop("version")))


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match=f"{tmp_path / 'none.yaml'}: scene file does not exist"):
        load_scene_file(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nsheet: [1, 2\n")
    with pytest.raises(ConfigError, match=f"{bad}: not valid YAML"):
        load_scene_file(bad)
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match=f"{bad}: a scene file must be a YAML mapping"):
        load_scene_file(bad)


def test_dict_input_is_validated_too():
    data = load_yaml(INTERFACES_EXAMPLE)
    broken = copy.deepcopy(data)
    broken["gravity"] = [0.0, -9.81]
    with pytest.raises(ConfigError, match="<dict>: gravity must be a list of 3 numbers"):
        load_scene_file(broken)
    assert load_scene_file(data).source == "<dict>"


def test_yaml_loader_reads_yaml12_floats():
    assert load_yaml("a: 3.0e9\nb: 1e-3\nc: 7\nd: '3.0e9'\n") == {"a": 3.0e9, "b": 1e-3, "c": 7, "d": "3.0e9"}


def test_the_gel_element_is_chosen_in_the_simulation_block():
    """``simulation.gel_element`` picks the gel's element (default Stable Neo-Hookean tets); a name that is none
    of :data:`sim_core.elastic.SOLID_ELEMENTS` is refused naming the key."""
    from sim_core.elastic import ElasticTerms
    from sim_core.energies.neohookean.reference import StableNeoHookean
    from sim_core.energies.nodal_pressure.reference import NodalPressureNeoHookean
    from sim_core.scenes.tactile_scene import build_tactile_scene

    data = load_yaml(INTERFACES_EXAMPLE)
    assert type(ElasticTerms(build_tactile_scene(data)).solids["gel"]) is StableNeoHookean
    data["simulation"] = {"gel_element": "nodal_pressure_neohookean"}
    model = build_tactile_scene(data)
    assert model.meta["solid_element"] == "nodal_pressure_neohookean"
    assert type(ElasticTerms(model).solids["gel"]) is NodalPressureNeoHookean
    data["simulation"] = {"gel_element": "mixed_p2"}
    with pytest.raises(ConfigError, match="simulation.gel_element"):
        build_tactile_scene(data)
