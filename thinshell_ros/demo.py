"""``thinshell demo`` (what ``make demo`` runs): the sim-to-real loop once, over real DDS, with progress.

1. **Robot**: the simulator node (``thinshell-sim-node``, a subprocess, ``fast`` mode) on a *hidden*
   scene: the bundled scene with other material values and one concealed effect
   (:mod:`thinshell_ros.demo_loop`: :data:`~thinshell_ros.demo_loop.HIDDEN`,
   :data:`~thinshell_ros.demo_loop.CONCEALED`), driven over DDS by the scripted commander (press,
   slide, lift, planned from the measured pose and sheet) and recorded into ``<run>/recorded_bag``;
   the recording states the nominal scene (as a real cell's would).
2. **Fit**: ``thinshell sysid`` on that recording, starting from the nominal scene, with
   ``--write-scene <run>/fitted_scene.yaml`` (fitted values, sigma, the modelled effect's term).
3. **Trajectory**: a press-slide-lift of its own (deeper and longer than the identification motion)
   planned from the recording's start, written as ``<run>/trajectory.yaml`` (the trajectory format
   the optimiser writes; stage 6 deploys the optimiser's).
4. **Deploy**: the robot again, driven by the deploy node (limits, abort; sim time from the robot's
   ``/clock``), recorded into ``<run>/deployed_bag``.
5. **Compare**: ``thinshell compare`` replays the deployed run in the fitted and in the nominal scene:
   RMS per channel, overlay plots, ``<run>/compare/report.html``.
6. **Task** (:mod:`thinshell_ros.demo_task`): the robot's gel works a ThinShellLab task cell (Forming)
   with a sheet of hidden stiffness. The gel fit is carried into the task scene, the task's reference
   trajectory is deployed and recorded, ``thinshell sysid`` fits the sheet from it (``--write-scene``),
   ``thinshell optimise`` optimises the task on that fitted scene (small budget), the deploy node runs
   the result on the task robot (recorded) and ``thinshell compare --task`` gives the fitted and nominal
   prediction error on the deployed run and the task reward achieved on the robot against the predicted
   ones (``<run>/task/``).

Stages that need nothing of the diagnosis or the fit run beside them, in four phases: the robot; the
diagnosis (a ``thinshell diagnose`` subprocess, ``<run>/diagnose.log``) beside the deployment and the task's
identification run (:func:`thinshell_ros.demo_task.start_task_stages`); the fit; the comparison (a
``thinshell compare`` subprocess, ``<run>/compare.log``) beside the rest of the task stage. Each phase's
wall and CPU seconds are in ``demo.json`` (``phases``, :mod:`thinshell_ros.demo_clock`).

``<run>/report.md`` links every step and reveals the hidden values; ``<run>/demo.json`` keeps the
timings, message counts, fit summary, deploy status and the comparison. ``<run>`` is
``<out>/<YYYYmmdd-HHMMSS>`` (``--out`` default ``demo_out``); nothing is overwritten without
``--force``. ``--quick`` shortens every stage (used by the tests).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import yaml

from sim_core.errors import ConfigError, ThinShellError
from sim_core.scenes.scene_file import load_yaml
from sysid.bagio import open_bag
from sysid.cli import sysid_main
from sysid.compare import compare_main
from sysid.diagnose.cli import diagnose_main
from sysid.fitted_scene import scene_with_values
from thinshell_ros.demo_clock import BackgroundTool, Phase
from thinshell_ros.demo_loop import (CONCEALED, HIDDEN, deploy_trajectory_from_bag, log_tail, rms_table,
                                     robot_noise_args, run_deploy_stage, start_sim_node, stop_process,
                                     write_hidden_scene)
from thinshell_ros.demo_task import (SHARED, TASK_HIDDEN, TaskStageResult, TaskStageSettings, finish_task_stages,
                                     start_task_stages)
from thinshell_ros.paths import DEFAULT_BAG, bundled_scene


@dataclass(frozen=True)
class DemoSettings:
    """Knobs of one demo run.

    Attributes:
        motion: commander parameters (:class:`thinshell_ros.commander.CommanderNode`: ``depth``,
            ``slide``, ``release`` in m, ``approach_speed``, ``press_speed``, ``slide_speed`` in m/s, ``hold`` in s).
        sysid_args: ``thinshell sysid`` options besides the bag, ``--scene``, ``--write-scene`` and ``--out``.
        diagnose_args: ``thinshell diagnose`` options besides the bag and ``--json`` (None: no diagnosis).
        deploy_motion: the deployed press-slide-lift (same keys as ``motion``).
        compare_args: ``thinshell compare`` options besides the bag, scenes and ``--out``.
        start_timeout: s of wall time for the sim node to come up and the plan to be made (its first start
            on a machine compiles the simulator's kernels, minutes on two loaded cores, unless
            ``thinshell compile`` has, as ``make setup`` does).
        motion_timeout: s of wall time for the scripted motion.
        task: the task stage's knobs (:mod:`thinshell_ros.demo_task`).
    """

    motion: dict[str, float]
    sysid_args: tuple[str, ...]
    diagnose_args: tuple[str, ...] | None = None
    deploy_motion: dict[str, float] = field(default_factory=dict)
    compare_args: tuple[str, ...] = ()
    start_timeout: float = 600.0
    motion_timeout: float = 600.0
    task: TaskStageSettings = TaskStageSettings()


FULL = DemoSettings(
    motion={"depth": 3.0e-4, "slide": 0.005, "release": 5.0e-4, "approach_speed": 0.04, "press_speed": 0.005,
            "slide_speed": 0.02, "hold": 0.05},
    # the press sets the gel modulus, the slide the gel-sheet friction (the diagnosed effect held at its
    # diagnosis value)
    # the robot's sensor is the scene's (no gain or intrinsics error): --no-sensor-calibration keeps the fit
    # from explaining physics with sensor gains
    sysid_args=("--params", "gel.youngs_modulus,friction.gel_sheet", "--dt", "0.01", "--max-nfev", "8",
                "--max-time", "180", "--no-sensor-calibration"),
    # thinshell diagnose as a user runs it: its defaults (the pipeline picks the score stage on this recording,
    # whose pose is its command: the whole candidate library, its calibration, held-out time blocks); the named
    # effect's refitted term goes into the scene the fit starts from. Two processes for the independent replays
    diagnose_args=("--workers", "2"),
    deploy_motion={"depth": 5.0e-4, "slide": 0.008, "release": 5.0e-4, "approach_speed": 0.04, "press_speed": 0.005,
                   "slide_speed": 0.02, "hold": 0.1},
    compare_args=("--dt", "0.01"),
    # Forming at its 50 steps; the sheet's bending stiffness from the reference run (4 replays); 5 gradient steps
    task=TaskStageSettings())
QUICK = DemoSettings(
    motion={"depth": 3.0e-4, "slide": 0.001, "release": 2.0e-4, "approach_speed": 0.08, "press_speed": 0.005,
            "slide_speed": 0.02, "hold": 0.01},
    sysid_args=("--params", "gel.youngs_modulus", "--dt", "0.02", "--max-nfev", "2",
                "--gel-resolution", "3,3,2", "--max-time", "60"),
    deploy_motion={"depth": 3.0e-4, "slide": 0.001, "release": 2.0e-4, "approach_speed": 0.04, "press_speed": 0.005,
                   "slide_speed": 0.02, "hold": 0.01},
    compare_args=("--dt", "0.02", "--gel-resolution", "3,3,2"),
    task=TaskStageSettings(horizon=10, episodes=1, sysid_args=("--params", "sheet.bending_stiffness", "--max-nfev", "2")))


@dataclass
class DemoResult:
    """What a demo run produced.

    Attributes:
        run_dir: the run's directory.
        recorded_bag: the bag recorded by the sim node.
        message_counts: topic -> messages in the recorded bag.
        sysid_out: the fit report directory.
        fit: :func:`thinshell_ros.sysid_node.summarise_fit` of the report.
        timings: stage -> wall seconds.
        hidden_scene: the robot's hidden scene; fitted_scene: sysid's fitted scene.
        diagnosis: ``explained_by`` and the named effects' terms of ``thinshell diagnose``, or None;
            diagnosed_scene: the nominal scene with those terms (where the fit starts), or None.
        trajectory: the deployed trajectory file; deployed_bag: the deployed run's recording.
        deploy: the deploy node's final status.
        compare_out: the comparison report directory; comparison: its ``compare.json``.
        task: the task stage's outputs (:class:`thinshell_ros.demo_task.TaskStageResult`).
        phases: the run's phases in order (:class:`thinshell_ros.demo_clock.Phase`: wall and CPU s of the
            stages that ran in each, side by side where several).
    """

    run_dir: Path
    recorded_bag: Path
    message_counts: dict[str, int] = field(default_factory=dict)
    sysid_out: Path | None = None
    fit: dict[str, Any] | None = None
    timings: dict[str, float] = field(default_factory=dict)
    hidden_scene: Path | None = None
    diagnosis: dict[str, Any] | None = None
    diagnosed_scene: Path | None = None
    fitted_scene: Path | None = None
    trajectory: Path | None = None
    deployed_bag: Path | None = None
    deploy: dict[str, Any] | None = None
    compare_out: Path | None = None
    comparison: dict[str, Any] | None = None
    task: TaskStageResult | None = None
    phases: list[Phase] = field(default_factory=list)


def make_run_dir(out: Path, force: bool, stamp: str | None = None) -> Path:
    """Create ``out/<stamp>`` (default stamp: local time ``YYYYmmdd-HHMMSS``).

    Raises:
        ConfigError: it exists and ``force`` is False.
    """
    run = Path(out) / (stamp or time.strftime("%Y%m%d-%H%M%S"))
    if run.exists():
        if not force:
            raise ConfigError(f"{run} exists; use --force to replace it")
        shutil.rmtree(run)
    run.mkdir(parents=True)
    return run


def _console():
    from rich.console import Console  # optional dependency: rich, for terminal output only

    return Console(highlight=False)


def _progress(console):
    # optional dependency: rich, for terminal output only
    from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    return Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"),
                    TimeElapsedColumn(), console=console, transient=False)


def run_simulation_stage(run: Path, settings: DemoSettings, scene: Path, mode: str, console: Any,
                         result: DemoResult, record_scene: Path | None = None,
                         extra_args: Sequence[str] = ()) -> None:
    """Stage 1: sim node subprocess on ``scene`` recording into ``result.recorded_bag`` (stating
    ``record_scene``, default ``scene``; ``extra_args``: further ``--ros-args`` of the node), commander,
    SIGINT, read back.

    Raises:
        ThinShellError: the node died, did not come up, or the motion timed out (the node log is quoted).
    """
    import rclpy  # optional heavy dependency: ROS 2 (rclpy), for ROS commands only
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    # optional heavy dependency: ROS 2 nodes (rclpy), for ROS commands only
    from thinshell_ros.commander import CommanderNode

    log_path = run / "sim_node.log"
    console.print(f"[bold]1/6 robot[/bold]: thinshell-sim-node ({mode} mode) on {scene.name}, "
                  f"recording into {result.recorded_bag} (log {log_path})")
    t0 = time.monotonic()
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    proc = start_sim_node(scene, result.recorded_bag, record_scene or scene, log_path, mode=mode, extra_args=extra_args)
    node = executor = None
    try:
        node = CommanderNode(context=ctx, parameter_overrides=[
            Parameter("scene", value=str(record_scene or scene)), Parameter("use_sim_time", value=True),
            *(Parameter(k, value=float(v)) for k, v in settings.motion.items())])
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        with _progress(console) as progress:
            start = progress.add_task("starting the sim node (a first start compiles its kernels)", total=None, info="")
            deadline = time.monotonic() + settings.start_timeout
            while node.schedule is None and not node.done.is_set():
                if proc.poll() is not None:
                    raise ThinShellError(f"the sim node exited with code {proc.returncode}:\n{log_tail(log_path)}")
                if time.monotonic() > deadline:
                    raise ThinShellError(f"the sim node did not come up within {settings.start_timeout:.0f} s:\n"
                                         f"{log_tail(log_path)}")
                executor.spin_once(timeout_sec=0.05)
                progress.update(start, info=f"sim t = {node.sim_time or 0.0:.3f} s")
            progress.update(start, total=1, completed=1, info="plan made")
            result.timings["sim_start_s"] = time.monotonic() - t0
            if node.schedule is None:
                raise ThinShellError("the commander could not plan the motion (see the log above)")
            sched = node.schedule
            motion = progress.add_task("press, slide, lift", total=1000, info="")
            deadline = time.monotonic() + settings.motion_timeout
            t1 = time.monotonic()
            while not node.done.is_set():
                if proc.poll() is not None:
                    raise ThinShellError(f"the sim node exited with code {proc.returncode}:\n{log_tail(log_path)}")
                if time.monotonic() > deadline:
                    raise ThinShellError(f"the motion did not finish within {settings.motion_timeout:.0f} s")
                executor.spin_once(timeout_sec=0.05)
                t = node.sim_time or sched.t0
                progress.update(motion, completed=1000 * node.progress(),
                                info=f"sim t = {t - sched.t0:.3f} / {sched.end - sched.t0:.3f} s")
            result.timings["motion_s"] = time.monotonic() - t1
            result.timings["motion_sim_s"] = sched.end - sched.t0
            stop = progress.add_task("stopping the sim node (SIGINT)", total=None, info="")
            t2 = time.monotonic()
            code = stop_process(proc)
            progress.update(stop, total=1, completed=1, info=f"exit code {code}")
            result.timings["sim_stop_s"] = time.monotonic() - t2
    finally:
        if proc.poll() is None:
            stop_process(proc)
        if executor is not None:
            executor.shutdown(timeout_sec=0)
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()
    if code != 0:
        raise ThinShellError(f"the sim node exited with code {code}:\n{log_tail(log_path)}")

    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        contents = open_bag(result.recorded_bag)
    result.message_counts = {t: info.message_count for t, info in sorted(contents.topics.items())}
    from rich.table import Table  # optional dependency: rich, for terminal output only

    table = Table(title=f"recorded bag {result.recorded_bag}", show_edge=False)
    table.add_column("topic")
    table.add_column("type")
    table.add_column("messages", justify="right")
    for topic, info in sorted(contents.topics.items()):
        table.add_row(topic, info.msgtype, str(info.message_count))
    console.print(table)
    span = (contents.end_ns - contents.start_ns) * 1e-9
    console.print(f"  {sum(result.message_counts.values())} messages over {span:.3f} s of sim time"
                  + (f"; notes: {'; '.join(contents.notes)}" if contents.notes else ""))


def run_robot_stage(run: Path, settings: DemoSettings, scene: Path, mode: str, console: Any,
                    result: DemoResult) -> None:
    """Stage 1 as the demo runs it: the robot's hidden scene (:func:`~thinshell_ros.demo_loop.write_hidden_scene`
    of the nominal ``scene``) written to ``<run>/robot_hidden_scene.yaml`` and recorded with the robot's
    measurement noise (seed 1) into ``result.recorded_bag``, the recording stating ``scene``.

    Raises:
        ThinShellError: the sim node or the motion failed (:func:`run_simulation_stage`).
    """
    result.hidden_scene = write_hidden_scene(scene, run / "robot_hidden_scene.yaml")
    run_simulation_stage(run, settings, result.hidden_scene, mode, console, result, record_scene=scene,
                         extra_args=robot_noise_args(seed=1))


def run_sysid_stage(run: Path, settings: DemoSettings, bag: Path, console: Any, result: DemoResult,
                    nominal: Path | None = None) -> None:
    """Stage 2: ``thinshell sysid`` on ``bag`` (from the ``nominal`` scene when given) into ``<run>/sysid``,
    writing ``<run>/fitted_scene.yaml``.

    Raises:
        ThinShellError: the fitter failed (its reason is on stderr).
    """
    # optional heavy dependency: ROS 2 nodes (rclpy), for ROS commands only
    from thinshell_ros.sysid_node import summarise_fit

    out = run / "sysid"
    result.fitted_scene = run / "fitted_scene.yaml"
    args = [str(bag), *settings.sysid_args, "--out", str(out), "--write-scene", str(result.fitted_scene)]
    if nominal is not None:
        args += ["--scene", str(nominal)]
    console.print(f"[bold]3/6 fit[/bold]: thinshell sysid {' '.join(args)}")
    t0 = time.monotonic()
    code = sysid_main(args)
    result.timings["sysid_s"] = time.monotonic() - t0
    if code != 0:
        raise ThinShellError(f"thinshell sysid exited with code {code}")
    result.sysid_out = out
    result.fit = summarise_fit(out)


def diagnose_command(run: Path, settings: DemoSettings, bag: Path) -> list[str]:
    """``thinshell diagnose``'s arguments in the demo (``<run>/diagnosis.json``)."""
    return [str(bag), *settings.diagnose_args, "--json", str(run / "diagnosis.json")]


