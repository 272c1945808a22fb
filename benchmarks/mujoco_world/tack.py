"""Tack bonds of a lift_fold: adhesive point bonds between card vertices and the gel's contact layer.

The reference world's tack (README of the reference set): adhesive point bonds of 0.25 N each,
``solref`` (0.005, 1.0), formed at ``t_tack_on``, broken at the peel ``t_tack_off`` or when a
bond's force exceeds its strength. Here each bond is a MuJoCo ``connect`` equality between a card
vertex under the gel footprint (at tack time) and the nearest vertex of the gel's bottom layer,
re-anchored at the pair's relative position when it forms.

Softness: MuJoCo's soft constraint lets through ``(1 - d)`` of the unconstrained acceleration ``a0``
of its row (``a1 = (1 - d) a0 + d a_ref``, MuJoCo documentation, "Computation: soft constraints"),
``d`` from ``solimp``; ``a_ref = -b v - k r`` with ``k = 1 / (d_max^2 tau^2 zeta^2)`` from ``solref``
(tau, zeta). A card vertex weighs about 4.6 mg, so the card's elastic pull gives ``a0`` of order
5e4 m/s^2, and a bond with MuJoCo's default ``d`` of 0.9-0.95 settles at ``r = (1 - d) a0 / (d k)``,
centimetres (it does not hold the card). With ``BOND_SOLIMP``'s ``d = 0.9999`` the same pull leaves
about 0.1 mm, and the bond force is the force that holds the pair together; ``solref`` still sets
how fast a drift is corrected.

Pure numpy except :func:`bond_rows` and :func:`bond_forces`, which read a ``mujoco.MjData``.
"""

from __future__ import annotations

from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np

BOND_SOLIMP = (0.9999, 0.9999, 1.0e-4, 0.5, 2.0)
"""solimp of the tack bonds: impedance d = 0.9999 at every violation (see the module docstring)."""


class TackCandidate(NamedTuple):
    """A possible adhesive bond: card grid vertex (ix, iy) and gel bottom vertex index (into the bottom layer,
    y outer, x inner, as ``mjcf.gel_bottom_rest``)."""

    card_ix: int
    card_iy: int
    gel_bottom: int


def tack_candidates(scene: Mapping[str, Any], start_xy: Sequence[float], gel_rest_xy: np.ndarray) -> list[TackCandidate]:
    """Card vertices under the gel footprint at ``start_xy`` (m, world) and the nearest gel bottom vertex of each.

    Args:
        scene: scene.yaml (v1) as a dict (sheet size / resolution / origin, tactile gel_size).
        start_xy: the effector's (x, y) over the card (m).
        gel_rest_xy: gel bottom-layer rest positions in the effector frame (m, shape (n_bottom, 2)).

    Returns:
        The candidates, card x index outer, y inner.
    """
    nx, ny = scene["sheet"]["resolution"]
    sx, sy = scene["sheet"]["size"]
    ox, oy, _ = scene["sheet"]["origin"]
    gx, gy, _ = scene["sensors"]["tactile"]["gel_size"]
    out = []
    for ix in range(nx):
        for iy in range(ny):
            p = np.array([ox + ix * sx / (nx - 1), oy + iy * sy / (ny - 1)]) - np.asarray(start_xy, dtype=float)
            if abs(p[0]) <= gx / 2 and abs(p[1]) <= gy / 2:
                out.append(TackCandidate(ix, iy, int(np.argmin(np.linalg.norm(gel_rest_xy - p, axis=1)))))
    return out


def under_footprint(card_xy: np.ndarray, ee_xy: Sequence[float], gel_size_xy: Sequence[float]) -> np.ndarray:
    """Which card points (m, shape (n, 2)) lie under the gel footprint centred at ``ee_xy`` (m): bool, shape (n,)."""
    d = np.abs(np.asarray(card_xy, dtype=float) - np.asarray(ee_xy, dtype=float))
    return (d[:, 0] <= gel_size_xy[0] / 2) & (d[:, 1] <= gel_size_xy[1] / 2)


def bonds_to_break(force_on_card: np.ndarray, active: np.ndarray, strength_N: float) -> np.ndarray:
    """Active bonds whose force exceeds their strength: bool, shape (n_bonds,).

    Args:
        force_on_card: each bond's force on its card vertex (N, world, shape (n_bonds, 3)).
        active: which bonds are active (bool, shape (n_bonds,)).
        strength_N: a bond's strength (N, > 0): it breaks when the norm of its force exceeds it.

    Raises:
        ValueError: a non-positive strength or mismatched shapes.
    """
    if not strength_N > 0.0:
        raise ValueError(f"bond strength must be positive, got {strength_N} N")
    f = np.asarray(force_on_card, dtype=float)
    active = np.asarray(active, dtype=bool)
    if f.shape != (active.size, 3):
        raise ValueError(f"force_on_card has shape {f.shape}, expected ({active.size}, 3)")
    return active & (np.linalg.norm(f, axis=1) > strength_N)


def bond_wrench(force_on_card: np.ndarray, at: np.ndarray, active: np.ndarray, origin: Sequence[float]) -> np.ndarray:
    """Force of the active bonds ON the gel and its torque about ``origin`` (world, N and N m, shape (6,)).

    A bond acts with ``+f`` on the card vertex and ``-f`` on the gel at ``at`` (the gel vertex, m, shape
    (n_bonds, 3)); ``force_on_card`` is ``f`` (N, shape (n_bonds, 3)).
    """
    active = np.asarray(active, dtype=bool)
    f = -np.asarray(force_on_card, dtype=float)[active]
    r = np.asarray(at, dtype=float)[active] - np.asarray(origin, dtype=float)
    return np.r_[f.sum(axis=0), np.cross(r, f).sum(axis=0)]


def bond_rows(data: Any, n_bonds: int, mujoco: Any) -> list[np.ndarray]:
    """The constraint rows (indices into ``data.efc_*``) of each active bond (equality ids 0..n_bonds-1);
    an inactive bond has none."""
    nefc = data.nefc
    eq = np.nonzero(data.efc_type[:nefc] == mujoco.mjtConstraint.mjCNSTR_EQUALITY)[0]
    ids = data.efc_id[eq]
    return [eq[ids == k] for k in range(n_bonds)]


def bond_forces(data: Any, rows: list[np.ndarray]) -> np.ndarray:
    """Each bond's force on its card vertex (N, world, shape (n_bonds, 3)); zero for a bond without rows.

    A ``connect`` equality's residual is ``p1 - p2`` (card vertex minus gel anchor) in world, its
    Jacobian ``d(p1 - p2)/dq``, so its three multipliers act as ``+f`` on body 1 (the card).
    """
    out = np.zeros((len(rows), 3))
    for k, r in enumerate(rows):
        if r.size == 3:
            out[k] = data.efc_force[r]
    return out
