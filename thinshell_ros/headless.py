"""``thinshell sim``: run a trajectory through the simulator without DDS and write a bag.

The bag has the same topics, types, frames and stamps as a recording of the simulator node
(INTERFACES.md): ``<effector>/pose_cmd`` (the command of each step, logged when it is sent),
``<effector>/pose``, ``<sensor>/markers`` (x y z u v), ``<sensor>/wrench``, optionally
``<sensor>/image``, ``sheet/points`` and ``/clock``, all stamped with sim time, plus ``scene.yaml``.
Trajectory formats: :mod:`thinshell_ros.trajectory`.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from sim_core.errors import ConfigError
from sim_core.simulation import Simulation
from sysid.bagio import BagWriter
from thinshell_ros.paths import bundled_scene
from thinshell_ros.trajectory import SCRIPTED, Trajectory, load_trajectory, scripted_trajectory


def scene_trajectory(sim: Any, name: str, **kwargs: Any) -> Trajectory:
    """Scripted trajectory ``name`` for the first sensor of ``sim`` (and the effector carrying it).

    The sheet top is the highest tracked sheet point plus half the sheet thickness.

    Raises:
        ConfigError: the scene has no tactile sensor or no sheet.
    """
    if not sim.sensor_names:
        raise ConfigError(f"scripted trajectory {name!r} needs a tactile sensor in the scene")
    sensor = sim.sensor_names[0]
    effector = sim.model.sensors[sensor].effector if hasattr(sim.model, "sensors") else sim.effector_names[0]
    obs = sim.observe()
    if not len(obs.sheet_points):
        raise ConfigError(f"scripted trajectory {name!r} needs a sheet in the scene")
    half = 0.5 * sim.get_parameter("sheet.thickness") if "sheet.thickness" in sim.parameter_names else 0.0
    top = float(obs.sheet_points[:, 2].max()) + half
    sensor_pose = sim.sensor_pose(sensor) if hasattr(sim, "sensor_pose") else obs.effector_pose[effector]
    return scripted_trajectory(name, obs.effector_pose[effector], sensor_pose, top, effector=effector, **kwargs)


def write_observation(bag: Any, obs: Any, namespace: str, image: bool) -> None:
    """Write one observation's outputs (pose, markers, wrench, image, sheet points) at ``obs.t``."""
    t_ns = int(round(obs.t * 1e9))
    for eff, pose in obs.effector_pose.items():
        bag.write_pose(f"{namespace}/{eff}/pose", t_ns, pose, "world")
    for sensor, r in obs.tactile.items():
        bag.write_points(f"{namespace}/{sensor}/markers", t_ns, r.markers_xyz, sensor,
                         extra_fields={"u": r.markers_uv[:, 0], "v": r.markers_uv[:, 1]})
        bag.write_wrench(f"{namespace}/{sensor}/wrench", t_ns, r.wrench, sensor)
        if image and r.image is not None:
            bag.write_image(f"{namespace}/{sensor}/image", t_ns, r.image, sensor)
    if len(obs.sheet_points):
        bag.write_points(f"{namespace}/sheet/points", t_ns, obs.sheet_points, "world")