def start_diagnose_stage(run: Path, settings: DemoSettings, bag: Path, console: Any) -> BackgroundTool:
    """Stage 2a started as a subprocess (``thinshell diagnose``, its output in ``<run>/diagnose.log``), to
    run beside the stages that do not need it; :func:`run_diagnose_stage` with ``started`` waits for it."""
    tool = BackgroundTool("diagnose", diagnose_command(run, settings, bag), run / "diagnose.log")
    console.print(f"[bold]2/6 diagnose[/bold] (in the background, log {tool.log}): {tool.command}")
    return tool


def run_diagnose_stage(run: Path, settings: DemoSettings, bag: Path, nominal: Path, console: Any,
                       result: DemoResult, started: BackgroundTool | None = None) -> Path:
    """Stage 2a: ``thinshell diagnose`` on ``bag``; the named effects' refitted terms are written into a copy
    of ``nominal`` (``<run>/diagnosed_scene.yaml``), the scene the fit starts from.

    ``started``: the diagnosis already running in the background (:func:`start_diagnose_stage`), waited for
    here; None: it runs here, in this process.

    Returns:
        the scene the fit starts from (``nominal`` when nothing was named).

    Raises:
        ThinShellError: the diagnosis failed.
    """
    out = run / "diagnosis.json"
    _tool_stage("diagnose", "2/6 diagnose", lambda: diagnose_command(run, settings, bag), diagnose_main, started,
                console, result)
    doc = json.loads(out.read_text())
    named = list(doc.get("explained_by") or [])
    refit = (doc.get("refit") or {}).get("params") or {}
    terms = {k: float(v) for k, v in refit.items() if any(k == f"candidate.{e}" or k.startswith(f"candidate.{e}.")
                                                         for e in named)}
    result.diagnosis = {"explained_by": named, "terms": terms, "json": str(out)}
    console.print(f"  explained by: {named or 'nothing'}" + (f"; terms {terms}" if terms else ""))
    if not terms:
        return nominal
    scene_doc = scene_with_values(load_yaml(Path(nominal).read_text()), terms)
    result.diagnosed_scene = run / "diagnosed_scene.yaml"
    result.diagnosed_scene.write_text("# the nominal scene with the effects thinshell diagnose named (diagnosis.json)\n"
                                      + yaml.safe_dump(scene_doc, sort_keys=False, default_flow_style=None, width=120))
    return result.diagnosed_scene


