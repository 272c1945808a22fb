"""The candidate library of the diagnosis: each missing effect k is a parameter beta_k, off at 0.

A candidate gives its signature ``J_k = d y_sim / d beta`` at ``beta = 0`` on the channels it acts
on (aligned to the evidence stamps, unwhitened, trailing axis = its q parameters) and a refit.

Observation-level candidates act after the simulator and are implemented here exactly:

- ``latency``: a stream is observed ``tau`` late, ``y_obs(t) = y(t - tau)``, so ``J = -dy/dt``
  (central differences of the prediction over its stamps). Refit: shift the per-step prediction
  and minimise the residual over tau (grid + bounded Brent).
- ``lens_distortion``: radial ``k1`` of the tactile camera on the marker pixels,
  ``J = d(u, v)/dk1 = (fx x_n r^2, fy y_n r^2)`` at the predicted marker positions
  (:meth:`PinholeCamera.project_parameter_derivative`); the pixels are linear in k1, so the refit is
  linear least squares.
- ``force_bias``: offset + linear drift on each wrench axis, ``w + b0 + b1 (t - t_mid) / T``
  (12 parameters, one joint test); linear.

Physics-level candidates set a simulator parameter and take a secant signature from one extra
rollout at a probe value ``beta_p``: ``J = (y(beta_p) - y(0)) / beta_p``. This is the derivative at
0 for smooth effects (``damping``: mass-proportional damping, 1/s) and the only usable direction for
threshold effects whose derivative at 0 vanishes (``bending_plasticity``: ``beta = 1 / yield_angle``,
probe yield angle = half the largest hinge angle of the nominal rollout). Further physics
candidates (stiction, gel viscoelasticity, adhesion, anisotropic bending) are taken from
``sim_core.candidates.DIAGNOSIS_CANDIDATES`` when that module provides it:
``{effect: {"parameter": name, "probe": value, "one_sided": bool}}`` with ``name`` a
``Simulation`` parameter whose value 0 switches the effect off. Two are adapted to the scene:
the sheet drag (``damping``) is first probed at :func:`sheet_drag_scale` (the drag whose per-step
spring matches the card's bending stiffness per vertex), and gel viscoelasticity is a family over
the relaxation times the recording resolves (:func:`relaxation_times`; the engine keeps the member
with the largest score, Bonferroni-corrected for the family size).
"""

from __future__ import annotations

import functools
import importlib
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sim_core.sensors.camera import PinholeCamera

EFFECTS = ("bending_plasticity", "anisotropic_bending", "damping", "stiction", "gel_viscoelasticity", "adhesion",
           "latency", "lens_distortion", "force_bias")
"""Effect vocabulary of SYSID.md."""

STREAMS = {"markers_xyz": "tactile/markers", "markers_uv": "tactile/markers", "wrench": "tactile/wrench",
           "sheet_points": "sheet/points"}
"""Channel -> the stream (topic without namespace) it is recorded on."""

PARAMETER_BOUNDS = {"candidate.anisotropic_bending": 0.95}
"""Largest |beta| a refit may use, where the simulator limits it (anisotropy must stay below 1)."""

LATENCY_BOUND_S = 0.2
"""Largest |tau| searched by the latency refit, s."""


@dataclass
class DiagnosisContext:
    """What every candidate needs: the recording, the nominal rollout and its prediction.

    Attributes:
        model: the ``sysid.observation.ObservationModel``.
        params: nominal (fitted) parameter values used for the rollout.
        trace: the nominal ``SimTrace`` (per simulation step).
        prediction: channel -> nominal prediction at the evidence stamps (shape of the data).
        channels: channels under test.
    """

    model: Any
    params: dict[str, float]
    trace: Any
    prediction: dict[str, np.ndarray]
    channels: tuple[str, ...]
    _camera: PinholeCamera | None = field(default=None, repr=False)

    def stamps_s(self, channel: str) -> np.ndarray:
        """Evidence stamps of ``channel`` in s from the first pose stamp, ``(n,)``."""
        t0 = int(self.model.step_times_ns[0])
        return (np.asarray(self.model.evidence.t_ns[channel], dtype=np.int64) - t0) * 1e-9

    @property
    def camera(self) -> PinholeCamera:
        """The tactile camera of the scene."""
        if self._camera is None:
            block = self.model.scene["sensors"][self.model.sensor]["camera"]
            self._camera = PinholeCamera.from_dict(block, where=f"sensors.{self.model.sensor}.camera")
        return self._camera

    def shifted(self, channel: str, tau: float) -> np.ndarray:
        """Prediction of ``channel`` observed ``tau`` s late: the per-step trace at ``t - tau`` (held at the ends)."""
        ts = (self.model.step_times_ns - self.model.step_times_ns[0]) * 1e-9
        per_step = np.asarray(self.trace.channel(channel), dtype=float)
        flat = per_step.reshape(per_step.shape[0], -1)
        t = self.stamps_s(channel) - tau
        i = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.shape[0] - 2)
        w = np.clip((t - ts[i]) / (ts[i + 1] - ts[i]), 0.0, 1.0)[:, None]
        out = (1.0 - w) * flat[i] + w * flat[i + 1]
        return out.reshape(t.shape[0], *per_step.shape[1:])


