"""An independent small-strain linear-elastic solver on a tet mesh: the known answer of a frictional slide.

Linear (P1) tetrahedra with the isotropic Hooke tensor, assembled here with NumPy from the textbook
element stiffness ``K_e = V B^T D B`` (Zienkiewicz & Taylor, *The Finite Element Method*, vol. 1,
6th ed., sec. 6.2), and nothing of ``sim_core`` but the mesh. It solves the steady full-slip state of a
block whose top face is held and whose bottom face is pressed by ``delta`` onto a rigid flat table that
slides under it with Coulomb friction ``mu``: on the bottom face ``u_z = delta``, the tangential
traction is ``mu`` times the normal reaction against the slide, and nothing else holds it. The
friction couples the normal and tangential equations (a non-symmetric linear system: the row of the
slide-direction force of each bottom vertex gets ``mu`` times its normal row), so the normal force at
constant depth changes with ``mu`` only through the elasticity of the block (Johnson, *Contact
Mechanics*, 1985, ch. 7: on a half space by the coupling constant ``beta = (1 - 2 nu) / (2 (1 - nu))``;
a finite block adds its own).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl


def hooke_matrix(youngs_modulus: float, poisson_ratio: float) -> np.ndarray:
    """Isotropic elasticity in Voigt order (xx, yy, zz, xy, yz, zx) with engineering shear strains, Pa, (6, 6)."""
    lam = youngs_modulus * poisson_ratio / ((1 + poisson_ratio) * (1 - 2 * poisson_ratio))
    mu = youngs_modulus / (2 * (1 + poisson_ratio))
    d = np.zeros((6, 6))
    d[:3, :3] = lam
    d[np.arange(3), np.arange(3)] += 2 * mu
    d[np.arange(3, 6), np.arange(3, 6)] = mu
    return d


def _p1_operators(x: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(B (k, 6, 12), volume (k,), dof (k, 12))``: the P1 strain-displacement matrices in Voigt order,
    the tet volumes (m^3) and the element DoFs."""
    corners = x[tets]  # (k, 4, 3)
    m = np.concatenate([np.ones((len(tets), 4, 1)), corners], axis=2)
    grads = np.linalg.inv(m)[:, 1:, :].transpose(0, 2, 1)  # (k, 4, 3): gradient of each shape function
    volume = np.abs(np.linalg.det(m)) / 6.0
    b = np.zeros((len(tets), 6, 12))
    for a in range(4):
        gx, gy, gz = grads[:, a, 0], grads[:, a, 1], grads[:, a, 2]
        c = 3 * a
        b[:, 0, c], b[:, 1, c + 1], b[:, 2, c + 2] = gx, gy, gz
        b[:, 3, c], b[:, 3, c + 1] = gy, gx
        b[:, 4, c + 1], b[:, 4, c + 2] = gz, gy
        b[:, 5, c], b[:, 5, c + 2] = gz, gx
    return b, volume, (3 * tets[:, :, None] + np.arange(3)).reshape(len(tets), 12)


def _assembled(x: np.ndarray, dof: np.ndarray, ke: np.ndarray) -> sp.csr_matrix:
    """Sum of element matrices ``ke`` ``(k, w, w)`` over DoFs ``dof`` ``(k, w)`` into ``(3 n, 3 n)``."""
    w = dof.shape[1]
    rows = np.repeat(dof, w, axis=1).reshape(-1)
    cols = np.tile(dof, (1, w)).reshape(-1)
    n = 3 * len(x)
    return sp.csr_matrix((ke.reshape(-1), (rows, cols)), shape=(n, n))


def linear_stiffness(x: np.ndarray, tets: np.ndarray, youngs_modulus: float, poisson_ratio: float) -> sp.csr_matrix:
    """Assembled P1 stiffness ``K`` (N/m), shape ``(3 n, 3 n)``, DoF ``3 i + axis``.

    Args:
        x: rest positions, m, shape ``(n, 3)``.
        tets: vertex indices, shape ``(k, 4)``.
        youngs_modulus: E in Pa.
        poisson_ratio: nu.
    """
    b, volume, dof = _p1_operators(x, tets)
    ke = volume[:, None, None] * np.einsum("kji,jl,klm->kim", b, hooke_matrix(youngs_modulus, poisson_ratio), b)
    return _assembled(x, dof, ke)