def run_deploy_stages(run: Path, settings: DemoSettings, nominal: Path, console: Any, result: DemoResult) -> None:
    """Stages 4-5: the trajectory file (planned from the recording's start) and its deployment on the
    robot (recorded). They need nothing of the diagnosis or the fit.

    Raises:
        ThinShellError: the deployment did not complete.
    """
    result.trajectory = deploy_trajectory_from_bag(result.recorded_bag, nominal, run / "trajectory.yaml",
                                                   settings.deploy_motion)
    console.print(f"[bold]4/6 trajectory[/bold]: {result.trajectory} (scripted press-slide-lift from the recording's start)")
    result.deployed_bag = run / "deployed_bag"
    console.print(f"[bold]5/6 deploy[/bold]: thinshell-deploy-node on the robot (sim time), recording into "
                  f"{result.deployed_bag}")
    t0 = time.monotonic()
    result.deploy = run_deploy_stage(result.hidden_scene, nominal, result.trajectory, result.deployed_bag,
                                     run / "robot_deploy.log", settings.motion_timeout, console)
    result.timings["deploy_s"] = time.monotonic() - t0
    if result.deploy["state"] != "completed":
        raise ThinShellError(f"the deployment {result.deploy['state']}: {result.deploy['reason']}")


def compare_command(run: Path, settings: DemoSettings, nominal: Path, result: DemoResult) -> list[str]:
    """``thinshell compare``'s arguments in the demo: the deployed run, fitted vs nominal, into ``<run>/compare``."""
    result.compare_out = run / "compare"
    return [str(result.deployed_bag), "--scene", str(result.fitted_scene), "--scene-nominal", str(nominal),
            "--label", "fitted", "--out", str(result.compare_out), *settings.compare_args]


