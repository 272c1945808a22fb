"""An effector driven along one world axis through a series spring: an impedance-controlled arm.

An impedance-controlled arm holds its tool with a spring of stiffness ``k_s`` (N/m) about the
commanded pose: under a contact load ``F`` along the spring's axis the tool sits ``b = F / k_s``
behind the command. :class:`SeriesSpringDrive` prescribes the effector's rotation and its position
across a unit axis ``n`` (world, pointing into the contact) kinematically, as
:mod:`sim_core.effector` does, and along ``n`` places it at ``p(b) = a - b n``, ``a`` the anchor (the
commanded position). An impedance also damps the tool's own velocity along ``n`` with a damper
``c`` (N s/m; an arm's Cartesian impedance is a spring and a damper, Hogan 1985, "Impedance Control: An
Approach to Manipulation", J. Dyn. Syst. Meas. Control 107(1)); with the tool massless and its velocity
taken over the step, ``(p(b) - p_prev) . n / dt`` (implicit Euler, ``p_prev`` the tool's position at
the step's start), a step is at rest when

    ``h(b) = F(b) - k_s b + c (p(b) - p_prev) . n / dt = F(b) - K b + c d / dt = 0``,

``K = k_s + c / dt``, ``d = (a - p_prev) . n``, ``F(b)`` (N) the load along ``-n`` that the step's
contact forces put on the driven body (the sum of the contact and friction forces on its vertices,
projected on ``-n``) when the effector ends the step at ``p(b)``. The damper is thus a second spring
``c / dt`` to the tool's last position; in free motion it keeps the tool ``c v / k_s`` behind a command
moving at ``v``. Each step is the implicit step of :class:`sim_core.simulation.Simulation` at that pose,
so ``F(b)`` is evaluated by taking the step from the same start state.

Convergence: the load cannot grow as the tool backs off (``F`` non-increasing in ``b``), so ``h`` is
strictly decreasing and has one root ``b*``. From any start ``b_0`` the root lies between ``b_0`` and
``b_0 + h(b_0) / K``: there ``h = F(b_0 + h(b_0)/K) - F(b_0)``, of the opposite sign of ``h(b_0)``.
The root is therefore bracketed after the first evaluation, and the safeguarded secant iteration
(a secant step when it lands strictly inside the bracket, else the bracket's midpoint, which halves
it; Brent 1973, "Algorithms for Minimization without Derivatives", ch. 4) converges from any start.
For a linear contact of stiffness ``k_c`` the load is the series spring's ``F = k_s k_c / (k_s + k_c) d``
(``d`` the anchor's depth past first contact), and the first secant step, taken with the contact's
slope (the previous step's estimate), lands on the root when that slope is exact.

The evaluations' Newton starts (:class:`CompressionLoad`, ``Control.position_guess``): the first from the
step's first iterate, the second from the first one's solution; after that, ``starts="chained"`` (default)
starts each from the previous evaluation's solution, ``starts="line"`` from the straight line through the
first two solutions, ``x(b_0) + (b - b_0) (x(b_1) - x(b_0)) / (b_1 - b_0)`` (``b_0`` and the first secant
step ``b_1`` are fixed by the step's inputs), a function of ``b`` alone: ``F(b)`` then does not depend on the
order in which the secant visits compressions. "line" needs a Newton tolerance that resolves the force
tolerance through the contact's stiffness: at the solver's default 1e-4 m/s (1 um a 10 ms step; a gel pad's
contact ~6e5 N/m) a pad's first touch gave loads 0.1 N off a monotone ``F(b)`` and the step ended on its
evaluation limit, where the chained starts (each a neighbour's solution) converged; at a replay's 1e-7 m/s
both converge (docs/benchmarks_log.md, session 57, s57-49release).

``solve="joint"`` takes ``b`` as one more unknown of the step's own Newton solve instead
(:mod:`sim_core.drive_compression`): one implicit step minimises the step's potential and the spring's and
damper's energies over the positions and ``b`` together, the driven (base) vertices tied rigidly to ``b``.
Its balance in ``b`` is ``h(b) = 0`` with ``F`` read as the base's reaction, which adds the driven body's
inertia and mass-proportional damping to the contact load (that module's docstring); the Newton path from
the start ``b_0`` picks the branch of a fold in ``F(b)`` by the energy, where the secant's bracket picks by
its starts. One evaluation a step; a joint solve that diverges is taken again by the secant from the step's start
(:attr:`SeriesDriveStep.joint` says which solved it).

An infinitely stiff spring (``k_s = inf``) is the kinematic drive: the effector at the anchor, one
step, ``b = 0`` (the step taken exactly as without the drive).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from sim_core.control import Control
from sim_core.drive_compression import CompressionUnknown
from sim_core.errors import ConfigError, SimulationDivergedError

SERIES_MAX_EVALUATIONS = 12
"""Default largest number of step evaluations of one drive step: the bracket's bisections alone
shrink it by 2^-10 within that count."""

SERIES_STARTS = ("chained", "line")
"""The evaluations' Newton starts of a drive step (module docstring)."""

