"""The system-identification node: fit material parameters to a bag on request, publish and apply them.

Parameters (read at every fit request, so ``ros2 param set`` between fits takes effect):

- ``bag`` (str): recording to fit (rosbag2 MCAP directory with ``scene.yaml``, INTERFACES.md).
- ``params`` (str): comma-separated global parameter names (``sheet.bending_stiffness,...``);
  empty: the fitter's defaults (:data:`sysid.fit.DEFAULT_PARAMETERS`).
- ``out`` (str): directory of the fit report; empty: a new ``./sysid_<bag name>_<timestamp>``.
- ``force`` (bool): replace an existing report directory.
- ``t_max`` (s), ``dt`` (s): fit only the first ``t_max`` s of the recording / replay at step ``dt``;
  0 = the fitter's defaults.
- ``max_nfev`` (int, 30), ``max_time`` (s, 0 = no budget), ``global_search`` (bool: CMA-ES before the
  local least squares), ``gel_resolution`` (str ``NX,NY,NZ``, empty = the scene's), ``gel_element`` (str, the
  gel's law as ``thinshell sysid --gel-element``: ``stable_neohookean`` | ``nodal_pressure_neohookean`` |
  ``green_strain`` | ``modified_stvk`` | ``auto``; empty = the scene's), ``workers`` (int),
  ``arch`` (``cpu`` | ``cuda`` | ``numpy``), ``sensor_calibration`` (bool, true): the fitter's settings
  (:class:`sysid.fit_recording.FitOptions`; the fit runs :func:`sysid.fit_recording.fit_recording`).
- ``write_scene`` (str): also write the fitted scene there (``thinshell sysid --write-scene``;
  replaced only with ``force``); empty: none. The result's ``scene`` names it.
- ``recording_map`` (str): recording map of a real cell's bag (``thinshell sysid --recording-map``;
  docs/recording_map.md); empty: the bag's ``recording.yaml``, else the INTERFACES.md topics.
- ``apply_to`` (str): fully qualified name of a running simulator node (``/thinshell_sim`` for
  ``thinshell-sim-node`` started without a ROS namespace); empty: do not apply.
- ``apply_timeout`` (s): how long to wait for ``<apply_to>/set_parameters``.
- ``namespace`` (str, default ``/thinshell``): prefix of the result topic in the root namespace (a node
  given a ROS namespace publishes ``sysid/result`` relative to it: :func:`thinshell_ros.runtime.topic_namespace`).

Diagnostics: a ``diagnostic_msgs/DiagnosticArray`` with the status ``<node name>: progress`` on
``/diagnostics`` every second (:func:`thinshell_ros.node_status.sysid_status`: idle / fitting /
applying, the running fit's wall time and its share of ``max_time``, fits done and failed, the last
outcome).

Service ``~/fit`` (std_srvs/Trigger) starts a fit in a worker thread and answers at once (the node
keeps spinning); a second request while one runs is refused. When the fit ends, the fitted values
are set on ``apply_to`` through its standard parameter service (``rcl_interfaces/srv/SetParameters``)
when that is configured, and then one JSON document is published on ``<namespace>/sysid/result``
(std_msgs/String, reliable, transient local: a late subscriber still gets the last result):
``{"status": "ok" | "error", "bag", "params": {name: value}, "initial", "sigma", "fit_status",
"message", "rms_final", "out", "report", "files", "scene", "wall_time_s", "apply_to",
"applied": {name: bool} | null, "apply_message"}`` (``"error"`` instead of the fit keys on failure).
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger

from sim_core.errors import ConfigError
from sysid.fit_recording import FitOptions, fit_recording
from sysid.results import load_fit_json
from thinshell_ros.node_status import sysid_status
from thinshell_ros.runtime import DIAGNOSTICS_TOPIC, STATUS_PERIOD, topic_namespace

RESULT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""QoS of ``sysid/result``: the last result is kept for subscribers that join later."""


@dataclass(frozen=True)
class FitRequest:
    """One fit job, from the node's parameters at the time of the request.

    Attributes:
        bag: recording path.
        out: report directory (None: a new ``./sysid_<bag name>_<timestamp>``, :func:`default_out`).
        force: replace an existing report.
        options: the fit's settings (:class:`sysid.fit_recording.FitOptions`).
        write_scene: fitted scene file to write (None: none).
    """

    bag: Path
    out: Path | None
    force: bool
    options: FitOptions
    write_scene: Path | None = None