@dataclass
class Refit:
    """A candidate's fitted parameters and the prediction they give.

    Attributes:
        beta: fitted beta, shape ``(q,)``.
        params: named values for the report (``latency_s``, ``k1``, ``damping`` ...).
        prediction: channel -> prediction (only the channels the candidate changes).
        sim_params: simulator parameters to add to the nominal ones (physics candidates).
    """

    beta: np.ndarray
    params: dict[str, float]
    prediction: dict[str, np.ndarray]
    sim_params: dict[str, float] = field(default_factory=dict)


def time_derivative(t_s: np.ndarray, y: np.ndarray) -> np.ndarray:
    """dy/dt along axis 0 by central differences on (possibly uneven) stamps, one-sided at the ends.

    Args:
        t_s: ``(n,)`` s, increasing.
        y: ``(n, ...)``.

    Returns:
        ``(n, ...)``, units of y per s.
    """
    return np.gradient(np.asarray(y, dtype=float), np.asarray(t_s, dtype=float), axis=0)


# ====================================================================================== observation level
class LatencyCandidate:
    """A stream observed late by tau seconds (two-sided: a lead is a negative tau)."""

    name = "latency"
    level = "observation"
    one_sided = False
    acts_on = ("markers_xyz", "markers_uv", "wrench", "sheet_points")

    def probe(self, ctx: DiagnosisContext) -> dict[str, float] | None:
        """No rollout needed."""
        return None

    def signature(self, ctx: DiagnosisContext, probe_prediction: Mapping[str, np.ndarray] | None = None
                  ) -> dict[str, np.ndarray]:
        """``J = -dy/dt`` per channel, shape ``(n, ..., 1)`` (units of y per s)."""
        return {ch: -time_derivative(ctx.stamps_s(ch), ctx.prediction[ch])[..., None]
                for ch in ctx.channels if ch in self.acts_on}

    def refit(self, ctx: DiagnosisContext, channels: Sequence[str], objective: Callable[[Mapping[str, np.ndarray]], float]
              ) -> Refit:
        """One tau for the stream of ``channels``, minimising ``objective(prediction)``."""
        from scipy.optimize import minimize_scalar

        def pred(tau: float) -> dict[str, np.ndarray]:
            return {ch: ctx.shifted(ch, tau) for ch in channels}

        grid = np.linspace(-LATENCY_BOUND_S, LATENCY_BOUND_S, 201)
        costs = [objective(pred(float(t))) for t in grid]
        i = int(np.argmin(costs))
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.shape[0] - 1)]
        res = minimize_scalar(lambda t: objective(pred(float(t))), bounds=(lo, hi), method="bounded",
                              options={"xatol": 1e-5})
        tau = float(res.x) if res.fun <= costs[i] else float(grid[i])
        return Refit(np.array([tau]), {"latency_s": tau}, pred(tau))


class LensDistortionCandidate:
    """Radial distortion k1 of the tactile camera, on the marker pixels."""

    name = "lens_distortion"
    level = "observation"
    one_sided = False
    acts_on = ("markers_uv",)

    def probe(self, ctx: DiagnosisContext) -> dict[str, float] | None:
        """No rollout needed."""
        return None

    def signature(self, ctx: DiagnosisContext, probe_prediction: Mapping[str, np.ndarray] | None = None
                  ) -> dict[str, np.ndarray]:
        """``d(u, v)/dk1`` at the predicted marker positions, shape ``(n, k, 2, 1)`` px."""
        if "markers_uv" not in ctx.channels or "markers_xyz" not in ctx.prediction:
            return {}
        xyz = ctx.prediction["markers_xyz"]
        d = np.stack([ctx.camera.project_parameter_derivative(p, "k1") for p in xyz])
        return {"markers_uv": d[..., None]}

    def refit(self, ctx: DiagnosisContext, channels: Sequence[str], objective: Callable[[Mapping[str, np.ndarray]], float]
              ) -> Refit:
        """Exact: the pixels are linear in k1; k1 minimises the quadratic ``objective`` (3-point fit)."""
        J = self.signature(ctx)["markers_uv"][..., 0]
        uv0 = ctx.prediction["markers_uv"]
        k1 = _quadratic_minimiser(lambda b: objective({"markers_uv": uv0 + b * J}), scale=1.0)
        return Refit(np.array([k1]), {"k1": k1 + ctx.camera.k1}, {"markers_uv": uv0 + k1 * J})