def start_compare_stage(run: Path, settings: DemoSettings, nominal: Path, console: Any,
                        result: DemoResult) -> BackgroundTool:
    """Stage 6 started as a subprocess (``thinshell compare``, output in ``<run>/compare.log``), to run beside
    the task stage; :func:`run_compare_stage` with ``started`` waits for it."""
    tool = BackgroundTool("compare", compare_command(run, settings, nominal, result), run / "compare.log")
    console.print(f"[bold]6/6 compare[/bold] (in the background, log {tool.log}): {tool.command}")
    return tool


def _tool_stage(tool: str, title: str, argv: Callable[[], list[str]], tool_main: Callable[[list[str]], int],
                started: BackgroundTool | None, console: Any, result: DemoResult) -> None:
    """Run ``thinshell TOOL`` in this process (``started`` None: its arguments from ``argv()``, printed under
    ``title``) or wait for it where it already runs in the background; its wall (and, from the background, CPU)
    seconds into ``result.timings`` as ``TOOL_s`` (``TOOL_cpu_s``).

    Raises:
        ThinShellError: the tool exited with a non-zero code (named, with the background log's tail).
    """
    if started is None:
        args = argv()
        console.print(f"[bold]{title}[/bold]: thinshell {tool} {' '.join(args)}")
        t0 = time.monotonic()
        code = tool_main(args)
        result.timings[f"{tool}_s"] = time.monotonic() - t0
    else:
        code = started.wait()
        result.timings[f"{tool}_s"] = started.wall_s
        if started.cpu_s is not None:
            result.timings[f"{tool}_cpu_s"] = started.cpu_s
    if code != 0:
        raise ThinShellError(f"thinshell {tool} exited with code {code}"
                             + (f" (log {started.log}):\n{started.log_tail()}" if started is not None else ""))


