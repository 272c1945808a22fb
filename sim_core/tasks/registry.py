"""Task files (``config/tasks/<name>.yaml``, format in ``docs/task_format.md``) loaded into TaskSpec.

Top-level keys (every key validated; an unknown key raises :class:`ConfigError` naming the file and
the dotted key)::

    format: thinshell-task     version: 1       name: str      kind: manipulation | inverse
    source: str                                  # the ThinShellLab files the facts come from
    scene: {file: path (relative to the task file), set: {dotted.key: value} (optional)} | {inline: SCENE}
    horizon: steps
    actions: [{effector, kind: pose, max_translation: m, max_rotation: rad}
              | {effector, kind: gripper, max_opening_change: m}, ...]   (may be empty: inverse tasks)
    cma: {control_points, sigma, population, generations, start: zero | reference (optional, default zero)}
    reward: {name, params}                        # sim_core.tasks.task_rewards
    scores: {human, oracle, success} (optional, each a number or null)
    infeasible: {max_force_N, min_contact_force_N, contact_after_step, contact_effectors} (optional)
    reference: [{steps: n, pose: {effector: [6 values]}, gripper: {effector: value}}, ...] (optional)
    identify: [parameter names] (inverse)         true_parameters: {name: value} (inverse, optional)
    tie: {follower: leader} (inverse, optional)   # identified names held equal, searched as one

The reference trajectory is piecewise constant: each block repeats its action row ``steps`` times;
blocks shorter than the horizon are padded with zero rows.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sim_core.bundled import config_dir
from sim_core.errors import ConfigError
from sim_core.scenes.task_scene import build_task_scene
from sim_core.tasks.rollout import TaskEpisode
from sim_core.tasks.spec import ACTION_KINDS, Infeasibility, TaskSpec
from sim_core.tasks.task_rewards import REWARD_UNITS, build_reward

TASK_FORMAT = "thinshell-task"
TASK_VERSION = 1
TASK_NAMES = ("lifting", "separating", "following", "folding_l", "folding_u", "pick_folding", "forming",
              "sliding", "bouncing", "card")
"""The ten ThinShellLab tasks, by file name."""

_TOP = {"format": True, "version": True, "name": True, "kind": True, "source": True, "scene": True, "horizon": True,
        "actions": True, "cma": True, "reward": True, "scores": False, "infeasible": False, "reference": False,
        "identify": False, "true_parameters": False, "tie": False}
_CMA = {"control_points": True, "sigma": True, "population": True, "generations": True, "start": False}
CMA_STARTS = ("zero", "reference")
_INFEASIBLE = {"max_force_N": False, "min_contact_force_N": False, "contact_after_step": False,
               "contact_effectors": False}


def default_tasks_dir() -> Path:
    """The bundled ``config/tasks`` (package data of :mod:`sim_core.bundled`).

    Raises:
        ConfigError: the package was installed without its configuration.
    """
    return config_dir() / "tasks"


def task_names() -> list[str]:
    """The ten task names (file stems under ``config/tasks``)."""
    return list(TASK_NAMES)


def _keys(value: Any, where: str, keys: dict[str, bool]) -> dict:
    if not isinstance(value, dict):
        raise ConfigError(f"{where} must be a mapping, got {type(value).__name__}")
    for k in value:
        if k not in keys:
            raise ConfigError(f"unknown key {where}.{k} (known: {sorted(keys)})")
    for k, required in keys.items():
        if required and k not in value:
            raise ConfigError(f"missing key {where}.{k}")
    return value


def _num(value: Any, where: str, positive: bool = False, integer: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{where} must be a number, got {value!r}") from err
    if not np.isfinite(v) or (positive and v <= 0) or (integer and v != int(v)):
        raise ConfigError(f"{where} must be a finite{' positive' if positive else ''}{' integer' if integer else ''}"
                          f" number, got {value!r}")
    return int(v) if integer else v


def set_dotted(doc: dict, dotted: str, value: Any, where: str) -> None:
    """Set ``doc[a][b][c] = value`` for ``dotted = "a.b.c"``; every key but the last must exist.

    Raises:
        ConfigError: a missing intermediate key (named with ``where``).
    """
    parts = dotted.split(".")
    node = doc
    for i, part in enumerate(parts[:-1]):
        if not isinstance(node, dict) or part not in node:
            raise ConfigError(f"{where}: {'.'.join(parts[:i + 1])} does not exist in the scene")
        node = node[part]
    if not isinstance(node, dict):
        raise ConfigError(f"{where}: {'.'.join(parts[:-1])} is not a mapping")
    node[parts[-1]] = copy.deepcopy(value)


def _scene(raw: Any, base_dir: Path | None, where: str) -> dict:
    if not isinstance(raw, dict) or len(raw.keys() & {"file", "inline"}) != 1:
        raise ConfigError(f"{where} must be {{file: path, set: {{...}}}} or {{inline: scene}}")
    base = base_dir
    if "inline" in raw:
        _keys(raw, where, {"inline": True})
        doc = copy.deepcopy(raw["inline"])
    else:
        _keys(raw, where, {"file": True, "set": False})
        path = Path(str(raw["file"]))
        if not path.is_absolute():
            path = (base_dir or Path.cwd()) / path
        try:
            doc = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as err:
            raise ConfigError(f"{where}.file: cannot read scene {path} ({err})") from err
        for dotted, value in (raw.get("set") or {}).items():
            set_dotted(doc, str(dotted), value, f"{where}.set.{dotted}")
        base = path.parent
    if not isinstance(doc, dict) or doc.get("kind") != "task":
        raise ConfigError(f"{where}: the scene must be a 'kind: task' scene document")
    # mesh files are named relative to the scene file (inline scenes: to the task file): made absolute,
    # so that the document builds from anywhere (TaskSpec.scene)
    for spec in (doc.get("meshes") or {}).values():
        if isinstance(spec, dict) and "file" in spec and not Path(str(spec["file"])).is_absolute():
            spec["file"] = str((base or Path.cwd()) / str(spec["file"]))
    return doc


def _actions(raw: Any, where: str) -> tuple[tuple[tuple[str, str], ...], np.ndarray]:
    if not isinstance(raw, list):
        raise ConfigError(f"{where} must be a list of action blocks")
    layout, high = [], []
    for i, block in enumerate(raw):
        w = f"{where}[{i}]"
        kind = block.get("kind") if isinstance(block, dict) else None
        if kind not in ACTION_KINDS:
            raise ConfigError(f"{w}.kind must be one of {ACTION_KINDS}, got {kind!r}")
        if kind == "pose":
            b = _keys(block, w, {"effector": True, "kind": True, "max_translation": True, "max_rotation": True})
            t, r = _num(b["max_translation"], f"{w}.max_translation", True), _num(b["max_rotation"], f"{w}.max_rotation", True)
            high += [t, t, t, r, r, r]
        else:
            b = _keys(block, w, {"effector": True, "kind": True, "max_opening_change": True})
            high.append(_num(b["max_opening_change"], f"{w}.max_opening_change", True))
        entry = (str(b["effector"]), kind)
        if entry in layout:
            raise ConfigError(f"{w}: duplicate action block {entry}")
        layout.append(entry)
    return tuple(layout), np.array(high, dtype=float)


def _reference(raw: Any, layout, horizon: int, where: str) -> np.ndarray:
    if not isinstance(raw, list):
        raise ConfigError(f"{where} must be a list of {{steps, pose: {{...}}, gripper: {{...}}}} blocks")
    cols, start = {}, 0
    for eff, kind in layout:
        width = 6 if kind == "pose" else 1
        cols[(eff, kind)] = slice(start, start + width)
        start += width
    rows = []
    for i, block in enumerate(raw):
        w = f"{where}[{i}]"
        b = _keys(block, w, {"steps": True, "pose": False, "gripper": False})
        n = _num(b["steps"], f"{w}.steps", positive=True, integer=True)
        row = np.zeros(start)
        for kind in ("pose", "gripper"):
            for eff, value in (b.get(kind) or {}).items():
                if (eff, kind) not in cols:
                    raise ConfigError(f"{w}.{kind}.{eff}: no {kind} action block for effector {eff!r}")
                vals = np.atleast_1d(np.asarray(value, dtype=float))
                if vals.shape != (cols[(eff, kind)].stop - cols[(eff, kind)].start,) or not np.all(np.isfinite(vals)):
                    raise ConfigError(f"{w}.{kind}.{eff}: wrong number of values or non-finite: {value!r}")
                row[cols[(eff, kind)]] = vals
        rows += [row] * n
    if len(rows) > horizon:
        raise ConfigError(f"{where}: {len(rows)} steps for a horizon of {horizon}")
    rows += [np.zeros(start)] * (horizon - len(rows))
    return np.array(rows).reshape(horizon, start)


def _optional_score(scores: dict, key: str, where: str) -> float | None:
    v = scores.get(key)
    return None if v is None else _num(v, f"{where}.{key}")


def _tie(raw: Any, identify: tuple[str, ...], true_parameters: dict[str, float]) -> dict[str, str]:
    """The ``tie`` block: ``{follower: leader}``, both identified, a leader never itself a follower, and
    equal hidden values (a tie states that the two are one physical parameter).

    Raises:
        ConfigError: not a mapping, a name not in ``identify``, a chain, or different hidden values.
    """
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ConfigError(f"tie must map a follower parameter to its leader, got {type(raw).__name__}")
    tied = {str(k): str(v) for k, v in raw.items()}
    for follower, leader in tied.items():
        for name in (follower, leader):
            if name not in identify:
                raise ConfigError(f"tie.{follower}: {name!r} is not identified (identify: {list(identify)})")
        if leader in tied or follower == leader:
            raise ConfigError(f"tie.{follower}: leader {leader!r} is itself tied; tie every follower to one leader")
        if true_parameters[follower] != true_parameters[leader]:
            raise ConfigError(f"tie.{follower}: hidden values differ ({true_parameters[follower]} against "
                              f"{leader} {true_parameters[leader]}); tied parameters are one value")
    return tied


def build_task(doc: dict, path: Path | None = None) -> TaskSpec:
    """Build a TaskSpec from a parsed task document.

    Args:
        doc: the mapping (schema in the module docstring).
        path: the file it came from (scene files are resolved relative to it), or None.

    Raises:
        ConfigError: an unknown or missing key (dotted), a bad value, a scene error, a reference outside
            the action bounds.
    """
    d = _keys(doc, "<task>", _TOP)
    if d["format"] != TASK_FORMAT or d["version"] != TASK_VERSION:
        raise ConfigError(f"format/version must be {TASK_FORMAT}/{TASK_VERSION}, got {d['format']!r}/{d['version']!r}")
    kind = d["kind"]
    if kind not in ("manipulation", "inverse"):
        raise ConfigError(f"kind must be manipulation|inverse, got {kind!r}")
    horizon = _num(d["horizon"], "horizon", positive=True, integer=True)
    scene = _scene(d["scene"], path.parent if path else None, "scene")
    identify = tuple(str(v) for v in (d.get("identify") or []))
    scene["task"] = {"type": kind, "horizon": horizon, **({"identify": list(identify)} if identify else {})}
    model = build_task_scene(copy.deepcopy(scene))  # validates the scene and the identified names
    layout, high = _actions(d["actions"], "actions")
    for eff, k in layout:
        if eff not in model.effectors:
            raise ConfigError(f"actions: unknown effector {eff!r}; the scene has {sorted(model.effectors)}")
        if k == "gripper" and model.effectors[eff].finger_sign is None:
            raise ConfigError(f"actions: effector {eff!r} has no fingers (not a gripper)")
    cma = _keys(d["cma"], "cma", _CMA)
    inf = _keys(d.get("infeasible") or {}, "infeasible", _INFEASIBLE)
    infeasible = Infeasibility(
        max_force_N=None if inf.get("max_force_N", 10.0) is None else _num(inf.get("max_force_N", 10.0), "infeasible.max_force_N", True),
        min_contact_force_N=(None if inf.get("min_contact_force_N") is None
                             else _num(inf["min_contact_force_N"], "infeasible.min_contact_force_N", True)),
        contact_after_step=_num(inf.get("contact_after_step", 10), "infeasible.contact_after_step", integer=True),
        contact_effectors=tuple(str(v) for v in inf.get("contact_effectors", []) or []),
    )
    for eff in infeasible.contact_effectors:
        if eff not in model.effectors:
            raise ConfigError(f"infeasible.contact_effectors: unknown effector {eff!r}")
    true_parameters = {name: model.get_parameter(name) for name in identify}  # default: the scene's values
    for name, value in (d.get("true_parameters") or {}).items():
        model.get_parameter(str(name))
        true_parameters[str(name)] = _num(value, f"true_parameters.{name}")
    tied = _tie(d.get("tie"), identify, true_parameters)
    scores = d.get("scores") or {}
    _keys(scores, "scores", {"human": False, "oracle": False, "success": False})
    reference = _reference(d["reference"], layout, horizon, "reference") if d.get("reference") is not None else None
    holder: dict[str, TaskSpec] = {}

    def reference_final():
        task = holder["task"]
        ep = TaskEpisode(task, task.true_parameters or None)
        for row in task.reference_actions:
            if ep.step(row) is None or ep.infeasible is not None:
                raise ConfigError(f"task {task.name}: its reference trajectory is infeasible ({ep.infeasible}); "
                                  "the reward's reference state cannot be computed")
        return ep.sim.state

    cma_start = str(cma.get("start", "zero"))
    if cma_start not in CMA_STARTS:
        raise ConfigError(f"cma.start must be one of {CMA_STARTS}, got {cma.get('start')!r}")
    if cma_start == "reference" and reference is None:
        raise ConfigError("cma.start: 'reference' needs the task's reference trajectory (key reference)")
    rw = _keys(d["reward"], "reward", {"name": True, "params": True})
    reward = build_reward(str(rw["name"]), rw["params"], "reward", reference_final if reference is not None else None)
    task = TaskSpec(
        name=str(d["name"]), kind=kind, scene=scene, horizon=horizon, dt=float(model.meta["dt"]), action_layout=layout,
        action_low=-high, action_high=high.copy(),
        control_points=_num(cma["control_points"], "cma.control_points", True, True),
        cma_sigma=_num(cma["sigma"], "cma.sigma", True), cma_population=_num(cma["population"], "cma.population", True, True),
        cma_generations=_num(cma["generations"], "cma.generations", True, True), cma_start=cma_start, reward=reward,
        success_score=_optional_score(scores, "success", "scores"), human_score=_optional_score(scores, "human", "scores"),
        oracle_score=_optional_score(scores, "oracle", "scores"), reference_actions=reference, identify=identify,
        source=str(d["source"]), reward_name=str(rw["name"]), reward_units=REWARD_UNITS[str(rw["name"])],
        infeasible=infeasible, true_parameters=true_parameters, tied=tied, path=None if path is None else str(path),
    )
    if reference is not None:
        task.check_actions(reference)
    holder["task"] = task
    return task


def load_task(name_or_path: str | Path, tasks_dir: Path | None = None) -> TaskSpec:
    """Load a task by name (``"lifting"``, a file under ``config/tasks``) or by path.

    Raises:
        ConfigError: unknown name, unreadable file, or any error of :func:`build_task` (prefixed with
            the file name).
    """
    p = Path(name_or_path)
    if p.suffix not in (".yaml", ".yml"):
        p = (tasks_dir or default_tasks_dir()) / f"{str(name_or_path).lower().replace('-', '_')}.yaml"
        if not p.is_file():
            raise ConfigError(f"unknown task {name_or_path!r}; known: {task_names()}")
    try:
        doc = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{p}: cannot read task file ({err})") from err
    try:
        return build_task(doc, p)
    except ConfigError as err:
        raise ConfigError(f"{p}: {err}") from err