class ForceBiasCandidate:
    """Offset and linear drift on the wrench axes (12 parameters tested jointly; the refit keeps the
    axes whose own offset and drift are supported by the data)."""

    name = "force_bias"
    level = "observation"
    one_sided = False
    acts_on = ("wrench",)

    def probe(self, ctx: DiagnosisContext) -> dict[str, float] | None:
        """No rollout needed."""
        return None

    @staticmethod
    def basis(t_s: np.ndarray) -> np.ndarray:
        """``(n, 2)``: 1 and ``(t - t_mid) / T`` (T = span)."""
        span = max(float(t_s[-1] - t_s[0]), 1e-9)
        return np.stack([np.ones_like(t_s), (t_s - 0.5 * (t_s[0] + t_s[-1])) / span], axis=1)

    def signature(self, ctx: DiagnosisContext, probe_prediction: Mapping[str, np.ndarray] | None = None
                  ) -> dict[str, np.ndarray]:
        """``(n, 6, 12)``: column ``2 a + j`` is basis j on axis a."""
        if "wrench" not in ctx.channels:
            return {}
        B = self.basis(ctx.stamps_s("wrench"))
        n = B.shape[0]
        J = np.zeros((n, 6, 12))
        for a in range(6):
            J[:, a, 2 * a: 2 * a + 2] = B
        return {"wrench": J}

    def refit(self, ctx: DiagnosisContext, channels: Sequence[str], objective: Callable[[Mapping[str, np.ndarray]], float],
              sigma: np.ndarray | None = None, rows: np.ndarray | None = None) -> Refit:
        """Exact per-axis least squares of the residual on the basis (on ``rows`` when given)."""
        t = ctx.stamps_s("wrench")
        B = self.basis(t)
        data = ctx.model.data("wrench")
        resid = data - ctx.prediction["wrench"]
        use = np.ones(t.shape[0], bool) if rows is None else rows
        coef, *_ = np.linalg.lstsq(B[use], resid[use], rcond=None)  # (2, 6)
        # keep an axis only where its own offset + drift pay for their two parameters (BIC per axis,
        # Schwarz 1978): a bias on fz alone then counts 2 parameters, not 12
        n = int(use.sum())
        sse0 = np.sum(resid[use] ** 2, axis=0)
        sse1 = np.sum((resid[use] - B[use] @ coef) ** 2, axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(sse1 > 0, sse0 / sse1, np.where(sse0 > 0, np.inf, 1.0))  # exact fit: keep
            gain = n * np.log(ratio) - 2.0 * math.log(max(n, 2))
        keep = gain > 0.0
        coef = np.where(keep[None, :], coef, 0.0)
        beta = coef[:, keep].T.reshape(-1)
        params = {}
        for a, axis in enumerate(("fx", "fy", "fz", "tx", "ty", "tz")):
            params[f"bias_{axis}"] = float(coef[0, a])
            params[f"drift_{axis}"] = float(coef[1, a])
        return Refit(beta, params, {"wrench": ctx.prediction["wrench"] + B @ coef})


def apply_observation_refit(hctx: DiagnosisContext, rf: Refit, pred: dict[str, np.ndarray]) -> None:
    """Apply an observation-level refit (latency, k1, bias) to another recording's prediction, in place.

    Args:
        hctx: context of the other recording (its nominal trace and prediction).
        rf: the refit (``latency_s``, ``k1`` or ``bias_*`` in its params).
        pred: channel -> prediction of the other recording, updated.
    """
    if "latency_s" in rf.params:
        for ch in rf.prediction:
            if ch in hctx.channels:
                pred[ch] = hctx.shifted(ch, float(rf.params["latency_s"]))
    elif "k1" in rf.params and "markers_uv" in hctx.channels:
        J = LensDistortionCandidate().signature(hctx)["markers_uv"][..., 0]
        pred["markers_uv"] = pred["markers_uv"] + float(rf.beta[0]) * J
    elif "bias_fx" in rf.params and "wrench" in hctx.channels:
        # the refit's beta holds only the axes it kept; the params hold all six (0 where dropped)
        axes = ("fx", "fy", "fz", "tx", "ty", "tz")
        coef = np.array([[float(rf.params[f"bias_{a}"]) for a in axes], [float(rf.params[f"drift_{a}"]) for a in axes]])
        B = ForceBiasCandidate.basis(hctx.stamps_s("wrench"))
        pred["wrench"] = pred["wrench"] + B @ coef


def _quadratic_minimiser(f: Callable[[float], float], scale: float) -> float:
    """Minimiser of a function known to be quadratic, from three evaluations."""
    f0, fp, fm = f(0.0), f(scale), f(-scale)
    curv = (fp + fm - 2.0 * f0) / scale ** 2
    if not curv > 0.0:
        return 0.0
    return float(-(fp - fm) / (2.0 * scale) / curv)


# ====================================================================================== physics level
class PhysicsParameterCandidate:
    """An effect switched on by a simulator parameter; secant signature from one probe rollout.

    Args:
        name: effect name (SYSID.md vocabulary).
        parameter: ``Simulation`` parameter name.
        probe_beta: beta of the probe rollout (> 0).
        one_sided: beta >= 0 only.
        to_parameter: beta -> parameter value (default identity; plasticity: ``1 / beta``).
        report_name: key of the fitted value in the report.
        scaled_probe: the probe is a fixed fraction of a scale estimated from the scene (the sheet
            drag or weight scale), not a value whose effect size is known: its first replay is the
            least likely to land in the probe target, so its chain is started first
            (:func:`start_rank`).
    """

    level = "physics"

    def __init__(self, name: str, parameter: str, probe_beta: float, one_sided: bool = True,
                 to_parameter: Callable[[float], float] | None = None, report_name: str | None = None,
                 settings: Mapping[str, float] | None = None, family_size: int = 1,
                 scaled_probe: bool = False) -> None:
        if not (math.isfinite(probe_beta) and probe_beta > 0.0):
            raise ValueError(f"candidate {name}: probe beta must be a positive number, got {probe_beta!r}")
        if int(family_size) < 1:
            raise ValueError(f"candidate {name}: family size must be >= 1, got {family_size!r}")
        self.name = name
        self.parameter = parameter
        # fixed secondary simulator settings of this member of a family (e.g. a relaxation time), set
        # with the effect whenever it is on; family_size = number of members tested for the effect
        self.settings = {k: float(v) for k, v in (settings or {}).items()}
        self.family_size = int(family_size)
        self.scaled_probe = bool(scaled_probe)
        self.probe_beta = float(probe_beta)
        self.one_sided = one_sided
        self.to_parameter = to_parameter or (lambda b: float(b))
        self.report_name = report_name or parameter
        # refits trust the secant signature up to a few probe sizes, and stay inside the parameter's range
        self.bound = min(4.0 * self.probe_beta, PARAMETER_BOUNDS.get(parameter, math.inf))
        self.acts_on = ("markers_xyz", "markers_uv", "wrench", "sheet_points")

    def shrink_probe(self, factor: float) -> None:
        """Scale ``probe_beta`` (and the refit bound that follows it) by ``factor`` in (0, 1)."""
        if not 0.0 < factor < 1.0:
            raise ValueError(f"candidate {self.name}: shrink factor must be in (0, 1), got {factor!r}")
        self.probe_beta *= factor
        self.bound = min(4.0 * self.probe_beta, PARAMETER_BOUNDS.get(self.parameter, math.inf))

    def grow_probe(self, factor: float) -> bool:
        """Scale ``probe_beta`` up by ``factor > 1`` (a probe too small to move the prediction above
        the noise gives a signature of round-off); stays below 90 % of the parameter's bound.

        Returns:
            whether the probe changed.

        Raises:
            ValueError: ``factor <= 1``.
        """
        if not factor > 1.0:
            raise ValueError(f"candidate {self.name}: grow factor must be > 1, got {factor!r}")
        new = min(self.probe_beta * factor, self.largest_probe)
        if not new > self.probe_beta:
            return False
        self.probe_beta = new
        self.bound = min(4.0 * self.probe_beta, PARAMETER_BOUNDS.get(self.parameter, math.inf))
        return True

    @property
    def largest_probe(self) -> float:
        """Largest probe :meth:`grow_probe` gives: 90 % of the parameter's bound (inf where it has none)."""
        return 0.9 * PARAMETER_BOUNDS.get(self.parameter, math.inf)

    @property
    def key(self) -> str:
        """Identifier of this member of its family: the effect name, plus its settings when it has any."""
        if not self.settings:
            return self.name
        return self.name + "[" + ", ".join(f"{k.rsplit('.', 1)[-1]}={v:.3g}" for k, v in sorted(self.settings.items())) + "]"

    def probe(self, ctx: DiagnosisContext) -> dict[str, float]:
        """Parameters of the probe rollout (nominal values plus the effect at ``probe_beta``)."""
        return {**ctx.params, self.parameter: self.to_parameter(self.probe_beta), **self.settings}

    def signature(self, ctx: DiagnosisContext, probe_prediction: Mapping[str, np.ndarray] | None = None
                  ) -> dict[str, np.ndarray]:
        """Secant ``(y(beta_p) - y(0)) / beta_p`` per tested channel, ``(n, ..., 1)``.

        Raises:
            ValueError: no probe prediction given.
        """
        if probe_prediction is None:
            raise ValueError(f"candidate {self.name} needs the prediction of its probe rollout")
        return {ch: ((probe_prediction[ch] - ctx.prediction[ch]) / self.probe_beta)[..., None]
                for ch in ctx.channels if ch in probe_prediction}

    def sim_parameters(self, beta: float) -> dict[str, float]:
        """Simulator parameters for beta (clipped at 0 for one-sided effects; ``{}`` when off)."""
        b = max(beta, 0.0) if self.one_sided else beta
        if b == 0.0:
            return {}  # off: the nominal model (an infinite yield angle cannot be set, it is the default)
        return {self.parameter: self.to_parameter(b), **self.settings}


def yield_angle_for(beta: float, theta_max: float) -> float:
    """Rest-angle yield threshold (rad) for exceedance ``beta = theta_max / theta_yield - 1 >= 0``."""
    return theta_max / (1.0 + beta)


def hinge_angle_history(model: Any, sheet_points: np.ndarray, stride: int = 1) -> np.ndarray | None:
    """Largest ``|theta|`` (rad) over the sheet's hinges at every ``stride``-th step of a replay.

    Args:
        model: the ``sysid.observation.ObservationModel`` of the replay (its scene's sheet grid).
        sheet_points: the replay's ``SimTrace.sheet_points`` ``(K + 1, nx * ny, 3)`` in m.
        stride: step stride (>= 1).

    Returns:
        the angles ``(ceil((K + 1) / stride),)``, or None when the scene has no grid sheet with
        hinges matching the sheet points.
    """
    from sim_core.energies.hinge_bending.reference import dihedral_angle
    from sim_core.mesh.sheet import grid_sheet, sheet_topology
    from sim_core.scenes.scene_file import load_scene_file

    sheet = getattr(load_scene_file(model.scene), "sheet", None)
    if sheet is None:
        return None
    pts = np.asarray(sheet_points, dtype=float)
    nx, ny = sheet.resolution
    if pts.ndim != 3 or pts.shape[1] != nx * ny:
        return None
    hinges = sheet_topology(grid_sheet(sheet.size, sheet.resolution, sheet.origin).triangles).hinges
    if hinges.shape[0] == 0:
        return None
    return np.array([float(np.max(np.abs(dihedral_angle(p[hinges])))) for p in pts[::stride]])


def max_hinge_angle(ctx: DiagnosisContext) -> float:
    """Largest |dihedral angle| (rad) of the sheet over the nominal rollout (flat rest shape;
    about 100 steps sampled)."""
    pts = np.asarray(ctx.trace.sheet_points, dtype=float)
    angles = hinge_angle_history(ctx.model, pts, max(1, pts.shape[0] // 100))
    return 0.0 if angles is None else float(angles.max())


def sheet_drag_scale(sim_model: Any, dt: float) -> float:
    """Drag coefficient (1/s) at which a sheet's drag is as stiff per step as its bending, ``c_ref``.

    Implicit Euler turns the drag ``-c m v`` into a spring ``c m_i / dt`` (N/m) that pulls vertex i
    back to where it was at the start of the step; the card's own restoring stiffness per vertex is
    about ``D / A_v`` (Kirchhoff bending stiffness D in N m over the rest area per vertex A_v). In a
    quasi-static press the drag changes the motion only where the two are comparable, so

        c_ref = D dt / (m_v A_v),   m_v = sheet mass / vertex count, A_v = rest area / vertex count,

    the smallest over the sheets (the most easily damped one). Far below ``c_ref`` the drag's change of
    the prediction is round-off or a contact-state flip, not its smooth response (the benchmark card:
    c_ref 3.4e5 1/s, a probe of 100 1/s moves the prediction by 1e-3 noise units).

    Args:
        sim_model: ``sim_core`` Model (bodies with ``kind``, ``vertices``, ``triangles``, ``material``;
            ``x_rest``; ``vertex_mass()``).
        dt: time step in s (> 0).

    Returns:
        ``c_ref`` in 1/s, or ``nan`` when there is no sheet with a positive bending stiffness and mass.
    """
    masses = sim_model.vertex_mass() if callable(getattr(sim_model, "vertex_mass", None)) else sim_model.vertex_mass
    out = math.inf
    for body in sim_model.bodies.values():
        if body.kind != "sheet":
            continue
        ids = np.unique(np.asarray(body.vertices, dtype=np.int64).reshape(-1))
        tri = np.asarray(body.triangles, dtype=np.int64)
        if ids.size == 0 or tri.size == 0:
            continue
        x = np.asarray(sim_model.x_rest, dtype=float)
        area = 0.5 * float(np.sum(np.linalg.norm(np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]]),
                                                 axis=1)))
        D = float(body.material.get("bending_stiffness", 0.0))
        m_v = float(np.sum(np.asarray(masses, dtype=float)[ids])) / ids.size
        a_v = area / ids.size
        if D > 0.0 and m_v > 0.0 and a_v > 0.0:
            out = min(out, D * dt / (m_v * a_v))
    return out if math.isfinite(out) else math.nan