def parse_params(text: str) -> tuple[str, ...]:
    """``"a, b,c"`` -> ``("a", "b", "c")``; empty entries are dropped.

    Raises:
        ConfigError: a name appears twice.
    """
    names = tuple(p.strip() for p in text.split(",") if p.strip())
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"parameter 'params' lists {dup} more than once")
    return names


def default_out(bag: Path, now: float | None = None) -> Path:
    """Report directory when ``out`` is empty: ``./sysid_<bag name>_<YYYYmmdd-HHMMSS>`` (never an existing one)."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    out = Path.cwd() / f"sysid_{bag.resolve().name}_{stamp}"
    k = 1
    while out.exists():
        k += 1
        out = Path.cwd() / f"sysid_{bag.resolve().name}_{stamp}_{k}"
    return out


def run_fit(request: FitRequest) -> dict[str, Any]:
    """Run the fitter (:func:`sysid.fit_recording.fit_recording`, what ``thinshell sysid`` runs) and
    summarise its ``fit.json``.

    Returns:
        the fit summary (:func:`summarise_fit`).

    Raises:
        ThinShellError: the fit failed (unreadable bag, invalid scene, diverged replay, existing
            report directory without ``force``, ...); CalibrationError: no valid ``fit.json``.
    """
    out = request.out if request.out is not None else default_out(request.bag)
    outcome = fit_recording(request.bag, out, request.options, force=request.force,
                            command=["thinshell-sysid-node", str(request.bag), repr(request.options)],
                            write_scene=request.write_scene)
    summary = summarise_fit(out)
    summary["scene"] = str(outcome.scene) if outcome.scene is not None else None
    return summary


def summarise_fit(out: Path) -> dict[str, Any]:
    """Fit summary from the report directory ``out`` written by ``thinshell sysid``.

    Returns:
        ``{"params": {name: value}, "initial": {name: value}, "sigma": {name: sigma | None},
        "sigma_robust": {name: sigma | None}, "robust_method": "hac" | "block_bootstrap" | None, "dt": s,
        "fit_status", "message", "rms_final": {channel: rms}, "out", "report", "files"}``
        (``sigma_robust``: the 1-sigma that holds under model error, :mod:`sysid.covariance`; ``dt``:
        the step the fit replayed at).

    Raises:
        CalibrationError: missing or invalid ``out/fit.json`` (:func:`sysid.results.load_fit_json`).
    """
    out = Path(out)
    doc = load_fit_json(out / "fit.json")
    params = doc["fit"]["parameters"]
    diag = doc["diagnostics"]
    return {"params": {n: p["value"] for n, p in params.items()},
            "initial": {n: p["initial"] for n, p in params.items()},
            "sigma": {n: p["sigma"] for n, p in params.items()},
            "sigma_robust": {n: p.get("sigma_robust") for n, p in params.items()},
            "robust_method": (doc["fit"].get("robust") or {}).get("method"), "dt": diag["dt"],
            "fit_status": diag["status"], "message": diag["message"],
            "rms_final": {ch: v.get("rms") for ch, v in (doc["metrics"]["rms_final"] or {}).items()},
            "out": str(out), "report": str(out / "report.html"), "files": sorted(p.name for p in out.iterdir())}


class SysidNode(Node):
    """ROS 2 node running system identification on request (module docstring).

    Args:
        runner: ``FitRequest -> summary dict`` with at least ``params`` (name -> fitted value);
            default :func:`run_fit`.
        node_name: ROS node name.
        **kwargs: passed to ``rclpy.node.Node`` (``context``, ``parameter_overrides``, ...).
    """

    def __init__(self, runner: Callable[[FitRequest], dict[str, Any]] | None = None,
                 node_name: str = "thinshell_sysid", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.runner = runner or run_fit
        for name, default in (("bag", ""), ("params", ""), ("out", ""), ("force", False), ("t_max", 0.0),
                              ("dt", 0.0), ("max_nfev", FitOptions.max_nfev), ("max_time", 0.0),
                              ("global_search", False), ("gel_resolution", ""), ("gel_element", ""),
                              ("workers", 1),
                              ("arch", FitOptions.arch), ("sensor_calibration", FitOptions.sensor_calibration),
                              ("apply_to", ""), ("apply_timeout", 10.0), ("write_scene", ""),
                              ("recording_map", "")):
            self.declare_parameter(name, default)
        self.namespace, prefix = topic_namespace(self, str(self.declare_parameter("namespace", "/thinshell").value))
        self._pub = self.create_publisher(String, f"{prefix}sysid/result", RESULT_QOS)
        self.result_topic = self._pub.topic_name
        self._lock = threading.Lock()
        self._worker: threading.Thread | None = None
        self._started = 0.0
        self._finished: dict[str, Any] | None = None
        self._pending_apply: dict[str, Any] | None = None
        self._set_param_clients: dict[str, Any] = {}
        self.results: list[dict[str, Any]] = []
        self._job: FitRequest | None = None
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self.create_service(Trigger, "~/fit", self._on_fit)
        self.create_timer(0.05, self._poll)
        self.create_timer(STATUS_PERIOD, self._publish_progress)
        self.get_logger().info(f"sysid node: call {self.get_fully_qualified_name()}/fit; results on {self.result_topic}")

    @property
    def busy(self) -> bool:
        """True while a fit (or the application of its result) is in progress."""
        with self._lock:
            return self._worker is not None

    def _param(self, name: str) -> Any:
        return self.get_parameter(name).value

    def _request(self) -> FitRequest:
        bag = str(self._param("bag")).strip()
        if not bag:
            raise ConfigError("parameter 'bag' is empty: set it to a recording (rosbag2 directory)")
        if not Path(bag).exists():
            raise ConfigError(f"parameter 'bag': {bag} does not exist")
        t_max, dt, max_time = (float(self._param(k)) for k in ("t_max", "dt", "max_time"))
        for key, value in (("t_max", t_max), ("dt", dt), ("max_time", max_time)):
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"parameter {key!r} must be >= 0 (0: the fitter's default), got {value}")
        resolution = str(self._param("gel_resolution")).strip()
        try:
            gel_resolution = tuple(int(v) for v in resolution.split(",")) if resolution else None
        except ValueError as err:
            raise ConfigError(f"parameter 'gel_resolution' must be NX,NY,NZ (integers), got {resolution!r}") from err
        params = parse_params(str(self._param("params")))
        recording_map = str(self._param("recording_map")).strip()
        if recording_map and not Path(recording_map).is_file():
            raise ConfigError(f"parameter 'recording_map': {recording_map} does not exist")
        defaults = FitOptions()
        options = FitOptions(params=params or defaults.params, dt=dt or defaults.dt, t_max=t_max or None,
                             max_nfev=int(self._param("max_nfev")), max_time=max_time or None,
                             global_method="cma" if self._param("global_search") else None,
                             gel_resolution=gel_resolution, gel_element=str(self._param("gel_element")).strip() or None,
                             workers=int(self._param("workers")),
                             arch=str(self._param("arch")),
                             sensor_calibration=bool(self._param("sensor_calibration")),
                             recording_map=recording_map or None,
                             # no fork from a process whose DDS threads hold locks: the calibration in one process
                             probe_worker=False)
        out = str(self._param("out")).strip()
        scene = str(self._param("write_scene")).strip()
        return FitRequest(Path(bag), Path(out) if out else None, bool(self._param("force")), options,
                          Path(scene) if scene else None)

    # ------------------------------------------------------------------------------ service
    def _on_fit(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            if self._worker is not None:
                response.success = False
                response.message = f"a fit is already running (for {time.monotonic() - self._started:.0f} s)"
                return response
            try:
                job = self._request()
            except ConfigError as err:
                response.success, response.message = False, str(err)
                return response
            self._started = time.monotonic()
            self._job = job
            self._worker = threading.Thread(target=self._work, args=(job,), name="sysid-fit", daemon=True)
            self._worker.start()
        names = ",".join(job.options.params)
        response.success = True
        response.message = f"fit started: {job.bag} ({names}); the result will be published on {self.result_topic}"
        self.get_logger().info(response.message)
        return response

    def _work(self, job: FitRequest) -> None:
        """Worker thread: run the fitter; the executor thread publishes and applies (``_poll``)."""
        t0 = time.monotonic()
        base = {"bag": str(job.bag), "apply_to": str(self._param("apply_to")) or None, "applied": None,
                "apply_message": ""}
        try:
            summary = self.runner(job)
            result = {"status": "ok", **base, **summary}
        except Exception as err:  # noqa: BLE001 - any failure is reported on the topic, the node lives on
            result = {"status": "error", **base, "error": f"{type(err).__name__}: {err}", "params": {}}
        result["wall_time_s"] = round(time.monotonic() - t0, 3)
        with self._lock:
            self._finished = result

    # ------------------------------------------------------------------------------ executor side
    def _poll(self) -> None:
        with self._lock:
            result, self._finished = self._finished, None
        if result is not None:
            target = result["apply_to"]
            if result["status"] == "ok" and target and result["params"]:
                self._pending_apply = {"result": result, "deadline": time.monotonic() + float(self._param("apply_timeout"))}
            else:
                self._publish(result)
        if self._pending_apply is not None:
            self._try_apply()

    def _publish_progress(self) -> None:
        """The 1 Hz ``<node name>: progress`` status (:func:`sysid_status`) on ``/diagnostics``."""
        with self._lock:
            running, job = self._worker is not None, self._job
        state = "idle" if not running else ("applying" if self._pending_apply is not None else "fitting")
        last = self.results[-1] if self.results else None
        outcome = "" if last is None else ("ok" if last["status"] == "ok" else f"error: {last.get('error', '')}")
        budget = float(job.options.max_time or 0.0) if job is not None else 0.0
        elapsed = time.monotonic() - self._started if running else 0.0
        status = sysid_status(f"{self.get_name()}: progress", state, elapsed, budget, len(self.results), sum(r["status"] != "ok" for r in self.results), outcome,
                              str(job.bag) if job is not None else "")
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_diagnostics.publish(msg)

    def _client(self, target: str):
        service = f"{target.rstrip('/')}/set_parameters"
        if service not in self._set_param_clients:
            self._set_param_clients[service] = self.create_client(SetParameters, service)
        return self._set_param_clients[service]

    def _try_apply(self) -> None:
        pending = self._pending_apply
        if pending.get("future") is not None:
            return
        result = pending["result"]
        client = self._client(result["apply_to"])
        if not client.service_is_ready():
            if time.monotonic() > pending["deadline"]:
                self._pending_apply = None
                result["applied"] = {name: False for name in result["params"]}
                result["apply_message"] = f"{client.srv_name} not available within {self._param('apply_timeout')} s"
                self.get_logger().error(result["apply_message"])
                self._publish(result)
            return
        names = list(result["params"])
        request = SetParameters.Request()
        request.parameters = [Parameter(n, Parameter.Type.DOUBLE, float(result["params"][n])).to_parameter_msg()
                              for n in names]
        future = client.call_async(request)
        pending["future"] = future
        future.add_done_callback(lambda fut: self._on_applied(fut, names, result))

    def _on_applied(self, future: Any, names: list[str], result: dict[str, Any]) -> None:
        self._pending_apply = None
        try:
            replies = future.result().results
            result["applied"] = {n: bool(r.successful) for n, r in zip(names, replies)}
            reasons = [f"{n}: {r.reason}" for n, r in zip(names, replies) if not r.successful]
            result["apply_message"] = "; ".join(reasons) if reasons else f"set on {result['apply_to']}"
        except Exception as err:  # noqa: BLE001
            result["applied"] = {n: False for n in names}
            result["apply_message"] = f"set_parameters failed: {err}"
        log = self.get_logger().info if all(result["applied"].values()) else self.get_logger().error
        log(f"apply to {result['apply_to']}: {result['apply_message']}")
        self._publish(result)

    def _publish(self, result: dict[str, Any]) -> None:
        self.results.append(result)
        self._pub.publish(String(data=json.dumps(result, default=float)))
        if result["status"] == "ok":
            values = ", ".join(f"{k}={v:.6g}" for k, v in result["params"].items())
            self.get_logger().info(f"fit of {result['bag']} done in {result['wall_time_s']:.1f} s: {values}")
        else:
            self.get_logger().error(f"fit of {result['bag']} failed: {result['error']}")
        with self._lock:
            self._worker = None


def main(argv: Sequence[str] | None = None) -> int:
    """Run the sysid node until SIGINT/SIGTERM; returns the exit code."""
    from sim_core.errors import ThinShellError
    from thinshell_ros.runtime import ros_session, spin_until_stopped

    args = list(sys.argv) if argv is None else ["thinshell-sysid-node", *argv]
    with ros_session(args) as stop:
        try:
            node = SysidNode()
        except ThinShellError as err:
            print(f"thinshell sysid node: error: {err}", file=sys.stderr)
            return 1
        try:
            spin_until_stopped(node, stop)
        finally:
            node.destroy_node()
    return 0


if __name__ == "__main__":
    sys.exit(main())