SERIES_SOLVES = ("secant", "joint")
"""How a drive step solves for the spring's compression: the safeguarded secant over whole step solves, or as
an unknown of the step's own Newton solve (module docstring)."""


@dataclass(frozen=True)
class SeriesDriveStep:
    """How one step of a :class:`SeriesSpringDrive` ended.

    Attributes:
        compression: the spring's compression ``b`` (m) the step ended at (the tool behind its anchor).
        load: the load ``F`` (N) along ``-n`` on the driven body at the end of the step.
        residual: ``h = F - K b + c d / dt`` (N; ``F - k_s b`` without a damper).
        evaluations: steps evaluated (each one implicit step of the simulation).
        converged: ``|h|`` within the force tolerance, or the bracket narrower than the offset tolerance.
        contact_slope: the last secant's estimate of ``-dF/db`` (N/m, >= 0; 0 when none), the
            next step's first guess of the contact's stiffness.
        joint: the step was solved with the compression among the Newton unknowns (``solve="joint"``); False:
            by the secant, also where a joint solve diverged and the step was taken again by the secant.
    """

    compression: float
    load: float
    residual: float
    evaluations: int
    converged: bool
    contact_slope: float
    joint: bool = False


class SeriesSpringDrive:
    """Drive one effector along a world axis through a series spring (module docstring).

    Args:
        effector: name of the driven effector.
        stiffness: the spring's stiffness ``k_s``, N/m (> 0; ``math.inf``: kinematic).
        load_vertices: global indices of the vertices whose contact forces load the tool (the body the
            effector drives, e.g. a tactile sensor's gel), shape ``(m,)``.
        force_tolerance: ``|h|`` (N) at which a step is accepted (> 0).
        offset_tolerance: bracket width (m) at which a step is accepted (> 0).
        max_evaluations: step evaluations allowed per step (>= 2).
        damping: the damper ``c`` on the tool's velocity along the axis, N s/m (>= 0; finite).
        starts: the evaluations' Newton starts, ``"chained"`` or ``"line"`` (module docstring; the secant's).
        solve: ``"secant"`` or ``"joint"`` (:data:`SERIES_SOLVES`; module docstring).

    Raises:
        ConfigError: a stiffness that is not positive, tolerances that are not positive, fewer than
            two evaluations, no load vertices, a damping that is negative or not finite, unknown starts or
            an unknown solve.
    """

    def __init__(self, effector: str, stiffness: float, load_vertices: np.ndarray,
                 force_tolerance: float = 1.0e-3, offset_tolerance: float = 1.0e-9,
                 max_evaluations: int = SERIES_MAX_EVALUATIONS, damping: float = 0.0,
                 starts: str = "chained", solve: str = "secant") -> None:
        if not stiffness > 0.0:
            raise ConfigError(f"series drive of {effector!r}: stiffness must be > 0 N/m (inf: kinematic), "
                              f"got {stiffness!r}")
        if not (math.isfinite(damping) and damping >= 0.0):
            raise ConfigError(f"series drive of {effector!r}: damping must be finite and >= 0 N s/m, got {damping!r}")
        if not (force_tolerance > 0.0 and offset_tolerance > 0.0):
            raise ConfigError(f"series drive of {effector!r}: tolerances must be > 0, got force "
                              f"{force_tolerance!r} N, offset {offset_tolerance!r} m")
        if int(max_evaluations) < 2:
            raise ConfigError(f"series drive of {effector!r}: max_evaluations must be >= 2, got {max_evaluations!r}")
        if starts not in SERIES_STARTS:
            raise ConfigError(f"series drive of {effector!r}: starts must be one of {SERIES_STARTS}, got {starts!r}")
        if solve not in SERIES_SOLVES:
            raise ConfigError(f"series drive of {effector!r}: solve must be one of {SERIES_SOLVES}, got {solve!r}")
        load_vertices = np.asarray(load_vertices, dtype=np.int64).reshape(-1)
        if load_vertices.size == 0:
            raise ConfigError(f"series drive of {effector!r}: no load vertices")
        self.effector = effector
        self.stiffness = float(stiffness)
        self.load_vertices = load_vertices
        self.force_tolerance = float(force_tolerance)
        self.offset_tolerance = float(offset_tolerance)
        self.max_evaluations = int(max_evaluations)
        self.damping = float(damping)
        self.starts = starts
        self.solve = solve

    @property
    def kinematic(self) -> bool:
        """Whether the spring is infinitely stiff (the effector at its anchor)."""
        return math.isinf(self.stiffness)

    def load(self, state, axis: np.ndarray) -> float:
        """Load ``F`` (N) along ``-axis`` on the load vertices in ``state`` (0 before any contact force)."""
        if state.contact_force is None:
            return 0.0
        total = np.asarray(state.contact_force, dtype=float)[self.load_vertices].sum(axis=0)
        return -float(np.dot(total, axis))

    def step(self, sim, control: Control, axis: np.ndarray, start: float = 0.0,
             contact_slope: float = 0.0) -> SeriesDriveStep:
        """Advance ``sim`` one step with the effector on the spring (module docstring).

        Args:
            sim: the :class:`~sim_core.simulation.Simulation`; its state is replaced by the step's.
            control: the step's control; ``control.effector_pose_target[effector]`` is the anchor pose.
            axis: unit axis ``n`` (3,), world, pointing into the contact.
            start: first compression tried, m (e.g. the previous step's); the joint solve's start.
            contact_slope: guess of ``-dF/db`` (N/m, >= 0) for the first secant step (returned as it is by the
                joint solve).

        The damper reads the tool's position at the step's start from ``sim.state.effector_pose``.

        Returns:
            the :class:`SeriesDriveStep`; ``sim.step_totals`` count the accepted step only.

        Raises:
            ConfigError: an axis that is not a unit vector.
            SimulationDivergedError: a step evaluation failed (from the solver; where a joint solve fails, the
                secant's).
        """
        axis = np.asarray(axis, dtype=float)
        if axis.shape != (3,) or abs(float(np.linalg.norm(axis)) - 1.0) > 1e-9:
            raise ConfigError(f"series drive of {self.effector!r}: axis must be a unit 3-vector, got {axis.tolist()}")
        if self.kinematic:
            sim.step(control)
            f = self.load(sim.state, axis)
            return SeriesDriveStep(0.0, f, 0.0, 1, True, 0.0)
        anchor = np.asarray(control.effector_pose_target[self.effector], dtype=float)
        k, pull, rate, reach = self.stiffness, 0.0, 0.0, 0.0
        if self.damping > 0.0:  # the damper as a spring c / dt to the tool's last position (module docstring)
            previous = np.asarray(sim.state.effector_pose[self.effector], dtype=float)[:3]
            rate, reach = self.damping / sim.dt, float(np.dot(anchor[:3] - previous, axis))
            k, pull = k + rate, rate * reach
        tried = 0
        if self.solve == "joint":
            unknown = CompressionUnknown(self.effector, axis, self.stiffness, rate, reach, float(start),
                                         self.load_vertices)
            totals0 = dataclasses.replace(sim.step_totals)
            try:
                sim.step(dataclasses.replace(control, compression=unknown))
            except SimulationDivergedError:
                # the step again by the secant from the same start state (Simulation.step replaces the state only
                # where it succeeds): a joint Newton solve that stalls (nominal_s101 from +30 %, step 189: the update
                # held at ~1e-3 m/s for 60 iterations, docs/benchmarks_log.md, session 58, lead) is not the end of
                # the replay where the secant's whole-step solves converge
                sim.step_totals, tried = totals0, 1
            else:
                tool = np.asarray(sim.state.effector_pose[self.effector], dtype=float)[:3]
                b = float(np.dot(anchor[:3] - tool, axis))
                f = self.load(sim.state, axis)
                return SeriesDriveStep(b, f, f - k * b + pull, 1, True, max(float(contact_slope), 0.0), joint=True)
        load = CompressionLoad(self, sim, control, axis)

        def h(b: float) -> tuple[float, float]:
            f = load(b)
            return f - k * b + pull, f

        b0 = float(start)
        h0, f0 = h(b0)
        n = 1
        slope = max(float(contact_slope), 0.0)
        if abs(h0) <= self.force_tolerance:
            return SeriesDriveStep(b0, f0, h0, n + tried, True, slope)
        # bracket [lo, hi] with h(lo) >= 0 >= h(hi) (module docstring)
        lo, hi = (b0, b0 + h0 / k) if h0 > 0.0 else (b0 + h0 / k, b0)
        b_prev, h_prev = b0, h0
        b = b0 + h0 / (k + slope)
        while True:
            hb, fb = h(b)
            n += 1
            if hb > 0.0:
                lo = b
            else:
                hi = b
            if b != b_prev and hb != h_prev:
                slope = max(-(hb - h_prev) / (b - b_prev) - k, 0.0)
            if abs(hb) <= self.force_tolerance or hi - lo <= self.offset_tolerance or n >= self.max_evaluations:
                converged = abs(hb) <= self.force_tolerance or hi - lo <= self.offset_tolerance
                return SeriesDriveStep(b, fb, hb, n + tried, converged, slope)
            secant = b - hb * (b - b_prev) / (hb - h_prev) if hb != h_prev else math.nan
            b_prev, h_prev = b, hb
            b = secant if lo < secant < hi else 0.5 * (lo + hi)