def run_compare_stage(run: Path, settings: DemoSettings, nominal: Path, console: Any, result: DemoResult,
                      started: BackgroundTool | None = None) -> None:
    """Stage 6: ``thinshell compare`` replays the deployed run in the fitted and the nominal scene
    (``<run>/compare``); ``started``: the comparison already running (:func:`start_compare_stage`), waited
    for here; None: it runs here.

    Raises:
        ThinShellError: the comparison failed.
    """
    _tool_stage("compare", "6/6 compare", lambda: compare_command(run, settings, nominal, result), compare_main,
                started, console, result)
    doc = json.loads((result.compare_out / "compare.json").read_text())
    result.comparison = {"rms": rms_table(doc), "better": doc["better"]}


def write_run_report(run: Path, result: DemoResult, hidden: dict[str, float]) -> Path:
    """``<run>/report.md``: every step with links, the hidden truth, fit and comparison figures."""
    rel = lambda p: os.path.relpath(p, run) if p is not None else "-"  # noqa: E731
    fit = result.fit or {}
    lines = ["# thinshell demo: fit -> deploy -> record -> compare", "",
             f"1. Robot (hidden scene [{rel(result.hidden_scene)}]({rel(result.hidden_scene)})) driven by the "
             f"commander, recorded: [{rel(result.recorded_bag)}]({rel(result.recorded_bag)})",
             (f"2. Diagnosis: explained by {result.diagnosis['explained_by'] or 'nothing'} "
              f"([{rel(result.diagnosis['json'])}]({rel(result.diagnosis['json'])}))"
              + (f", terms {result.diagnosis['terms']} written into [{rel(result.diagnosed_scene)}]"
                 f"({rel(result.diagnosed_scene)})" if result.diagnosed_scene else "")
              if result.diagnosis else "2. Diagnosis: not run (--quick)"),
             f"3. Fit: [sysid report]({rel(result.sysid_out)}/report.html), fitted scene "
             f"[{rel(result.fitted_scene)}]({rel(result.fitted_scene)})",
             f"4. Trajectory: [{rel(result.trajectory)}]({rel(result.trajectory)})",
             f"5. Deployed on the robot: {(result.deploy or {}).get('state')} "
             f"({(result.deploy or {}).get('reason')}), recorded: [{rel(result.deployed_bag)}]({rel(result.deployed_bag)})",
             f"6. Comparison: [compare report]({rel(result.compare_out)}/report.html)", "",
             "## Fit vs hidden truth", "", f"Replayed at dt = {fit.get('dt', '-')} s; sigma (GN) is the Gauss-Newton "
             f"1-sigma, the robust interval value +- 2 sigma ({fit.get('robust_method') or 'not computed'}, "
             "sysid.covariance) holds under model error.", "",
             "| parameter | nominal | fitted | sigma (GN) | robust 2-sigma interval | hidden |", "|---|---|---|---|---|---|"]
    for name, value in fit.get("params", {}).items():
        sigma, robust = fit.get("sigma", {}).get(name), (fit.get("sigma_robust") or {}).get(name)
        interval = "-" if robust is None else f"[{value - 2.0 * robust:.4g}, {value + 2.0 * robust:.4g}]"
        lines.append(f"| {name} | {fit['initial'][name]:.4g} | {value:.4g} | "
                     f"{'-' if sigma is None else f'{sigma:.2g}'} | {interval} | {hidden.get(name, '-')} |")
    for name, value in ((result.diagnosis or {}).get("terms") or {}).items():
        lines.append(f"| {name} (diagnosed) | 0 | {value:.4g} | - | - | {hidden.get(name, '-')} |")
    modelled = set(fit.get("params", {})) | set(((result.diagnosis or {}).get("terms") or {}))
    hidden_only = [n for n in hidden if n not in modelled]
    if hidden_only:
        lines += ["", "Hidden but not fitted: " + ", ".join(f"{n} = {hidden[n]}" for n in hidden_only)]
    if result.comparison:
        lines += ["", "## Deployed run: prediction RMS (recording - simulation)", "",
                  "| channel | fitted scene | nominal scene | fitted / nominal |", "|---|---|---|---|"]
        for ch, v in result.comparison["rms"].items():
            lines.append(f"| {ch} | {v['fitted']:.4g} | {v['nominal']:.4g} | {v['fitted'] / v['nominal']:.3f} |")
    if result.task is not None:
        lines += task_report_lines(result.task, rel)
    lines.append("")
    path = run / "report.md"
    path.write_text("\n".join(lines))
    return path


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:.4g}"


