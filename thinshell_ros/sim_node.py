"""The simulator node: a :class:`sim_core.simulation.Simulation` behind the INTERFACES.md topics.

Parameters (``--ros-args -p name:=value``; a file in ``config/nodes/sim_node.yaml``):

- ``scene`` (str): scene file; default the bundled ``config/scenes/press_slide.yaml``.
- ``backend`` (str): the solver backend (``SolverConfig.backend``, :mod:`sim_core.backend`):
  ``auto`` (default: the fastest available, Taichi's CUDA or CPU kernels, else NumPy), ``numpy``,
  ``taichi-cpu``, ``taichi-cuda`` (``thinshell bench forming --arch cpu`` measures ``taichi-cpu``).
  Not used when the node is given a built simulation (its solver's backend stands). The node's
  solver repeats a fixed point (``SolverConfig.repeat_fixed_points``): while the scene rests, a step
  whose inputs equal the last one's takes its result instead of a Newton solve; and it lets a body at
  rest that nothing moving can reach sleep (``SolverConfig.sleeping``, :mod:`sim_core.sleeping`: the
  card while the pad moves above it), held out of the Newton system until something could change it;
  and it starts each step's Newton iterations with the pad carried by its effector's motion over
  the step (``SolverConfig.carried_start``, :mod:`sim_core.carried_start`: a move of the pad in the
  air takes 1 Newton iteration instead of 3; the result differs within the Newton tolerance).
- ``settle_steps_max`` (int, default :data:`DEFAULT_SETTLE_STEPS_MAX`): at start-up and after
  ``~/reset``, before the clock starts and before the first output, the scene is stepped under zero
  commands until it is at rest (:func:`sim_core.settle.settle`: the Newton tolerance tightened below
  the sleeping threshold, then the node's own solver settings until a step leaves the state
  unchanged), at most this many steps; the settled state starts at t = 0. A scene file's initial
  state is not exactly at the equilibrium of the step (the bundled scene's card: a Newton update of
  7.9e-7 m/s, above ``sleep_velocity``), so without it the card stays awake, and in every solve,
  until the first command. The steps taken, the residual velocity and the largest vertex move are
  logged and published as a diagnostic status ``<node name>: settle`` (``OK``; ``WARN`` when the
  scene did not settle within the cap: the node starts anyway). 0: off. Only for the simulation the
  node builds from ``scene`` (a given simulation starts as given).
- ``mode`` (str): ``realtime`` (one step per ``dt`` of wall time, or slower when the solver is
  slower: steps are counted against the wall clock, :class:`thinshell_ros.pacing.RealtimePacer`; a
  tick of the timer takes the due steps back to back until one takes a ``dt`` or more, so the steps
  a late tick missed are taken, a lag over :data:`REALTIME_MAX_LAG` is dropped, and a command that
  arrives between two steps starts its step at once when it would be due within one ``dt``, else as
  soon as it would be, not at the timer's next tick),
  ``fast`` (steps back to back), ``stepped`` (only the ``~/step`` service steps).
- ``rate`` (Hz, sim time): publication rate of the sensor outputs; 0 publishes after every step.
  ``/clock`` is published after every step.
- ``mesh_rate`` (Hz, sim time): rate of the ``sheet/mesh`` marker (0 = off).
- ``namespace`` (str, default ``/thinshell``): prefix of every topic while the node runs in the root
  namespace; a node given a ROS namespace (``--ros-args -r __ns:=/robot``) creates its topics with
  relative names in it instead (:func:`thinshell_ros.runtime.topic_namespace`), which also follow
  remapping rules. Services stay private (``~/reset``).
- ``publish_image`` (bool): render and publish ``<sensor>/image``.
- ``record`` (str): bag directory to record inputs and outputs into (empty: off);
  ``record_force`` replaces an existing one; ``record_scene`` (str) is the scene written beside the
  recording as ``scene.yaml`` (default: ``scene``; a "robot" run with hidden values states the
  nominal scene, as a real cell's recording would).
- ``command_timeout`` (s of sim time): commands older than this are stale (hold position); 0 = never.
- ``workspace_min``, ``workspace_max`` (``[x, y, z]`` m in ``world``): the box every effector
  position command must lie in; a pose command outside is rejected like one with NaN or a zero
  quaternion (logged, the last valid command stays), a twist stops at the boundary. Default (both
  empty): the bounding box of the effectors' initial positions and the sheet, grown by
  ``workspace_margin`` (m, default 0.1) on every side. ``workspace_margin < 0`` with no box: no limit.
- ``noise_markers`` (m), ``noise_pixels`` (px), ``noise_force`` (N), ``noise_torque`` (N m),
  ``noise_points`` (m), ``noise_seed``: standard deviations of white Gaussian noise added to the
  published (and recorded) marker positions, marker pixels, wrench and sheet points, per axis, as a
  real sensor's; default 0 (exact outputs). The effector pose stays exact.
- every material parameter of the scene by its global name (``sheet.youngs_modulus``,
  ``friction.gel_sheet``, ...): settable at runtime, validated by the simulation.

- ``error_log_period`` (s of wall time, default :data:`DEFAULT_ERROR_LOG_PERIOD`): at most one error
  line per kind (rejected commands by effector, topic and reason; recording errors) per period, each
  with the count of the errors it stands for (:class:`~thinshell_ros.command_intake.ErrorThrottle`).
- ``step_count`` (int, default 1, settable at runtime): the steps one call of ``~/step`` takes.

- ``executor`` (str): the executor :func:`main` spins the node in, ``single`` (default: rclpy's
  ``SingleThreadedExecutor``) or ``events`` (rclpy's ``EventsExecutor``, ``rclpy.experimental``:
  callbacks one at a time in arrival order from a C++ event queue, no wait-set rebuild per spin;
  lower command-to-output latency, docs/benchmarks.md "Sim node through DDS").

Commands (``<effector>/pose_cmd``, ``twist_cmd``, ``gripper_cmd``; reliable, keep-last
:data:`thinshell_ros.runtime.COMMAND_DEPTH`): every step, and every command callback, starts by taking
all queued commands (:meth:`SimNode.take_pending_commands`: one executor turn for a burst), each
recorded at the sim time it is taken; pose commands are taken as CDR bytes and checked as a batch,
the newest valid one submitted (:class:`~thinshell_ros.command_intake.CommandIntake`, cheap under a
flood: docs/ros.md); the newest valid command controls the step. The outputs a step publishes
(stamped with its end time) are the first to reflect the commands it took; a command that arrives during a step is taken by the next one, which in
``realtime`` mode starts as soon as the step in progress has ended and the schedule lets it (at most
one step ahead of the wall clock).

Services: ``~/reset`` (Trigger), ``~/pause`` (SetBool), ``~/step`` (Trigger: ``step_count`` steps);
topic ``~/step_n`` (``std_msgs/UInt32``: that many steps, at most :data:`MAX_STEP_N`).
Bad input never stops the node: it is logged (with the reason, throttled per kind) and the last
valid command stays.

Camera: ``<sensor>/camera_info`` (``sensor_msgs/CameraInfo`` of the tactile camera,
:func:`thinshell_ros.conversions.camera_info_msg`; reliable, transient local) at start-up, after
``~/reset`` or a parameter change, and with every ``<sensor>/image`` (same stamp).

Runtime status: every :data:`~thinshell_ros.runtime.STATUS_PERIOD` s a ``<node name>: status`` on
``/diagnostics`` (:meth:`thinshell_ros.node_status.RuntimeStats.status`: real-time factor, step p95,
rejected commands).

Solver diagnostics: a step accepted above the solver's strict tolerance (``StepInfo.converged_strict``
false: a stalled residual or a failed line search accepted at a relaxed tolerance) or taken in
retried substeps (``StepInfo.retries``) is logged as a warning and published as a ``WARN``
``diagnostic_msgs/DiagnosticStatus`` on ``/diagnostics`` (the ROS diagnostics convention); a failed
step as ``ERROR``; the next strictly converged step after either as ``OK``. The status is named
``<node name>: solver`` and its values say how the step ended (:func:`solver_status`). A step after
which a body fell asleep, or at which one was woken, is published as ``OK`` with the sleeping bodies
(values ``sleeping``, ``fell_asleep``, ``woken``, ``wake_redos``).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, Callable, Sequence

import numpy as np

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidHandle
from rclpy.executors import SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Float64, UInt32
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker

from sim_core.backend import BACKEND_CHOICES, check_backend
from sim_core.errors import ConfigError, ThinShellError
from sim_core.settle import SettleInfo, settle
from sim_core.simulation import Simulation
from sim_core.solver import NewtonSolver, SolverConfig, StepInfo
from thinshell_ros import conversions as cv
from thinshell_ros.command_intake import CommandIntake, ErrorThrottle
from thinshell_ros.commands import CommandArbiter, CommandLimits, Workspace, unknown_effector_topics
from thinshell_ros.node_status import RuntimeStats, settle_status, solver_status
from thinshell_ros.paths import bundled_scene
from thinshell_ros.pacing import RealtimePacer
from thinshell_ros.recorder import BagRecorder
from thinshell_ros.runtime import (CAMERA_INFO_QOS, CLOCK_QOS, COMMAND_QOS, DIAGNOSTICS_TOPIC, MARKER_QOS, SENSOR_QOS,
                                   STATUS_PERIOD, BurstGate, freeze_start_up_objects, ros_session, spin_until_stopped,
                                   topic_namespace)

MODES = ("realtime", "fast", "stepped")

EXECUTORS = {"single": SingleThreadedExecutor, "events": EventsExecutor}
"""Values of the ``executor`` parameter: the rclpy executor factory :func:`main` spins the node in."""

DEFAULT_WORKSPACE_MARGIN = 0.1
"""m around the scene's bounding box (effector start positions and sheet) of the default workspace."""