ADHESION_PROBE_WEIGHTS = 4.0
"""Adhesion probe, in units of :func:`adhesion_weight_scale`: bonds that together could lift four
times the sheet's weight."""


def adhesion_weight_scale(sim_model: Any) -> float:
    """Bond strength per pair (N) at which the gel's contact-face pairs together bear the sheets' weight.

    A tacky gel lifts a light card once its bonds together hold more than the card's weight (and
    bending); far above that the card follows the gel whatever the strength, and only the pull on the
    gel (wrench, markers) still grows with it. The fixed probe of 0.05 N per pair (330 card weights on
    the benchmark's 20 face vertices) made the linearised refit land on the probe itself, which pulled
    the gel 20 times harder than the recording showed (docs/benchmarks_log.md, 2026-11-22).

        w = g m_sheets / n_face,

    with ``g`` the gravity magnitude, ``m_sheets`` the total sheet mass and ``n_face`` the number of
    gel contact-face vertices (every tactile sensor's ``contact_triangles``).

    Args:
        sim_model: ``sim_core`` Model (``bodies`` with ``kind``/``vertices``, ``sensors`` with
            ``contact_triangles``, ``gravity``, ``vertex_mass()``).

    Returns:
        ``w`` in N, or ``nan`` without a sheet, gravity or contact face.
    """
    masses = np.asarray(sim_model.vertex_mass() if callable(getattr(sim_model, "vertex_mass", None))
                        else sim_model.vertex_mass, dtype=float)
    sheet = [np.unique(np.asarray(b.vertices, dtype=np.int64).reshape(-1)) for b in sim_model.bodies.values()
             if b.kind == "sheet"]
    face = [np.unique(np.asarray(t.contact_triangles, dtype=np.int64)) for t in sim_model.sensors.values()
            if getattr(t, "contact_triangles", None) is not None]
    g = float(np.linalg.norm(np.asarray(getattr(sim_model, "gravity", np.zeros(3)), dtype=float)))
    n_face = int(np.unique(np.concatenate(face)).size) if face else 0
    mass = float(sum(np.sum(masses[ids]) for ids in sheet))
    if not (g > 0.0 and mass > 0.0 and n_face > 0):
        return math.nan
    return g * mass / n_face