def task_report_lines(task: TaskStageResult, rel: Any) -> list[str]:
    """The task stage's part of ``report.md`` (``rel``: path -> link relative to the run directory)."""
    link = lambda p, name=None: f"[{name or rel(p)}]({rel(p)})"  # noqa: E731
    fit, opt, cmp = task.fit or {}, task.optimise or {}, task.comparison or {}
    reward = cmp.get("reward") or {}
    unit = reward.get("unit", "")
    lines = ["", "## Task: a ThinShellLab task optimised on the fitted scene, deployed on the robot", "",
             f"1. Task robot: hidden scene {link(task.hidden_scene)}; nominal task scene {link(task.nominal_scene)}; "
             f"carried from the tactile fit {task.carried}: {link(task.start_scene)}",
             f"2. Identification: the task's reference trajectory {link(task.reference_trajectory)} deployed "
             f"({(task.id_deploy or {}).get('state')}), recorded {link(task.id_bag)}; fit "
             f"{link(Path(task.sysid_out) / 'report.html', 'sysid report')}, fitted task scene {link(task.fitted_scene)}",
             f"3. Optimisation: {link(Path(task.optimise_out) / 'report.html', 'optimise report')} ({opt.get('method')}, "
             f"{opt.get('episodes')} episodes), trajectory {link(task.trajectory)}",
             f"4. Deployed on the task robot: {(task.deploy or {}).get('state')} ({(task.deploy or {}).get('reason')}), "
             f"recorded {link(task.deployed_bag)}",
             f"5. Comparison: {link(Path(task.compare_out) / 'report.html', 'compare report')}", "",
             "| parameter | nominal | fitted | sigma | hidden |", "|---|---|---|---|---|"]
    for name, value in fit.get("params", {}).items():
        sigma = fit.get("sigma", {}).get(name)
        lines.append(f"| {name} | {fit['initial'][name]:.4g} | {value:.4g} | "
                     f"{'-' if sigma is None else f'{sigma:.2g}'} | {_num(TASK_HIDDEN.get(name))} |")
    for name, value in task.carried.items():
        lines.append(f"| {name} (carried: the tactile fit) | - | {value:.4g} | - | "
                     f"{_num({v: HIDDEN.get(k) for k, v in SHARED.items()}.get(name))} |")
    if cmp:
        lines += ["", "| deployed run | fitted scene | nominal scene | fitted / nominal |", "|---|---|---|---|"]
        for ch, v in cmp["rms"].items():
            lines.append(f"| RMS {ch} (m) | {v['fitted']:.4g} | {v['nominal']:.4g} | {v['fitted'] / v['nominal']:.3f} |")
    if reward:
        pred = reward["predicted"]
        lines += ["", f"Task reward ({reward['task']}, {unit}; higher is better, Table A success score "
                      f"{reward.get('success_score')}):", "",
                  f"- achieved on the robot by the optimised trajectory: **{reward['recording']:.4g}**",
                  f"- predicted for the deployed run: fitted scene {pred['fitted']:.4g}, nominal scene {pred['nominal']:.4g}; "
                  f"by the optimiser (its own rollout on the fitted scene) {opt.get('best_reward', float('nan')):.4g}",
                  f"- achieved on the robot by the task's reference trajectory (the identification run): "
                  f"{task.id_reward:.4g}"]
    return lines


