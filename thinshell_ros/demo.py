"""``thinshell demo`` (what ``make demo`` runs): the whole pipeline once, with progress shown throughout.

1. Start the simulator node (``thinshell-sim-node``, a subprocess, ``fast`` mode by default) on the
   bundled scene, recording its inputs and outputs into ``<run>/recorded_bag`` (its ``record``
   parameter).
2. Drive it over DDS with the scripted commander (:mod:`thinshell_ros.commander`: press, slide,
   lift, planned from the measured effector pose and sheet), in sim time; then stop the node with
   SIGINT so that it closes the bag, and read the bag back (:func:`sysid.bagio.open_bag`).
3. Fit material parameters to the bundled recording ``bags/nominal_s101`` with ``thinshell sysid``
   (a short window and a coarse replay step keep it to a couple of minutes on two cores).
4. Print where everything is; ``<run>/demo.json`` keeps the timings, message counts and fit summary.

``<run>`` is ``<out>/<YYYYmmdd-HHMMSS>`` (``--out`` default ``demo_out``); nothing is overwritten
without ``--force``. ``--quick`` shortens every stage (used by the tests).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from sim_core.errors import ConfigError, ThinShellError
from sysid.bagio import open_bag
from sysid.cli import sysid_main
from thinshell_ros.paths import bundled_scene, config_dir

DEFAULT_BAG = "nominal_s101"


@dataclass(frozen=True)
class DemoSettings:
    """Knobs of one demo run.

    Attributes:
        motion: commander parameters (:class:`thinshell_ros.commander.CommanderNode`: ``depth``,
            ``slide``, ``release`` in m, ``approach_speed``, ``press_speed``, ``slide_speed`` in m/s, ``hold`` in s).
        sysid_args: ``thinshell sysid`` options besides the bag and ``--out``.
        start_timeout: s of wall time for the sim node to come up and the plan to be made.
        motion_timeout: s of wall time for the scripted motion.
    """

    motion: dict[str, float]
    sysid_args: tuple[str, ...]
    start_timeout: float = 120.0
    motion_timeout: float = 600.0


FULL = DemoSettings(
    motion={"depth": 3.0e-4, "slide": 0.005, "release": 5.0e-4, "approach_speed": 0.04, "press_speed": 0.005,
            "slide_speed": 0.02, "hold": 0.05},
    # press (0.6-0.9 s) and the start of the slide of nominal_s101; the gel modulus sets the normal force
    sysid_args=("--params", "gel.youngs_modulus", "--t-max", "1.0", "--dt", "0.01", "--max-nfev", "6",
                "--max-time", "120"))
QUICK = DemoSettings(
    motion={"depth": 3.0e-4, "slide": 0.001, "release": 2.0e-4, "approach_speed": 0.08, "press_speed": 0.005,
            "slide_speed": 0.02, "hold": 0.01},
    sysid_args=("--params", "gel.youngs_modulus", "--t-max", "0.2", "--dt", "0.02", "--max-nfev", "2",
                "--gel-resolution", "3,3,2", "--max-time", "60"))


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
    """

    run_dir: Path
    recorded_bag: Path
    message_counts: dict[str, int] = field(default_factory=dict)
    sysid_out: Path | None = None
    fit: dict[str, Any] | None = None
    timings: dict[str, float] = field(default_factory=dict)


def bundled_bag(name: str = DEFAULT_BAG) -> Path:
    """``bags/<name>`` of the source tree (beside ``config/``).

    Raises:
        ConfigError: no such bag directory.
    """
    path = config_dir().parent / "bags" / name
    if not (path / "metadata.yaml").is_file():
        raise ConfigError(f"bundled recording {path} not found (expected metadata.yaml, .mcap and scene.yaml)")
    return path


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


def _stop_process(proc: subprocess.Popen, timeout: float = 60.0) -> int:
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


def _tail(path: Path, n: int = 2000) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""