RELAXATION_GRID_RATIO = 3.0
"""Spacing of the relaxation-time grid of the gel viscoelasticity candidate (factor between taus)."""

RELAXATION_MIN_STEPS = 5
"""Shortest relaxation time of the grid, in simulation steps (a shorter one is not resolved)."""


def relaxation_times(dt: float, duration: float, ratio: float = RELAXATION_GRID_RATIO,
                     min_steps: int = RELAXATION_MIN_STEPS) -> list[float]:
    """Log-spaced relaxation times (s) a recording can resolve: from ``min_steps dt`` up to its duration.

    A gel's relaxation time is not known beforehand, and the signature of a Maxwell branch depends on
    it much more than on anything the nominal fit can absorb (on the benchmark's gel recording at
    strength 2.6 the residual supports a branch with tau 0.1 s at one scale on the markers, pixels and
    wrench -- 0.87, 0.90, 0.93 -- and one with tau 0.3 s at 0.56, 0.58, 0.13). The candidate is
    therefore a family over ``tau_min, tau_min ratio, ...`` (the last one <= duration, at least one):
    a discrete relaxation spectrum (Prony series, Park & Schapery 1999) of which the diagnosis tests
    every member and keeps the best, Bonferroni-corrected for the size of the grid.

    Raises:
        ValueError: non-positive ``dt``, ``ratio <= 1`` or ``min_steps < 1``.
    """
    if not (dt > 0 and ratio > 1 and min_steps >= 1):
        raise ValueError(f"relaxation_times: need dt > 0, ratio > 1, min_steps >= 1 (got {dt}, {ratio}, {min_steps})")
    tau = min_steps * dt
    out = [tau]
    while out[-1] * ratio <= duration * (1 + 1e-9):
        out.append(out[-1] * ratio)
    return out