def run_demo(out: Path, force: bool = False, quick: bool = False, mode: str = "fast", scene: Path | None = None,
             bag: Path | None = None, console: Any = None) -> DemoResult:
    """Run the demo (module docstring) and return what it produced.

    Args:
        out: parent of the run directory.
        force: replace an existing run directory of the same time stamp.
        quick: the short settings (:data:`QUICK`) instead of :data:`FULL`.
        mode: the robot's sim node mode in the identification run, ``fast`` or ``realtime``.
        scene: the nominal scene (default the bundled one); the robot runs it with hidden values.
        bag: recording to fit instead of the robot's identification run.
        console: a ``rich.console.Console`` (default: a new one on stdout).

    Raises:
        ConfigError: bad mode, missing scene / bag, existing run directory without ``force``.
        ThinShellError: a stage failed.
    """
    if mode not in ("fast", "realtime"):
        raise ConfigError(f"--mode must be fast or realtime, got {mode!r}")
    settings = QUICK if quick else FULL
    scene = Path(scene) if scene else bundled_scene()
    if not scene.is_file():
        raise ConfigError(f"scene {scene} not found")
    if bag is not None and not Path(bag).exists():
        raise ConfigError(f"bag {bag} not found")
    console = console or _console()
    t0 = time.monotonic()
    run = make_run_dir(Path(out), force)
    result = DemoResult(run_dir=run, recorded_bag=run / "recorded_bag")
    console.rule(f"thinshell demo{' --quick' if quick else ''}: {run}")
    phase = Phase("robot", ("robot",))
    run_robot_stage(run, settings, scene, mode, console, result)
    result.phases.append(phase.stop())
    fit_bag = Path(bag) if bag else result.recorded_bag
    start = scene
    # the diagnosis (a subprocess) beside the robot runs that need no fit: the deployment and the task's
    # identification run (their robots' start-ups and DDS waits leave the cores to the diagnosis)
    diagnosed = settings.diagnose_args is not None
    phase = Phase(("diagnose | " if diagnosed else "") + "deploy, task identification run",
                  ("diagnose", "deploy", "task_id_run") if diagnosed else ("deploy", "task_id_run"))
    diagnosis = start_diagnose_stage(run, settings, fit_bag, console) if diagnosed else None
    try:
        run_deploy_stages(run, settings, scene, console, result)
        task = start_task_stages(run, settings.task, HIDDEN, console)
        if diagnosis is not None:
            start = run_diagnose_stage(run, settings, fit_bag, scene, console, result, started=diagnosis)
    finally:
        if diagnosis is not None:
            diagnosis.stop()
    result.phases.append(phase.stop())
    phase = Phase("sysid", ("sysid",))
    run_sysid_stage(run, settings, fit_bag, console, result, nominal=start)
    result.phases.append(phase.stop())
    # the comparison of the deployed run (a subprocess) beside the task's fit, optimisation and deployment
    phase = Phase("compare | task", ("compare", "task_sysid", "task_optimise", "task_deploy", "task_compare"))
    comparison = start_compare_stage(run, settings, scene, console, result)
    try:
        result.task = finish_task_stages(task, settings.task, (result.fit or {}).get("params", {}), console)
        run_compare_stage(run, settings, scene, console, result, started=comparison)
    finally:
        comparison.stop()
    result.phases.append(phase.stop())
    result.timings.update(result.task.timings)
    result.timings["total_s"] = time.monotonic() - t0
    hidden = {**HIDDEN, **CONCEALED}
    report = write_run_report(run, result, hidden)
    summary = {"run_dir": str(run), "quick": quick, "mode": mode, "scene": str(scene),
               "hidden": hidden, "hidden_scene": str(result.hidden_scene), "diagnosis": result.diagnosis,
               "diagnosed_scene": str(result.diagnosed_scene) if result.diagnosed_scene else None,
               "sysid_bag": str(bag or result.recorded_bag), "recorded_bag": str(result.recorded_bag),
               "message_counts": result.message_counts, "sysid_out": str(result.sysid_out), "fit": result.fit,
               "fitted_scene": str(result.fitted_scene), "trajectory": str(result.trajectory),
               "deployed_bag": str(result.deployed_bag), "deploy": result.deploy,
               "compare_out": str(result.compare_out), "comparison": result.comparison, "task": task_summary(result.task),
               "report": str(report),
               "timings_s": {k: round(v, 2) for k, v in result.timings.items()},
               "phases": {ph.name: ph.as_dict() for ph in result.phases}}
    (run / "demo.json").write_text(json.dumps(summary, indent=2) + "\n")
    console.rule("done")
    for name, value in (result.fit or {}).get("params", {}).items():
        sigma = result.fit["sigma"].get(name)
        console.print(f"  fitted {name} = {value:.6g}" + (f" +- {sigma:.3g}" if sigma is not None else "")
                      + f" (nominal {result.fit['initial'][name]:.6g}, hidden {hidden.get(name, '-')})")
    for ch, v in (result.comparison or {}).get("rms", {}).items():
        console.print(f"  deployed run, RMS {ch}: fitted {v['fitted']:.4g}, nominal {v['nominal']:.4g}")
    task = result.task
    for ch, v in task.comparison["rms"].items():
        console.print(f"  task {task.comparison['reward']['task']}, deployed optimised run, RMS {ch}: fitted "
                      f"{v['fitted']:.4g}, nominal {v['nominal']:.4g}")
    reward = task.comparison["reward"]
    console.print(f"  task reward on the robot: {reward['recording']:.4g} {reward['unit']} (predicted: fitted "
                  f"{reward['predicted']['fitted']:.4g}, nominal {reward['predicted']['nominal']:.4g}; the reference "
                  f"trajectory achieved {task.id_reward:.4g})")
    console.print(f"  recorded bag:  {result.recorded_bag}")
    console.print(f"  sysid report:  {result.sysid_out / 'report.html'} (also report.md, fit.json, plots)")
    console.print(f"  fitted scene:  {result.fitted_scene}")
    console.print(f"  deployed bag:  {result.deployed_bag}")
    console.print(f"  comparison:    {result.compare_out / 'report.html'}")
    console.print(f"  task:          {task.optimise_out / 'report.html'} (optimiser), {task.compare_out / 'report.html'} "
                  "(deployed run)")
    console.print(f"  report:        {report}")
    console.print(f"  summary:       {run / 'demo.json'}")
    t = result.timings
    stages = [("robot", t.get("sim_start_s", 0) + t.get("motion_s", 0)), ("diagnose", t.get("diagnose_s")),
              ("sysid", t.get("sysid_s", 0)), ("deploy", t.get("deploy_s", 0)), ("compare", t.get("compare_s", 0)),
              ("task", sum(v for k, v in t.items() if k.startswith("task_")))]
    console.print(f"  wall time:     {t['total_s']:.1f} s (stages: "
                  + ", ".join(f"{name} {sec:.1f} s" for name, sec in stages if sec is not None) + ")")
    console.print("  phases:        " + "; ".join(f"{ph.name} {ph.wall_s:.1f} s wall, {ph.cpu_s:.1f} CPU s"
                                                   for ph in result.phases))
    return result