REALTIME_MAX_LAG = 0.05
"""s behind the wall-clock schedule (10 steps of the bundled scene's 5 ms) beyond which the
``realtime`` mode drops the lag instead of catching it up (:class:`~thinshell_ros.pacing.RealtimePacer`):
a longer lag is the solver being slower than real time, not a late tick."""

REALTIME_STEPS_PER_TICK = 4
"""Due steps the ``realtime`` timer callback takes at most before it returns to the executor
(services, parameters, the other timers run between)."""

DEFAULT_SETTLE_STEPS_MAX = 400
"""Default of the ``settle_steps_max`` parameter: the cap on the start-up settling steps (2 s of the
bundled scene's 5 ms steps; it settles in 5)."""

MAX_CONSECUTIVE_FAILURES = 3
"""Failed steps in a row (with the effectors held) after which the node pauses itself."""

DEFAULT_ERROR_LOG_PERIOD = 1.0
"""Default of the ``error_log_period`` parameter: s between two error lines of one kind."""

BURST_MESSAGES = 3
"""Command messages taken in one executor turn from which the sim node treats the traffic as a burst
and holds its command subscriptions out of the executor for one step (:meth:`SimNode._stepping`); a
commander at a steady rate delivers one per turn."""

POSE_TYPE = "geometry_msgs/msg/PoseStamped"
"""ROS type of the pose commands, recorded as the CDR bytes they arrive in."""

MAX_STEP_N = 100_000
"""Most steps one ``~/step_n`` message or the ``step_count`` parameter may ask for."""