DRAG_PROBE_FRACTION = 1.0
"""The damping candidate's first probe, as a fraction of :func:`sheet_drag_scale`. At ``c_ref`` the
drag's smooth response is about the probe target (0.6-1.3 noise units on the benchmark card); a
smaller probe is not more linear there but less reliable: below ``c_ref`` the change of a
quasi-static press-slide can be dominated by one contact-state flip that any small drag triggers
(benchmark damping x4, SciPy solver: at 1e4 and 3.4e4 1/s the change is 0.5-0.9 noise units with
per-channel regression scales of mixed sign, -1.5 to 0.5; at 1e5-3.4e5 1/s one scale, 0.84-1.1,
fits every channel). The probe calibration then rescales it towards its target change."""


def _known_parameter(model: Any, name: str, names: set[str]) -> bool:
    """Whether the simulator accepts parameter ``name`` (``candidate.<x>`` are not listed in
    ``parameter_names`` but are readable through ``get_parameter``)."""
    if name in names:
        return True
    try:
        model.simulation().get_parameter(name)
    except Exception:  # ConfigError: the simulator does not know this candidate
        return False
    return True


RELAXATION_SETTING = "candidate.gel_viscoelasticity.tau"
"""Simulator setting of the gel candidate's relaxation time, s."""


def _duration_s(ctx: DiagnosisContext) -> float:
    """Span of the replayed steps in s."""
    steps = np.asarray(ctx.model.step_times_ns, dtype=np.int64)
    return float(steps[-1] - steps[0]) * 1e-9


