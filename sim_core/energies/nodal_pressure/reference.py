"""Average-nodal-pressure Stable Neo-Hookean tetrahedra: a gel element that locks far less at nu -> 0.5.

Linear tets lock when nearly incompressible: each tet's volume is penalised on its own, so a mesh has
about as many volume constraints as vertices and bends too little (the four-layer default gel is 1.11x /
1.13x too stiff in compression at nu = 0.45, tests/sim_core/test_known_answers_gel_compression.py). The
average nodal pressure tetrahedron (Bonet and Burton, "A simple average nodal pressure tetrahedral element
for incompressible and nearly incompressible dynamic explicit applications", Commun. Numer. Meth. Eng. 14,
437-449, 1998; Bonet, Marriott, Hassan, "An averaged nodal deformation gradient linear
tetrahedral element for large strain explicit dynamic applications", Commun. Numer. Meth. Eng. 17,
551-561, 2001) keeps the shear per tet and takes the volume change per *node*::

    E(x) = sum_t V_t psi_s(F_t) + sum_a V_a U(J_a),
    V_a  = sum_{t ∋ a} V_t / 4,   v_a(x) = sum_{t ∋ a} v_t(x) / 4,   J_a = v_a / V_a,
    U(J) = kappa / 2 (J - 1)^2,

with ``v_t = V_t det F_t`` the current tet volume: one volume constraint per vertex instead of one per tet (about
five times fewer on a tet mesh). Measured on the default gel (nu 0.45, 240 vertices): 1.074x the converged layer
in compression where the linear tets give 1.112x; at nu 0.3 both give 1.02x, so about half of what nu 0.45 adds
remains on a mesh this coarse (docs/known_answers.md).

The split of Stable Neo-Hookean (Smith, de Goes, Kim 2018, eq. 14, the gel's law in
:mod:`sim_core.energies.neohookean.reference`) used here: with ``alpha = 1 + 3 mu / (4 lam)``,
``lam / 2 (J - alpha)^2 = lam / 2 (J - 1)^2 - 3 mu / 4 (J - 1) + const``, so for every ``lam_s``::

    psi_SNH(F; mu, lam) = psi_SNH(F; mu, lam_s) + (lam - lam_s) / 2 (J - 1)^2 + const.

The shear part ``psi_s`` is Stable Neo-Hookean with ``lam_s = mu / 8``, and ``kappa = lam - mu / 8``.
This ``lam_s`` is the one whose linearisation has zero bulk modulus (``lam_LE,s = lam_s - 5 mu / 8 =
-2/3 mu_LE``: ``psi_s`` is purely deviatoric at small strain, its 9x9 ``d2psi_s/dF2`` at rest PSD with one
zero eigenvalue, the dilation), and ``kappa = lam_LE + 2/3 mu_LE`` is the small-strain bulk modulus
``E / (3 (1 - 2 nu))``. So under a uniform deformation (every ``J_a = J_t``) the element's energy *is*
Stable Neo-Hookean's with the same ``E``, ``nu`` at any strain (the patch test), and at small strain its
material is linear elasticity with ``E``, ``nu``.

Derivatives (``g_t = d v_t / dx = V_t cof(F_t) dF/dx``, ``b_a = d v_a / dx = sum_{t ∋ a} g_t / 4``):

- gradient: ``sum_t V_t (P_s(F_t) + p_t cof F_t) dF/dx`` with the tet's averaged pressure
  ``p_t = sum_{a ∈ t} U'(J_a) / 4`` (Bonet and Burton: the nodal pressures averaged back to the tet);
- Hessian: ``sum_t V_t (dF/dx)^T (d2psi_s/dF2 + p_t d2J/dF2) (dF/dx) + sum_a U''(J_a) / V_a b_a b_a^T``.
  The second sum couples every vertex of node ``a``'s tet ring (up to 15 vertices on the structured
  ``tet_box``; ``b_a`` is zero outside it): the Hessian's sparsity reaches the vertices two edges apart.

PSD projection, by construction: the per-tet 9x9 ``d2psi_s/dF2 + p_t d2J/dF2`` has Stable Neo-Hookean's
analytic eigensystem with ``p_t`` added to the ``lam (J - alpha)`` of every eigenvalue
(:meth:`~sim_core.energies.neohookean.reference.StableNeoHookean.d2psi_dF2_eigensystem`); its negative
eigenvalues are clamped (or flipped) and the result mapped by ``dF/dx`` (a congruence, PSD per tet). The
nodal term ``kappa / V_a b_a b_a^T`` is PSD as it is (``U'' = kappa > 0``). A sum of PSD blocks is PSD. At
rest ``p_t = 0`` and the projection changes nothing: the linear response is exact.

Two parts for the solver (:meth:`NodalPressureNeoHookean.parts`, read by
:meth:`sim_core.elastic.ElasticTerms.potentials`): the shear part is a plain :class:`StableNeoHookean` (with
``lam = lam_s``: the fused Stable Neo-Hookean kernel evaluates it on the Taichi backends) and
:class:`NodalVolume` the nodal term with its ``p_t d2J`` (NumPy). Their sum is the element's energy, gradient
and exact Hessian; projected apart, each is PSD (``p_t d2J/dF2`` alone clamped per tet), a PSD matrix no
tighter than the joint projection of :meth:`NodalPressureNeoHookean.hessian`.

Hessian blocks: one block per node over its ring (:attr:`NodalPressureNeoHookean.ring`, ``(nodes, m)``,
padded with the node itself where a ring has fewer than ``m`` vertices, those entries zero), holding the
node's ``b_a b_a^T`` term and the per-tet blocks of the tets whose first vertex it is (every vertex of a tet
lies in the ring of each of its vertices).
"""

