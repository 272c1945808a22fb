"""The fitted scene: a recording's scene with the values sysid fitted, loadable like any scene.

``thinshell sysid BAG --write-scene fitted.yaml`` (and the sysid node's ``write_scene``) write the scene
the fit simulated (the bag's ``scene.yaml`` or ``--scene``, with its ``simulation:`` overrides) with every
fitted global parameter put into the scene key that sets it (:data:`SCENE_KEYS`), plus a record::

    fitted:
      params: {gel.youngs_modulus: 2.7e5}        # the fitted values (also in the scene's keys)
      sigma: {gel.youngs_modulus: 3.1e3}         # 1-sigma (Gauss-Newton), null when not computed
      sigma_robust: {gel.youngs_modulus: 2.4e4}  # 1-sigma under model error (sysid.covariance), and its
      sigma_robust_method: hac                   # method; absent when not computed
      initial: {gel.youngs_modulus: 3.0e5}
      effects: [stiction]                        # modelled missing physics: fitted candidate.* parameters and
                                                 # the candidate terms the scene carries (simulation.candidates)
      bag: /abs/path/to/bag   bag_sha256: ...   rms: {markers_xyz: 1.2e-5, ...}   status: converged
      sensor_calibration: {force_gain: 1.02, fx: 301.2, ...}   # when the fit was judged through one

Parameter -> scene key: ``sheet.youngs_modulus | poisson_ratio | bending_stiffness`` ->
``sheet.material.*``; ``sheet.density`` -> ``sheet.density``; ``<gel body>.youngs_modulus |
poisson_ratio | density`` -> ``sensors.<s>.gel_material.*``; ``friction.<gel body>_sheet`` ->
``sensors.<s>.friction``; ``friction.sheet_table`` / ``friction.<gel>_table`` -> ``table.friction``
(one value for both pairs); ``contact.stiffness`` -> ``simulation.contact_stiffness``;
``contact.eps_v`` -> ``simulation.contact_eps_v``; ``damping`` ->
``simulation.damping``; ``sheet.yield_angle`` -> ``simulation.sheet_yield_angle``; ``candidate.<name>``
-> ``simulation.candidates.<name>`` (the effect's term); ``sensor.normal_offset`` -> the sensor's
``mount`` moved by that offset along its +z (the replay's shift of the effector along the sensor
normal, made permanent). A parameter with no scene key is refused.

A task scene (``kind: task``, ``docs/scene_schema.md``) keeps its own keys: ``<sheet>.bending_stiffness``
-> ``sheets.<sheet>.bending: {bending_stiffness: D}`` (replacing ThinShellLab's ``k_bend_thinshelllab``),
``<sheet>.thickness | yield_angle | density`` -> ``sheets.<sheet>.*``, ``<sheet>.youngs_modulus |
poisson_ratio`` -> ``sheets.<sheet>.membrane.*`` (an ``stvk`` membrane only: a spring membrane's
modulus is derived), ``<effector or elastic box>.youngs_modulus | poisson_ratio | density`` ->
``effectors.<e>.material.*`` / ``boxes.<b>.material.*``, ``friction.<a>_<b>`` -> the ``mu`` of that
pair in ``friction``, ``contact.stiffness | eps_v`` -> ``contact.*``, ``damping`` -> ``damping``.

The sensor calibration that ``thinshell sysid`` fits in closed form before the parameters (wrench
gains, marker scales, camera intrinsics: :mod:`sysid.calibration`) acts on the predictions, not on the
physics; it is recorded as ``fitted.sensor_calibration`` and applied by the tools that predict a
recording (``thinshell compare``: :func:`sensor_calibration_of`). ``Simulation.from_scene`` and the
sim node simulate the raw sensor with the scene's camera.

:func:`fitted_scene_document` checks its own work: the scene it returns is built and every fitted
Model parameter read back must equal the fitted value.
"""

from __future__ import annotations

import copy
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from sim_core.errors import ConfigError
from sim_core.plain import plain
from sim_core.scenes import load_scene
from sim_core.transforms import quat_to_matrix
from sysid.calibration import SensorCalibration

_SHEET_MATERIAL = ("youngs_modulus", "poisson_ratio", "bending_stiffness")
_GEL_MATERIAL = ("youngs_modulus", "poisson_ratio", "density")
_TASK_SHEET_KEYS = ("youngs_modulus", "poisson_ratio", "thickness", "bending_stiffness", "density", "yield_angle")


def _gel_body(sensor_names: Sequence[str], index: int) -> str:
    """The gel body name of the ``index``-th sensor (``sim_core.scenes.tactile_scene``: ``gel``, ``gel_<s>``)."""
    return "gel" if index == 0 else f"gel_{sensor_names[index]}"


def _set(doc: dict, path: Sequence[str], value: Any) -> None:
    node = doc
    for key in path[:-1]:
        node = node.setdefault(key, {})
        if node is None:
            raise ConfigError(f"scene key {'.'.join(path)} cannot be set")
    node[path[-1]] = value


