"""Exact derivatives of lagged IPC friction w.r.t. the start-of-step positions x^n (for the adjoint).

Lagged friction (Li et al. 2020) freezes, at x^n, each active pair's normal force lam, contact
normal n (hence tangent basis T) and closest-point weights w. These are smooth functions of x^n
inside a contact region; this module recomputes the frozen rows of a step's ``LaggedFriction`` and
their first derivatives per region with forward-mode jets (``sim_core.collision.jets``), so that
``sim_core.adjoint`` can differentiate the friction gradient w.r.t. x^n exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_core.collision import jets
from sim_core.collision.distances import (
    EdgeEdgeRegion,
    PointTriangleRegion,
    edge_edge_closest_points,
    point_triangle_closest_point,
)
from sim_core.contact_set import ContactSet, FrictionRowSource
from sim_core.energies.contact.reference import EdgeEdgeContact, PlaneContact, VertexTriangleContact
from sim_core.errors import ThinShellError
from sim_core.model import Model
from sim_core.energies.friction.reference import (
    LaggedFriction,
    smooth_friction_f1_over_x,
    smooth_friction_f2_x_minus_f1_over_x3,
)
from sim_core.energies.sphere_contact.reference import SphereContact
from sim_core.state import State


# ============================================================================ lagged friction frames
@dataclass
class FrictionRows:
    """The lagged friction pairs of one step with the derivatives of their frozen frames.

    Attributes:
        friction: the :class:`LaggedFriction` of the step (rebuilt from ``x^n`` and the side memory).
        vertices: shape ``(k, 4)``; rows as in ``friction``.
        body_pairs: per row, the unordered pair of body/plane names (for ``friction.<pair>``).
        dlam: d lam / d z^n, shape ``(k, 12)`` (local DoF ``3 a + d`` of ``vertices[:, a]``).
        normal, dnormal: unit normals ``(k, 3)`` and their derivatives ``(k, 3, 12)``.
        weights, dweights: closest-point weights ``(k, 4)`` and derivatives ``(k, 4, 12)``.
    """

    friction: LaggedFriction
    vertices: np.ndarray
    body_pairs: list[frozenset]
    dlam: np.ndarray
    normal: np.ndarray
    dnormal: np.ndarray
    weights: np.ndarray
    dweights: np.ndarray


def _const(k: int, value) -> jets.Jet:
    val = np.broadcast_to(np.asarray(value, dtype=float), (k,)).copy()
    return jets.Jet(val, np.zeros((k, 12)), None, 1)


def _vec_scale(u: jets.Jet, s: jets.Jet) -> jets.Jet:
    """Vector jet times scalar jet."""
    return jets.Jet(u.val * s.val[:, None], u.grad * s.val[:, None, None] + u.val[:, :, None] * s.grad[:, None, :],
                    None, 1)


def _unit(u: jets.Jet) -> tuple[jets.Jet, jets.Jet]:
    length = jets.norm(u)
    return _vec_scale(u, jets.reciprocal(length)), length


def _divide(a: jets.Jet, b: jets.Jet) -> jets.Jet:
    return jets.multiply(a, jets.reciprocal(b))


def _variables(z: np.ndarray) -> list[jets.Jet]:
    return [jets.variable(z[:, a], a, 12, 1) for a in range(4)]


def _frame_out(k: int):
    return (np.zeros(k), np.zeros((k, 12)), np.zeros((k, 3)), np.zeros((k, 3, 12)), np.zeros((k, 4)),
            np.zeros((k, 4, 12)))


def _store(out, mask, d: jets.Jet, n: jets.Jet, w: list[jets.Jet]) -> None:
    dist, ddist, nrm, dnrm, wt, dwt = out
    dist[mask], ddist[mask], nrm[mask], dnrm[mask] = d.val, d.grad, n.val, n.grad
    wt[mask] = np.stack([c.val for c in w], axis=1)
    dwt[mask] = np.stack([c.grad for c in w], axis=1)


def _scatter_weights(k: int, slots: list[np.ndarray], parts: list[jets.Jet]) -> list[jets.Jet]:
    """Per-slot weight jets ``[w_0 .. w_3]`` from jets ``parts[i]`` placed at local vertex ``slots[i]``
    of each row (int shape ``(k,)``; the other slots get weight 0)."""
    out = []
    for a in range(4):
        val, grad = np.zeros(k), np.zeros((k, 12))
        for slot, part in zip(slots, parts):
            m = slot == a
            val[m] += part.val[m]
            grad[m] += part.grad[m]
        out.append(jets.Jet(val, grad, None, 1))
    return out


def vertex_triangle_frames(z: np.ndarray, side: np.ndarray):
    """Contact distance, normal and weights of vertex-triangle pairs with derivatives (jets).

    Mirrors :meth:`VertexTriangleContact.contact_frames` region by region (Ericson 2005, 5.1.5):
    face: ``n = side * unit((b - a) x (c - a))``, ``d = n.(p - a)``, barycentrics of the projection;
    edge: closest point ``q = u + s (v - u)`` on the edge ``(u, v)`` (ab, bc or ca) with
    ``s = (v - u).(p - u) / |v - u|^2``, ``n = unit(p - q)``, ``d = |p - q|``; vertex: ``q`` the corner
    (``s = 0``). The six edge and vertex regions are one batch (their corners picked per row).

    Args:
        z: ``[p, a, b, c]`` per pair, shape ``(k, 4, 3)``.
        side: remembered sides, shape ``(k,)``.

    Returns:
        ``(d (k,), dd (k,12), n (k,3), dn (k,3,12), w (k,4), dw (k,4,12))``, weights ``[1, -bary]``.
    """
    k = z.shape[0]
    out = _frame_out(k)
    if k == 0:
        return out
    _, region = point_triangle_closest_point(z[:, 0], z[:, 1], z[:, 2], z[:, 3])
    R = PointTriangleRegion
    face = region == R.FACE
    if np.any(face):
        p, a, b, c = _variables(z[face])
        km = int(face.sum())
        one = _const(km, 1.0)
        ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
        n, _ = _unit(jets.cross(ab, ac))
        n = n.scaled(side[face])
        d = jets.dot(n, ap)
        d1, d2, d3, d4 = jets.dot(ab, ap), jets.dot(ac, ap), jets.dot(ab, bp), jets.dot(ac, bp)
        d5, d6 = jets.dot(ab, cp), jets.dot(ac, cp)
        vc = jets.multiply(d1, d4) - jets.multiply(d3, d2)
        vb = jets.multiply(d5, d2) - jets.multiply(d1, d6)
        va = jets.multiply(d3, d6) - jets.multiply(d5, d4)
        total = va + vb + vc
        bv, bw = _divide(vb, total), _divide(vc, total)
        _store(out, face, d, n, [one, (one - bv - bw).scaled(-1.0), bv.scaled(-1.0), bw.scaled(-1.0)])
    if np.all(face):
        return out
    rest = ~face
    code = region[rest]
    # per row: the edge (u, v) as local vertex slots 1..3 (a, b, c); vertex regions: the corner as u
    u_slot = np.select([code == R.EDGE_AB, code == R.EDGE_BC, code == R.EDGE_CA, code == R.VERTEX_A,
                        code == R.VERTEX_B], [1, 2, 1, 1, 2], 3)
    v_slot = np.select([code == R.EDGE_AB, code == R.EDGE_BC, code == R.EDGE_CA, code == R.VERTEX_A,
                        code == R.VERTEX_B], [2, 3, 3, 2, 3], 1)
    vertex = code >= R.VERTEX_A
    zr = z[rest]
    km = zr.shape[0]
    rows = np.arange(km)
    p = jets.variable(zr[:, 0], 0, 12, 1)
    u = jets.variable(zr[rows, u_slot], u_slot, 12, 1)
    v = jets.variable(zr[rows, v_slot], v_slot, 12, 1)
    one = _const(km, 1.0)
    uv, up = v - u, p - u
    s = _divide(jets.dot(uv, up), jets.dot(uv, uv))
    s = jets.Jet(np.where(vertex, 0.0, s.val), np.where(vertex[:, None], 0.0, s.grad), None, 1)
    q = _vec_scale(u, one - s) + _vec_scale(v, s)
    n, d = _unit(p - q)
    bary = _scatter_weights(km, [u_slot, v_slot], [one - s, s])
    _store(out, rest, d, n, [one] + [bary[a].scaled(-1.0) for a in (1, 2, 3)])
    return out


def edge_edge_frames(z: np.ndarray, side: np.ndarray):
    """Contact distance, normal and weights of edge-edge pairs with derivatives (jets).

    Mirrors :meth:`EdgeEdgeContact.contact_frames` (Ericson 2005, 5.1.9): with ``ea = a1 - a0``,
    ``eb = b1 - b0``, ``r = a0 - b0``: interior ``s = (B F - C E) / (A E - B^2)``, ``t = (B s + F) / E``,
    ``n = side * unit(ea x eb)``, ``d = n.r``; an endpoint region fixes s or t to 0/1 and projects
    the other (``t = (B s + F) / E`` or ``s = (B t - C) / A``), ``n = unit(rel)``, ``d = |rel|``.
    The regions are batched as interior, s fixed, t fixed and both fixed.

    Args:
        z: ``[a0, a1, b0, b1]``, shape ``(k, 4, 3)``.
        side: remembered sides, shape ``(k,)``.

    Returns:
        as :func:`vertex_triangle_frames`, weights ``[1 - s, s, -(1 - t), -t]``.
    """
    k = z.shape[0]
    out = _frame_out(k)
    if k == 0:
        return out
    s_val, t_val, region = edge_edge_closest_points(z[:, 0], z[:, 1], z[:, 2], z[:, 3])
    R = EdgeEdgeRegion
    groups = (
        ("interior", region == R.INTERIOR),
        ("s_fixed", (region == R.A0_EDGE_B) | (region == R.A1_EDGE_B)),
        ("t_fixed", (region == R.B0_EDGE_A) | (region == R.B1_EDGE_A)),
        ("both_fixed", region >= R.A0_B0),
    )
    for kind, m in groups:
        if not np.any(m):
            continue
        a0, a1, b0, b1 = _variables(z[m])
        km = int(m.sum())
        one = _const(km, 1.0)
        ea, eb, r = a1 - a0, b1 - b0, a0 - b0
        A, E, B, C, F = jets.dot(ea, ea), jets.dot(eb, eb), jets.dot(ea, eb), jets.dot(ea, r), jets.dot(eb, r)
        if kind == "interior":
            den = jets.multiply(A, E) - jets.multiply(B, B)
            s = _divide(jets.multiply(B, F) - jets.multiply(C, E), den)
            t = _divide(jets.multiply(B, s) + F, E)
        elif kind == "s_fixed":
            s = _const(km, np.where(region[m] == R.A0_EDGE_B, 0.0, 1.0))
            t = _divide(jets.multiply(B, s) + F, E)
        elif kind == "t_fixed":
            t = _const(km, np.where(region[m] == R.B0_EDGE_A, 0.0, 1.0))
            s = _divide(jets.multiply(B, t) - C, A)
        else:
            s, t = _const(km, s_val[m]), _const(km, t_val[m])
        w = [one - s, s, (one - t).scaled(-1.0), t.scaled(-1.0)]
        if kind == "interior":
            n, _ = _unit(jets.cross(ea, eb))
            n = n.scaled(side[m])
            d = jets.dot(n, r)
        else:
            rel = _vec_scale(a0, w[0]) + _vec_scale(a1, w[1]) + _vec_scale(b0, w[2]) + _vec_scale(b1, w[3])
            n, d = _unit(rel)
        _store(out, m, d, n, w)
    return out


def friction_rows(model: Model, contact: ContactSet, state: State, friction: LaggedFriction) -> FrictionRows:
    """Identify the rows of a step's lagged friction and differentiate their frozen frames.

    Each row's kind, remembered side and bodies come from ``friction.row_sources``
    (:class:`~sim_core.contact_set.FrictionRowSource`, recorded by :meth:`ContactSet.friction` from
    the step's own potentials); a ``LaggedFriction`` without them (built elsewhere) is matched by
    the same :class:`ContactSet` call as the solver's instead (pairs near ``x^n`` with the state's
    side memory: a second broad phase and distance pass). Each row's frame is then differentiated
    with :func:`vertex_triangle_frames`, :func:`edge_edge_frames`, the constant plane normal or the
    radial normal of a rigid sphere (``dn/dx_i = (I - n n^T) / r = -dn/dc``).

    Args:
        model: the model.
        contact: a ``ContactSet(model)`` (its per-step scratch is overwritten; only used without
            ``friction.row_sources``).
        state: the state the step started from.
        friction: the step's :class:`LaggedFriction` (from ``StepRecord.terms``).

    Raises:
        ThinShellError: the rebuilt rows disagree with the contact set's friction (contract drift).
    """
    x_n = state.x
    sources = getattr(friction, "row_sources", None)
    if sources is None:
        sources = _search_row_sources(contact, x_n, state)
    names = list(model.bodies)
    body = model.body_of_vertex()
    parts, pairs = [], []
    k_c, eps = contact.stiffness, contact.eps
    for obstacle, pot, rows in sources:
        if rows.size == 0:
            continue
        if isinstance(pot, (VertexTriangleContact, EdgeEdgeContact)):
            verts = pot.vertices[rows]
            fn = vertex_triangle_frames if isinstance(pot, VertexTriangleContact) else edge_edge_frames
            d, dd, n, dn, w, dw = fn(x_n[verts], pot.resolved_sides(x_n, rows))
            parts.append((verts, k_c * (eps - d), -k_c * dd, n, dn, w, dw))
            second = 1 if isinstance(pot, VertexTriangleContact) else 2
            pairs += _body_pairs(names, body[verts[:, 0]], body[verts[:, second]])
        elif isinstance(pot, PlaneContact):
            v = pot.vertices[rows]
            k = v.size
            dlam = np.zeros((k, 12))
            dlam[:, :3] = -k_c * pot.normal
            w = np.zeros((k, 4))
            w[:, 0] = 1.0
            d = x_n[v] @ pot.normal - pot.offset
            parts.append((np.repeat(v[:, None], 4, axis=1), k_c * (eps - d), dlam,
                          np.broadcast_to(pot.normal, (k, 3)).copy(), np.zeros((k, 3, 12)), w, np.zeros((k, 4, 12))))
            pairs += _obstacle_pairs(names, body[v], obstacle)
        elif isinstance(pot, SphereContact):
            v = pot.vertices[rows]
            k = v.size
            rel = x_n[v] - x_n[pot.center]
            r = np.linalg.norm(rel, axis=1)
            n = rel / r[:, None]
            proj = (np.eye(3) - n[:, :, None] * n[:, None, :]) / r[:, None, None]  # dn/dx_i; dn/dc = -dn/dx_i
            dlam = np.zeros((k, 12))
            dlam[:, :3], dlam[:, 3:6] = -k_c * n, k_c * n
            dn = np.zeros((k, 3, 12))
            dn[:, :, :3], dn[:, :, 3:6] = proj, -proj
            w = np.zeros((k, 4))
            w[:, 0], w[:, 1] = 1.0, -1.0
            verts = np.column_stack([v, np.full(k, pot.center), v, v])  # padded as concatenate_frames does
            parts.append((verts, k_c * (eps - (r - pot.radius)), dlam, n, dn, w, np.zeros((k, 4, 12))))
            pairs += _obstacle_pairs(names, body[v], obstacle)
        else:
            raise ThinShellError(f"adjoint: lagged-friction rows from an unknown contact term {type(pot).__name__}")
    if not parts:
        parts.append((np.zeros((0, 4), np.int64), np.zeros(0), np.zeros((0, 12)), np.zeros((0, 3)),
                      np.zeros((0, 3, 12)), np.zeros((0, 4)), np.zeros((0, 4, 12))))
    cat = [np.concatenate([p[j] for p in parts]) for j in range(7)]
    verts, lam = cat[0], cat[1]
    # lam = k_c (eps - d) near activation is a small difference: d's rounding scales with the positions'
    # magnitude (a stacked batch's copies sit up to metres from the origin), and so does the tolerance
    atol = max(1e-12 * max(1.0, float(np.max(np.abs(lam), initial=0.0))),
               64.0 * np.finfo(float).eps * k_c * float(np.max(np.abs(x_n), initial=0.0)))
    if verts.shape != friction.vertices.shape or not np.array_equal(verts, friction.vertices) or not np.allclose(
        lam, friction.lam, rtol=1e-9, atol=atol
    ):
        raise ThinShellError(
            "adjoint: the rebuilt lagged-friction rows do not match ContactSet.friction (pair order or normal "
            "forces differ); sim_core/adjoint.py friction_rows must follow sim_core/contact_set.py"
        )
    return FrictionRows(friction, verts, pairs, cat[2], cat[3], cat[4], cat[5], cat[6])


def _search_row_sources(contact: ContactSet, x_n: np.ndarray, state: State) -> list[FrictionRowSource]:
    """The row sources of ``ContactSet.friction`` at ``x^n``, found again (pairs, sides, active sets)."""
    memory = contact.begin_step(x_n, state.contact_memory)
    pots = contact.potentials(x_n, x_n, memory)
    sources = [FrictionRowSource(None, pot, np.flatnonzero(pot.distance(x_n) < pot.eps))
               for pot in pots if isinstance(pot, (VertexTriangleContact, EdgeEdgeContact)) and len(pot.pairs)]
    for name, obstacle in contact.planes + contact.spheres:
        sources.append(FrictionRowSource(name, obstacle, np.flatnonzero(obstacle.distance(x_n) < obstacle.eps)))
    return sources


def _body_pairs(names: list[str], body_a: np.ndarray, body_b: np.ndarray) -> list[frozenset]:
    """Unordered body-name pairs of rows with body indices ``body_a``, ``body_b`` (shape ``(k,)``)."""
    cache: dict[tuple[int, int], frozenset] = {}
    out = []
    for a, b in zip(body_a.tolist(), body_b.tolist()):
        key = cache.get((a, b))
        if key is None:
            key = cache[(a, b)] = frozenset((names[a], names[b]))
        out.append(key)
    return out


def _obstacle_pairs(names: list[str], bodies: np.ndarray, obstacle: str) -> list[frozenset]:
    """``{body name, obstacle}`` per row with body indices ``bodies`` (shape ``(k,)``)."""
    keys = {b: frozenset((names[b], obstacle)) for b in np.unique(bodies).tolist()}
    return [keys[b] for b in bodies.tolist()]


def friction_state_jacobian(rows: FrictionRows, x: np.ndarray) -> np.ndarray:
    """d(friction gradient at x)/d(x^n) per row, shape ``(k, 12, 12)`` (rows: output DoF, cols: x^n DoF).

    Per row: ``g_j = mu lam phi(y) w_j q`` with ``r = sum_i w_i (z_i - z^n_i)``, ``q = (I - n n^T) r``,
    ``y = |q|``, ``phi = f1(y)/y``; differentiated through ``lam, n, w`` (frames at ``x^n``) and the
    explicit ``-w_i`` of ``r``; ``dphi = ((f1' y - f1)/y^3) q.dq``.
    """
    fr = rows.friction
    k = rows.vertices.shape[0]
    mu, lam, n, w = fr.mu, fr.lam, rows.normal, rows.weights
    dz = x[rows.vertices] - fr.x_prev[rows.vertices]  # (k, 4, 3)
    r = np.einsum("ka,kad->kd", w, dz)
    dr = np.einsum("kav,kad->kdv", rows.dweights, dz)
    dr.reshape(k, 3, 4, 3)[...] -= w[:, None, :, None] * np.eye(3)[None, :, None, :]  # -w_a at (d, 3 a + d)
    nr = np.einsum("kd,kd->k", n, r)
    q = r - n * nr[:, None]
    dnr = np.einsum("kdv,kd->kv", rows.dnormal, r) + np.einsum("kd,kdv->kv", n, dr)
    dq = dr - rows.dnormal * nr[:, None, None] - n[:, :, None] * dnr[:, None, :]
    y = np.linalg.norm(q, axis=1)
    phi = smooth_friction_f1_over_x(y, fr.eps_u)
    dphi = smooth_friction_f2_x_minus_f1_over_x3(y, fr.eps_u)[:, None] * np.einsum("kd,kdv->kv", q, dq)
    s = (rows.dlam * phi[:, None] + lam[:, None] * dphi) * mu[:, None]  # (k, 12)
    J = s[:, None, None, :] * w[:, :, None, None] * q[:, None, :, None]
    J += (mu * lam * phi)[:, None, None, None] * (
        rows.dweights[:, :, None, :] * q[:, None, :, None] + w[:, :, None, None] * dq[:, None, :, :]
    )
    return J.reshape(k, 12, 12)


# ============================================================================ effector kinematics
