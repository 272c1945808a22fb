"""The task stage of ``thinshell demo``: a ThinShellLab task optimised on a fitted scene, deployed on the
"robot" and scored there.

The robot's tactile dome (its gel) also works a task cell: the demo's second robot is the sim node on
the task's scene (default :data:`TASK`, ThinShellLab's Forming: the dome presses and drags a hairpin
sheet towards a target shape) with hidden values: the gel modulus of the tactile robot
(:data:`thinshell_ros.demo_loop.HIDDEN`, the same gel) and a sheet of another bending stiffness than
the task's nominal one (:data:`TASK_HIDDEN`, a sheet the tactile stage never touched). Stages:

``thinshell demo`` runs stage 2's robot run (:func:`start_task_stages`) beside the tactile diagnosis: it
needs nothing of the tactile fit; the rest follows the fit (:func:`finish_task_stages`).

1. **Carry**: the tactile fit's shared values (:data:`SHARED`: the gel modulus, fitted by the tactile
   stage) are written into the task's nominal scene: ``<run>/task/start_scene.yaml``.
2. **Identify**: the task's reference (human-designed) trajectory is deployed on the task robot by
   the deploy node and recorded (``<run>/task/id_bag``); ``thinshell sysid`` fits the sheet's bending
   stiffness from that recording, starting from the carried scene, and writes the fitted task scene
   (``--write-scene``, ``<run>/task/fitted_scene.yaml``).
3. **Optimise**: ``thinshell optimise TASK --scene fitted_scene.yaml --method gd`` with a small budget:
   Adam on the adjoint gradient from the reference trajectory (the method for a budget of a few
   episodes: CMA-ES needs a population per generation), ``<run>/task/optimise/trajectory.yaml``.
4. **Deploy**: the optimised trajectory on the task robot (deploy node, limits of
   :data:`TASK_DEPLOY_LIMITS`), recorded into ``<run>/task/deployed_bag``.
5. **Compare**: ``thinshell compare --task TASK`` replays the deployed run in the fitted and in the
   nominal task scene: sheet-point RMS of each, and the task reward achieved on the robot against the
   reward each scene predicts (``<run>/task/compare``).

The task scenes have no tactile sensor (``docs/scene_schema.md``): the robot publishes no wrench, so
the deploy node runs with ``require_wrench:=false`` (by default it refuses a cell whose force it
cannot watch) and logs that its wrench limit is not enforced; its workspace, speed and acceleration
limits, pose-lag abort and start-pose check still apply.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from sim_core.errors import ThinShellError
from sim_core.optim.cli import optimise_main
from sim_core.optim.episode import Episode
from sim_core.optim.tasks import task_at_horizon
from sim_core.plain import plain
from sim_core.trajectory_file import Trajectory, write_trajectory
from sysid.cli import sysid_main
from sysid.compare import compare_main
from sysid.evidence import load_evidence
from sysid.fitted_scene import scene_with_values
from sysid.task_reward import TaskRewardProbe, reward_sample_index
from thinshell_ros.demo_loop import rms_table, run_deploy_stage

TASK = "forming"
"""The demo's task (``config/tasks/forming.yaml``): its reward, ``-sum |x - x_target|^2`` over the sheet,
reads only sheet positions, so it can be measured on a recording (:mod:`sysid.task_reward`)."""

SHARED = {"gel.youngs_modulus": "dome.youngs_modulus"}
"""Tactile-scene parameter -> task-scene parameter of the same physical part (the robot's gel)."""

TASK_HIDDEN = {"sheet.bending_stiffness": 2.9629629629629632e-3}
"""The task robot's sheet: bending stiffness D = 2 K_b dx^2 / 9 with K_b = 300 (the task's nominal
K_b = 200 gives 1.975e-3 N m)."""

TASK_DEPLOY_LIMITS = {"max_linear_speed": 0.25, "max_angular_speed": 5.0, "max_linear_acceleration": 50.0,
                      "max_angular_acceleration": 500.0}
"""The task cell's deploy limits: ThinShellLab's tasks move the dome up to 1 mm per 5 ms step (0.2 m/s)."""


TASK_ROBOT_ARGS = ("-p", "settle_steps_max:=0")
"""``--ros-args`` of the task robot (sim node): no start-up settling. The task's hairpin sheet does not come to
rest within the node's 400-step cap (it is still moving at 1.5 mm/s), so the node settled for 400 Forming
steps (45 s at load 11) and then started from the scene's own state anyway; the optimiser's rollouts and
``thinshell compare --task`` start from that state too (:class:`sim_core.optim.episode.Episode` does not settle)."""

SETTLE = 0.05
"""s of robot (sim) time the task robot keeps running after the last command: the state it produced is
recorded (the reward is measured there, :mod:`sysid.task_reward`)."""


@dataclass(frozen=True)
class TaskStageSettings:
    """Knobs of the task stage.

    Attributes:
        task: task name or file. horizon: steps (None: the task's).
        sysid_args: ``thinshell sysid`` options besides the bag, ``--scene``, ``--dt``, ``--out``,
            ``--write-scene``.
        episodes: the optimiser's budget (``--episodes``); optimise_args: further ``thinshell optimise`` options.
        compare_args: further ``thinshell compare`` options.
        timeout: s of wall time for each robot run.
    """

    task: str = TASK
    horizon: int | None = None
    sysid_args: tuple[str, ...] = ("--params", "sheet.bending_stiffness", "--max-nfev", "4")
    episodes: int = 5
    optimise_args: tuple[str, ...] = ("--method", "gd")
    compare_args: tuple[str, ...] = ()
    timeout: float = 300.0


@dataclass
class TaskStageResult:
    """What the task stage produced (paths under ``<run>/task``; values in the task's units).

    Attributes:
        nominal_scene, hidden_scene, start_scene, fitted_scene: the task scenes (nominal, robot, carried, fitted).
        carried: task-scene parameter -> value carried from the tactile fit.
        reference_trajectory, id_bag, id_deploy, id_reward: the identification run (trajectory, recording,
            deploy status, reward achieved on the robot).
        sysid_out, fit: the fit's report directory and summary.
        optimise_out, optimise: the optimiser's directory and ``result.json`` summary.
        trajectory, deployed_bag, deploy: the optimised trajectory, its recording, the deploy status.
        compare_out, comparison: the comparison directory and its RMS table and rewards.
        timings: stage -> wall seconds.
    """

    nominal_scene: Path
    hidden_scene: Path
    start_scene: Path | None = None
    fitted_scene: Path | None = None
    carried: dict[str, float] = field(default_factory=dict)
    reference_trajectory: Path | None = None
    id_bag: Path | None = None
    id_deploy: dict[str, Any] | None = None
    id_reward: float | None = None
    sysid_out: Path | None = None
    fit: dict[str, Any] | None = None
    optimise_out: Path | None = None
    optimise: dict[str, Any] | None = None
    trajectory: Path | None = None
    deployed_bag: Path | None = None
    deploy: dict[str, Any] | None = None
    compare_out: Path | None = None
    comparison: dict[str, Any] | None = None
    timings: dict[str, float] = field(default_factory=dict)


def _write_scene(path: Path, doc: Mapping[str, Any], header: str) -> Path:
    path.write_text(f"# {header}\n" + yaml.safe_dump(plain(dict(doc)), sort_keys=False, default_flow_style=None,
                                                    width=120))
    return path


def write_task_scenes(task: Any, out: Path, hidden: Mapping[str, float]) -> tuple[Path, Path]:
    """The task's nominal scene (its scene with the task file's ``set`` applied) and the robot's hidden
    one (``hidden``: task-scene parameter -> value), written into ``out``."""
    nominal = _write_scene(out / "nominal_scene.yaml", task.scene,
                           f"task {task.name}'s scene (config/tasks), as the task runs it (thinshell demo)")
    doc = scene_with_values(task.scene, hidden)
    doc["name"] = f"{doc.get('name', 'scene')} (hidden robot)"
    return nominal, _write_scene(out / "robot_hidden_scene.yaml", doc, "the demo task robot's hidden scene "
                                 "(thinshell_ros/demo_task.py)")


def carried_values(fit_params: Mapping[str, float]) -> dict[str, float]:
    """Task-scene parameter -> the tactile fit's value of the same part (:data:`SHARED`)."""
    return {task_name: float(fit_params[name]) for name, task_name in SHARED.items() if name in fit_params}


def reference_trajectory(task: Any, out: Path, scene_path: Path) -> Path:
    """The task's reference actions rolled out in its nominal scene, written as a trajectory file
    (the reached effector poses every step, as ``thinshell optimise`` writes its result).

    Raises:
        ThinShellError: the task has no reference trajectory, or it is infeasible.
    """
    if task.reference_actions is None:
        raise ThinShellError(f"task {task.name} has no reference trajectory to identify the robot with")
    ep = Episode(task, task.horizon)
    res = ep.run(np.asarray(task.reference_actions)[:task.horizon])
    if not res.feasible:
        raise ThinShellError(f"task {task.name}: the reference trajectory is infeasible ({res.infeasible})")
    traj = Trajectory(t=task.dt * np.arange(res.steps_done + 1), poses=dict(res.effector_poses),
                      gripper=dict(res.gripper), scene_path=str(scene_path), scene_name=str(task.scene.get("name")),
                      prediction={"reward": float(res.reward)},
                      provenance={"tool": "thinshell demo (the task's reference trajectory)", "task": task.name,
                                  "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
    return write_trajectory(out, traj, force=True)


def recorded_reward(task: Any, bag: Path) -> float:
    """The task's reward achieved in a task-scene recording, at the end of its commanded motion
    (:mod:`sysid.task_reward`)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ev = load_evidence(bag)
    k = reward_sample_index(ev, ev.t_ns["sheet_points"])
    return TaskRewardProbe(task)(ev.sheet_points[k])


def run_task_stages(run: Path, settings: TaskStageSettings, fit_params: Mapping[str, float],
                    hidden_gel: Mapping[str, float], console: Any) -> TaskStageResult:
    """Stages 1-5 of the module docstring in ``<run>/task``: :func:`start_task_stages` (the identification
    run, which needs no fit) then :func:`finish_task_stages` (``thinshell demo`` runs the first beside the
    tactile diagnosis).

    Args:
        run: the demo's run directory.
        settings: the stage's knobs.
        fit_params: the tactile fit's values (``gel.youngs_modulus``, ...); :data:`SHARED` ones are carried.
        hidden_gel: the tactile robot's hidden values (:data:`SHARED` ones are the task robot's too).
        console: a ``rich.console.Console``.

    Raises:
        ThinShellError: a stage failed (a tool's exit code, a deployment that did not complete).
    """
    res = start_task_stages(run, settings, hidden_gel, console)
    return finish_task_stages(res, settings, fit_params, console)


def start_task_stages(run: Path, settings: TaskStageSettings, hidden_gel: Mapping[str, float],
                      console: Any) -> TaskStageResult:
    """Stage 2's robot run (module docstring) in ``<run>/task``: the task scenes written, the task's
    reference trajectory deployed on the task robot and recorded. It needs nothing of the tactile fit
    (the robot's gel is hidden; the reference is rolled out in the nominal scene).

    Raises:
        ThinShellError: the reference is infeasible or the identification run did not complete.
    """
    out = run / "task"
    out.mkdir()
    task = task_at_horizon(settings.task, settings.horizon)
    hidden = {**carried_values(hidden_gel), **TASK_HIDDEN}
    nominal, hidden_scene = write_task_scenes(task, out, hidden)
    res = TaskStageResult(nominal_scene=nominal, hidden_scene=hidden_scene)
    limits = {**TASK_DEPLOY_LIMITS, "rate": 1.0 / task.dt}

    t0 = time.monotonic()
    res.reference_trajectory = reference_trajectory(task, out / "reference_trajectory.yaml", nominal)
    res.id_bag = out / "id_bag"
    console.print(f"[bold]task 1/5 identification run[/bold]: {task.name}'s reference trajectory deployed on the task robot, "
                  f"recording into {res.id_bag}")
    res.id_deploy = run_deploy_stage(hidden_scene, nominal, res.reference_trajectory, res.id_bag, out / "robot_id.log",
                                     settings.timeout, console, limits=limits,
                                     settle=SETTLE, require_wrench=False, robot_args=TASK_ROBOT_ARGS)
    if res.id_deploy["state"] != "completed":
        raise ThinShellError(f"the identification run {res.id_deploy['state']}: {res.id_deploy['reason']}")
    res.id_reward = recorded_reward(task, res.id_bag)
    res.timings["task_id_run_s"] = time.monotonic() - t0
    return res


def finish_task_stages(res: TaskStageResult, settings: TaskStageSettings, fit_params: Mapping[str, float],
                       console: Any) -> TaskStageResult:
    """Stages 1 and 2's fit to 5 (module docstring) after :func:`start_task_stages`: the tactile fit's
    shared values carried into the task scene, the sheet fitted from the identification run, the task
    optimised on the fitted scene, deployed on the task robot and compared.

    Raises:
        ThinShellError: a stage failed (a tool's exit code, a deployment that did not complete).
    """
    out = res.nominal_scene.parent
    task = task_at_horizon(settings.task, settings.horizon)
    nominal, hidden_scene = res.nominal_scene, res.hidden_scene
    limits = {**TASK_DEPLOY_LIMITS, "rate": 1.0 / task.dt}
    res.carried = carried_values(fit_params)
    res.start_scene = _write_scene(out / "start_scene.yaml", scene_with_values(task.scene, res.carried),
                                   f"task {task.name}'s scene with the values carried from the tactile fit {res.carried}")
    console.print(f"[bold]task 2/5 carry and fit[/bold]: {task.name}, robot gel from the tactile fit {res.carried} -> "
                  f"{res.start_scene}")

    from thinshell_ros.sysid_node import summarise_fit  # optional heavy dependency: ROS 2 nodes (rclpy)

    res.sysid_out, res.fitted_scene = out / "sysid", out / "fitted_scene.yaml"
    args = [str(res.id_bag), *settings.sysid_args, "--scene", str(res.start_scene), "--dt", repr(task.dt),
            "--out", str(res.sysid_out), "--write-scene", str(res.fitted_scene)]
    console.print(f"  thinshell sysid {' '.join(args)}")
    t0 = time.monotonic()
    if sysid_main(args) != 0:
        raise ThinShellError("thinshell sysid (task scene) failed (its reason is on stderr)")
    res.timings["task_sysid_s"] = time.monotonic() - t0
    res.fit = summarise_fit(res.sysid_out)

    res.optimise_out = out / "optimise"
    args = [settings.task, "--scene", str(res.fitted_scene), *settings.optimise_args, "--episodes",
            str(settings.episodes), "--out", str(res.optimise_out), "--no-progress"]
    if settings.horizon is not None:
        args += ["--horizon", str(settings.horizon)]
    console.print(f"[bold]task 3/5 optimise[/bold]: thinshell optimise {' '.join(args)}")
    t0 = time.monotonic()
    if optimise_main(args) != 0:
        raise ThinShellError("thinshell optimise failed")
    res.timings["task_optimise_s"] = time.monotonic() - t0
    doc = json.loads((res.optimise_out / "result.json").read_text())
    res.optimise = {k: doc[k] for k in ("method", "episodes", "best_reward", "start_reward", "success_score",
                                        "human_score", "stop_reason", "wall_time_s")}
    res.trajectory = res.optimise_out / "trajectory.yaml"

    res.deployed_bag = out / "deployed_bag"
    console.print(f"[bold]task 4/5 deploy[/bold]: {res.trajectory} on the task robot, recording into {res.deployed_bag}")
    t0 = time.monotonic()
    res.deploy = run_deploy_stage(hidden_scene, nominal, res.trajectory, res.deployed_bag, out / "robot_deploy.log",
                                  settings.timeout, console, limits=limits,
                                  settle=SETTLE, require_wrench=False, robot_args=TASK_ROBOT_ARGS)
    res.timings["task_deploy_s"] = time.monotonic() - t0
    if res.deploy["state"] != "completed":
        raise ThinShellError(f"the task deployment {res.deploy['state']}: {res.deploy['reason']}")

    res.compare_out = out / "compare"
    args = [str(res.deployed_bag), "--scene", str(res.fitted_scene), "--scene-nominal", str(nominal), "--label",
            "fitted", "--task", settings.task, "--dt", repr(task.dt), "--out", str(res.compare_out),
            *settings.compare_args]
    if settings.horizon is not None:
        args += ["--horizon", str(settings.horizon)]
    console.print(f"[bold]task 5/5 compare[/bold]: thinshell compare {' '.join(args)}")
    t0 = time.monotonic()
    if compare_main(args) != 0:
        raise ThinShellError("thinshell compare (task run) failed")
    res.timings["task_compare_s"] = time.monotonic() - t0
    doc = json.loads((res.compare_out / "compare.json").read_text())
    res.comparison = {"rms": rms_table(doc), "better": doc["better"], "reward": doc["reward"]}
    return res
