"""Observation model of system identification: replay a recording's effector motion in the simulator.

The recorded (measured) effector pose ``pose`` is resampled at the simulation step,
``t_k = t_0 + k dt`` (k = 0 .. K), and fed as the kinematic target of step k (the effector reaches
it at the end of the step; ``sim_core.effector`` rate-limits it). The simulator's state after step k
is observed at ``t_k`` (markers in the sensor frame and their pixels, net wrench on the gel, sheet
points in ``world``), and each observed stream is interpolated linearly in time to the stamps of the
matching evidence channel (:meth:`ObservationModel.align`). The initial effector pose of the scene
is replaced by the recorded pose at ``t_0`` so that the gel is built where the recording starts.
With a series drive (:meth:`ObservationModel.set_drive_stiffness`) the pad's position along the sensor
normal is solved each step, on a spring anchored at the recorded command (:mod:`sysid.replay_drive`).

A task scene (``kind: task``; :mod:`sim_core.scenes.task_scene`) is replayed the same way with
every effector driven: each by its recorded ``<effector>/pose_cmd`` held as the robot holds it
(zero-order hold: step k, from ``t_{k-1}`` to ``t_k``, takes the last command logged at or before
``t_{k-1}`` within half a step, and the effector's recorded start pose before the first command).
A command's time is its log time, when the robot took it (:func:`sysid.bagio.read_effector_streams`):
``thinshell sim`` logs one every step at the step's start, the sim node logs one when it takes it,
between steps, whatever the deploy node scheduled it for; the replay applies the same effector rate
limits. Where no command was recorded (an effector held still) the effector follows its
``<effector>/pose`` resampled at ``t_k`` as above; its finger opening follows ``<effector>/gripper_cmd``
held the same way (the scene's ``opening`` before the first) when recorded (``Evidence.effectors``). Each
effector starts at its recorded pose at ``t_0``. A task scene without a tactile sensor
has no ``markers_*`` / ``wrench`` channels; ``sheet_points`` are the vertices of its body named
``sheet`` in grid order (``Simulation.observe``), their count checked against the recording.

Residuals are whitened per channel and axis by the white-noise level estimated from the recording
(``Evidence.noise``, :mod:`sysid.noise`): ``r = (y_data - y_sim) / sigma``, so that weighted least
squares with ``W = diag(1 / sigma^2)`` is ordinary least squares on ``r``. Marker pixels read off
images carry a per-marker weight ``w`` in ``[0, 1]`` (``Evidence.markers_uv_weight``: 0 for a marker the
tracker interpolated, the visible fraction for one cut by the image border): their residual is
``r = sqrt(w) (y_data - y_sim) / sigma``, so an interpolated marker does not count.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sim_core.backend import backend_of_arch
from sim_core.control import Control
from sim_core.errors import CalibrationError
from sim_core.kernel_compile import compile_kernels
from sim_core.scenes import load_scene
from sim_core.scenes.scene_file import SceneFile, load_scene_file
from sim_core.scenes.task_file import TaskSceneFile, is_task_scene, load_any_scene_file
from sim_core.scenes.task_scene import build_task_scene
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from sim_core.transforms import quat_to_matrix
from sysid.command_path import anchor_path
from sysid.evidence import Evidence, resample_pose
from sysid.replay_drive import ReplayDrive
from sysid.replay_trace import PREDICTABLE_CHANNELS, Resume, SimTrace
from sysid.replay_time import held as _held, interpolation as _interpolation

DEFAULT_FIT_CHANNELS = ("markers_xyz", "wrench", "sheet_points")
"""Channels fitted by default: ``markers_uv`` is a function of ``markers_xyz`` (camera model) and
would count the same measurement twice, so it is only fitted when ``markers_xyz`` is absent."""

CHANNEL_UNITS = {"markers_xyz": "m", "markers_uv": "px", "wrench": "N | N m", "sheet_points": "m"}

SENSOR_PARAMETERS = ("sensor.normal_offset",)
"""Replay parameters of the sensor mount that are not ``Model`` parameters: ``sensor.normal_offset``
(m) moves the replayed effector along the sensor normal (+ = into the contact), i.e. it corrects where
contact begins for an error of the mount or of the effector's height calibration."""

NOISE_FLOOR = {"markers_xyz": 1e-7, "markers_uv": 1e-3, "wrench": 1e-4, "sheet_points": 1e-7}
"""Lower bound of a per-axis noise level (SI / px): a noise-free (synthetic or quantised) channel
would otherwise get an infinite weight."""


REPLAY_DT_HALVINGS = 4
"""Substep retries of a replay step whose Newton solve fails (``SolverConfig.dt_halvings_on_failure``):
dt/2, dt/4, ... down to dt/16 before the replay gives up; ``Simulation.step_totals`` counts them."""

REPLAY_TOL_VELOCITY = 1e-7
"""Newton tolerance of every replay step (``SolverConfig.tol_velocity``, m/s; the simulator's default is 1e-4).

A step stopped at the simulator's default stops on a Newton update it does not apply, so its result is off the step's
minimiser by up to ``tol_velocity * dt`` (1 um at the fit's 10 ms step with 1e-4), and whether a step ends one iteration
earlier or later jumps with the parameters. Where the card slides on the table under the gel, its rigid motion is held
by little but inertia and a saturated friction, and such a jump grows step by step: at 1e-4, nominal_s101 replayed
(kinematic, first 2 s) at gel moduli 1e-5 apart moved the markers by 0.0085 whitened RMS and the cost by -42 where its
slope gives +3. Solved to 1e-7 m/s the same pair differs by 2e-5 / 1.1e-4 (markers / wrench, linear in the step), and
the cost is converged to 1e-6 of itself (docs/benchmarks_log.md, session 55, s55-49rest)."""

