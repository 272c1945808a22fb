"""Tack bonds of a lift_fold: adhesive point bonds between card vertices and the gel's contact layer.

The reference world's tack (README of the reference set): adhesive point bonds of 0.25 N each,
``solref`` (0.005, 1.0), formed at ``t_tack_on``, broken at the peel ``t_tack_off`` or when a
bond's force exceeds its strength. Here each bond is a MuJoCo ``connect`` equality between a card
vertex under the gel footprint (at tack time) and the nearest vertex of the gel's bottom layer,
re-anchored at the pair's relative position when it forms.

Softness: MuJoCo's soft constraint lets through ``(1 - d)`` of the unconstrained acceleration ``a0``
of its row (``a1 = (1 - d) a0 + d a_ref``, ``a_ref = -b v - k r``, ``k = d / (d_max^2 tau^2 zeta^2)``
from ``solref`` (tau, zeta) and ``solimp``; MuJoCo documentation, "Computation: soft
constraints"), with the regulariser ``R = (1 - d) / d * A_hat``, ``A_hat`` the row's inverse mass
from the bodies' bare masses. At rest (``a1 = 0``) the row then acts as a spring of stiffness
``K = k / R = d k m_hat / (1 - d)``, which for ``d_min = d_max = d`` is ``m_hat / ((1 - d) tau^2 zeta^2)``,
``m_hat = 1 / (1/m_card + 1/m_gel)`` (the vertices' bare masses, about 4.6 and 4.9 mg). With MuJoCo's
default ``solimp`` (d 0.9-0.95) that is about 1-2 N/m: the card slides out of such bonds and stays
a straight ramp on a fold-back; with ``d`` near 1 the bond is rigid and the card buckles into an
arch as soon as the fold moves back. The reference's bonds are neither: in its three lift-folds
the tacked patch lags the gel by 4.7-12.4 mm in x during the hold while the gel is pulled by
0.52-0.71 N (``BOND_STIFFNESS_N_PER_M``). So each bond's ``solimp`` gets the ``d`` that makes it
a spring of that stiffness (:func:`bond_impedance`); ``solref`` stays the reference's, so the
bond's damping and drift correction are the reference's.

Pure numpy except :func:`bond_rows` and :func:`bond_forces`, which read a ``mujoco.MjData``.
"""

from __future__ import annotations

from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np

BOND_STIFFNESS_N_PER_M = 8.3
"""Stiffness of one tack bond at rest, N/m: the tangential pull on the gel in the hold divided by the
bonds' count and the tacked patch's mean lag behind the gel, in the reference's lift-folds:
plastic_s102 0.574 N / (12 x 4.65 mm) = 10.3, nominal_s109 0.521 N / (12 x 6.0 mm) = 7.2,
damped_s104 0.714 N / (8 x 12.3 mm) = 7.3; their mean. Leave-one-out: the mean of the other two
is within 30 % of each (7.25 against 10.3, 8.8 against 7.2, 8.75 against 7.3)."""


def bond_impedance(m_card: float, m_gel: float, stiffness: float, solref: Sequence[float]) -> float:
    """The impedance ``d`` (solimp ``d_min = d_max``) that makes a connect bond a spring of ``stiffness`` at rest.

    ``K = m_hat / ((1 - d) tau^2 zeta^2)`` (module docstring) solved for ``d``.

    Args:
        m_card, m_gel: bare masses of the two bonded bodies (kg, > 0).
        stiffness: the bond's stiffness at rest (N/m, > 0).
        solref: (timeconst tau s, dampratio zeta) of the bond, both > 0.

    Raises:
        ValueError: a non-positive input, or a stiffness below ``m_hat / (tau zeta)^2`` (no ``d`` in (0, 1)).
    """
    tau, zeta = float(solref[0]), float(solref[1])
    if min(m_card, m_gel, stiffness, tau, zeta) <= 0.0:
        raise ValueError(f"masses, stiffness and solref must be positive, got {m_card}, {m_gel}, {stiffness}, {solref}")
    m_hat = 1.0 / (1.0 / m_card + 1.0 / m_gel)
    one_minus_d = m_hat / (stiffness * tau * tau * zeta * zeta)
    if not one_minus_d < 1.0:
        raise ValueError(f"a bond of {stiffness} N/m between {m_hat:.3g} kg is softer than any impedance gives")
    return 1.0 - one_minus_d


def bond_solimp(d: float) -> tuple[float, float, float, float, float]:
    """solimp with the impedance ``d`` at every violation (width, midpoint and power then do not matter)."""
    return (d, d, 1.0e-4, 0.5, 2.0)


def bond_stiffness(m_card: float, m_gel: float, d: float, solref: Sequence[float]) -> float:
    """The stiffness at rest (N/m) of a connect bond of impedance ``d`` (``d_min = d_max``) between bare masses (kg)."""
    m_hat = 1.0 / (1.0 / m_card + 1.0 / m_gel)
    return m_hat / ((1.0 - d) * float(solref[0]) ** 2 * float(solref[1]) ** 2)


class TackCandidate(NamedTuple):
    """A possible adhesive bond: card grid vertex (ix, iy) and gel bottom vertex index (into the bottom layer,
    y outer, x inner, as ``mjcf.gel_bottom_rest``)."""

    card_ix: int
    card_iy: int
    gel_bottom: int


def tack_candidates(scene: Mapping[str, Any], start_xy: Sequence[float],
                    gel_rest_xy: np.ndarray) -> list[TackCandidate]:
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


BOND_WRENCH_CONVENTIONS = ("reference", "physical")
"""How the bonds enter the recorded wrench. ``physical``: their force ON the gel (``-f``), as the
contacts' force. ``reference``: the force on the card (``+f``), which is what the reference's
lift-folds record: in the hold their F_x is -0.52 to -0.71 N and F_z -0.25 to -0.66 N (sensor frame)
while their markers shear +47 to +146 um along x (sensor frame, the direction of the force on the
gel's face), and our physical bonds give +F_x, +F_z of similar size with the same +x shear; in the
reference's press-slides force and shear agree (cos 1.00)."""


def bond_wrench(force_on_card: np.ndarray, at: np.ndarray, active: np.ndarray, origin: Sequence[float],
                convention: str = "physical") -> np.ndarray:
    """Force of the active bonds in the wrench and its torque about ``origin`` (world, N and N m, shape (6,)).

    A bond acts with ``+f`` on the card vertex and ``-f`` on the gel at ``at`` (the gel vertex, m, shape
    (n_bonds, 3)); ``force_on_card`` is ``f`` (N, shape (n_bonds, 3)). ``convention`` (one of
    ``BOND_WRENCH_CONVENTIONS``): ``physical`` gives ``-f`` (the force ON the gel), ``reference`` ``+f``.

    Raises:
        ValueError: an unknown convention.
    """
    if convention not in BOND_WRENCH_CONVENTIONS:
        raise ValueError(f"unknown bond wrench convention {convention!r}; one of {BOND_WRENCH_CONVENTIONS}")
    sign = -1.0 if convention == "physical" else 1.0
    active = np.asarray(active, dtype=bool)
    f = sign * np.asarray(force_on_card, dtype=float)[active]
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