def scene_keys_for(scene: Mapping[str, Any], name: str) -> list[tuple[str, ...]]:
    """The scene keys (dotted paths as tuples) that set global parameter ``name``.

    Raises:
        ConfigError: a parameter no scene key sets.
    """
    sensors = list((scene.get("sensors") or {}).keys())
    gels = {_gel_body(sensors, i): s for i, s in enumerate(sensors)}
    body, _, key = name.partition(".")
    if body == "sheet" and key in _SHEET_MATERIAL:
        return [("sheet", "material", key)]
    if name == "sheet.density":
        return [("sheet", "density")]
    if name == "sheet.yield_angle":
        return [("simulation", "sheet_yield_angle")]
    if body in gels and key in _GEL_MATERIAL:
        return [("sensors", gels[body], "gel_material", key)]
    if name == "contact.stiffness":
        return [("simulation", "contact_stiffness")]
    if name == "contact.eps_v":
        return [("simulation", "contact_eps_v")]
    if name == "damping":
        return [("simulation", "damping")]
    if body == "candidate" and key:
        return [("simulation", "candidates", key)]
    if body == "friction":
        a_b = key
        for gel, s in gels.items():
            if a_b in (f"{gel}_sheet", f"sheet_{gel}"):
                return [("sensors", s, "friction")]
            if a_b in (f"{gel}_table", f"table_{gel}"):
                return [("table", "friction")]
        if a_b in ("sheet_table", "table_sheet"):
            return [("table", "friction")]
    raise ConfigError(f"parameter {name!r} has no scene key; it cannot be written into a fitted scene")


def scene_with_values(scene: Mapping[str, Any], values: Mapping[str, float], *,
                      sensor: str | None = None) -> dict[str, Any]:
    """A copy of ``scene`` (without any ``fitted:`` record) with global parameters set in its keys.

    Args:
        scene: scene v1 or a task scene (``kind: task``) as a plain dict.
        values: global parameter name -> value (SI units); mapping in the module docstring.
        sensor: the sensor whose mount ``sensor.normal_offset`` moves (default: the first).

    Raises:
        ConfigError: a parameter without a scene key, or a non-finite value.
    """
    doc = copy.deepcopy(dict(scene))
    doc.pop("fitted", None)
    if doc.get("kind") == "task":
        return _task_scene_with_values(doc, values)
    sensors = list((doc.get("sensors") or {}).keys())
    for name, value in values.items():
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"fitted value of {name!r} is not finite: {value}")
        if name == "sensor.normal_offset":
            s = sensor or (sensors[0] if sensors else None)
            if s is None:
                raise ConfigError("sensor.normal_offset: the scene has no sensor")
            mount = np.asarray(doc["sensors"][s].get("mount") or [0, 0, 0, 0, 0, 0, 1], dtype=float)
            mount[:3] += value * quat_to_matrix(mount[3:7])[:, 2]
            doc["sensors"][s]["mount"] = [float(v) for v in mount]
            continue
        for path in scene_keys_for(doc, name):
            _set(doc, path, value)
    return doc


def _task_scene_with_values(doc: dict[str, Any], values: Mapping[str, float]) -> dict[str, Any]:
    """``doc`` (a ``kind: task`` scene, modified in place) with global parameters set in its keys
    (:data:`TASK_SCENE_KEYS`)."""
    sheets = doc.get("sheets") or {}
    solids = {**{n: ("effectors", n) for n in (doc.get("effectors") or {})},
              **{n: ("boxes", n) for n, b in (doc.get("boxes") or {}).items() if not b.get("frozen")}}
    for name, value in values.items():
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"fitted value of {name!r} is not finite: {value}")
        body, _, key = name.partition(".")
        if body in sheets and key in _TASK_SHEET_KEYS:
            sheet = sheets[body]
            if key == "bending_stiffness":
                sheet["bending"] = {"bending_stiffness": value}
                continue
            if key in ("youngs_modulus", "poisson_ratio"):
                if (sheet.get("membrane") or {}).get("model") != "stvk":
                    raise ConfigError(f"parameter {name!r}: sheet {body!r} has a spring membrane (derived modulus); "
                                      "it cannot be written into a fitted scene")
                sheet["membrane"][key] = value
                continue
            if key == "density" and "density" not in sheet:
                raise ConfigError(f"parameter {name!r}: sheet {body!r} gives areal_density; it cannot be written "
                                  "into a fitted scene")
            sheet[key] = value
        elif body in solids and key in _GEL_MATERIAL:
            section, solid = solids[body]
            doc[section][solid].setdefault("material", {})[key] = value
        elif body == "friction":
            for entry in doc.get("friction") or []:
                a, b = entry["pair"]
                if key in (f"{a}_{b}", f"{b}_{a}"):
                    entry["mu"] = value
                    break
            else:
                raise ConfigError(f"parameter {name!r}: the scene's friction list has no such pair")
        elif name in ("contact.stiffness", "contact.eps_v"):
            doc["contact"][key] = value
        elif name == "damping":
            doc["damping"] = value
        else:
            raise ConfigError(f"parameter {name!r} has no key in a task scene; it cannot be written into a fitted scene")
    return doc


