"""Batched second-order forward-mode derivatives ("jets") of small geometric expressions.

A :class:`Jet` holds, for ``k`` elements at once, the value of a scalar or 3-vector quantity and its
gradient and Hessian with respect to the element's ``N`` local variables (the stacked coordinates of
its vertices, local DoF ``3 a + d``). Sums are linear, products follow the Leibniz rule
``(u v)'' = u v'' + u'' v + u' v'^T + v' u'^T`` and unary functions the chain rule
``f(a)'' = f'(a) a'' + f''(a) a' a'^T``, so the derivatives are exact up to rounding. The narrow phase
uses jets to differentiate the contact distances (point-plane, point-line, point-point, line-line).

``order`` selects what is carried: 0 value only, 1 value and gradient, 2 all three. A Hessian of
``None`` means identically zero (the variables themselves are linear).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

@dataclass(frozen=True)
class Jet:
    """Value and derivatives of a batched scalar or 3-vector.

    Attributes:
        val: shape ``(k,)`` (scalar) or ``(k, 3)`` (vector).
        grad: ``val.shape + (N,)`` or None (order 0).
        hess: ``val.shape + (N, N)`` or None (order < 2, or identically zero).
        order: derivative order carried (0, 1, 2).
    """

    val: np.ndarray
    grad: np.ndarray | None
    hess: np.ndarray | None
    order: int = 2

    def __add__(self, other: "Jet") -> "Jet":
        return Jet(self.val + other.val, _add(self.grad, other.grad), _add(self.hess, other.hess), self.order)

    def __sub__(self, other: "Jet") -> "Jet":
        return self + other.scaled(-1.0)

    def scaled(self, c: np.ndarray | float) -> "Jet":
        """Product with a constant ``c`` (float or shape ``(k,)``)."""
        c = np.asarray(c, dtype=float)
        cv = c.reshape(c.shape + (1,) * (self.val.ndim - c.ndim)) if c.ndim else c
        cg = cv[..., None] if c.ndim else c
        ch = cv[..., None, None] if c.ndim else c
        return Jet(
            self.val * cv,
            None if self.grad is None else self.grad * cg,
            None if self.hess is None else self.hess * ch,
            self.order,
        )


def _add(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    if a is None:
        return b
    if b is None:
        return a
    return a + b


def variable(points: np.ndarray, slot: np.ndarray | int, var_count: int, order: int) -> Jet:
    """A vertex position as an independent variable.

    Args:
        points: positions, shape ``(k, 3)``.
        slot: local vertex index of each element (int or shape ``(k,)``); its DoFs are
            ``3 slot + d`` among the ``var_count`` variables.
        var_count: number of local variables N (3 x vertices per element).
        order: derivative order carried (0, 1, 2).

    Returns:
        Vector jet with gradient ``e_{3 slot + d}`` and zero Hessian.
    """
    k = points.shape[0]
    grad = None
    if order >= 1:
        grad = np.zeros((k, 3, var_count))
        slot = np.broadcast_to(np.asarray(slot, dtype=np.int64), (k,))
        rows = np.arange(k)
        for d in range(3):
            grad[rows, d, 3 * slot + d] = 1.0
    return Jet(np.asarray(points, dtype=float), grad, None, order)


def _component(u: Jet, index: list[int]) -> Jet:
    """Vector jet with components permuted by ``index``."""
    return Jet(
        u.val[:, index],
        None if u.grad is None else u.grad[:, index],
        None if u.hess is None else u.hess[:, index],
        u.order,
    )


def _componentwise(u: Jet, v: Jet) -> Jet:
    """``w_i = u_i v_i`` for vector jets (Leibniz rule per component)."""
    val = u.val * v.val
    grad = hess = None
    if u.grad is not None:
        grad = u.val[..., None] * v.grad + v.val[..., None] * u.grad
        if u.order >= 2:
            outer = u.grad[..., :, None] * v.grad[..., None, :]
            hess = outer + np.swapaxes(outer, -1, -2)
            if u.hess is not None:
                hess = hess + v.val[..., None, None] * u.hess
            if v.hess is not None:
                hess = hess + u.val[..., None, None] * v.hess
    return Jet(val, grad, hess, u.order)


def dot(u: Jet, v: Jet) -> Jet:
    """Scalar product of two vector jets."""
    w = _componentwise(u, v)
    return Jet(
        w.val.sum(axis=1),
        None if w.grad is None else w.grad.sum(axis=1),
        None if w.hess is None else w.hess.sum(axis=1),
        w.order,
    )


_NEXT, _PREV = [1, 2, 0], [2, 0, 1]


def cross(u: Jet, v: Jet) -> Jet:
    """Cross product: ``(u x v)_i = u_{i+1} v_{i+2} - u_{i+2} v_{i+1}`` (indices mod 3)."""
    return _componentwise(_component(u, _NEXT), _component(v, _PREV)) - _componentwise(
        _component(u, _PREV), _component(v, _NEXT)
    )


def multiply(a: Jet, b: Jet) -> Jet:
    """Product of two scalar jets."""
    val = a.val * b.val
    grad = hess = None
    if a.grad is not None:
        grad = a.val[:, None] * b.grad + b.val[:, None] * a.grad
        if a.order >= 2:
            outer = a.grad[:, :, None] * b.grad[:, None, :]
            hess = outer + np.swapaxes(outer, 1, 2)
            if b.hess is not None:
                hess = hess + a.val[:, None, None] * b.hess
            if a.hess is not None:
                hess = hess + b.val[:, None, None] * a.hess
    return Jet(val, grad, hess, a.order)


def unary(
    a: Jet,
    f: Callable[[np.ndarray], np.ndarray],
    df: Callable[[np.ndarray], np.ndarray],
    d2f: Callable[[np.ndarray], np.ndarray],
) -> Jet:
    """``f(a)`` for a scalar jet, given f and its first two derivatives."""
    val = f(a.val)
    grad = hess = None
    if a.grad is not None:
        f1 = df(a.val)
        grad = f1[:, None] * a.grad
        if a.order >= 2:
            hess = d2f(a.val)[:, None, None] * a.grad[:, :, None] * a.grad[:, None, :]
            if a.hess is not None:
                hess = hess + f1[:, None, None] * a.hess
    return Jet(val, grad, hess, a.order)


def sqrt(a: Jet) -> Jet:
    """Square root of a positive scalar jet."""
    return unary(a, np.sqrt, lambda y: 0.5 / np.sqrt(y), lambda y: -0.25 / (y * np.sqrt(y)))


def reciprocal(a: Jet) -> Jet:
    """``1 / a`` for a non-zero scalar jet."""
    return unary(a, lambda y: 1.0 / y, lambda y: -1.0 / (y * y), lambda y: 2.0 / (y * y * y))


def norm(u: Jet) -> Jet:
    """Euclidean length of a non-zero vector jet."""
    return sqrt(dot(u, u))
