"""Settling a scene to rest before it is driven: the initial state of a scene file is close to, but
not exactly at, the equilibrium of its implicit-Euler step.

A step solved to ``SolverConfig.tol_velocity`` (1e-4 m/s) stops on a Newton update it does not apply
(:mod:`sim_core.newton_stop`), so a scene whose initial state is within that tolerance of its
equilibrium repeats its initial state step after step without reaching it; a body whose own part of
that update is above ``SolverConfig.sleep_velocity`` (1e-7 m/s) then never falls asleep
(:mod:`sim_core.sleeping`; the bundled press_slide scene's card: 7.9e-7 m/s) and stays in every solve
until the first command moves something. :func:`settle` steps the scene under zero commands with the
Newton tolerance tightened below the rest threshold until every vertex is at rest by the sleeping
criterion, then takes steps with the solver's own settings until one leaves the state unchanged,
after which every body that may sleep and that nothing moving can reach is asleep. Dynamic
relaxation to a static equilibrium by the dynamic solver itself (Otter, Cassell & Hobbs, "Dynamic
relaxation", Proc. ICE 35, 1966) with the step's own damping.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from sim_core.errors import SimulationDivergedError
from sim_core.simulation import Simulation
from sim_core.sleeping import sleeping_eligible

SETTLE_TOLERANCE_FRACTION = 0.5
"""The settling steps' Newton tolerance ``tol_velocity``, as a fraction of ``SolverConfig.sleep_velocity``:
a step they accept strictly has a Newton update below the rest threshold everywhere."""


class SettleInfo(NamedTuple):
    """How :func:`settle` ended.

    Attributes:
        settled: every vertex came to rest (velocities in and out and the last Newton update below
            ``sleep_velocity``, m/s) and a step with the solver's own settings left the state unchanged.
        steps: steps taken (at most ``max_steps``).
        max_steps: the cap on steps it was given.
        residual_velocity: at the last step, the largest of the velocities in and out and the step's
            scaled Newton update ``StepInfo.residual_velocity``, m/s (0 when no step was taken).
        displacement: the largest move of a vertex from the state settling started at, m (when not
            settled: the move it had made at the cap, before the state was put back).
        sleeping: the bodies asleep after the last step (``SolverConfig.sleeping``), sorted names.
        awake: the bodies that may sleep (:func:`~sim_core.sleeping.sleeping_eligible`) but are awake
            after the last step (with ``SolverConfig.sleeping``: a moving vertex within reach, or not
            settled), sorted names.
        reason: why it did not settle ("" when it did).
    """

    settled: bool
    steps: int
    max_steps: int
    residual_velocity: float
    displacement: float
    sleeping: tuple[str, ...]
    awake: tuple[str, ...]
    reason: str

    def describe(self) -> str:
        """One line for a log: settled or not, steps, residual, displacement, the sleeping bodies."""
        head = (f"settled in {self.steps} steps" if self.settled
                else f"did not settle in {self.steps} steps (cap {self.max_steps}): {self.reason}; "
                     f"starting from the scene's own state")
        return (f"{head}; residual velocity {self.residual_velocity:.3g} m/s, largest vertex move "
                f"{self.displacement:.3g} m; asleep: {', '.join(self.sleeping) or 'none'}"
                + (f"; awake: {', '.join(self.awake)}" if self.awake else ""))


def settle(sim: Simulation, max_steps: int) -> SettleInfo:
    """Step ``sim`` under zero commands (every effector holds its pose) until the scene is at rest, at
    most ``max_steps`` steps; the settled state then starts at the time and step index ``sim`` had.

    Two phases, both within ``max_steps``:

    1. steps solved with ``tol_velocity = min(tol_velocity, SETTLE_TOLERANCE_FRACTION * sleep_velocity)``
       (the solver's other settings unchanged) until one is accepted by a strict test with every
       vertex's velocity in and out below ``sleep_velocity``;
    2. steps with the solver's own settings until one is accepted strictly and leaves the positions
       bitwise unchanged at zero velocity: its Newton update (below ``sleep_velocity``) is not applied,
       and with ``SolverConfig.sleeping`` every body that may sleep and that no moving vertex can
       reach falls asleep after it.

    A step that raises :class:`~sim_core.errors.SimulationDivergedError` ends settling (not settled).
    A scene that does not settle (a failed step, still moving at the cap: a falling block), or whose
    rest lies farther from its starting state than one step's Newton tolerance (``dt * tol_velocity``:
    a sheet that sags by more than that), is put back to the state it started at, so that it starts
    as its file says and a replay of the node's recording (which starts from the scene file) follows
    it. The solver's settings are restored in every case. The
    steps count in ``sim.step_totals``.

    Args:
        sim: the simulation, at the state to settle from (its state, solver caches and sleeping
            bodies are changed).
        max_steps: the cap on steps (>= 0; 0 takes none and reports not settled).

    Returns:
        :class:`SettleInfo`.

    Raises:
        ValueError: ``max_steps`` < 0.
    """
    if max_steps < 0:
        raise ValueError(f"settle: max_steps must be >= 0, got {max_steps}")
    solver = sim.solver
    own = solver.config
    tight = dataclasses.replace(own, tol_velocity=min(own.tol_velocity, SETTLE_TOLERANCE_FRACTION * own.sleep_velocity))
    rest = own.sleep_velocity
    start = sim.state
    original = start.copy()
    x0 = start.x.copy()
    steps, residual, phase, info, reason = 0, 0.0, 1, None, ""
    try:
        while steps < max_steps:
            solver.config = tight if phase == 1 else own
            before = sim.state
            try:
                info = sim.step(sim.model.control())
            except SimulationDivergedError as err:
                reason = f"step {steps + 1} failed: {err}"
                break
            steps += 1
            after = sim.state
            speed = max(_largest(before.v), _largest(after.v))
            residual = max(speed, float(info.residual_velocity))
            if not info.converged_strict:
                continue
            if phase == 1:
                if speed <= rest:
                    phase = 2
            elif not np.any(after.v) and np.array_equal(after.x, before.x):
                break
        else:
            reason = ("no step was allowed" if max_steps == 0 else
                      f"still moving after {steps} steps" if phase == 1 else
                      f"at rest at the settling tolerance, but no step with the solver's own settings left the state "
                      f"unchanged in {steps} steps")
    finally:
        solver.config = own
    displacement = _largest(sim.state.x - x0)
    tolerance = sim.dt * own.tol_velocity
    if not reason and displacement > tolerance:
        reason = (f"its rest is {displacement:.3g} m from the scene's state, more than one step's Newton tolerance "
                  f"({tolerance:.3g} m): a replay of what the node records starts from the scene's state")
    settled = not reason
    if settled:
        sim.state.t, sim.state.step_index = start.t, start.step_index
        sleeping = tuple(sorted(info.sleeping + info.fell_asleep)) if info is not None and own.sleeping else ()
    else:
        # a scene that moves on its own (a falling block) or a failed step: it starts as its file says
        sim.state = original
        sleeping = ()
    awake = tuple(sorted(set(sleeping_eligible(sim.model)) - set(sleeping))) if own.sleeping else ()
    return SettleInfo(settled=settled, steps=steps, max_steps=int(max_steps), residual_velocity=residual,
                      displacement=displacement, sleeping=sleeping, awake=awake, reason=reason)


def _largest(a: np.ndarray) -> float:
    """The largest row norm of ``a`` ``(n, 3)`` (0 for no rows)."""
    a = np.asarray(a, dtype=float).reshape(-1, 3)
    return float(np.sqrt(np.max(np.sum(a * a, axis=1)))) if len(a) else 0.0