def _drag_scale_of(ctx: DiagnosisContext) -> float:
    """:func:`sheet_drag_scale` of the context's simulator at its step, with fitted sheet bending
    stiffness / density / thickness in ``ctx.params`` taken into account (``c_ref`` is proportional to
    ``D / (density thickness)``); ``nan`` when not available."""
    try:
        c_ref = sheet_drag_scale(ctx.model.simulation().model, float(ctx.model.dt))
        for name, power in (("sheet.bending_stiffness", 1.0), ("sheet.density", -1.0), ("sheet.thickness", -1.0)):
            if name in ctx.params:
                c_ref *= (float(ctx.params[name]) / float(ctx.model.parameter_value(name))) ** power
        return float(c_ref)
    except Exception:  # noqa: BLE001 -- a scene without a sheet or a simulator without these fields
        return math.nan


def _weight_scale_of(ctx: DiagnosisContext) -> float:
    """:func:`adhesion_weight_scale` of the context's simulator (fitted sheet density / thickness in
    ``ctx.params`` taken into account: the mass is proportional to both); ``nan`` when not available."""
    try:
        w = adhesion_weight_scale(ctx.model.simulation().model)
        for name in ("sheet.density", "sheet.thickness"):
            if name in ctx.params:
                w *= float(ctx.params[name]) / float(ctx.model.parameter_value(name))
        return float(w)
    except Exception:  # noqa: BLE001 -- a scene without a sheet or a simulator without these fields
        return math.nan


def default_candidates(ctx: DiagnosisContext, extra: Mapping[str, Mapping[str, Any]] | None = None,
                       damping_probe: float = 2.0) -> list[Any]:
    """The candidate library available for this scene.

    Args:
        ctx: diagnosis context (the plasticity probe needs the nominal rollout).
        extra: additional physics candidates ``{effect: {"parameter", "probe", "one_sided"}}``
            (default: ``sim_core.candidates.DIAGNOSIS_CANDIDATES`` when that module defines it).
        damping_probe: probe of the mass-proportional damping, 1/s.

    Returns:
        candidate objects: latency, lens_distortion, force_bias, damping (the global
        mass-proportional one only when ``extra`` has no ``damping`` the simulator knows),
        bending_plasticity (when the sheet bends at all in the nominal rollout; left out while
        ``ctx.trace`` is None), then the extra ones whose parameter the simulator knows.
    """
    out: list[Any] = [LatencyCandidate(), LensDistortionCandidate(), ForceBiasCandidate()]
    names = set(ctx.model.simulation().parameter_names)
    if extra is None:
        try:
            extra = getattr(importlib.import_module("sim_core.candidates"), "DIAGNOSIS_CANDIDATES", None)
        except ImportError:
            extra = None
    # the library's own damping (sheets only) replaces the global mass-proportional one when available
    own_damping = "damping" in (extra or {}) and _known_parameter(ctx.model, extra["damping"]["parameter"], names)
    if (not own_damping and "damping" in names
            and float(ctx.params.get("damping", ctx.model.parameter_value("damping"))) == 0.0):
        out.append(PhysicsParameterCandidate("damping", "damping", damping_probe, True, report_name="damping_per_s"))
    if (ctx.trace is not None and "sheet.yield_angle" in names
            and not math.isfinite(float(ctx.params.get("sheet.yield_angle", ctx.model.parameter_value("sheet.yield_angle"))))):
        theta_max = max_hinge_angle(ctx)
        if theta_max > 1e-3:
            # beta = theta_max / theta_yield - 1: the effect starts at beta = 0 (yield at the largest
            # bend of the nominal rollout) and grows with it, so the secant signature and the
            # linearised refit stay on the side where the sheet yields; the probe (beta = 1) yields at
            # half the largest bend
            out.append(PhysicsParameterCandidate("bending_plasticity", "sheet.yield_angle", 1.0, True,
                                                 to_parameter=functools.partial(yield_angle_for, theta_max=theta_max),
                                                 report_name="yield_exceedance"))
    for effect, spec in (extra or {}).items():
        if effect not in EFFECTS:
            raise ValueError(f"candidate {effect!r} is not in the effect vocabulary ({', '.join(EFFECTS)})")
        if effect not in {c.name for c in out} and _known_parameter(ctx.model, spec["parameter"], names):
            probe = float(spec["probe"])
            scaled = False
            if effect == "damping":
                # the library's sheet drag: probe where the drag acts (sheet_drag_scale), not at a fixed
                # value three decades below it, whose change is round-off or a contact-state flip
                c_ref = _drag_scale_of(ctx)
                if math.isfinite(c_ref) and c_ref > 0.0:
                    probe = max(probe, DRAG_PROBE_FRACTION * c_ref)
                    scaled = True
            if effect == "adhesion":
                # probe where the bonds carry the sheet (adhesion_weight_scale), not at a fixed strength
                # hundreds of sheet weights above it
                w = _weight_scale_of(ctx)
                if math.isfinite(w) and w > 0.0:
                    probe = ADHESION_PROBE_WEIGHTS * w
                    scaled = True
            if effect == "gel_viscoelasticity" and _known_parameter(ctx.model, RELAXATION_SETTING, names):
                taus = relaxation_times(float(ctx.model.dt), _duration_s(ctx))
                out.extend(PhysicsParameterCandidate(effect, spec["parameter"], probe, bool(spec.get("one_sided", True)),
                                                     settings={RELAXATION_SETTING: tau}, family_size=len(taus))
                           for tau in taus)
                continue
            out.append(PhysicsParameterCandidate(effect, spec["parameter"], probe,
                                                 bool(spec.get("one_sided", True)), scaled_probe=scaled))
    return out


