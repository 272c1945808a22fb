"""Task rewards as pure functions of the state (ThinShellLab's task definitions, public code).

* Forming: ``-sum_i |x_i - x_i^target|^2`` over the sheet's vertices (m^2).
* Folding: the plastic rest angles of two creases, ``-sum_c w_c sum_{hinges on c} theta_bar``
  (rad); Folding-L and Folding-U use opposite weights on the creases at grid columns 7 and 8.
* Lifting: ``-sum_i |x_i - x0_i - d|^2`` over the block's vertices (m^2).
* Separating / Following: weighted sums of x coordinates over bodies (m).
* Pick-Folding: rest angle plus 0.01 x the current angle along one crease (rad).
* Inverse tasks: ``-sum_i |x_i - x_i^obs|^2`` against the observed final state (m^2, ``forming_reward``).

The bindings of these functions to a task's model and state are in :mod:`sim_core.tasks.task_rewards`.
"""

from __future__ import annotations

import numpy as np

from sim_core.errors import ConfigError


def forming_reward(sheet_x: np.ndarray, target_x: np.ndarray) -> float:
    """Negative squared distance of the sheet to its target shape.

    Args:
        sheet_x: sheet vertex positions in m, shape ``(p, 3)``.
        target_x: target positions in m, shape ``(p, 3)``.

    Returns:
        ``-sum |sheet_x - target_x|^2`` in m^2 (0 at the target, negative elsewhere).

    Raises:
        ConfigError: shapes differ.
    """
    a, b = np.asarray(sheet_x, dtype=float), np.asarray(target_x, dtype=float)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
        raise ConfigError(f"forming_reward: sheet {a.shape} and target {b.shape} must both be (p, 3)")
    return 0.0 - float(np.sum((a - b) ** 2))  # 0.0 - s: no negative zero at the target


def crease_columns(hinges_local: np.ndarray, nx: int) -> np.ndarray:
    """Grid column of each hinge whose edge runs along y (both edge vertices in one column), else -1.

    Args:
        hinges_local: ``[e0, e1, opp0, opp1]`` indices relative to the sheet, shape ``(h, 4)``; vertex
            ``(ix, iy)`` is ``iy * nx + ix``.
        nx: vertices along x.

    Returns:
        column per hinge, shape ``(h,)``, int64.
    """
    h = np.asarray(hinges_local, dtype=np.int64)
    c0, c1 = h[:, 0] % nx, h[:, 1] % nx
    return np.where(c0 == c1, c0, -1)


def folding_reward(hinge_theta_bar: np.ndarray, hinges_local: np.ndarray, nx: int,
                   crease_weights: dict[int, float]) -> float:
    """Weighted sum of the rest angles on grid creases (ThinShellLab Folding).

    Args:
        hinge_theta_bar: rest dihedral angles in rad, shape ``(h,)`` (``State.hinge_theta_bar[sheet]``).
        hinges_local: hinges relative to the sheet, shape ``(h, 4)``.
        nx: vertices along x.
        crease_weights: grid column -> weight w_c (e.g. ``{7: 1.0, 8: -1.0}``).

    Returns:
        ``-sum_c w_c sum_{hinges on column c} theta_bar`` in rad.

    Raises:
        ConfigError: shapes differ or a column has no crease hinge.
    """
    tb = np.asarray(hinge_theta_bar, dtype=float)
    cols = crease_columns(hinges_local, nx)
    if tb.shape != cols.shape:
        raise ConfigError(f"folding_reward: {tb.shape[0]} rest angles for {cols.shape[0]} hinges")
    total = 0.0
    for column, w in crease_weights.items():
        on = cols == int(column)
        if not on.any():
            raise ConfigError(f"folding_reward: grid column {column} has no crease hinge (nx = {nx})")
        total -= float(w) * float(tb[on].sum())
    return total


def body_displacement_reward(body_x: np.ndarray, body_x0: np.ndarray, offset: np.ndarray) -> float:
    """Negative squared distance of a body to its initial position moved by ``offset``
    (ThinShellLab Lifting: the block carried 12 mm along -x and -y).

    Args:
        body_x: the body's vertex positions in m, shape ``(p, 3)``.
        body_x0: the same vertices at the initial state, m, shape ``(p, 3)``.
        offset: the wanted displacement in m, shape ``(3,)``.

    Returns:
        ``-sum_i |x_i - x0_i - offset|^2`` in m^2.

    Raises:
        ConfigError: shapes differ.
    """
    return forming_reward(body_x, np.asarray(body_x0, dtype=float) + np.asarray(offset, dtype=float).reshape(1, 3))


def coordinate_sum_reward(terms: list[tuple[np.ndarray, int, float]]) -> float:
    """Weighted sums of one coordinate over bodies (ThinShellLab Separating / Following).

    Args:
        terms: ``(body_x, axis, weight)``: a body's positions in m (shape ``(p, 3)``), the axis 0/1/2
            and a weight.

    Returns:
        ``sum_terms weight * sum_i body_x[i, axis]`` in m.
    """
    return float(sum(float(w) * float(np.sum(np.asarray(x, dtype=float)[:, int(axis)])) for x, axis, w in terms))


def crease_fold_reward(hinge_theta_bar: np.ndarray, hinge_theta: np.ndarray, hinges_local: np.ndarray, nx: int,
                       column: int, angle_weight: float) -> float:
    """Rest angle plus a fraction of the current angle along one grid crease (ThinShellLab Pick-Folding).

    Args:
        hinge_theta_bar: rest dihedral angles in rad, shape ``(h,)``.
        hinge_theta: current dihedral angles in rad, shape ``(h,)``.
        hinges_local: hinges relative to the sheet, shape ``(h, 4)``.
        nx: vertices along x.
        column: the crease's grid column.
        angle_weight: weight of the current angle (the original: 0.01).

    Returns:
        ``sum_{hinges on the column} (theta_bar + angle_weight theta)`` in rad.

    Raises:
        ConfigError: the column has no crease hinge or shapes differ.
    """
    cols = crease_columns(hinges_local, nx)
    tb, th = np.asarray(hinge_theta_bar, dtype=float), np.asarray(hinge_theta, dtype=float)
    if tb.shape != cols.shape or th.shape != cols.shape:
        raise ConfigError(f"crease_fold_reward: {tb.shape} / {th.shape} angles for {cols.shape[0]} hinges")
    on = cols == int(column)
    if not on.any():
        raise ConfigError(f"crease_fold_reward: grid column {column} has no crease hinge (nx = {nx})")
    return float(tb[on].sum() + float(angle_weight) * th[on].sum())