from __future__ import annotations

import copy

import numpy as np

from sim_core.energies.base import BorrowedWorkspace, HessianBlocks, Projection
from sim_core.energies.neohookean.reference import StableNeoHookean, _snh_lame_derivatives


def nodal_pressure_moduli(mu: float, lam: float) -> tuple[float, float]:
    """``(lam_s, kappa)`` in Pa of the split of an SNH ``(mu, lam)``: ``lam_s = mu / 8`` (the shear part's,
    zero small-strain bulk modulus) and ``kappa = lam - mu / 8`` (the nodal volumetric part's)."""
    return mu / 8.0, lam - mu / 8.0


class NodalVolume(BorrowedWorkspace):
    """The nodal volumetric term ``sum_a V_a kappa / 2 (J_a - 1)^2`` of :class:`NodalPressureNeoHookean` as a
    potential of its own (module docstring): value, gradient, Hessian blocks over the vertex rings.

    Args:
        shear: the shear part, whose tets, rest volumes, ``dF/dx`` and deformation memo this term reads.
        kappa: bulk modulus in Pa, > 0.

    Attributes:
        nodes: the global vertices of the tets, sorted, ``(nodes,)``.
        node_rest_volume: ``V_a`` in m^3, ``(nodes,)``.
        ring: global vertices of each node's tet ring, ``(nodes, m)`` (the Hessian blocks' vertices), padded
            with the node itself.
    """

    parameter_names: tuple[str, ...] = ()

    def __init__(self, shear: StableNeoHookean, kappa: float) -> None:
        self.shear = shear
        self.kappa = float(kappa)
        self.tets, self.tet_rest_volume = shear.tets, shear.tet_rest_volume
        self.nodes, node_of = np.unique(self.tets, return_inverse=True)
        self._node_of = node_of.reshape(self.tets.shape)  # (k, 4) node index of each tet corner
        count = self.nodes.size
        self.node_rest_volume = np.bincount(self._node_of.ravel(), weights=np.repeat(self.tet_rest_volume / 4.0, 4),
                                            minlength=count)
        self._build_rings(count)

    def _build_rings(self, count: int) -> None:
        """:attr:`ring` and the scatter maps of the ring-vector ``b_a`` and of the per-tet blocks into it."""
        k = self.tets.shape[0]
        owner = np.repeat(self._node_of, 4, axis=1).ravel()  # (k 16): node a = corner i of tet t, for each j
        member = np.tile(self._node_of, (1, 4)).ravel()  # node of corner j
        pairs = np.unique(owner * count + member)
        a, b = np.divmod(pairs, count)
        size = np.bincount(a, minlength=count)
        m = int(size.max())
        start = np.concatenate([[0], np.cumsum(size)[:-1]])
        pos = np.arange(pairs.size) - start[a]
        ring_nodes = np.repeat(np.arange(count)[:, None], m, axis=1)  # padding: the node itself
        ring_nodes[a, pos] = b
        self.ring = self.nodes[ring_nodes]

        def ring_position(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
            return pos[np.searchsorted(pairs, rows * count + cols)]

        # b_a: corner j of tet t adds g_t[j] / 4 to b_a at a's ring position of corner j, for each corner a of t
        self._b_index = owner * m + ring_position(owner, member)  # (k 16,) flat (node, ring position)
        self._b_source = (np.repeat(np.arange(k), 16), np.tile(np.arange(4), 4 * k))  # (tet, corner j)
        # per-tet 12x12 blocks into the block of the tet's first corner
        first = np.repeat(self._node_of[:, :1], 4, axis=1)
        local = ring_position(first.ravel(), self._node_of.ravel()).reshape(k, 4)  # (k, 4)
        dof = (3 * local[:, :, None] + np.arange(3)).reshape(k, 12)
        w = 3 * m
        self._tet_slot = (self._node_of[:, :1, None] * w * w + dof[:, :, None] * w + dof[:, None, :]).ravel()

    def kinematics(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(F (k,3,3), cof F (k,3,3), J_a - 1 (nodes,), sum_{a in t} (J_a - 1) / 4 (k,))`` at ``x`` ``(n, 3)``
        (the last times ``kappa`` is the tet's averaged pressure ``p_t``)."""
        F = self.shear._deformation(np.asarray(x, dtype=float))
        _, J, cof = self.shear._invariants(F)
        v_change = np.bincount(self._node_of.ravel(), weights=np.repeat(self.tet_rest_volume * (J - 1.0) / 4.0, 4),
                               minlength=self.nodes.size)
        strain = v_change / self.node_rest_volume
        return F, cof, strain, strain[self._node_of].mean(axis=1)

    def ring_blocks(self, tet_blocks: np.ndarray, cof: np.ndarray) -> HessianBlocks:
        """The per-tet blocks ``(k, 12, 12)`` (N/m) placed in the ring blocks, plus ``kappa / V_a b_a b_a^T``."""
        count, m = self.ring.shape
        w = 3 * m
        blocks = np.bincount(self._tet_slot, weights=tet_blocks.ravel(), minlength=count * w * w).reshape(count, w, w)
        # g_t[j] = V_t cof(F_t) dF/dx_j, (k, 4, 3); b_a in ring coordinates, (nodes, m, 3)
        g = self.tet_rest_volume[:, None, None] * np.einsum("kij,kaj->kai", cof, self.shear.tet_dFdx)
        part = g[self._b_source] / 4.0
        b = np.stack([np.bincount(self._b_index, weights=part[:, d], minlength=count * m) for d in range(3)], axis=1)
        c = b.reshape(count, w) * np.sqrt(self.kappa / self.node_rest_volume)[:, None]
        for j in range(w):  # column by column: no (nodes, 3m, 3m) temporary (fresh pages cost more than the sums)
            blocks[:, :, j] += c * c[:, j:j + 1]
        return HessianBlocks(self.ring, blocks)

    def energy(self, x: np.ndarray) -> float:
        """``sum_a V_a kappa / 2 (J_a - 1)^2`` in J at ``x`` ``(n, 3)``."""
        strain = self.kinematics(x)[2]
        return 0.5 * self.kappa * float(np.dot(self.node_rest_volume, strain**2))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``: ``V_t p_t cof F_t dF/dx`` summed per vertex."""
        x = np.asarray(x, dtype=float)
        _, cof, _, p = self.kinematics(x)
        return self.shear._forces_from_pk1(x, (self.kappa * p)[:, None, None] * cof)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Ring blocks in N/m: ``V_t (dF/dx)^T p_t d2J/dF2 (dF/dx)`` per tet (its eigenvalues ``+-p_t sigma_k``
        clamped or flipped per ``projection``: the Stable Neo-Hookean eigensystem with ``mu = lam = 0``)
        plus ``kappa / V_a b_a b_a^T`` (PSD)."""
        F, cof, _, p = self.kinematics(x)
        pressure = self.kappa * p
        if projection == "none":
            return self.ring_blocks(_pressure_blocks(self.shear, F, pressure), cof)
        return self.ring_blocks(_mapped(self.shear, _pressure_only(self.shear).d2psi_dF2_projected(F, projection,
                                                                                                     pressure)), cof)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """No parameters of its own (:class:`NodalPressureNeoHookean` carries ``E``, ``nu``).

        Raises:
            KeyError: always.
        """
        raise KeyError(f"NodalVolume has no parameter {name!r}; the element's E and nu are NodalPressureNeoHookean's")


def _pressure_blocks(snh: StableNeoHookean, F: np.ndarray, pressure: np.ndarray) -> np.ndarray:
    """``V_t p_t d2J/dx2`` per tet, ``(k, 12, 12)`` N/m: the vertex block ``(a, b)`` is ``V_t p_t [F (g_a x g_b)]_x``
    (``d2J/dF_ij dF_kl = eps_ikm eps_jln F_mn`` contracted with ``g_a = dF/dx_a``; ``[w]_x`` the cross-product matrix,
    ``[w]_x[i, j] = -eps_ijm w_m``), as the fused Stable Neo-Hookean kernel forms it."""
    g = snh.tet_dFdx  # (k, 4, 3)
    k = g.shape[0]
    w = np.einsum("kmn,kabn->kabm", F, np.cross(g[:, :, None, :], g[:, None, :, :]))  # (k, 4, 4, 3)
    w *= (snh.tet_rest_volume * pressure)[:, None, None, None]
    H = np.zeros((k, 4, 3, 4, 3))
    for i, j, m in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        H[:, :, i, :, j] = w[..., m]
        H[:, :, j, :, i] = -w[..., m]
    return H.reshape(k, 12, 12)


def _pressure_only(shear: StableNeoHookean) -> StableNeoHookean:
    """``shear`` with ``mu = lam = 0``: its ``d2psi/dF2`` with a pressure is ``p d2J/dF2`` alone, whose eigensystem
    is Stable Neo-Hookean's (Smith et al. 2018, section 4.2) with the pressure as its ``lam (J - alpha)``. Only its
    pressure's Hessian may be read (the projection reads no memo: its SVD is of ``F`` itself)."""
    zero = copy.copy(shear)
    zero.mu, zero.lam, zero.alpha = 0.0, 0.0, 0.0
    return zero


def _mapped(snh: StableNeoHookean, A: np.ndarray) -> np.ndarray:
    """``V_t (dF/dx)^T A (dF/dx)`` per tet, ``(k, 12, 12)`` N/m, for ``A`` ``(k, 9, 9)`` Pa."""
    M = snh.tet_dvecF_dx
    return np.matmul(np.swapaxes(M, 1, 2), np.matmul(A, M)) * snh.tet_rest_volume[:, None, None]


class NodalPressureNeoHookean(BorrowedWorkspace):
    """Stable Neo-Hookean tets with an average nodal pressure (module docstring): the same ``E``, ``nu``
    and constructor as :class:`~sim_core.energies.neohookean.reference.StableNeoHookean`.

    Args:
        tets, x_rest, youngs_modulus, poisson_ratio: as :class:`StableNeoHookean`'s (tets ``(k, 4)``, rest positions
            ``(n, 3)`` m, small-strain ``E`` in Pa and ``nu``), and raising as it does.

    Attributes:
        shear: the shear part, a :class:`StableNeoHookean` with ``lam_s = mu / 8``.
        volume: the nodal volumetric part, :class:`NodalVolume` (its ``ring`` is this element's block vertices).
        per_tet: the Stable Neo-Hookean of the same ``E``, ``nu`` (per-tet volume; locks).
    """

    parameter_names: tuple[str, ...] = ("youngs_modulus", "poisson_ratio")

    def __init__(self, tets: np.ndarray, x_rest: np.ndarray, youngs_modulus: float, poisson_ratio: float) -> None:
        whole = StableNeoHookean(tets, x_rest, youngs_modulus, poisson_ratio)  # validates E, nu, the mesh
        self.youngs_modulus, self.poisson_ratio = whole.youngs_modulus, whole.poisson_ratio
        self.mu, self.lam = whole.mu, whole.lam
        lam_s, self.kappa = nodal_pressure_moduli(whole.mu, whole.lam)
        self.shear = whole.with_lame(whole.mu, lam_s)
        self.volume = NodalVolume(self.shear, self.kappa)
        self.per_tet = whole  # the plain Stable Neo-Hookean of the same E, nu (the gel's Maxwell branch uses it)
        self.tets, self.tet_rest_volume = whole.tets, whole.tet_rest_volume
        self.ring = self.volume.ring

    def parts(self) -> tuple[StableNeoHookean, NodalVolume]:
        """The two potentials whose sum this is, for the solver (module docstring): the shear part (a Stable
        Neo-Hookean: the fused kernel takes it) and the nodal volumetric part."""
        return self.shear, self.volume

    def nodal_jacobian(self, x: np.ndarray) -> np.ndarray:
        """``J_a`` of every node, ``(nodes,)`` (order of ``volume.nodes``)."""
        return 1.0 + self.volume.kinematics(x)[2]

    def deformation_gradient(self, x: np.ndarray) -> np.ndarray:
        """``F`` per tet at ``x`` ``(n, 3)``, shape ``(k, 3, 3)`` (the gel candidates' relaxed states read it)."""
        return self.per_tet.deformation_gradient(x)

    # ------------------------------------------------------------------ Potential contract
    def energy(self, x: np.ndarray) -> float:
        """``sum_t V_t psi_s(F_t) + sum_a V_a kappa / 2 (J_a - 1)^2`` in J at ``x`` ``(n, 3)`` (0 at rest)."""
        return self.shear.energy(x) + self.volume.energy(x)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``: ``V_t (P_s(F_t) + p_t cof F_t) dF/dx`` summed per vertex."""
        x = np.asarray(x, dtype=float)
        F, cof, _, p = self.volume.kinematics(x)
        return self.shear._forces_from_pk1(x, self.shear.first_piola(F) + (self.kappa * p)[:, None, None] * cof)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-node Hessian blocks over :attr:`ring` in N/m (module docstring).

        Args:
            x: positions ``(n, 3)``.
            projection: ``"none"`` (exact), ``"clamp"`` or ``"abs"``: applied to each tet's 9x9
                ``d2psi_s/dF2 + p_t d2J/dF2`` (jointly); the nodal ``kappa / V_a b_a b_a^T`` is PSD as it is.

        Returns:
            :class:`HessianBlocks` with ``vertices = ring`` ``(nodes, m)`` and blocks ``(nodes, 3m, 3m)``.
        """
        F, cof, _, p = self.volume.kinematics(x)
        A = self.shear.d2psi_dF2_projected(F, projection, self.kappa * p)
        return self.volume.ring_blocks(_mapped(self.shear, A), cof)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/dp for ``p`` in :attr:`parameter_names`, shape ``(n, 3)``.

        The gradient is linear in ``(mu, lam_s, kappa)`` = ``(mu, mu / 8, lam - mu / 8)``, each a function of
        ``E``, ``nu`` through :func:`~sim_core.energies.neohookean.reference.snh_lame_parameters`.

        Raises:
            KeyError: unknown parameter name.
        """
        if name not in self.parameter_names:
            raise KeyError(f"NodalPressureNeoHookean has no parameter {name!r}; known: {self.parameter_names}")
        x = np.asarray(x, dtype=float)
        dmu, dlam = _snh_lame_derivatives(self.youngs_modulus, self.poisson_ratio, name)
        F, cof, _, p = self.volume.kinematics(x)
        P_mu, P_lam = self.shear._pk1_parts(F)
        dP = dmu * P_mu + dmu / 8.0 * P_lam + ((dlam - dmu / 8.0) * p)[:, None, None] * cof
        return self.shear._forces_from_pk1(x, dP)