def nodal_pressure_stiffness(x: np.ndarray, tets: np.ndarray, youngs_modulus: float,
                             poisson_ratio: float) -> sp.csr_matrix:
    """Small-strain stiffness (N/m, ``(3 n, 3 n)``) of the average nodal pressure tetrahedron (Bonet and
    Burton, Commun. Numer. Meth. Eng. 14, 1998, linearised): the deviatoric Hooke tensor per tet,
    ``2 mu (I - m m^T / 3)`` in Voigt form, and the bulk modulus ``K = lam + 2 mu / 3`` on the nodal
    volume strain ``theta_a = sum_{e ∋ a} V_e div u_e / 4 / V_a`` with ``V_a = sum_{e ∋ a} V_e / 4``:
    ``K_vol = sum_a K V_a grad(theta_a)^T grad(theta_a)``. Assembled here from the P1 ``B`` matrices, nothing
    of sim_core."""
    lam = youngs_modulus * poisson_ratio / ((1 + poisson_ratio) * (1 - 2 * poisson_ratio))
    mu = youngs_modulus / (2 * (1 + poisson_ratio))
    b, volume, dof = _p1_operators(x, tets)
    trace = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    deviatoric = hooke_matrix(youngs_modulus, poisson_ratio) - lam * np.outer(trace, trace)
    deviatoric -= 2.0 * mu / 3.0 * np.outer(trace, trace)
    shear = _assembled(x, dof, volume[:, None, None] * np.einsum("kji,jl,klm->kim", b, deviatoric, b))
    n = len(x)
    # rows: nodes; theta_a = (1 / V_a) sum_e V_e / 4 (trace . B_e u_e)
    div = volume[:, None] * np.einsum("j,kjm->km", trace, b) / 4.0  # (k, 12)
    nodal_volume = np.bincount(tets.ravel(), weights=np.repeat(volume / 4.0, 4), minlength=n)
    rows = np.repeat(tets, 12, axis=1).reshape(-1)
    cols = np.tile(dof, (1, 4)).reshape(-1)
    weights = np.repeat(div[:, None, :], 4, axis=1).reshape(-1)
    volume_change = sp.csr_matrix((weights, (rows, cols)), shape=(n, 3 * n))  # d v_a / d u
    used = nodal_volume > 0
    scale = sp.diags(np.where(used, (lam + 2.0 * mu / 3.0) / np.where(used, nodal_volume, 1.0), 0.0))
    return (shear + volume_change.T @ scale @ volume_change).tocsr()


def sliding_block_reaction(stiffness: sp.csr_matrix, top: np.ndarray, bottom: np.ndarray, delta: float,
                           mu: float) -> np.ndarray:
    """Net reaction of the table on the block's bottom face in steady full slip, N, shape ``(3,)``.

    The top vertices are held (u = 0); the bottom vertices have ``u_z = delta`` (pressed up by the
    table) and carry the friction ``f_x = -mu R_z`` of their own normal reaction ``R_z`` (the table
    moves along -x under the block, i.e. the block slides along +x), ``f_y = 0``.

    Args:
        stiffness: from :func:`linear_stiffness`.
        top: held vertex indices, shape ``(t,)``.
        bottom: vertex indices on the table, shape ``(b,)``.
        delta: normal compression, m (> 0).
        mu: Coulomb coefficient (>= 0).

    Returns:
        ``(R_x, R_y, R_z)`` summed over the bottom face, N (``R_z > 0``: the table pushes up).
    """
    n = stiffness.shape[0]
    fixed = np.zeros(n, dtype=bool)
    fixed[(3 * top[:, None] + np.arange(3)).reshape(-1)] = True
    fixed[3 * bottom + 2] = True
    coupling = sp.identity(n, format="lil")
    coupling[3 * bottom, 3 * bottom + 2] = mu  # equation x_i + mu * equation z_i: f_x + mu R_z = 0
    a = (coupling.tocsr() @ stiffness).tocsr()
    u = np.zeros(n)
    u[3 * bottom + 2] = delta
    free = ~fixed
    u[free] = spl.spsolve(a[free][:, free].tocsc(), -(a @ u)[free])
    reaction = stiffness @ u
    return np.array([reaction[3 * bottom + axis].sum() for axis in range(3)])