def fitted_scene_document(scene: Mapping[str, Any], values: Mapping[str, float],
                          sigma: Mapping[str, float] | None = None, *, sensor: str | None = None,
                          record: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The scene with the fitted values and the ``fitted:`` record (module docstring).

    Args:
        scene: the scene the fit simulated (scene v1 or a task scene, as a plain dict).
        values: fitted global parameter values (SI units).
        sigma: their 1-sigma, or None.
        sensor: the sensor whose mount ``sensor.normal_offset`` moves (default: the first).
        record: further entries of ``fitted:`` (``bag``, ``bag_sha256``, ``rms``, ``initial``, ``status``, ...).

    Returns:
        the new scene document (the input is not modified).

    Raises:
        ConfigError: a parameter without a scene key, a non-finite value, or a scene that does not
            read back the fitted values.
    """
    doc = scene_with_values(scene, values, sensor=sensor)
    # modelled effects: fitted candidate terms, and those the scene already carried (e.g. from a diagnosis)
    carried = {k for k, v in ((doc.get("simulation") or {}).get("candidates") or {}).items() if "." not in k and v}
    effects = sorted(carried | {n.split(".", 1)[1].split(".")[0] for n in values if n.startswith("candidate.")})
    fitted: dict[str, Any] = {"params": {k: float(v) for k, v in values.items()},
                              "sigma": {k: (None if sigma is None or sigma.get(k) is None else float(sigma[k]))
                                        for k in values},
                              "effects": effects}
    fitted.update(plain(dict(record or {})))
    doc["fitted"] = fitted
    model = load_scene(doc)
    for name, value in values.items():
        if name == "sensor.normal_offset":
            continue
        got = float(model.get_parameter(name))
        if not math.isclose(got, float(value), rel_tol=1e-12, abs_tol=1e-300):
            raise ConfigError(f"fitted scene: {name} reads back {got!r}, not the fitted {float(value)!r}")
    return doc




def write_fitted_scene(path: str | Path, doc: Mapping[str, Any], *, force: bool = False) -> Path:
    """Write a fitted scene document atomically (temporary file + rename).

    Raises:
        ConfigError: the file exists and ``force`` is false.
    """
    path = Path(path)
    if path.exists() and not force:
        raise ConfigError(f"{path}: exists (use --force to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True)
    text = ("# thinshell scene with the values fitted by thinshell sysid (see fitted:); sysid/fitted_scene.py\n"
            + yaml.safe_dump(plain(dict(doc)), sort_keys=False, default_flow_style=None, width=120))
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def fitted_scene_from_result(result: Any, evidence: Any, t_max: float | None = None,
                             calibrated: Mapping[str, float] | None = None) -> dict[str, Any]:
    """The fitted scene of a :class:`sysid.fit.FitResult` on ``evidence`` (the scene its model simulated).

    Args:
        result: the fit.
        evidence: the recording it was fitted to.
        t_max: the fit's time window end, s (recorded).
        calibrated: name -> value of the simulator parameters the calibration set before the fit
            (:attr:`sysid.calibration.CalibrationResult.params`, e.g. the stick speed
            ``contact.eps_v`` of its secant stage): the fit's replays ran with them, so the scene
            holds them too (no uncertainty: ``sigma`` None); the fit's own values take precedence.

    Raises:
        ConfigError: see :func:`fitted_scene_document`.
    """
    model = result.model
    rms = {ch: float(v["rms"]) for ch, v in result.rms_final.items()}
    record = {"initial": {k: float(v) for k, v in result.initial.items()}, "status": result.status,
              "rms": rms, "channels": list(result.channels), "dt": float(result.dt), "t_max": t_max,
              "bag": str(evidence.source.bag_path), "bag_sha256": evidence.source.sha256}
    if model.sensor_calibration is not None:
        # the fit was judged through this sensor calibration (thinshell sysid's default): it is part of the fit
        record["sensor_calibration"] = model.sensor_calibration.as_dict()
    values = {**{k: float(v) for k, v in (calibrated or {}).items()}, **result.values}
    sigma = {**{k: None for k in (calibrated or {})}, **(result.sigma or {})}
    if getattr(result, "robust", None) is not None and result.sigma_robust:
        record["sigma_robust"] = {k: float(v) for k, v in result.sigma_robust.items()}
        record["sigma_robust_method"] = result.robust.method
    if calibrated:
        record["calibrated"] = sorted(k for k in calibrated if k not in result.values)
    return fitted_scene_document(model.scene, values, sigma, sensor=model.sensor, record=record)


def sensor_calibration_of(scene: Mapping[str, Any]):
    """The :class:`sysid.calibration.SensorCalibration` a fitted scene records, or None.

    Raises:
        ConfigError: a ``fitted.sensor_calibration`` with unknown or non-numeric entries.
    """
    block = (scene.get("fitted") or {}).get("sensor_calibration")
    if block is None:
        return None
    try:
        return SensorCalibration(**{k: float(v) for k, v in dict(block).items()})
    except (TypeError, ValueError) as err:
        raise ConfigError(f"fitted.sensor_calibration: {err}") from err