REPLAY_SLEEPING = True
"""Whether a plain replay (:meth:`ObservationModel.simulate`) lets a body at rest that nothing moving can reach sleep
(``SolverConfig.sleeping``, :mod:`sim_core.sleeping`): on. The card lying on the table while the pad is in the air (the
approach, and on a lift after the release) is otherwise solved at every Newton iteration for an update of ~1e-15 m/s;
asleep, its DoFs are held and its elastic, contact and friction terms are not evaluated, and the replay moves by less
than ``sleep_velocity * dt`` a step it sleeps (1e-9 m; nominal_s109's whole replay by 2.8e-17 m, in 357 of its 472
steps asleep, CPU 16.0 -> 12.0 s: docs/benchmarks_log.md, session 64, 64step). The tangents' replays
(:func:`sysid.replay_drive.drive_sensitivities`) keep every body awake: a sleeping step's record is not differentiable."""

REPLAY_APPLY_LAST_UPDATE = False
"""Whether a replay step ends with its last Newton update applied (``SolverConfig.apply_last_update``): off.

Its tangents are exact (the solver marks such a step's Newton matrix as the previous iterate's, and the tangents take
the exact Hessian at the result: tests/sim_core/test_applied_update.py), but at the 1e-5 m/s where it would replace
1e-7 unapplied it is neither cheaper nor as smooth (docs/benchmarks_log.md, session 56, s56-49applied):
nominal_s101 through its drive (361 steps), 1,979 Newton iterations against 2,443 but 2,025 factorisations against
1,910 (the simplified Newton test, which ends most unapplied steps without one, is not run with the update applied)
and 361 refactorisations at the result for the tangents against 309; and on tests/sysid/test_calibration.py's
press-slip at eps_v x 0.55 its central differences in eps_v (step 1e-3) are 1.04 % off the converged replay's
(1e-7 unapplied: 1e-4; 1e-6 applied: 1e-6, but 912 factorisations against 768 on the kinematic 2 s)."""

class ObservationWarning(UserWarning):
    """A channel cannot be fitted (absent from the recording, or not predictable)."""