def run_headless(sim: Any, trajectory: Trajectory, bag: Any, duration: float | None = None, rate: float = 0.0,
                 image: bool = False, namespace: str = "/thinshell", progress: bool = False) -> dict[str, float]:
    """Drive ``sim`` along ``trajectory`` and write commands and outputs into ``bag`` (a BagWriter).

    Args:
        sim: Simulation facade.
        trajectory: effector waypoints; ``trajectory.effector`` None means the first effector.
        bag: open :class:`sysid.bagio.BagWriter`.
        duration: simulated seconds (default: the trajectory's duration).
        rate: output rate in Hz of sim time (0: every step); commands and /clock every step.
        image: render and write ``<sensor>/image``.
        namespace: topic prefix.
        progress: print a progress line to stderr every second of wall time.

    Returns:
        ``{"steps", "sim_time", "wall_time", "real_time_factor"}``.

    Raises:
        ConfigError: unknown effector; SimulationDivergedError: a step failed.
    """
    effector = trajectory.effector or sim.effector_names[0]
    if effector not in sim.effector_names:
        raise ConfigError(f"trajectory effector {effector!r} is not in the scene (effectors: {sim.effector_names})")
    duration = trajectory.duration if duration is None else float(duration)
    steps = int(math.ceil(duration / sim.dt - 1e-9))
    cmd_topic = f"{namespace}/{effector}/pose_cmd"
    grip_topic = f"{namespace}/{effector}/gripper_cmd"
    render = {"render_image": True} if image else {}
    obs = sim.observe(**render)
    bag.write_clock(int(round(obs.t * 1e9)))
    write_observation(bag, obs, namespace, image)
    next_out = obs.t + (1.0 / rate if rate > 0 else 0.0)
    wall0 = last_print = time.monotonic()
    for k in range(steps):
        t_now = sim.t
        target = trajectory.sample(t_now + sim.dt)
        t_ns = int(round(t_now * 1e9))
        bag.write_pose(cmd_topic, t_ns, target, "world")
        control = sim.model.control()
        control.effector_pose_target[effector] = target
        opening = trajectory.sample_gripper(t_now + sim.dt)
        if opening is not None:
            control.gripper_target[effector] = opening
            bag.write_float64(grip_topic, t_ns, opening)
        sim.step(control)
        bag.write_clock(int(round(sim.t * 1e9)))
        if rate <= 0 or sim.t >= next_out - 1e-9 or k == steps - 1:
            write_observation(bag, sim.observe(**render), namespace, image)
            next_out = sim.t + (1.0 / rate if rate > 0 else 0.0)
        if progress and time.monotonic() - last_print > 1.0:
            last_print = time.monotonic()
            print(f"thinshell sim: t = {sim.t:.3f} / {duration:.3f} s", file=sys.stderr)
    wall = time.monotonic() - wall0
    return {"steps": float(steps), "sim_time": float(sim.t), "wall_time": wall,
            "real_time_factor": float(sim.t / wall) if wall > 0 else float("inf")}


def sim_main(argv: Sequence[str]) -> int:
    """``thinshell sim --scene S --trajectory T --out DIR [--duration s] [--rate Hz] [--image] [--force]``.

    ``T`` is a YAML/CSV trajectory file or a scripted name (``press_slide``, ``press_slide_lift``).
    Returns the exit code.
    """
    parser = argparse.ArgumentParser(prog="thinshell sim", description="simulate a trajectory headless (no DDS) "
                                     "and write a rosbag2 MCAP bag with scene.yaml")
    parser.add_argument("--scene", default=None, help="scene file (default: the bundled press_slide scene)")
    parser.add_argument("--trajectory", default="press_slide",
                        help=f"YAML/CSV trajectory file or one of {list(SCRIPTED)} (default press_slide)")
    parser.add_argument("--out", required=True, help="bag directory to create")
    parser.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the trajectory's)")
    parser.add_argument("--rate", type=float, default=0.0, help="output rate in Hz of sim time (0: every step)")
    parser.add_argument("--depth", type=float, default=1.0e-3, help="scripted: press depth in m")
    parser.add_argument("--slide", type=float, default=0.015, help="scripted: slide distance in m")
    parser.add_argument("--namespace", default="/thinshell")
    parser.add_argument("--image", action="store_true", help="render and write <sensor>/image")
    parser.add_argument("--force", action="store_true", help="replace an existing bag directory")
    args = parser.parse_args(list(argv))
    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration must be > 0, got {args.duration}")
    scene = Path(args.scene) if args.scene else bundled_scene()
    sim = Simulation.from_scene(scene)
    if args.trajectory in SCRIPTED:
        traj = scene_trajectory(sim, args.trajectory, depth=args.depth, slide=args.slide)
    else:
        traj = load_trajectory(args.trajectory)
    namespace = "/" + args.namespace.strip("/")
    with BagWriter(args.out, scene=scene, force=args.force) as bag:
        stats = run_headless(sim, traj, bag, duration=args.duration, rate=args.rate, image=args.image,
                             namespace=namespace, progress=True)
        counts = bag.message_counts
    print(f"thinshell sim: wrote {args.out}: {int(stats['steps'])} steps, {stats['sim_time']:.3f} s simulated in "
          f"{stats['wall_time']:.1f} s (real-time factor {stats['real_time_factor']:.3g}), "
          f"{sum(counts.values())} messages on {len(counts)} topics")
    return 0


if __name__ == "__main__":
    sys.exit(sim_main(sys.argv[1:]))