def task_summary(task: TaskStageResult | None) -> dict[str, Any] | None:
    """The task stage's entry of ``demo.json`` (paths as strings)."""
    if task is None:
        return None
    doc = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(task).items()}
    doc["hidden"] = {**{v: HIDDEN[k] for k, v in SHARED.items() if k in HIDDEN}, **TASK_HIDDEN}
    return doc


def demo_main(argv: Sequence[str]) -> int:
    """``thinshell demo [--out DIR] [--force] [--quick] [--mode fast|realtime] [--scene S] [--bag B]``.

    Returns the exit code (0 on success).
    """
    parser = argparse.ArgumentParser(prog="thinshell demo", description="the main job: a hidden-scene robot (sim "
                                     "node) recorded, fitted (sysid --write-scene), a trajectory deployed on it and "
                                     "recorded, the fitted and nominal scenes compared on the deployed run; then a "
                                     "ThinShellLab task (Forming) optimised on the fitted task scene, deployed on the "
                                     "task robot, its reward achieved vs predicted")
    parser.add_argument("--out", default="demo_out", help="parent of the timestamped run directory (default demo_out)")
    parser.add_argument("--force", action="store_true", help="replace an existing run directory")
    parser.add_argument("--quick", action="store_true", help="shorter motion and fit (a smoke test)")
    parser.add_argument("--mode", default="fast", choices=("fast", "realtime"), help="sim node mode")
    parser.add_argument("--scene", default=None, help="nominal scene (default: the bundled press_slide)")
    parser.add_argument("--bag", default=None, help="recording to fit instead of the robot's identification run "
                                                   f"(e.g. bags/{DEFAULT_BAG})")
    args = parser.parse_args([str(a) for a in argv])
    run_demo(Path(args.out), force=args.force, quick=args.quick, mode=args.mode,
             scene=Path(args.scene) if args.scene else None, bag=Path(args.bag) if args.bag else None)
    return 0


if __name__ == "__main__":
    sys.exit(demo_main(sys.argv[1:]))