def run_simulation_stage(run: Path, settings: DemoSettings, scene: Path, mode: str, console: Any,
                         result: DemoResult) -> None:
    """Stages 1-2: sim node subprocess recording into ``result.recorded_bag``, commander, SIGINT, read back.

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
    env = dict(os.environ)
    repo = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = repo + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    cmd = [sys.executable, "-m", "thinshell_ros.sim_node", "--ros-args", "-p", f"scene:={scene}",
           "-p", f"mode:={mode}", "-p", "mesh_rate:=0.0", "-p", f"record:={result.recorded_bag}"]
    console.print(f"[bold]1/3 simulator[/bold]: thinshell-sim-node ({mode} mode) on {scene.name}, "
                  f"recording into {result.recorded_bag} (log {log_path})")
    t0 = time.monotonic()
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
    node = executor = None
    try:
        node = CommanderNode(context=ctx, parameter_overrides=[
            Parameter("scene", value=str(scene)), *(Parameter(k, value=float(v)) for k, v in settings.motion.items())])
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        with _progress(console) as progress:
            start = progress.add_task("starting the sim node", total=None, info="")
            deadline = time.monotonic() + settings.start_timeout
            while node.schedule is None and not node.done.is_set():
                if proc.poll() is not None:
                    raise ThinShellError(f"the sim node exited with code {proc.returncode}:\n{_tail(log_path)}")
                if time.monotonic() > deadline:
                    raise ThinShellError(f"the sim node did not come up within {settings.start_timeout:.0f} s:\n"
                                         f"{_tail(log_path)}")
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
                    raise ThinShellError(f"the sim node exited with code {proc.returncode}:\n{_tail(log_path)}")
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
            code = _stop_process(proc)
            progress.update(stop, total=1, completed=1, info=f"exit code {code}")
            result.timings["sim_stop_s"] = time.monotonic() - t2
    finally:
        if proc.poll() is None:
            _stop_process(proc)
        if executor is not None:
            executor.shutdown(timeout_sec=0)
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()
    if code != 0:
        raise ThinShellError(f"the sim node exited with code {code}:\n{_tail(log_path)}")

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


def run_sysid_stage(run: Path, settings: DemoSettings, bag: Path, console: Any, result: DemoResult) -> None:
    """Stage 3: ``thinshell sysid`` on ``bag`` into ``<run>/sysid``.

    Raises:
        ThinShellError: the fitter failed (its reason is on stderr).
    """
    # optional heavy dependency: ROS 2 nodes (rclpy), for ROS commands only
    from thinshell_ros.sysid_node import summarise_fit

    out = run / "sysid"
    args = [str(bag), *settings.sysid_args, "--out", str(out)]
    console.print(f"[bold]3/3 system identification[/bold]: thinshell sysid {' '.join(args)}")
    t0 = time.monotonic()
    code = sysid_main(args)
    result.timings["sysid_s"] = time.monotonic() - t0
    if code != 0:
        raise ThinShellError(f"thinshell sysid exited with code {code}")
    result.sysid_out = out
    result.fit = summarise_fit(out)


def run_demo(out: Path, force: bool = False, quick: bool = False, mode: str = "fast", scene: Path | None = None,
             bag: Path | None = None, console: Any = None) -> DemoResult:
    """Run the demo (module docstring) and return what it produced.

    Args:
        out: parent of the run directory.
        force: replace an existing run directory of the same time stamp.
        quick: the short settings (:data:`QUICK`) instead of :data:`FULL`.
        mode: sim node mode, ``fast`` or ``realtime``.
        scene: scene for the simulator (default the bundled one).
        bag: recording to fit (default the bundled ``bags/nominal_s101``).
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
    bag = Path(bag) if bag else bundled_bag()
    if not bag.exists():
        raise ConfigError(f"bag {bag} not found")
    console = console or _console()
    t0 = time.monotonic()
    run = make_run_dir(Path(out), force)
    result = DemoResult(run_dir=run, recorded_bag=run / "recorded_bag")
    console.rule(f"thinshell demo{' --quick' if quick else ''}: {run}")
    run_simulation_stage(run, settings, scene, mode, console, result)
    console.print(f"[bold]2/3 recording[/bold] closed: {result.recorded_bag}")
    run_sysid_stage(run, settings, bag, console, result)
    result.timings["total_s"] = time.monotonic() - t0
    summary = {"run_dir": str(run), "quick": quick, "mode": mode, "scene": str(scene), "sysid_bag": str(bag),
               "recorded_bag": str(result.recorded_bag), "message_counts": result.message_counts,
               "sysid_out": str(result.sysid_out), "fit": result.fit,
               "timings_s": {k: round(v, 2) for k, v in result.timings.items()}}
    (run / "demo.json").write_text(json.dumps(summary, indent=2) + "\n")
    console.rule("done")
    for name, value in (result.fit or {}).get("params", {}).items():
        sigma = result.fit["sigma"].get(name)
        console.print(f"  fitted {name} = {value:.6g}" + (f" +- {sigma:.3g}" if sigma is not None else "")
                      + f" (nominal {result.fit['initial'][name]:.6g})")
    console.print(f"  recorded bag:  {result.recorded_bag}")
    console.print(f"  sysid report:  {result.sysid_out / 'report.html'} (also report.md, fit.json, plots)")
    console.print(f"  summary:       {run / 'demo.json'}")
    console.print(f"  wall time:     {result.timings['total_s']:.1f} s "
                  f"(sim {result.timings.get('sim_start_s', 0) + result.timings.get('motion_s', 0):.1f} s, "
                  f"sysid {result.timings.get('sysid_s', 0):.1f} s)")
    return result


def demo_main(argv: Sequence[str]) -> int:
    """``thinshell demo [--out DIR] [--force] [--quick] [--mode fast|realtime] [--scene S] [--bag B]``.

    Returns the exit code (0 on success).
    """
    parser = argparse.ArgumentParser(prog="thinshell demo", description="the main job: sim node + scripted "
                                     "commander + recording, then sysid on the bundled bag")
    parser.add_argument("--out", default="demo_out", help="parent of the timestamped run directory (default demo_out)")
    parser.add_argument("--force", action="store_true", help="replace an existing run directory")
    parser.add_argument("--quick", action="store_true", help="shorter motion and fit (a smoke test)")
    parser.add_argument("--mode", default="fast", choices=("fast", "realtime"), help="sim node mode")
    parser.add_argument("--scene", default=None, help="scene for the sim node (default: the bundled press_slide)")
    parser.add_argument("--bag", default=None, help=f"recording to fit (default: bags/{DEFAULT_BAG})")
    args = parser.parse_args([str(a) for a in argv])
    run_demo(Path(args.out), force=args.force, quick=args.quick, mode=args.mode,
             scene=Path(args.scene) if args.scene else None, bag=Path(args.bag) if args.bag else None)
    return 0


if __name__ == "__main__":
    sys.exit(demo_main(sys.argv[1:]))
