"""Reward bindings: a task file's ``reward: {name, params}`` turned into ``reward(model, state) -> float``.

Each binding validates its parameters (errors name the task file's key) and wraps one pure function
of :mod:`sim_core.tasks.rewards`. Registered names and parameters:

| name | params | value | unit |
|---|---|---|---|
| ``sheet_target`` | ``body`` | ``-sum_i |x_i - x_i^ref|^2`` over the body, ``x^ref`` = the body at the end of the task's reference trajectory | m^2 |
| ``crease_rest_angle`` | ``body, weights: {column: w}`` | ``-sum_c w_c sum theta_bar`` (:func:`~sim_core.tasks.rewards.folding_reward`) | rad |
| ``crease_fold`` | ``body, column, angle_weight`` | ``sum (theta_bar + w theta)`` on one crease | rad |
| ``body_displacement`` | ``body, offset: [dx dy dz]`` | ``-sum_i |x_i - x0_i - d|^2`` | m^2 |
| ``coordinate_sum`` | ``terms: [{body, axis: x/y/z, weight}]`` | ``sum w sum_i x_i[axis]`` | m |
| ``observed_motion`` | ``bodies: [names]`` | ``-sum_i |x_i - x_i^obs|^2`` over the bodies, ``x^obs`` = the end of the reference trajectory at the task's ``true_parameters`` | m^2 |

Dihedral angles enter the crease rewards in ThinShellLab's sign convention,
``theta_ThinShellLab = -theta`` (:data:`THINSHELLLAB_ANGLE_SIGN`; ours, :func:`~sim_core.energies.hinge_bending.reference.dihedral_angle`,
is positive when the wings fold towards the sheet normal): with it the human-designed motions of
Folding-L, Folding-U and Pick-Folding score with the signs of Table A.

``sheet_target`` and ``observed_motion`` need the final state of the reference trajectory; it is
computed on first use by the ``reference_final`` callable the task loader passes in, and cached.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from sim_core.energies.hinge_bending.reference import dihedral_angle
from sim_core.errors import ConfigError
from sim_core.model import Model
from sim_core.state import State
from sim_core.tasks import rewards

RewardFn = Callable[[Model, State], float]
THINSHELLLAB_ANGLE_SIGN = -1.0
ReferenceFinal = Callable[[], State]

REWARD_UNITS = {"sheet_target": "m^2", "crease_rest_angle": "rad", "crease_fold": "rad", "body_displacement": "m^2",
                "coordinate_sum": "m", "observed_motion": "m^2"}
_PARAMS = {"sheet_target": {"body"}, "crease_rest_angle": {"body", "weights"},
           "crease_fold": {"body", "column", "angle_weight"}, "body_displacement": {"body", "offset"},
           "coordinate_sum": {"terms"}, "observed_motion": {"bodies"}}
_AXES = {"x": 0, "y": 1, "z": 2}


def _body_x(model: Model, state: State, name: str) -> np.ndarray:
    b = model.bodies[name]
    return state.x[b.vertex_start:b.vertex_stop]


def _initial_x(model: Model, name: str) -> np.ndarray:
    b = model.bodies[name]
    x0 = model.x_rest if model.initial_x is None else model.initial_x
    return x0[b.vertex_start:b.vertex_stop]


def _sheet_hinges(model: Model, name: str, where: str) -> tuple[np.ndarray, int]:
    b = model.bodies[name]
    if b.hinges is None or b.grid_shape is None:
        raise ConfigError(f"{where}: body {name!r} is not a grid sheet")
    return b.hinges - b.vertex_start, int(b.grid_shape[0])


def build_reward(name: str, params: dict[str, Any], where: str, reference_final: ReferenceFinal | None = None) -> RewardFn:
    """The reward function of a task file's ``reward`` block.

    Args:
        name: a registered name (table in the module docstring).
        params: its parameters.
        where: the key path for error messages (``"tasks/lifting.yaml: reward"``).
        reference_final: returns the final state of the task's reference trajectory (at the true
            parameters for inverse tasks); needed by ``sheet_target`` and ``observed_motion``.

    Returns:
        ``reward(model, state) -> float`` (larger is better; unit ``REWARD_UNITS[name]``). Body names are
        checked against the model on first call.

    Raises:
        ConfigError: unknown name, missing or unknown parameter, bad value.
    """
    if name not in _PARAMS:
        raise ConfigError(f"{where}.name: unknown reward {name!r}; known: {sorted(_PARAMS)}")
    if not isinstance(params, dict):
        raise ConfigError(f"{where}.params must be a mapping, got {type(params).__name__}")
    unknown, missing = set(params) - _PARAMS[name], _PARAMS[name] - set(params)
    if unknown or missing:
        raise ConfigError(f"{where}.params: reward {name} takes {sorted(_PARAMS[name])}; "
                          f"unknown {sorted(unknown)}, missing {sorted(missing)}")
    if name in ("sheet_target", "observed_motion") and reference_final is None:
        raise ConfigError(f"{where}: reward {name} needs the task's reference trajectory (key reference)")
    cache: dict[str, State] = {}

    def reference() -> State:
        if "state" not in cache:
            cache["state"] = reference_final()
        return cache["state"]

    if name == "sheet_target":
        body = str(params["body"])

        def reward(model: Model, state: State) -> float:
            return rewards.forming_reward(_body_x(model, state, body), _body_x(model, reference(), body))
        return reward
    if name == "observed_motion":
        bodies = params["bodies"]
        if not isinstance(bodies, list) or not bodies:
            raise ConfigError(f"{where}.params.bodies must be a non-empty list of body names")

        def reward(model: Model, state: State) -> float:
            return float(sum(rewards.forming_reward(_body_x(model, state, b), _body_x(model, reference(), b))
                             for b in bodies))
        return reward
    if name == "crease_rest_angle":
        body = str(params["body"])
        w = params["weights"]
        if not isinstance(w, dict) or not w:
            raise ConfigError(f"{where}.params.weights must map grid columns to weights")
        weights = {int(k): float(v) for k, v in w.items()}

        def reward(model: Model, state: State) -> float:
            hinges, nx = _sheet_hinges(model, body, where)
            return rewards.folding_reward(THINSHELLLAB_ANGLE_SIGN * state.hinge_theta_bar[body], hinges, nx, weights)
        return reward
    if name == "crease_fold":
        body, column, aw = str(params["body"]), int(params["column"]), float(params["angle_weight"])

        def reward(model: Model, state: State) -> float:
            hinges, nx = _sheet_hinges(model, body, where)
            theta = dihedral_angle(_body_x(model, state, body)[hinges])
            return rewards.crease_fold_reward(THINSHELLLAB_ANGLE_SIGN * state.hinge_theta_bar[body],
                                              THINSHELLLAB_ANGLE_SIGN * theta, hinges, nx, column, aw)
        return reward
    if name == "body_displacement":
        body = str(params["body"])
        offset = np.asarray(params["offset"], dtype=float)
        if offset.shape != (3,) or not np.all(np.isfinite(offset)):
            raise ConfigError(f"{where}.params.offset must be 3 finite numbers (m), got {params['offset']!r}")

        def reward(model: Model, state: State) -> float:
            return rewards.body_displacement_reward(_body_x(model, state, body), _initial_x(model, body), offset)
        return reward
    # coordinate_sum
    terms = params["terms"]
    if not isinstance(terms, list) or not terms:
        raise ConfigError(f"{where}.params.terms must be a non-empty list of {{body, axis, weight}}")
    parsed = []
    for i, t in enumerate(terms):
        if not isinstance(t, dict) or set(t) != {"body", "axis", "weight"} or t["axis"] not in _AXES:
            raise ConfigError(f"{where}.params.terms[{i}] must be {{body, axis: x|y|z, weight}}, got {t!r}")
        parsed.append((str(t["body"]), _AXES[t["axis"]], float(t["weight"])))

    def reward(model: Model, state: State) -> float:
        return rewards.coordinate_sum_reward([(_body_x(model, state, b), ax, w) for b, ax, w in parsed])
    return reward