class SimNode(Node):
    """ROS 2 node stepping a Simulation and publishing its observations.

    Args:
        sim: an already built simulation (facade API of ``sim_core.simulation.Simulation``); default:
            built from the ``scene`` parameter.
        node_name: ROS node name.
        wall_clock: the clock (s, monotonic) the ``realtime`` mode's schedule reads
            (:class:`~thinshell_ros.pacing.RealtimePacer`); default ``time.monotonic``.
        **kwargs: passed to ``rclpy.node.Node`` (``context``, ``parameter_overrides``, ...).

    Raises:
        ConfigError: invalid parameter (mode, rate, backend, material value) or scene; a backend that
            cannot start here.
    """

    def __init__(self, sim: Any | None = None, node_name: str = "thinshell_sim",
                 wall_clock: Callable[[], float] = time.monotonic, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        ro = ParameterDescriptor(read_only=True)
        self.scene_path = str(self.declare_parameter("scene", "", ro).value) or (str(bundled_scene()) if sim is None else "")
        backend = self.declare_parameter("backend", "auto", ParameterDescriptor(
            read_only=True, description=f"solver backend, one of {', '.join(BACKEND_CHOICES)} (auto: the fastest "
                                        "available); ignored when the node is given a built simulation")).value
        self.mode = str(self.declare_parameter("mode", "realtime", ro).value)
        self.executor_name = str(self.declare_parameter("executor", "single", ParameterDescriptor(
            read_only=True, description=f"executor main() spins the node in, one of {', '.join(EXECUTORS)}")).value)
        self.rate = float(self.declare_parameter("rate", 0.0, ro).value)
        self.mesh_rate = float(self.declare_parameter("mesh_rate", 10.0, ro).value)
        self.namespace, prefix = topic_namespace(self, str(self.declare_parameter("namespace", "/thinshell", ro).value))
        self.publish_image = bool(self.declare_parameter("publish_image", False).value)
        record = str(self.declare_parameter("record", "", ro).value)
        record_force = bool(self.declare_parameter("record_force", False, ro).value)
        record_scene = str(self.declare_parameter("record_scene", "", ro).value)
        self.noise = {key: float(self.declare_parameter(f"noise_{key}", 0.0, ParameterDescriptor(
            read_only=True, description=f"std of the Gaussian noise added to the published {what}")).value)
            for key, what in (("markers", "marker positions, m"), ("pixels", "marker pixels, px"),
                              ("force", "forces, N"), ("torque", "torques, N m"), ("points", "sheet points, m"))}
        if not all(math.isfinite(v) and v >= 0 for v in self.noise.values()):
            raise ConfigError(f"noise parameters must be finite and >= 0, got {self.noise}")
        self._rng = np.random.default_rng(int(self.declare_parameter("noise_seed", 0, ro).value))
        timeout = float(self.declare_parameter("command_timeout", 1.0, ro).value)
        ws_min = list(self.declare_parameter("workspace_min", Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            read_only=True, description="[x, y, z] lower corner of the allowed effector positions, m in world "
                                        "(empty: the scene's bounding box grown by workspace_margin)")).value or [])
        ws_max = list(self.declare_parameter("workspace_max", Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            read_only=True, description="[x, y, z] upper corner of the allowed effector positions, m in world")).value or [])
        ws_margin = float(self.declare_parameter("workspace_margin", DEFAULT_WORKSPACE_MARGIN, ParameterDescriptor(
            read_only=True, description="m added on every side of the scene's bounding box when no workspace_min/max "
                                        "is given; < 0: no workspace limit")).value)
        settle_steps_max = int(self.declare_parameter("settle_steps_max", DEFAULT_SETTLE_STEPS_MAX, ParameterDescriptor(
            read_only=True, description="cap on the steps that settle the scene to rest under zero commands at "
                                        "start-up and after ~/reset (0: off); only for the simulation built from "
                                        "'scene'")).value)
        if settle_steps_max < 0:
            raise ConfigError(f"parameter 'settle_steps_max' must be >= 0, got {settle_steps_max}")
        error_log_period = float(self.declare_parameter("error_log_period", DEFAULT_ERROR_LOG_PERIOD, ParameterDescriptor(
            read_only=True, description="s of wall time between two error lines of one kind (rejected commands "
                                        "by topic and reason, recording errors); each line counts the ones it "
                                        "stands for")).value)
        if not (math.isfinite(error_log_period) and error_log_period > 0):
            raise ConfigError(f"parameter 'error_log_period' must be > 0 s, got {error_log_period}")
        self.step_count = self._checked_step_count(self.declare_parameter("step_count", 1, ParameterDescriptor(
            description="steps one call of ~/step takes (>= 1; settable at runtime)")).value)
        if self.mode not in MODES:
            raise ConfigError(f"parameter 'mode' must be one of {MODES}, got {self.mode!r}")
        if self.executor_name not in EXECUTORS:
            raise ConfigError(f"parameter 'executor' must be one of {tuple(EXECUTORS)}, got {self.executor_name!r}")
        if not (math.isfinite(self.rate) and self.rate >= 0) or not (math.isfinite(self.mesh_rate) and self.mesh_rate >= 0):
            raise ConfigError(f"parameters 'rate' and 'mesh_rate' must be >= 0 Hz, got {self.rate}, {self.mesh_rate}")
        check_backend(backend, "node parameter 'backend'")
        sim_built = sim is None
        if sim is None:
            # a scene at rest repeats its fixed point instead of solving it again (StepInfo.repeated),
            # a resting body nothing moving can reach sleeps (StepInfo.sleeping), and a step starts
            # with the pad carried by its effector (sim_core.carried_start)
            sim = Simulation.from_scene(self.scene_path, solver_config=SolverConfig(
                backend=backend, repeat_fixed_points=True, sleeping=True, carried_start=True))
            # the solver's per-model structures (the fused evaluators and patterns, awake and with the
            # resting bodies asleep) now, not in the first steps that need them
            sim.warm_up()
        self.sim = sim
        self.settle_steps_max = settle_steps_max if sim_built else 0
        self.settle_info: SettleInfo | None = self._settle()
        self.dt = float(sim.dt)
        self._declare_material_parameters()

        self.workspace = self._workspace(ws_min, ws_max, ws_margin)
        limits = {}
        for name in sim.effector_names:
            eff = getattr(getattr(sim, "model", None), "effectors", {}).get(name)
            limits[name] = CommandLimits(
                max_translation_per_step=float(getattr(eff, "max_translation_per_step", 1e-3)),
                max_rotation_per_step=float(getattr(eff, "max_rotation_per_step", 0.02)),
                timeout=timeout, workspace=self.workspace)
        self.arbiter = CommandArbiter(limits)
        self.paused = self.mode == "stepped"
        self._error_throttle = ErrorThrottle(error_log_period, time.monotonic)
        self.intake = CommandIntake(self.arbiter, limits, lambda: float(self.sim.t), self._record_input,
                                    lambda line: self.get_logger().error(line), self._error_throttle)
        self._status = RuntimeStats(wall_clock=time.monotonic, sim_time=float(sim.t))
        self.failed_steps = 0
        self.consecutive_failures = 0
        self.relaxed_steps = 0  # steps accepted above the strict tolerance or retried in substeps
        self._solver_status_level = DiagnosticStatus.OK
        self._next_publish_t = 0.0
        self._next_mesh_t = 0.0
        self._warned_topics: set[str] = set()
        self._steps = 0
        self._advancing = False  # inside advance(): a command taken there does not start a step
        self._command_timer = None  # realtime: the one-shot wake-up of a command waiting for its step
        self._pacer = RealtimePacer(self.dt, REALTIME_MAX_LAG)
        self._wall_clock = wall_clock
        self._wall0 = time.monotonic()
        self._sim0 = sim.t

        self.recorder = None
        if record:
            self.recorder = BagRecorder(record, scene=record_scene or self.scene_path or None, force=record_force)
            self.get_logger().info(f"recording into {record}")

        self._pub_pose = {e: self.create_publisher(PoseStamped, f"{prefix}{e}/pose", SENSOR_QOS) for e in sim.effector_names}
        self._pub_markers = {s: self.create_publisher(PointCloud2, f"{prefix}{s}/markers", SENSOR_QOS) for s in sim.sensor_names}
        self._pub_wrench = {s: self.create_publisher(WrenchStamped, f"{prefix}{s}/wrench", SENSOR_QOS) for s in sim.sensor_names}
        self._pub_image = {s: self.create_publisher(Image, f"{prefix}{s}/image", SENSOR_QOS) for s in sim.sensor_names}
        self._pub_camera_info = {s: self.create_publisher(CameraInfo, f"{prefix}{s}/camera_info", CAMERA_INFO_QOS)
                                 for s in sim.sensor_names if self._camera(s) is not None}
        self._pub_points = self.create_publisher(PointCloud2, f"{prefix}sheet/points", SENSOR_QOS)
        self._pub_mesh = self.create_publisher(Marker, f"{prefix}sheet/mesh", MARKER_QOS)
        self._pub_clock = self.create_publisher(Clock, "/clock", CLOCK_QOS)
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._command_handlers: list[tuple[Any, Callable[[Any], None]]] = []  # (subscription, handler)
        self.command_gate = BurstGate()  # holds the command subscriptions out of the executor after a burst
        for e in sim.effector_names:
            for msg_type, suffix in ((PoseStamped, "pose_cmd"), (TwistStamped, "twist_cmd"), (Float64, "gripper_cmd")):
                handler = self.intake.handler(e, suffix)
                sub = self.create_subscription(msg_type, f"{prefix}{e}/{suffix}", self._stepping(handler), COMMAND_QOS,
                                               raw=msg_type is PoseStamped, callback_group=self.command_gate)
                self._command_handlers.append((sub, handler))
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(SetBool, "~/pause", self._on_pause)
        self.create_service(Trigger, "~/step", self._on_step)
        self.create_subscription(UInt32, "~/step_n", self._on_step_n, COMMAND_QOS)
        if self.mode != "stepped":
            self.create_timer(self.dt if self.mode == "realtime" else 0.0, self._on_timer)
        # realtime: wakes the node when a command that arrived one step ahead of the schedule may start
        # its step (_step_for_command); idle otherwise
        self._command_timer = self.create_timer(self.dt, self._on_command_due, autostart=False) \
            if self.mode == "realtime" else None
        self.create_timer(0.2, self._clock_heartbeat)
        self.create_timer(1.0, self._check_graph)
        self.create_timer(5.0, self._log_progress)
        self.create_timer(STATUS_PERIOD, self._publish_runtime_status)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._publish_settle_status()
        self.publish_camera_info()
        self.publish_outputs(force=True)
        self.get_logger().info(
            f"thinshell sim node: scene {self.scene_path or '<given>'}, mode {self.mode}, dt {self.dt:g} s, "
            f"backend {self._solver_backend()}, "
            f"effectors {sim.effector_names}, sensors {sim.sensor_names}, topics under {self.namespace}, workspace "
            f"{self.workspace.describe() if self.workspace else 'unlimited'}")

    def _workspace(self, low: list[float], high: list[float], margin: float) -> Workspace | None:
        """The declared workspace, or the scene's bounding box grown by ``margin`` (module docstring)."""
        if low or high:
            try:
                return Workspace(tuple(low), tuple(high))
            except ValueError as err:
                raise ConfigError(f"parameters 'workspace_min'/'workspace_max': {err}") from err
        if not math.isfinite(margin):
            raise ConfigError(f"parameter 'workspace_margin' must be finite, got {margin}")
        if margin < 0:
            return None
        obs = self.sim.observe()
        pts = [np.asarray(p, dtype=float)[:3] for p in obs.effector_pose.values()]
        pts = np.vstack([np.asarray(pts).reshape(-1, 3), np.asarray(obs.sheet_points, dtype=float).reshape(-1, 3)])
        return Workspace(tuple(pts.min(axis=0) - margin), tuple(pts.max(axis=0) + margin))

    # ------------------------------------------------------------------------------ parameters
    def _declare_material_parameters(self) -> None:
        self.material_names = list(self.sim.parameter_names)
        for name in self.material_names:
            current = float(self.sim.get_parameter(name))
            desc = ParameterDescriptor(dynamic_typing=True, description=f"simulation parameter {name} (SI units)")
            value = self.declare_parameter(name, current, desc).value
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ConfigError(f"parameter {name!r} must be a number, got {value!r}")
            if float(value) != current:
                self.sim.set_parameter(name, float(value))

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Validate and apply material parameters atomically (all or none)."""
        applied: list[tuple[str, float]] = []
        step_count = self.step_count
        try:
            for p in params:
                if p.name not in self.material_names:
                    continue
                if not isinstance(p.value, (int, float)) or isinstance(p.value, bool):
                    raise ConfigError(f"parameter {p.name!r} must be a number, got {p.value!r}")
                old = float(self.sim.get_parameter(p.name))
                self.sim.set_parameter(p.name, float(p.value))
                applied.append((p.name, old))
                self.get_logger().info(f"parameter {p.name} = {float(p.value):g}")
            for p in params:
                if p.name == "step_count":
                    step_count = self._checked_step_count(p.value)
                if p.name == "publish_image":
                    if not isinstance(p.value, bool):
                        raise ConfigError(f"parameter 'publish_image' must be a bool, got {p.value!r}")
                    self.publish_image = p.value
        except (ThinShellError, ValueError) as err:
            for name, old in reversed(applied):
                self.sim.set_parameter(name, old)
            self.get_logger().error(f"parameter change rejected: {err}")
            return SetParametersResult(successful=False, reason=str(err))
        self.step_count = step_count
        if applied:
            self.publish_camera_info()  # a camera parameter may have changed
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------------------ commands
    @property
    def rejected_commands(self) -> int:
        """Commands rejected so far (:class:`~thinshell_ros.command_intake.CommandIntake`)."""
        return self.intake.rejected_commands

    def _log_error(self, kind: str, line: str) -> None:
        """Log an error line of ``kind`` through the error throttle."""
        out = self._error_throttle.report(kind, line)
        if out is not None:
            self.get_logger().error(out)

    def _record_input(self, effector: str, suffix: str, msg: Any) -> None:
        """Record a taken command (rclpy message, or CDR bytes of a pose command) at the sim time now."""
        if self.recorder is not None and not self.recorder.closed:
            topic = f"{self.namespace}/{effector}/{suffix}"
            try:
                if isinstance(msg, bytes):
                    self.recorder.write_serialized(topic, POSE_TYPE, cv.seconds_to_ns(self.sim.t), msg)
                else:
                    self.recorder.write(topic, msg, cv.seconds_to_ns(self.sim.t))
            except ThinShellError as err:
                self._log_error(f"recording {topic}", f"recording {topic}: {err}")

    def _stepping(self, handle):
        """The subscription callback of a command topic: ``handle`` the message, take every other
        queued command (:meth:`take_pending_commands`: one executor turn for a burst, not one per
        message), then, in ``realtime`` mode, start the step that applies them when it may start now
        (:meth:`_step_for_command`). A turn that found :data:`BURST_MESSAGES` or more holds the command
        subscriptions out of the executor for one step (:class:`~thinshell_ros.runtime.BurstGate`):
        during a flood the next step takes what queued meanwhile (the newest
        :data:`~thinshell_ros.runtime.COMMAND_DEPTH` per topic), and the executor's turns go to the steps."""

        def on_command(msg: Any) -> None:
            handle(msg)
            if 1 + self.take_pending_commands() >= BURST_MESSAGES:
                self.command_gate.hold(self.dt)
            self._step_for_command()
        return on_command

    def _step_for_command(self) -> None:
        """In ``realtime`` mode, running and not inside a step: take the next step now when the
        schedule lets it start (:meth:`RealtimePacer.may_start`: due within one ``dt``), else as soon
        as it does (:meth:`RealtimePacer.start_time`, by a one-shot wake-up), so that a command does
        not wait for the timer's tick at the step's due time (up to a ``dt`` later)."""
        if self.mode != "realtime" or self.paused or self._advancing:
            return
        now = self._wall_clock()
        if self._pacer.may_start(now):
            self._pacer.stepped()
            self.advance()
            return
        delay = max(self._pacer.start_time(now) - now, 1e-4)
        self._command_timer.timer_period_ns = int(delay * 1e9)
        self._command_timer.reset()

    def _on_command_due(self) -> None:
        """The one-shot wake-up of a command that waits for its step (:meth:`_step_for_command`)."""
        self._command_timer.cancel()
        self._step_for_command()

    def take_pending_commands(self) -> int:
        """Take every command message queued on the command subscriptions, handle it (record, queue or
        submit) and submit the newest valid pose command of each effector (:meth:`_submit_poses`).

        rclpy's executors take one message per ready subscription per wait, and the ``fast`` mode's step
        timer runs before the subscriptions of the same wait: without this, a command that arrived during
        a step waits behind the next step, and with a shallow queue a newer one replaces it unseen; under
        a burst, each message would cost an executor turn (a wait-set rebuild). Each step, and each
        command callback, therefore takes all queued commands (in arrival order, oldest first; the newest
        valid one controls the step). Taking uses the subscription's handle as rclpy's executor does
        (``Executor._take_subscription``).

        Returns:
            the number of messages taken.
        """
        taken = 0
        for sub, handle in self._command_handlers:
            while True:
                try:
                    with sub.handle:
                        msg_info = sub.handle.take_message(sub.msg_type, sub.raw)
                except InvalidHandle:  # destroyed while shutting down
                    break
                if msg_info is None:
                    break
                handle(msg_info[0])
                taken += 1
        self.intake.submit_all()
        return taken

    def _check_graph(self) -> None:
        try:
            topics = [name for name, _ in self.get_topic_names_and_types()]
            for topic, effector in unknown_effector_topics(topics, self.namespace, self.sim.effector_names):
                if topic not in self._warned_topics:
                    self._warned_topics.add(topic)
                    self.get_logger().warning(f"{topic}: the scene has no effector {effector!r} "
                                              f"(effectors: {self.sim.effector_names}); its commands are ignored")
        except Exception as err:  # noqa: BLE001
            self.get_logger().error(f"graph check failed: {err}")

    # ------------------------------------------------------------------------------ stepping
    def advance(self) -> bool:
        """One simulation step with the current commands, then publish; returns whether it succeeded."""
        self._advancing = True
        if self._command_timer is not None:
            self._command_timer.cancel()  # this step applies every command handled so far
        try:
            return self._advance()
        finally:
            self._advancing = False

    def _advance(self) -> bool:
        self.take_pending_commands()
        try:
            targets = self.arbiter.step_targets(self.sim.t, self.dt, self._measured_poses())
            for event in targets.events:
                self.get_logger().warning(event)
            control = self.sim.model.control()
            control.effector_pose_target.update(targets.effector_pose_target)
            control.gripper_target.update(targets.gripper_target)
            t = float(self.sim.t)
            start = time.perf_counter()
            info = self.sim.step(control)
            self._status.stepped(time.perf_counter() - start)
            self._steps += 1
            self.consecutive_failures = 0
        except Exception as err:  # noqa: BLE001 - a failed step keeps the last state; the node lives on
            self.failed_steps += 1
            self.consecutive_failures += 1
            self.arbiter.hold()
            self.get_logger().error(f"step at t={self.sim.t:.4f} s failed ({type(err).__name__}: {err}); "
                                    "holding the effectors", throttle_duration_sec=1.0)
            self._publish_solver_status(solver_status(self._status_name, float(self.sim.t),
                                                      error=f"{type(err).__name__}: {err}"))
            if self.consecutive_failures >= MAX_CONSECUTIVE_FAILURES:
                self.paused = True
                self.get_logger().error(
                    f"{self.consecutive_failures} consecutive steps failed even with the effectors held: "
                    "simulation paused; call ~/reset (or ~/pause false to retry)")
            self.publish_outputs(force=True)
            return False
        self.publish_outputs()  # the outputs first, then the bookkeeping (diagnostics)
        if isinstance(info, StepInfo):
            self._report_step(t, info)
        return True

    def _settle(self) -> SettleInfo | None:
        """Settle the scene to rest (``settle_steps_max``, :func:`sim_core.settle.settle`) and log how it
        ended; None when off."""
        if self.settle_steps_max <= 0:
            return None
        start = time.monotonic()
        info = settle(self.sim, self.settle_steps_max)
        log = self.get_logger()
        (log.info if info.settled else log.warning)(
            f"start state: {info.describe()} ({time.monotonic() - start:.3g} s of wall time)"
            + ("" if info.settled else "; starting anyway"))
        return info

    def _publish_settle_status(self) -> None:
        """Publish the last settling's diagnostic status (:func:`settle_status`), if there was one."""
        if self.settle_info is not None:
            self._publish_solver_status(settle_status(f"{self.get_name()}: settle", self.settle_info),
                                        track_level=False)

    def _solver_backend(self) -> str:
        """The concrete backend of the simulation's solver, ``"<given>"`` for a stand-in without one."""
        solver = getattr(self.sim, "solver", None)
        return str(solver.backend) if isinstance(solver, NewtonSolver) else "<given>"

    @property
    def _status_name(self) -> str:
        return f"{self.get_name()}: solver"

    def _report_step(self, t: float, info: StepInfo) -> None:
        """Warn about and publish a step that was not strictly converged or needed substep retries;
        publish ``OK`` on the first strict step after one, and on a step at which bodies fell asleep or
        were woken."""
        if info.needs_attention:
            self.relaxed_steps += 1
            status = solver_status(self._status_name, t, info)
            self.get_logger().warning(f"step at t={t:.4f} s: {status.message} (residual "
                                      f"{info.residual_velocity:.3g} m/s, {info.iterations} iterations)",
                                      throttle_duration_sec=1.0)
            self._publish_solver_status(status)
        elif self._solver_status_level != DiagnosticStatus.OK or info.fell_asleep or info.woken:
            self._publish_solver_status(solver_status(self._status_name, t, info))

    def _publish_solver_status(self, status: DiagnosticStatus, track_level: bool = True) -> None:
        if track_level:
            self._solver_status_level = status.level
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = cv.stamp_from_ns(cv.seconds_to_ns(self.sim.t))
        try:
            self._pub_diagnostics.publish(msg)
        except Exception as err:  # noqa: BLE001 - a diagnostic never stops the node
            self.get_logger().error(f"publishing {DIAGNOSTICS_TOPIC} failed: {err}", throttle_duration_sec=1.0)

    def _publish_runtime_status(self) -> None:
        """The 1 Hz ``<node name>: status`` (:meth:`RuntimeStats.status`: real-time factor, step p95,
        rejected commands) on ``/diagnostics``, and the error lines the throttle held back a period."""
        for line in self._error_throttle.flush():
            self.get_logger().error(line)
        counters = {"rejected_commands": self.rejected_commands, "failed_steps": self.failed_steps,
                    "relaxed_steps": self.relaxed_steps, "error_lines": self._error_throttle.lines}
        status = self._status.status(f"{self.get_name()}: status", float(self.sim.t), self.intake.rejected_by_kind,
                                     counters, self.mode, self.paused)
        self._publish_solver_status(status, track_level=False)

    def _measured_poses(self) -> dict[str, Any]:
        state = getattr(self.sim, "state", None)
        if state is not None and getattr(state, "effector_pose", None):
            return state.effector_pose
        return self.sim.observe().effector_pose

    def _clock_heartbeat(self) -> None:
        """While paused (or stepped), keep ``/clock`` alive for sim-time clients (not recorded)."""
        if self.paused:
            self._pub_clock.publish(cv.clock_msg(cv.seconds_to_ns(self.sim.t)))

    def _on_timer(self) -> None:
        """The step timer: in ``fast`` mode one step; in ``realtime`` mode the due steps back to back, at
        most :data:`REALTIME_STEPS_PER_TICK`, and none after a step that took a ``dt`` or more of wall
        time (a Newton solve: the lag waits for the next tick, and until then the executor is free for
        a command to start its step at once, :meth:`_step_for_command`); the schedule restarts while
        paused."""
        if self.mode != "realtime":
            if not self.paused:
                self.advance()
            return
        for _ in range(REALTIME_STEPS_PER_TICK):
            if self.paused:
                self._pacer.restart()
                return
            start = self._wall_clock()
            if not self._pacer.due(start):
                return
            self._pacer.stepped()
            self.advance()
            if self._wall_clock() - start >= self.dt:
                return

    # ------------------------------------------------------------------------------ outputs
    def _publish(self, pub: Any, msg: Any, t_ns: int) -> None:
        pub.publish(msg)
        if self.recorder is not None and not self.recorder.closed:
            try:
                self.recorder.write(pub.topic_name, msg, t_ns)
            except ThinShellError as err:
                self.get_logger().error(f"recording {pub.topic_name}: {err}", throttle_duration_sec=1.0)

    def _noisy(self, values: Any, key: str) -> np.ndarray:
        """``values`` plus white Gaussian noise of the ``noise_<key>`` standard deviation (0: unchanged)."""
        values = np.asarray(values, dtype=float)
        sigma = self.noise[key]
        return values if sigma == 0 else values + self._rng.normal(0.0, sigma, values.shape)

    def _wanted(self, pub: Any) -> bool:
        """Whether a message on ``pub`` is read by anyone: the recording, or a matched subscription."""
        return (self.recorder is not None and not self.recorder.closed) or pub.get_subscription_count() > 0

    def publish_outputs(self, force: bool = False) -> None:
        """Publish ``/clock`` and, when due (``rate``) or ``force``, every sensor output: the effector
        poses (the state's) first, then the tactile outputs and sheet points (:meth:`Simulation.observe`).

        A sensor output is built only when it is read (:meth:`_wanted`: while recording, every one;
        else those with a matched subscription, which is all DDS would deliver it to), and the
        observation is read only when one of them is: with no subscriber to the markers, wrench,
        image, points and mesh, a step publishes ``/clock`` and the poses only.
        """
        t = float(self.sim.t)
        t_ns = cv.seconds_to_ns(t)
        try:
            self._publish(self._pub_clock, cv.clock_msg(t_ns), t_ns)
            due = force or self.rate <= 0 or t >= self._next_publish_t - 1e-9
            if not due:
                return
            if self.rate > 0:
                self._next_publish_t = t + 1.0 / self.rate
            # the effector poses are the state's (the step's kinematic result), published before the
            # tactile observation is read: a command's pose does not wait for the sensor model
            for e, pose in self._measured_poses().items():
                self._publish(self._pub_pose[e], cv.pose_to_msg(pose, t_ns, "world"), t_ns)
            mesh_due = self.mesh_rate > 0 and (force or t >= self._next_mesh_t - 1e-9)
            tactile = {s: (self._wanted(self._pub_markers[s]), self._wanted(self._pub_wrench[s]),
                           self.publish_image and self._wanted(self._pub_image[s])) for s in self._pub_markers}
            points, mesh = self._wanted(self._pub_points), mesh_due and self._wanted(self._pub_mesh)
            if not (points or mesh or any(any(w) for w in tactile.values())):
                return
            obs = self.sim.observe(render_image=self.publish_image) if self.publish_image else self.sim.observe()
            for s, reading in obs.tactile.items():
                markers, wrench_wanted, image = tactile.get(s, (False, False, False))
                if markers:
                    xyz, uv = self._noisy(reading.markers_xyz, "markers"), self._noisy(reading.markers_uv, "pixels")
                    self._publish(self._pub_markers[s], cv.markers_to_msg(xyz, uv, t_ns, s), t_ns)
                if wrench_wanted:
                    wrench = np.asarray(reading.wrench, dtype=float)
                    wrench = np.concatenate([self._noisy(wrench[:3], "force"), self._noisy(wrench[3:], "torque")])
                    self._publish(self._pub_wrench[s], cv.wrench_to_msg(wrench, t_ns, s), t_ns)
                if image and reading.image is not None:
                    self._publish(self._pub_image[s], cv.image_to_msg(reading.image, t_ns, s), t_ns)
                    if s in self._pub_camera_info:  # the image's calibration, with its stamp (the ROS convention)
                        self._publish(self._pub_camera_info[s], cv.camera_info_msg(self._camera(s), t_ns, s), t_ns)
            if len(obs.sheet_points):
                if points:
                    self._publish(self._pub_points, cv.points_to_msg(self._noisy(obs.sheet_points, "points"), t_ns,
                                                                     "world"), t_ns)
                if mesh_due:
                    self._next_mesh_t = t + 1.0 / self.mesh_rate
                    if mesh:
                        self._publish(self._pub_mesh, cv.mesh_to_marker(obs.sheet_points, obs.sheet_triangles, t_ns),
                                      t_ns)
        except Exception as err:  # noqa: BLE001
            self.get_logger().error(f"publishing at t={t:.4f} s failed: {err}", throttle_duration_sec=1.0)

    def _camera(self, sensor: str) -> Any | None:
        """The tactile camera of ``sensor`` (its current intrinsics, which material parameters may
        change), or None for a simulation without one (a stand-in)."""
        model_sensor = getattr(getattr(self.sim, "model", None), "sensors", {}).get(sensor)
        return getattr(model_sensor, "camera", None)

    def publish_camera_info(self) -> None:
        """Publish (and record) each tactile camera's ``<sensor>/camera_info`` at the current sim time
        (:func:`thinshell_ros.conversions.camera_info_msg`; kept for late subscribers, CAMERA_INFO_QOS)."""
        t_ns = cv.seconds_to_ns(float(self.sim.t))
        for s, pub in self._pub_camera_info.items():
            try:
                self._publish(pub, cv.camera_info_msg(self._camera(s), t_ns, s), t_ns)
            except Exception as err:  # noqa: BLE001 - an output never stops the node
                self._log_error("camera_info", f"publishing {s}/camera_info failed: {err}")

    def _log_progress(self) -> None:
        wall = time.monotonic() - self._wall0
        if wall > 0 and self._steps:
            rtf = (self.sim.t - self._sim0) / wall
            lag = f", {self._pacer.dropped:.3g} s of lag dropped so far" if self.mode == "realtime" else ""
            self.get_logger().info(f"t={self.sim.t:.3f} s, {self._steps} steps, real-time factor {rtf:.3g}{lag}")
        self._wall0, self._sim0, self._steps = time.monotonic(), self.sim.t, 0

    # ------------------------------------------------------------------------------ services
    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            self.sim.reset()
            self.settle_info = self._settle()
            self._publish_settle_status()
            self.arbiter.reset()
            self._pacer.restart()
            self.consecutive_failures = 0
            self._next_publish_t = self._next_mesh_t = 0.0
            self.publish_camera_info()
            self.publish_outputs(force=True)
            response.success, response.message = True, f"reset to t={self.sim.t:g} s"
        except Exception as err:  # noqa: BLE001
            response.success, response.message = False, f"reset failed: {err}"
        return response

    def _on_pause(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        self.paused = bool(request.data) if self.mode != "stepped" else True
        response.success = self.mode != "stepped" or bool(request.data)
        response.message = "paused" if self.paused else "running"
        if self.mode == "stepped" and not request.data:
            response.message = "stepped mode: use ~/step to advance"
        return response

    def _on_step(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """``~/step``: take ``step_count`` steps (parameter, default 1); fails at the first failed step."""
        done = self.step_n(self.step_count)
        response.success = done == self.step_count
        response.message = (f"t={self.sim.t:.6f} s" + (f" after {done} steps" if done > 1 else "") if response.success
                            else f"step failed at t={self.sim.t:.6f} s after {done} steps (see log)")
        return response

    def _on_step_n(self, msg: UInt32) -> None:
        """``~/step_n`` (``std_msgs/UInt32``): take ``msg.data`` steps (at most :data:`MAX_STEP_N`)."""
        try:
            n = self._checked_step_count(int(msg.data))
        except ConfigError as err:
            self._log_error("~/step_n", f"~/step_n: {err}")
            return
        done = self.step_n(n)
        self.get_logger().info(f"~/step_n: {done} of {n} steps taken, t={self.sim.t:.6f} s")

    def step_n(self, n: int) -> int:
        """Take up to ``n`` steps, stopping at the first failed one; returns the steps that succeeded."""
        for k in range(n):
            if not self.advance():
                return k
        return n

    @staticmethod
    def _checked_step_count(n: Any) -> int:
        """``n`` as a step count in ``1..MAX_STEP_N``.

        Raises:
            ConfigError: not an integer in that range.
        """
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_STEP_N:
            raise ConfigError(f"parameter 'step_count' / ~/step_n must be an integer in 1..{MAX_STEP_N}, got {n!r}")
        return n

    # ------------------------------------------------------------------------------ shutdown
    def make_executor(self) -> Any:
        """A new executor of the ``executor`` parameter's kind (:data:`EXECUTORS`) on the node's context:
        an ``rclpy.executors.SingleThreadedExecutor`` or an ``EventsExecutor`` (a C++ class of rclpy)."""
        return EXECUTORS[self.executor_name](context=self.context)

    def close(self) -> None:
        """Close the recording (idempotent)."""
        if self.recorder is not None and not self.recorder.closed:
            counts = self.recorder.message_counts
            self.recorder.close()
            self.get_logger().info(f"recording closed: {sum(counts.values())} messages on {len(counts)} topics")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the node until SIGINT/SIGTERM; the recording (if any) is closed. Returns the exit code."""
    args = list(sys.argv) if argv is None else ["thinshell-sim-node", *argv]
    with ros_session(args) as stop:
        try:
            node = SimNode()
        except (ThinShellError, FileNotFoundError) as err:
            print(f"thinshell sim node: error: {err}", file=sys.stderr)
            return 1
        freeze_start_up_objects()  # no full collection traverses the start-up state while the node runs
        try:
            spin_until_stopped(node, stop, executor=node.make_executor())
        finally:
            node.close()
            node.destroy_node()
    return 0


if __name__ == "__main__":
    sys.exit(main())