def scene_dict_for(evidence: Evidence, scene: str | Path | Mapping[str, Any] | SceneFile | None = None,
                   simulation: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The scene used to simulate ``evidence``, as a plain dict.

    Args:
        evidence: the recording.
        scene: overriding scene (path, mapping or :class:`SceneFile`); default the bag's ``scene.yaml``.
        simulation: keys merged into the scene's optional ``simulation:`` block
            (``sim_core.scenes.tactile_scene``), e.g. ``{"gel_resolution": [5, 4, 2]}``.

    Raises:
        CalibrationError: no scene given and the bag has none.
        ConfigError: invalid scene (names the file and key).
    """
    if scene is None:
        if evidence.scene is None:
            raise CalibrationError(f"{evidence.source.bag_path}: the bag has no scene.yaml; pass a scene file")
        parsed = evidence.scene
    else:
        parsed = load_any_scene_file(scene)
    out = copy.deepcopy(parsed.to_dict())
    if isinstance(parsed, TaskSceneFile):
        return out  # validated when its model is built
    if simulation:
        block = dict(out.get("simulation") or {})
        block.update(simulation)
        out["simulation"] = block
    load_scene_file(out)
    return out


class ObservationModel:
    """Predict a recording's channels with the simulator driven by its recorded effector poses.

    Args:
        evidence: the recording (:func:`sysid.evidence.load_evidence`).
        scene: scene overriding the bag's ``scene.yaml`` (path, mapping or :class:`SceneFile`).
        dt: simulation step in s (the recording is replayed at this step).
        t_max: use only the first ``t_max`` seconds of the recording (None: all of it).
        channels: channels to fit (default :data:`DEFAULT_FIT_CHANNELS`, or ``markers_uv`` instead of
            ``markers_xyz`` when only pixels were recorded). Channels absent from the recording are
            dropped with an :class:`ObservationWarning`.
        simulation: overrides of the scene's ``simulation:`` block.
        noise: per-channel noise overrides ``{channel: sigma per axis}``; default ``evidence.noise``.
        arch: elastic terms of the replays: ``"numpy"`` (reference potentials) or ``"cpu"`` /
            ``"cuda"`` (the fused Taichi kernels of :mod:`sim_core.fused_elastic`, same values to
            round-off; Taichi is initialised on first use, also in worker processes).

    Attributes:
        evidence: the (cropped) recording.
        scene: the scene dict actually simulated.
        sensor, effector: names of the tactile sensor and its effector (None for a task scene).
        task: True for a task scene (``kind: task``): every effector replayed (module docstring).
        task_controls, task_grippers: of a task scene, effector -> targets ``(K + 1, 7)`` and
            effector -> finger openings ``(K + 1,)`` m (row k drives step k).
        channels: fitted channels, in residual order.
        dropped: channel -> why it is not fitted.
        sigma: channel -> per-axis noise level used for whitening.
        sigma_scale: None, or channel -> factor (>= 1) on ``sigma`` in :meth:`residuals` and
            :meth:`whiten_derivative` only: the model-form weights of a fit
            (:func:`sysid.fit.fit` ``reweight_channels``); reported RMS values stay in noise units.
        step_times_ns: ``(K + 1,)`` simulation step times (recording clock).
        controls: ``(K + 1, 7)`` effector target poses (row 0 = initial pose).
        drive_stiffness: stiffness (N/m) of the effector's drive along the sensor normal
            (:meth:`set_drive_stiffness`); ``inf`` (default): the recorded pose driven kinematically.
        drive_damping: the drive's damper on the effector's velocity along the normal, N s/m (0 by default).
        commands: ``(K + 1, 7)`` recorded commanded poses (``pose_cmd``) at the step times, as the robot took
            them where the recording holds its timing (:func:`sysid.command_path.anchor_path`: held from their log
            times, else interpolated between their header stamps), or None.
        warm_start: None, or vertex positions ``(K + 1, n, 3)`` in m of a replay at nearby
            parameters (``SimTrace.positions``): every replay then starts the Newton solve of step
            k from row k (``Control.position_guess``) instead of from step k - 1's solution. Each
            step still converges to the solver's tolerance; a start within a few noise units of the
            solution takes about half the Newton iterations. Forked replay workers inherit it.
            Replays whose result must not depend on another one (the nominal) are run with it None.
        row_mask: None, or channel -> bool ``(n,)`` over its recorded rows: the rows the fit and the sensor's gains
            use (False: weight 0 in :meth:`residuals` and :meth:`whiten_derivative`; the reported RMS keeps every row).
            Set where a sensor check finds rows that contradict the channel's contract
            (:mod:`sysid.wrench_check`).
        batch_sizing: the ``sim_core.batch.sizing.BatchSizing`` of batched replays of ``batch_size="auto"``
            (:func:`sysid.replay_batch.simulate_batch`), measured on their first call; None before it.

    Raises:
        CalibrationError: no pose channel, no fittable channel, bad ``dt`` / ``t_max``, or a sensor
            that the scene does not define; of a task scene, an effector without a recorded pose or
            pose_cmd topic, or tactile channels asked of a scene without a sensor.
    """

    def __init__(self, evidence: Evidence, scene: str | Path | Mapping[str, Any] | SceneFile | None = None,
                 dt: float = 0.01, t_max: float | None = None, channels: Sequence[str] | None = None,
                 simulation: Mapping[str, Any] | None = None,
                 noise: Mapping[str, Sequence[float]] | None = None, arch: str = "numpy") -> None:
        bag = evidence.source.bag_path
        if arch not in ("numpy", "cpu", "cuda"):
            raise CalibrationError(f"arch must be numpy, cpu or cuda, got {arch!r}")
        self.arch = arch
        if not (math.isfinite(dt) and dt > 0.0):
            raise CalibrationError(f"simulation dt must be a positive number of seconds, got {dt!r}")
        if "pose" not in evidence.channels_present:
            raise CalibrationError(f"{bag}: no effector pose ({evidence.channels_missing.get('pose', 'pose missing')}); "
                                   "the effector motion cannot be replayed")
        start = int(evidence.t_ns["pose"][0])
        if t_max is not None:
            if not (math.isfinite(t_max) and t_max > 0.0):
                raise CalibrationError(f"t_max must be a positive number of seconds, got {t_max!r}")
            try:
                evidence = evidence.crop(start, start + int(round(t_max * 1e9)))
            except ValueError as err:
                raise CalibrationError(f"{bag}: t_max={t_max} s: {err}") from err
        self.evidence = evidence
        self.dt = float(dt)
        self.t_max = t_max
        self.scene = scene_dict_for(evidence, scene, simulation)
        self.task = is_task_scene(self.scene)
        if self.task:
            parsed = evidence.scene if scene is None else load_any_scene_file(scene)
            self._base_dir = getattr(parsed, "base_dir", None)
            self.sensor, self.effector = None, None
            self._task_effectors = self._task_streams()
        else:
            self.sensor, self.effector = self._pick_sensor()
            self.scene["effectors"][self.effector]["initial_pose"] = [float(v) for v in evidence.pose[0]]
        self._choose_channels(channels)
        self.sigma = self._noise_levels(noise)
        self._build_replay()
        self._sim = None
        self._sensor_mount: np.ndarray | None = None
        self.warm_start: np.ndarray | None = None
        self.batch_sizing = None
        self.normal_offset = 0.0
        self.nominal_normal_offset = 0.0
        self.sensor_calibration = None
        self.gain_profile = None  # sysid.gain_profile.GainProfile: the gains refitted at every predict
        self.marker_rest: np.ndarray | None = None
        self.sigma_scale: dict[str, float] | None = None
        self.row_mask: dict[str, np.ndarray] | None = None
        self.drive_stiffness = math.inf
        self.drive_damping = 0.0
        commanded = not self.task and "pose_cmd" in evidence.channels_present
        self.commands = anchor_path(evidence, self.step_times_ns) if commanded else None

    # ------------------------------------------------------------------------------ set-up
    def _pick_sensor(self) -> tuple[str, str]:
        sensors = self.scene.get("sensors") or {}
        if not sensors:
            raise CalibrationError(f"{self.scene_source}: the scene defines no tactile sensor")
        topic = self.evidence.source.topics.get("markers_xyz") or self.evidence.source.topics.get("wrench") or ""
        name = next((n for n in sensors if topic.rstrip("/").endswith(f"{n}/markers") or
                     topic.rstrip("/").endswith(f"{n}/wrench")), next(iter(sensors)))
        effector = sensors[name]["effector"]
        pose_topic = self.evidence.source.topics.get("pose", "")
        mapped = self.evidence.source.recording_map is not None  # a map names the effector's frame, not its topic
        if pose_topic and not mapped and not pose_topic.rstrip("/").endswith(f"{effector}/pose"):
            warnings.warn(f"pose topic {pose_topic} does not name effector {effector!r} of sensor {name!r}; "
                          "replaying it on that effector", ObservationWarning, stacklevel=3)
        return name, effector

    def _task_streams(self) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
        """The recorded streams of every effector of a task scene; each effector's initial pose becomes
        its recorded pose at ``t_0``.

        Raises:
            CalibrationError: an effector of the scene has neither a pose nor a pose_cmd stream.
        """
        ev = self.evidence
        streams = ev.effectors
        t0 = np.asarray([ev.t_ns["pose"][0]], dtype=np.int64)
        for name, spec in (self.scene.get("effectors") or {}).items():
            got = streams.get(name, {})
            source = got.get("pose") or got.get("pose_cmd")
            if source is None:
                raise CalibrationError(f"{ev.source.bag_path}: effector {name!r} of {self.scene_source} has no "
                                       f"recorded pose or pose_cmd topic; its motion cannot be replayed")
            spec["initial_pose"] = [float(v) for v in resample_pose(source[0], source[1], t0, outside="clamp")[0]]
        return streams

    @property
    def scene_source(self) -> str:
        """Where the scene came from (for messages)."""
        src = self.evidence.source.scene_path
        return str(src) if src is not None else str(self.evidence.source.bag_path)

    def _choose_channels(self, channels: Sequence[str] | None) -> None:
        present = self.evidence.channels_present
        if channels is None:
            wanted = list(DEFAULT_FIT_CHANNELS)
            if "markers_xyz" not in present and "markers_uv" in present:
                wanted[0] = "markers_uv"
        else:
            wanted = list(channels)
        self.dropped: dict[str, str] = {}
        chosen = []
        if self.task and not (self.scene.get("sensors") or {}):
            tactile = [ch for ch in wanted if ch != "sheet_points"]
            if tactile and channels is not None:
                raise CalibrationError(f"{self.scene_source}: the scene has no tactile sensor; channels "
                                       f"{', '.join(tactile)} cannot be fitted (fittable: sheet_points)")
            warnings.warn(f"{self.scene_source}: the scene has no tactile sensor; fitting without tactile channels "
                          "(markers, wrench)", ObservationWarning, stacklevel=3)
            wanted = [ch for ch in wanted if ch == "sheet_points"]
            self.dropped.update({ch: "the scene has no tactile sensor" for ch in tactile})
        for ch in wanted:
            if ch not in PREDICTABLE_CHANNELS:
                raise CalibrationError(f"channel {ch!r} cannot be fitted (fittable: {', '.join(PREDICTABLE_CHANNELS)})")
            if ch not in present:
                why = self.evidence.channels_missing.get(ch, f"{ch} not in the recording")
                self.dropped[ch] = why
                warnings.warn(f"{self.evidence.source.bag_path}: {why}; fitting without {ch}",
                              ObservationWarning, stacklevel=3)
                continue
            chosen.append(ch)
        if not chosen:
            why = "; ".join(self.dropped[ch] for ch in wanted if ch in self.dropped)
            raise CalibrationError(f"{self.evidence.source.bag_path}: none of the channels {', '.join(wanted)} is in "
                                   f"the recording ({why}); nothing to fit")
        self.channels = tuple(chosen)

    def _noise_levels(self, noise: Mapping[str, Sequence[float]] | None) -> dict[str, np.ndarray]:
        out = {}
        for ch in PREDICTABLE_CHANNELS:
            if ch not in self.evidence.channels_present:
                continue
            axes = self.evidence.values(ch).shape[-1]
            if noise is not None and ch in noise:
                s = np.asarray(noise[ch], dtype=float).reshape(-1)
            elif ch in self.evidence.noise:
                s = np.asarray(self.evidence.noise[ch], dtype=float)
            else:
                s = np.full(axes, np.nan)
            if s.shape != (axes,):
                raise CalibrationError(f"noise of {ch} must have {axes} entries, got {s.shape[0]}")
            s = np.where(np.isfinite(s), s, NOISE_FLOOR[ch])
            out[ch] = np.maximum(s, NOISE_FLOOR[ch])
        return out

    def _build_replay(self) -> None:
        ev = self.evidence
        t_pose = ev.t_ns["pose"]
        t0 = int(t_pose[0])
        # every channel predicted, fitted or not (the calibration reads them all), lies within the replay
        t_end = max(int(ev.t_ns[ch][-1]) for ch in PREDICTABLE_CHANNELS if ch in ev.channels_present)
        dt_ns = int(round(self.dt * 1e9))
        steps = max(1, int(math.ceil((t_end - t0) / dt_ns)))
        self.step_times_ns = t0 + dt_ns * np.arange(steps + 1, dtype=np.int64)
        self.controls = resample_pose(t_pose, ev.pose, self.step_times_ns, outside="clamp")
        if self.task:
            self._build_task_controls(dt_ns)
        self._interp = {}
        for ch in PREDICTABLE_CHANNELS:
            if ch in ev.channels_present:
                t = ev.t_ns[ch]
                keep = (t >= t0) & (t <= self.step_times_ns[-1])
                if not keep.all():
                    raise CalibrationError(f"{ev.source.bag_path}: {ch} has samples before the first pose stamp")
                self._interp[ch] = _interpolation(self.step_times_ns, t)

    def _build_task_controls(self, dt_ns: int) -> None:
        """Per-effector targets ``(K + 1, 7)`` and finger openings ``(K + 1,)`` of a task scene's replay
        (module docstring: commands held from their log time)."""
        before = np.maximum(self.step_times_ns - dt_ns, self.step_times_ns[0])  # t_{k-1}: step k's start
        self.task_controls: dict[str, np.ndarray] = {}
        self.task_grippers: dict[str, np.ndarray] = {}
        effectors = self.scene.get("effectors") or {}
        for name, got in self._task_effectors.items():
            if name not in effectors:
                continue
            if "pose_cmd" in got:
                start = np.asarray(effectors[name]["initial_pose"], dtype=float)
                self.task_controls[name] = _held(*got["pose_cmd"], before, dt_ns, start)
            else:
                self.task_controls[name] = resample_pose(*got["pose"], self.step_times_ns, outside="clamp")
            if "gripper_cmd" in got:
                t, v = got["gripper_cmd"]
                opening = effectors[name].get("opening")
                self.task_grippers[name] = _held(t, v, before, dt_ns, np.asarray(v[0] if opening is None else opening,
                                                                                dtype=float))

    # ------------------------------------------------------------------------------ simulation
    @property
    def step_count(self) -> int:
        """Number of simulation steps K of one replay."""
        return int(self.step_times_ns.shape[0] - 1)

    def simulation(self):
        """The (cached) ``sim_core.simulation.Simulation`` of the scene at step ``dt``, each step solved to
        :data:`REPLAY_TOL_VELOCITY`, retrying a failed step in substeps (:data:`REPLAY_DT_HALVINGS`; counted in its
        ``step_totals``)."""
        if self._sim is None:
            # the backend starts (Taichi initialised once) with the solver; ConfigError names a problem
            config = SolverConfig(backend=backend_of_arch(self.arch), dt_halvings_on_failure=REPLAY_DT_HALVINGS,
                                  tol_velocity=REPLAY_TOL_VELOCITY, apply_last_update=REPLAY_APPLY_LAST_UPDATE)
            model = build_task_scene(self.scene, self._base_dir) if self.task else load_scene(self.scene)
            self._sim = Simulation(model, dt=self.dt, solver_config=config)
            if self.task:
                self._check_task_model(self._sim)
            self._nominal = {n: float(self._sim.get_parameter(n)) for n in self._sim.parameter_names}
            self._scene_nominal = dict(self._nominal)
        return self._sim

    def _check_task_model(self, sim) -> None:
        """The recorded sheet points must be the task model's tracked points.

        Raises:
            CalibrationError: another point count (names the topic).
        """
        if "sheet_points" in self.evidence.channels_present:
            p = self.evidence.sheet_points.shape[1]
            n = np.asarray(sim.observe().sheet_points).shape[0]
            if p != n:
                topic = self.evidence.source.topics.get("sheet_points", "sheet/points")
                raise CalibrationError(f"topic {topic} has {p} points but the scene {self.scene_source} tracks {n}")

    def compile_kernels(self) -> float:
        """JIT-compile, in this process, the Taichi kernels a replay calls; seconds (0 for ``numpy``).

        Processes forked from this one (the parallel replays of ``sysid.diagnose``) inherit the
        compiled kernels. A kernel that a forked child has to compile itself, because the parent never
        ran it and Taichi's offline cache does not hold it yet, hangs the child: Taichi's compile thread
        pool does not survive ``fork``. So pools call this before they fork
        (:func:`sim_core.kernel_compile.compile_kernels`: fused elastic terms, the projected fallback,
        contact, broad-phase and friction kernels).

        Raises:
            ConfigError: the Taichi backend cannot be initialised for ``arch``.
        """
        if self.arch == "numpy":
            return 0.0

        sim = self.simulation()
        return compile_kernels(sim.solver.elastic.potentials(sim.state.hinge_theta_bar), sim.state.x,
                               sim.solver.config.projection)

    def parameter_value(self, name: str) -> float:
        """Nominal (scene) value of parameter ``name``.

        Raises:
            ConfigError: unknown parameter (lists the known names).
        """
        if name in SENSOR_PARAMETERS:
            return float(self.nominal_normal_offset)
        self.simulation()
        if name not in self._nominal:
            value = float(self._sim.get_parameter(name))  # raises ConfigError listing the known names
            # a missing-physics term (candidate.<name>): its scene value (0 when the scene has none) is
            # its nominal from now on, so prepare() resets it for replays that do not set it
            self._nominal[name] = self._scene_nominal[name] = value
        return self._nominal[name]

    def set_nominal(self, values: Mapping[str, float]) -> None:
        """Make ``values`` the nominal of every later replay (a calibration's fitted parameters):
        a replay that does not set a parameter uses its value here, and :meth:`parameter_value`
        returns it (``sensor.normal_offset``: :attr:`nominal_normal_offset`).

        Raises:
            ConfigError: unknown parameter or a value outside its physical range (nothing is changed).
        """
        checked = {}
        for name, value in values.items():
            value = float(value)
            if name not in SENSOR_PARAMETERS:
                self.parameter_value(name)  # unknown names raise, listing the known ones
                current = self._sim.get_parameter(name)
                self._sim.set_parameter(name, value)  # range check; prepare() sets it again per replay
                self._sim.set_parameter(name, current)
            checked[name] = value
        for name, value in checked.items():
            if name in SENSOR_PARAMETERS:
                self.nominal_normal_offset = value
            else:
                self._nominal[name] = value

    def reset_nominal(self) -> None:
        """Scene values as the nominal of every later replay again (undoes :meth:`set_nominal`;
        the sensor offset back to 0)."""
        self.simulation()
        self._nominal.update(self._scene_nominal)
        self.nominal_normal_offset = 0.0

    def prepare(self, params: Mapping[str, float]):
        """The cached simulation with ``params`` set (others at their scene values), reset to t_0.

        Raises:
            ConfigError: unknown parameter or a value outside its physical range.
        """
        sim = self.simulation()
        self.normal_offset = float(params.get("sensor.normal_offset", self.nominal_normal_offset))
        for name, nominal in self._nominal.items():
            if name not in params and sim.get_parameter(name) != nominal:
                sim.set_parameter(name, nominal)
        for name, value in params.items():
            if name not in SENSOR_PARAMETERS:
                sim.set_parameter(name, float(value))
        sim.reset()
        return sim

    def set_drive_stiffness(self, stiffness: float, damping: float = 0.0) -> None:
        """Replay the effector on a series spring of ``stiffness`` (N/m) along the sensor normal, anchored
        at the recorded command, with a damper of ``damping`` (N s/m) on its velocity there
        (:mod:`sysid.replay_drive`; ``inf``: the recorded pose, kinematic, and no damper).

        Raises:
            CalibrationError: a stiffness that is not > 0; a finite one for a task scene; a damping that is
                negative or not finite.
        """
        stiffness, damping = float(stiffness), float(damping)
        if not stiffness > 0.0 or (self.task and not math.isinf(stiffness)):
            raise CalibrationError(f"drive stiffness must be > 0 N/m (inf: kinematic) and infinite for a task "
                                   f"scene, got {stiffness!r}")
        if not (math.isfinite(damping) and damping >= 0.0):
            raise CalibrationError(f"drive damping must be finite and >= 0 N s/m, got {damping!r}")
        self.drive_stiffness = stiffness
        self.drive_damping = damping if math.isfinite(stiffness) else 0.0

    def replay_drive(self) -> ReplayDrive | None:
        """The series drive of :attr:`drive_stiffness` and :attr:`drive_damping` for the next replay (None:
        kinematic; :meth:`sysid.replay_drive.ReplayDrive.of_model`)."""
        return ReplayDrive.of_model(self)

    def controls_list(self, guess: np.ndarray | None = None) -> list[Control]:
        """The K kinematic controls of one replay, with the Newton start of each step from
        ``guess`` ``(K + 1, n, 3)`` (default :attr:`warm_start`; see :meth:`control`).

        Raises:
            CalibrationError: ``guess`` is not ``K + 1`` position arrays; a series drive is set
                (:meth:`set_drive_stiffness`: its steps are solved, not given by controls).
        """
        if not math.isinf(self.drive_stiffness):
            raise CalibrationError("a replay through a series drive has no kinematic controls (no tangents)")
        guess = self._checked_guess(guess)
        return [self.control(k, guess) for k in range(1, self.step_count + 1)]

    def control(self, k: int, guess: np.ndarray | None = None, normal_offset: float | None = None) -> Control:
        """Kinematic control of step ``k`` (1-based): the recorded pose at ``t_k`` moved by ``normal_offset`` (m,
        default the replay's ``sensor.normal_offset``) along the sensor normal; with ``guess``
        ``(K + 1, n, 3)``, row ``k`` is the step's Newton start (``Control.position_guess``)."""
        if self.task:
            return Control({n: c[k].copy() for n, c in self.task_controls.items()},
                           gripper_target={n: float(g[k]) for n, g in self.task_grippers.items()},
                           position_guess=None if guess is None else guess[k])
        pose = self.controls[k].copy()
        offset = self.normal_offset if normal_offset is None else float(normal_offset)
        if offset:
            pose[:3] += offset * self.sensor_normal(pose)
        return Control({self.effector: pose}, position_guess=None if guess is None else guess[k])

    def sensor_normal(self, pose: np.ndarray) -> np.ndarray:
        """World direction ``(3,)`` of the sensor's +z (out of the gel) at effector pose ``pose``."""
        if self._sensor_mount is None:
            # read from the scene's model without a simulation, which would start Taichi: a process may still fork
            # replay workers after the drive's calibration asks for the normal (sysid.diagnose.probe_worker)
            model = self._sim.model if self._sim is not None else (
                build_task_scene(self.scene, self._base_dir) if self.task else load_scene(self.scene))
            self._sensor_mount = np.asarray(model.sensors[self.sensor].mount, dtype=float)
        mount = self._sensor_mount
        return quat_to_matrix(pose[3:7]) @ quat_to_matrix(mount[3:7]) @ np.array([0.0, 0.0, 1.0])

    def _checked_guess(self, guess: np.ndarray | None) -> np.ndarray | None:
        guess = self.warm_start if guess is None else guess
        if guess is not None and (np.ndim(guess) != 3 or len(guess) != self.step_count + 1):
            raise CalibrationError(f"warm start: expected {self.step_count + 1} position arrays (n, 3), "
                                   f"got shape {np.shape(guess)}")
        return guess

    def simulate(self, params: Mapping[str, float],
                 on_step: Callable[[int, int], None] | None = None, keep_positions: bool = False,
                 keep_states: bool = False, resume: Resume | None = None) -> SimTrace:
        """Replay the recording with parameter values ``params`` and observe every step.

        Each step's Newton solve starts from :attr:`warm_start` when it is set; through a series drive
        (:meth:`set_drive_stiffness`) for the spring's compression too (counts in ``SimTrace.drive``). A body at rest
        that nothing moving can reach sleeps (:data:`REPLAY_SLEEPING`).

        Args:
            params: global parameter name -> value (``Model.set_parameter`` names); others keep
                their scene values.
            on_step: called as ``on_step(k, K)`` after step k.
            keep_positions: also return every vertex position (``SimTrace.positions``).
            keep_states: also return every simulation state (``SimTrace.states``).
            resume: take steps ``0..resume.step`` from another replay known to be the same until
                then (:class:`Resume`) and simulate the later ones only; not with
                ``keep_positions`` or ``keep_states``.

        Returns:
            the :class:`SimTrace`.

        Raises:
            ConfigError: unknown parameter or a value outside its physical range; a warm start
                of the wrong vertex count.
            CalibrationError: a warm start of the wrong step count; a resume step outside
                ``0..K``, a resume state of another step or vertex count, a prefix too short, or
                a resume with ``keep_positions``/``keep_states``.
            SimulationDivergedError: the solver failed (names the step).
        """
        guess = self._checked_guess(None)
        sim = self.prepare(params)
        t_start = time.perf_counter()
        K = self.step_count
        if resume is None:
            start, obs = 0, [self.observe_step(sim)]
        else:
            start = self._checked_resume(resume, keep_positions or keep_states, sim)
            sim.state = resume.state.copy()
            p = resume.prefix
            obs = [(p.markers_xyz[k], p.markers_uv[k], p.wrench[k], p.sheet_points[k]) for k in range(start + 1)]
        positions = [sim.state.x.copy()] if keep_positions else None
        states = [sim.state.copy()] if keep_states else None
        drive = self.replay_drive()
        config = sim.solver.config
        previous = config.sleeping  # a plain replay differentiates no step record (REPLAY_SLEEPING)
        config.sleeping = previous or (REPLAY_SLEEPING and not config.lockstep)
        try:
            for k in range(start + 1, K + 1):
                if drive is None:
                    sim.step(self.control(k, guess))
                else:
                    drive.step(sim, self.control(k, guess), k)
                obs.append(self.observe_step(sim))
                if positions is not None:
                    positions.append(sim.state.x.copy())
                if states is not None:
                    states.append(sim.state.copy())
                if on_step is not None:
                    on_step(k, K)
        finally:
            config.sleeping = previous
        trace = self.trace_from(obs, time.perf_counter() - t_start, None if positions is None else np.stack(positions))
        trace = dataclasses.replace(trace, step_totals=dataclasses.replace(sim.step_totals),
                                    drive=None if drive is None else drive.summary())
        return trace if states is None else dataclasses.replace(trace, states=states)

    def _checked_resume(self, resume: Resume, keeping: bool, sim) -> int:
        """``resume.step`` after checking the resume against this model (see :meth:`simulate`)."""
        K, k = self.step_count, int(resume.step)
        problem = None
        if keeping:
            problem = "cannot keep positions or states of a resumed replay"
        elif not 0 <= k <= K:
            problem = f"step {k} is outside 0..{K}"
        elif int(getattr(resume.state, "step_index", -1)) != k:
            problem = f"the state is of step {getattr(resume.state, 'step_index', None)}, not {k}"
        elif np.shape(resume.state.x) != np.shape(sim.state.x):
            problem = f"the state has {np.shape(resume.state.x)[0]} vertices, the simulation {np.shape(sim.state.x)[0]}"
        elif resume.prefix.markers_xyz.shape[0] < k + 1:
            problem = f"the prefix has {resume.prefix.markers_xyz.shape[0]} steps, {k + 1} needed"
        if problem is not None:
            raise CalibrationError(f"resumed replay of {self.evidence.source.bag_path}: {problem}")
        return k

    def trace_of(self, sim, states: Sequence[Any], wall_time_s: float = 0.0) -> SimTrace:
        """The :class:`SimTrace` of an already simulated replay: ``states`` are its ``K + 1`` states
        (e.g. ``Trajectory.states`` of a rollout of :meth:`prepare`'d ``sim`` through :meth:`controls_list`).

        Raises:
            ValueError: not ``K + 1`` states.
        """
        if len(states) != self.step_count + 1:
            raise ValueError(f"expected {self.step_count + 1} states, got {len(states)}")
        return self.trace_from([self.observe_step(sim, s) for s in states], wall_time_s)

    def trace_from(self, obs: list, wall_time_s: float, positions: np.ndarray | None = None) -> SimTrace:
        """The :class:`SimTrace` of a replay's per-step observations ``obs`` (:meth:`observe_step` of steps 0..K)."""
        return SimTrace(
            t_ns=self.step_times_ns.copy(),
            markers_xyz=np.stack([o[0] for o in obs]), markers_uv=np.stack([o[1] for o in obs]),
            wrench=np.stack([o[2] for o in obs]), sheet_points=np.stack([o[3] for o in obs]),
            wall_time_s=wall_time_s, positions=positions,
        )

    def observe_step(self, sim, state=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What a replay observes of ``sim`` (at ``state``, default its own): markers ``(k, 3)`` m and ``(k, 2)`` px,
        wrench ``(6,)`` N, N m, sheet points ``(p, 3)`` m (no sensor: empty markers, zero wrench)."""
        o = sim.observe(state=state)
        if self.sensor is None:
            return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(6), np.asarray(o.sheet_points, float)
        r = o.tactile[self.sensor]
        return (np.asarray(r.markers_xyz, float), np.asarray(r.markers_uv, float), np.asarray(r.wrench, float),
                np.asarray(o.sheet_points, float))

    # ------------------------------------------------------------------------------ alignment
    def align(self, channel: str, per_step: np.ndarray) -> np.ndarray:
        """Interpolate a per-step array ``(K + 1, ...)`` to the stamps of evidence ``channel``.

        Linear in the per-step values, so it also maps per-step derivatives ``(K + 1, ..., p)``.

        Returns:
            ``(n_stamps, ...)``.
        """
        per_step = np.asarray(per_step, dtype=float)
        if per_step.shape[0] != self.step_times_ns.shape[0]:
            raise ValueError(f"{channel}: expected {self.step_times_ns.shape[0]} steps, got {per_step.shape[0]}")
        return self._interp[channel].apply(per_step)

    def predict(self, trace: SimTrace) -> dict[str, np.ndarray]:
        """Predictions aligned to every predictable channel the recording holds, through the
        sensor calibration (:attr:`sensor_calibration`, :mod:`sysid.calibration`) when one is set; with a
        :attr:`gain_profile` the gains are refitted to this prediction first (and kept as :attr:`sensor_calibration`).

        Returns:
            channel -> array shaped like ``evidence.values(channel)``.
        """
        raw = self.predict_raw(trace)
        if self.gain_profile is not None:  # the gains refitted to this prediction (sysid.gain_profile)
            out = self.gain_profile(raw)
            self.sensor_calibration = self.gain_profile.last[0]
            return out
        if self.sensor_calibration is None:
            return raw
        return self.sensor_calibration.apply(raw, self.marker_rest)

    def predict_raw(self, trace: SimTrace) -> dict[str, np.ndarray]:
        """The simulator's predictions aligned to the recording, without the sensor calibration."""
        return {ch: self.align(ch, trace.channel(ch)) for ch in self._interp}

    # ------------------------------------------------------------------------------ residuals
    def data(self, channel: str) -> np.ndarray:
        """Recorded values of ``channel`` (float64)."""
        return np.asarray(self.evidence.values(channel), dtype=float)

    @property
    def residual_count(self) -> int:
        """Length of the whitened residual vector."""
        return int(sum(self.data(ch).size for ch in self.channels))

    def residual_slices(self) -> dict[str, slice]:
        """Channel -> its slice of the residual vector."""
        out, i = {}, 0
        for ch in self.channels:
            n = self.data(ch).size
            out[ch] = slice(i, i + n)
            i += n
        return out

    def residuals(self, prediction: Mapping[str, np.ndarray]) -> np.ndarray:
        """Whitened residual ``r = sqrt(w) (y_data - y_sim) / (sigma s)`` over the fitted channels, ``(m,)``
        (``s`` the channel's :attr:`sigma_scale`, 1 without one; ``w`` :meth:`residual_weight_root` squared)."""
        return np.concatenate([((self.data(ch) - prediction[ch]) / (self.sigma[ch] * self._scale(ch))
                                * self.residual_weight_root(ch)).reshape(-1) for ch in self.channels])

    def residual_weight_root(self, channel: str) -> np.ndarray | float:
        """``sqrt(w)`` of every sample of ``channel``, broadcastable to its data ``(n, k, 1)`` / ``(n, 1)``: the
        markers' weights of pixels read off images (``Evidence.markers_uv_weight``) times the channel's
        :attr:`row_mask`, else 1.0."""
        weight = self.evidence.markers_uv_weight if channel == "markers_uv" else None
        root = 1.0 if weight is None else np.sqrt(np.asarray(weight, dtype=float))[..., None]
        mask = None if self.row_mask is None else self.row_mask.get(channel)
        if mask is None:
            return root
        shape = (-1,) + (1,) * (self.data(channel).ndim - 1)
        return np.asarray(mask, dtype=float).reshape(shape) * root

    def _scale(self, channel: str) -> float:
        return 1.0 if self.sigma_scale is None else float(self.sigma_scale.get(channel, 1.0))

    def channel_slices(self) -> dict[str, slice]:
        """Channel -> its rows in :meth:`residuals` (and in a whitened Jacobian)."""
        out, start = {}, 0
        for ch in self.channels:
            n = int(self.data(ch).size)
            out[ch] = slice(start, start + n)
            start += n
        return out

    def whiten_derivative(self, channel: str, d_prediction: np.ndarray) -> np.ndarray:
        """d r / d theta of one channel from the aligned prediction derivative ``(n, ..., axes, p)``.

        Returns:
            ``(n * ... * axes, p)`` (the sign of ``r = data - sim`` applied).
        """
        p = d_prediction.shape[-1]
        root = self.residual_weight_root(channel)
        root = root if isinstance(root, float) else root[..., None]
        return (-d_prediction / (self.sigma[channel][:, None] * self._scale(channel)) * root).reshape(-1, p)

    def channel_rms(self, prediction: Mapping[str, np.ndarray]) -> dict[str, dict[str, Any]]:
        """Per-channel RMS of ``data - prediction`` over every predictable channel present.

        Returns:
            channel -> ``{"rms", "per_axis", "whitened_rms", "unit", "fitted"}``; for the wrench
            ``rms`` is over the force components (N) and ``torque_rms`` over the torques (N m); a channel with a
            :attr:`row_mask` also ``whitened_rms_kept_rows`` (over the rows the fit used).
        """
        out = {}
        for ch in self._interp:
            e = self.data(ch) - prediction[ch]
            axes = e.reshape(-1, e.shape[-1])
            per_axis = np.sqrt(np.mean(axes ** 2, axis=0))
            entry: dict[str, Any] = {
                "rms": float(np.sqrt(np.mean(e ** 2))), "per_axis": [float(v) for v in per_axis],
                "whitened_rms": float(np.sqrt(np.mean((axes / self.sigma[ch]) ** 2))),
                "unit": CHANNEL_UNITS[ch], "fitted": ch in self.channels,
            }
            keep = None if self.row_mask is None else self.row_mask.get(ch)
            if keep is not None:  # the rows the fit used (the others contradict the channel's contract)
                kept = e[np.asarray(keep, dtype=bool)].reshape(-1, e.shape[-1])
                entry["whitened_rms_kept_rows"] = float(np.sqrt(np.mean((kept / self.sigma[ch]) ** 2)))
            if ch == "wrench":
                entry["rms"] = float(np.sqrt(np.mean(axes[:, :3] ** 2)))
                entry["torque_rms"] = float(np.sqrt(np.mean(axes[:, 3:] ** 2)))
                entry["unit"] = "N"
            out[ch] = entry
        return out