class CompressionLoad:
    """The load ``F(b)`` of one drive step as a function of the spring's compression (module docstring).

    Each call takes the step from the same start state with the tool at ``p(b) = a - b n``; its Newton
    iterations start from the step's own first iterate (``control.position_guess``; None: the solver's) for
    the first call, from the first call's solution for the second, and after that as ``drive.starts`` says:
    the previous call's solution (``"chained"``) or the straight line through the first two calls' solutions
    at ``b`` (``"line"``: a function of ``b`` alone).

    Args:
        drive: the :class:`SeriesSpringDrive`.
        sim: the :class:`~sim_core.simulation.Simulation` at the step's start; each call replaces its state
            (and ``step_totals``) by that call's step.
        control: the step's control; ``control.effector_pose_target[drive.effector]`` is the anchor pose.
        axis: unit axis ``n`` (3,), world, pointing into the contact.

    Attributes:
        base: ``[(b, x(b))]``: the compressions (m) and solutions ``(n, 3)`` (m) the starts are made of (the
            first two calls'; "chained": the last call's).
    """

    def __init__(self, drive: SeriesSpringDrive, sim, control: Control, axis: np.ndarray) -> None:
        self.drive, self.sim, self.control, self.axis = drive, sim, control, np.asarray(axis, dtype=float)
        self.state0, self.totals0 = sim.state, dataclasses.replace(sim.step_totals)
        self.anchor = np.asarray(control.effector_pose_target[drive.effector], dtype=float)
        self.base: list[tuple[float, np.ndarray]] = []

    def first_iterate(self, b: float) -> np.ndarray | None:
        """The Newton start of the evaluation at compression ``b`` (m): positions ``(n, 3)``, m, or None."""
        if not self.base:
            return self.control.position_guess
        (b0, x0), (b1, x1) = self.base[0], self.base[-1]
        if len(self.base) == 1 or b1 == b0:
            return x0
        return x0 + ((b - b0) / (b1 - b0)) * (x1 - x0)

    def __call__(self, b: float) -> float:
        """The load ``F`` (N) along ``-n`` on the load vertices after the step with compression ``b`` (m)."""
        b = float(b)
        pose = self.anchor.copy()
        pose[:3] -= b * self.axis
        control = self.control
        trial = dataclasses.replace(control, effector_pose_target={**control.effector_pose_target,
                                                                   self.drive.effector: pose},
                                    position_guess=self.first_iterate(b))
        self.sim.state, self.sim.step_totals = self.state0, dataclasses.replace(self.totals0)
        self.sim.step(trial)
        solution = (b, np.array(self.sim.state.x, dtype=float))
        if self.drive.starts == "chained":
            self.base = [solution]
        elif len(self.base) < 2:
            self.base.append(solution)
        return self.drive.load(self.sim.state, self.axis)
