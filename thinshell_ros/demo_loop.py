"""The sim-to-real loop stages of ``thinshell demo``: hidden "robot", fitted scene, deploy, compare.

The "robot" is the sim node started on a *hidden* scene: the nominal scene with other material values
(:data:`HIDDEN`) and one concealed effect (:data:`CONCEALED`, a missing-physics term of
:mod:`sim_core.candidates`). Its recordings state the nominal scene (the sim node's ``record_scene``),
as a real cell's would; the hidden scene is kept aside in the run directory and revealed in the
report only.

- :func:`write_hidden_scene`: the hidden scene file.
- :func:`deploy_trajectory_from_bag`: a press-slide-lift planned from the first measured pose and sheet
  of a recording, written as a trajectory file (``docs/trajectory_format.md``): the motion the demo
  deploys on the tactile cell (the optimiser's trajectory is deployed on the task cell,
  :mod:`thinshell_ros.demo_task`).
- :func:`stop_process`, :func:`log_tail`: the robot subprocess's end and its log.
- :func:`run_deploy_stage`: the robot again, driven by the deploy node (sim time: the robot's
  ``/clock``), recording the deployed run.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from sim_core.errors import ThinShellError
from sim_core.scenes.scene_file import load_scene_file, load_yaml
from sim_core.trajectory_file import Trajectory, write_trajectory
from sysid.bagio import open_bag
from sysid.fitted_scene import scene_with_values

HIDDEN = {"gel.youngs_modulus": 4.5e5, "friction.gel_sheet": 0.6}
"""Material values of the "robot" (the nominal press_slide scene has 3.0e5 Pa and 0.8)."""

CONCEALED = {"candidate.gel_viscoelasticity": 0.4, "candidate.gel_viscoelasticity.tau": 0.3}
"""The concealed effect: a Maxwell branch in the gel (stiffness ratio 0.4, relaxation time 0.3 s)."""


SENSOR_NOISE = {"markers": 15e-6, "pixels": 0.15, "force": 0.15, "torque": 4e-4, "points": 10e-6}
"""Standard deviations of the robot's measurement noise (sim node ``noise_*``), about those of the
bundled recording ``bags/nominal_s101``."""

WRENCH_LIMIT = 40.0
"""N: the deploy node's wrench limit on the demo robot (its stiffer gel presses the card with about 20 N)."""


def start_sim_node(scene: Path, bag: Path, record_scene: Path, log_path: Path, mode: str = "fast",
                   extra_args: Sequence[str] = ()) -> subprocess.Popen:
    """Start ``thinshell-sim-node`` on ``scene`` as a subprocess of this checkout, recording into
    ``bag`` with ``record_scene`` as the bag's scene.yaml; its output goes to ``log_path``.

    Returns:
        the process (stop it with :func:`stop_process`).
    """
    env = dict(os.environ)
    repo = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = repo + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    cmd = [sys.executable, "-m", "thinshell_ros.sim_node", "--ros-args", "-p", f"scene:={scene}",
           "-p", f"mode:={mode}", "-p", "mesh_rate:=0.0", "-p", f"record:={bag}", "-p", f"record_scene:={record_scene}",
           *extra_args]
    with open(log_path, "w") as log:
        return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)


def stop_process(proc: subprocess.Popen, timeout: float = 60.0) -> int:
    """SIGINT (the node closes its bag), then SIGTERM, then SIGKILL; returns the exit code."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        try:
            return proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            continue
    if proc.poll() is None:
        proc.kill()
    return proc.wait()


def log_tail(path: Path, n: int = 2000) -> str:
    """The last ``n`` characters of a log file ("" when unreadable)."""
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""


def robot_noise_args(seed: int) -> list[str]:
    """``--ros-args`` ``-p`` pairs of the robot's measurement noise (:data:`SENSOR_NOISE`)."""
    args = []
    for key, sigma in SENSOR_NOISE.items():
        args += ["-p", f"noise_{key}:={sigma!r}"]
    return [*args, "-p", f"noise_seed:={seed}"]


def write_hidden_scene(nominal: Path, path: Path, hidden: Mapping[str, float] = HIDDEN,
                       concealed: Mapping[str, float] = CONCEALED) -> Path:
    """The nominal scene with the hidden values and the concealed effect, written to ``path``."""
    doc = scene_with_values(load_yaml(Path(nominal).read_text()), {**hidden, **concealed})
    doc["name"] = f"{doc.get('name', 'scene')} (hidden robot)"
    path.write_text("# the demo robot's hidden scene (thinshell_ros/demo_loop.py)\n"
                    + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))
    return path