def start_rank(c: Any, index: int) -> tuple[int, int]:
    """Start order of a candidate's replay chain among those of the library (lower first).

    Probes sized from a scene scale (:attr:`PhysicsParameterCandidate.scaled_probe`) come first, then
    the others in library order: a scaled probe's prediction change is known only to a decade or two
    (latency_s103: damping's first probe moved the prediction by 68 noise units against a target of 2,
    and its chain took four replays in a row), and a long chain started last leaves one worker alone
    at the end of the probe phase (docs/benchmarks_log.md, session 10). Only when replays start changes;
    what each chain returns does not.

    Args:
        c: a library member.
        index: its position in the library.

    Returns:
        ``(0 for a scaled probe else 1, index)``.
    """
    return (0 if getattr(c, "scaled_probe", False) else 1, int(index))


def in_start_order(library: Sequence[Any]) -> list[Any]:
    """``library`` sorted by :func:`start_rank` (scaled probes first, then library order)."""
    return [library[i] for i in sorted(range(len(library)), key=lambda i: start_rank(library[i], i))]


def rollout_free_probes(model: Any, params: Mapping[str, float], channels: Sequence[str],
                        names: Sequence[str] | None = None) -> list[dict[str, float]]:
    """Probe parameter sets known before the nominal rollout, in chain start order (:func:`start_rank`).

    Every physics candidate's probe except bending plasticity's (sized from the nominal rollout's
    largest bend) depends only on the scene and the nominal parameters, so these replays can run
    while the nominal one does (:meth:`sysid.diagnose.schedule.ReplayScheduler.prefetch`).
    They are the very parameter sets :func:`default_candidates` gives once the rollout is in.

    Args:
        model: the ``sysid.observation.ObservationModel``.
        params: nominal (fitted) parameter values.
        channels: channels under test.
        names: restrict to these effects (None: all).

    Returns:
        one ``Model.set_parameter`` dict per probe.
    """
    ctx = DiagnosisContext(model, dict(params), None, {}, tuple(channels))
    library = [c for c in default_candidates(ctx) if names is None or c.name in names]
    return [p for p in (c.probe(ctx) for c in in_start_order(library)) if p is not None]


# ====================================================================================== families
def member_key(c: Any) -> str:
    """A library member's identifier (:attr:`PhysicsParameterCandidate.key`; the name for the others)."""
    return getattr(c, "key", c.name)


def select_family_members(library: list, tests: list[dict[str, Any]], notes: list[str]) -> tuple[list, list[dict[str, Any]]]:
    """Keep one member per candidate family (the gel's Maxwell branch over a grid of relaxation times).

    A family tests one effect with a nuisance setting that only exists under the alternative (the
    relaxation time of a branch whose stiffness is 0 under the null; Davies 1987). Every member is
    tested; the one with the largest statistic (over channels) is kept, and its p-values are
    multiplied by the family size before Holm (Bonferroni over the members: the family-wise error
    stays at ``alpha`` whichever member is picked). Members of other families: factor 1.

    Args:
        library: candidates (several may share a name: the members of a family).
        tests: score tests, each with ``effect``, ``key`` (:func:`member_key`) and ``result``.
        notes: the report's notes (one line per family is appended).

    Returns:
        the library with one member per effect, and the tests of the kept members with ``p_family``.
    """
    groups: dict[str, list] = {}
    for c in library:
        groups.setdefault(c.name, []).append(c)
    keep = []
    for name, members in groups.items():
        if len(members) == 1:
            keep.append(members[0])
            continue
        best = {member_key(c): max((t["result"].statistic for t in tests if t["key"] == member_key(c)), default=-math.inf)
                for c in members}
        chosen = max(members, key=lambda c: best[member_key(c)])
        keep.append(chosen)
        notes.append(f"{name}: {len(members)} members tested ("
                     + ", ".join(f"{k} S {v:.3g}" for k, v in best.items())
                     + f"); kept {member_key(chosen)}, p-values x {len(members)}")
    kept = {member_key(c) for c in keep}
    size = {member_key(c): len(groups[c.name]) for c in keep}
    out = []
    for t in tests:
        if t["key"] in kept:
            t["p_family"] = min(1.0, size[t["key"]] * float(t["result"].p_value))
            out.append(t)
    return keep, out
