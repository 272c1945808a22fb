"""The incremental potential of one Newton step, set up once before its iterations: the data record
the solver's step functions share (:class:`StepTerms`, built by ``NewtonSolver._set_up_step`` in
:mod:`sim_core.solver`), the free DoFs of its fixed mask (:class:`FreeDofs`) and the contact force of a step's
result (:func:`contact_force`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_core.fused_elastic import FusedElastic
from sim_core.state import State

__all__ = ["FreeDofs", "StepTerms", "contact_force"]


@dataclass
class StepTerms:
    """The incremental potential of one step, set up once before its Newton iterations
    (``NewtonSolver._set_up_step``).

    Attributes:
        state_in: the state at the start of the step.
        dt: step size, s.
        fixed: Dirichlet vertices (static + effector-driven), shape ``(n,)`` bool.
        free: free DoFs, shape ``(3 n,)`` bool.
        x_target: prescribed positions of the fixed vertices, m, shape ``(n, 3)``.
        poses, openings: effector poses and finger openings reached at the end of the step.
        x_n: positions at the start, m, shape ``(n, 3)``.
        diag: diagonal of the inertia (+ damping) Hessian, the assembler's ``diag`` argument.
        fixed_terms: the potentials that do not change within the step (inertia, gravity,
            [damping], elastic..., [friction], candidates...; :attr:`StepRecord.terms` without contacts).
        elastic_terms: the elastic potentials of the step.
        fused: the fused elastic evaluator of the Taichi path, or None.
        loop_terms: the terms the Newton loop evaluates besides contacts (``fused`` in place of
            the terms it covers).
        friction: the step's lagged friction, or None.
        cand_contact: candidate contact-like terms (their forces count in ``contact_force``).
        dynamic_terms: the non-contact terms assembled into the dynamic pattern each iteration
            ([friction] + candidate terms without a fused part).
        memory: the contact memory of the step (:meth:`ContactSet.begin_step`).
        max_displacement: cap on any vertex's move per iteration, m.
        simplified: whether the simplified Newton test may end the step.
        loop_energy_x, loop_energy: the positions array object the loop terms' energy (J) was last
            evaluated at, and that energy.
        last_update: the Newton update (m, ``(3 n,)``) the stopping test measured at the accepted
            iterate (the ordinary or simplified correction), None when the step ended otherwise.
        applied: the step ended at its last iterate plus ``last_update`` (``SolverConfig.apply_last_update``), so
            the last Newton matrix is that of the iterate before the result, not the result's.
        compression: a series spring's compression among the step's unknowns
            (:class:`~sim_core.drive_compression.CompressionPotential`: its base vertices free in ``fixed`` and
            ``free``, tied to it), or None.
    """

    state_in: State
    dt: float
    fixed: np.ndarray
    free: np.ndarray
    x_target: np.ndarray
    poses: dict
    openings: dict
    x_n: np.ndarray
    diag: np.ndarray
    fixed_terms: list
    elastic_terms: list
    fused: FusedElastic | None
    loop_terms: list
    friction: object | None
    cand_contact: list
    dynamic_terms: list
    memory: object
    max_displacement: float
    simplified: bool
    loop_energy_x: np.ndarray | None = None
    loop_energy: float = 0.0
    last_update: np.ndarray | None = None
    applied: bool = False
    compression: object | None = None


class FreeDofs:
    """The free DoFs of a step's fixed-vertex mask and that mask by DoF, kept while the boundary gives the same
    read-only mask object from step to step (a stacked scene's, :class:`~sim_core.batch.effectors.StackedBoundary`):
    the step's free mask is then the same object too (the solver's caches keyed by it hold)."""

    def __init__(self) -> None:
        self._kept: tuple | None = None  # (fixed mask, free DoFs, fixed DoFs)

    def __call__(self, fixed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(free, fixed_dofs)`` of ``fixed`` ``(n,)`` bool: the free DoFs ``(3 n,)`` bool and the fixed ones as an
        ``(n, 3)`` bool mask (``np.copyto``'s ``where`` without broadcasting: a tenth of the time of a ``(n, 1)``
        mask's), both read-only; kept when ``fixed`` is read-only (made anew for a writeable mask)."""
        kept = self._kept
        if kept is None or kept[0] is not fixed:
            free = np.repeat(~fixed, 3)
            fixed_dofs = ~free.reshape(-1, 3)
            free.flags.writeable = fixed_dofs.flags.writeable = False
            kept = (fixed, free, fixed_dofs)
            self._kept = None if fixed.flags.writeable else kept
        return kept[1], kept[2]


def contact_force(x: np.ndarray, terms: list) -> np.ndarray:
    """Minus the sum of the contact ``terms``' gradients at the accepted ``x`` ``(n, 3)``: a new array, N."""
    force = np.zeros_like(x)
    for p in terms:
        force -= p.gradient(x)
    return force