def deploy_trajectory_from_bag(bag: Path, nominal: Path, out: Path, motion: Mapping[str, float]) -> Path:
    """Plan a press-slide-lift from a recording's first measured pose and sheet and write it.

    Args:
        bag: a recording of the robot (its start pose and sheet).
        nominal: the nominal scene (sensor mount, sheet thickness).
        out: the trajectory file to write.
        motion: :func:`thinshell_ros.commander.plan_from_observation` keyword arguments.

    Raises:
        ThinShellError: unreadable bag, or a motion that cannot be planned.
    """
    from thinshell_ros.commander import plan_from_observation  # optional heavy dependency: ROS 2 (rclpy)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        contents = open_bag(bag, skip_roles=("image", "markers", "wrench", "clock", "pose_cmd"))
    pose = contents.series["pose"].values[0]
    points = contents.series["sheet_points"].values[0][:, :3]
    scene = load_scene_file(nominal)
    plan = plan_from_observation(scene, pose, points, "press_slide_lift", **motion)
    effector = plan.effector or next(iter(scene.sensors.values())).effector
    traj = Trajectory(t=plan.t, poses={effector: plan.poses}, scene_path=str(nominal), scene_name=scene.name,
                      provenance={"tool": "thinshell demo (scripted press-slide-lift of the tactile cell)",
                                  "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "from_bag": str(bag)})
    return write_trajectory(out, traj, force=True)


def run_deploy_stage(hidden_scene: Path, nominal: Path, trajectory: Path, bag: Path, log_path: Path,
                     timeout: float, console: Any, limits: Mapping[str, float] | None = None,
                     settle: float = 0.0, require_wrench: bool = True,
                     robot_args: Sequence[str] = ()) -> dict[str, Any]:
    """Start the robot (sim node on the hidden scene, ``fast`` mode, recording into ``bag``), deploy
    ``trajectory`` on it with the deploy node in sim time, stop the robot (SIGINT closes the bag).

    ``limits``: further float parameters of the deploy node (``rate``, ``max_linear_speed``, ...;
    :data:`thinshell_ros.deploy_node.FLOAT_PARAMETERS`); the wrench limit is :data:`WRENCH_LIMIT`.
    ``settle``: s of the robot's (sim) clock it keeps running, and recording, after the last command
    (the state the last command produced is then in the bag).
    ``require_wrench``: the deploy node's parameter (false for a robot that publishes no wrench: its
    wrench limit is then not enforced).

    Returns:
        the deploy node's final status (``state``, ``reason``, ``published``, ...) and ``wall_s``.

    Raises:
        ThinShellError: the robot did not start or exited, or the deployment did not end in ``timeout`` s.
    """
    import rclpy  # optional heavy dependency: ROS 2 (rclpy), for ROS commands only
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from thinshell_ros.deploy_node import DeployNode

    t0 = time.monotonic()
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    proc = start_sim_node(hidden_scene, bag, nominal, log_path, extra_args=[*robot_noise_args(seed=2), *robot_args])
    node = executor = None
    try:
        node = DeployNode(context=ctx, parameter_overrides=[
            Parameter("trajectory", value=str(trajectory)), Parameter("use_sim_time", value=True),
            Parameter("start_timeout", value=120.0), Parameter("wrench_limit", value=WRENCH_LIMIT),
            Parameter("require_wrench", value=bool(require_wrench)),
            *(Parameter(k, value=float(v)) for k, v in (limits or {}).items())])
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        deadline = time.monotonic() + timeout
        while not node.done.is_set():
            if proc.poll() is not None:
                raise ThinShellError(f"the robot (sim node) exited with code {proc.returncode}:\n{log_tail(log_path)}")
            if time.monotonic() > deadline:
                node.abort(f"demo timeout {timeout:.0f} s")
                raise ThinShellError(f"the deployment did not finish within {timeout:.0f} s ({node.status()})")
            executor.spin_once(timeout_sec=0.05)
        status = node.status()
        if status["state"] == "completed" and settle > 0:
            clock = node.get_clock()  # the robot's /clock (use_sim_time)
            end = clock.now().nanoseconds * 1e-9 + settle
            while clock.now().nanoseconds * 1e-9 < end:
                if proc.poll() is not None or time.monotonic() > deadline:
                    break
                executor.spin_once(timeout_sec=0.05)
        code = stop_process(proc)
    finally:
        if proc.poll() is None:
            stop_process(proc)
        if executor is not None:
            executor.shutdown(timeout_sec=0)
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()
    if code != 0 and status["state"] == "completed":
        raise ThinShellError(f"the robot (sim node) exited with code {code}:\n{log_tail(log_path)}")
    status["wall_s"] = time.monotonic() - t0
    console.print(f"  deploy {status['state']}: {status['reason']}")
    return status


def rms_table(compare_doc: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """Channel -> {label: RMS} of a ``compare.json`` document."""
    out: dict[str, dict[str, float]] = {}
    for label, channels in compare_doc["rms"].items():
        for ch, entry in channels.items():
            out.setdefault(ch, {})[label] = float(entry["rms"])
    return out


def improvement(table: Mapping[str, Mapping[str, float]], better: str = "fitted", worse: str = "nominal") -> dict[str, float]:
    """Channel -> RMS(better) / RMS(worse) (< 1: ``better`` predicts the recording better)."""
    return {ch: (v[better] / v[worse] if v[worse] > 0 else float(np.nan)) for ch, v in table.items()}
