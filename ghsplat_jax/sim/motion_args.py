"""The robot and trajectory options that `ghsplat simulate` and `ghsplat localize` share,
and how they become a Robot and a Trajectory (explicit values, nothing stored on `args`)."""

from __future__ import annotations

import argparse
import tomllib
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trajectory", default="aisles", metavar="aisles|FILE",
                   help="'aisles' (serpentine along every aisle), a waypoint file (.csv x,y[,yaw][,t] / .json / "
                        ".toml), or a .csv of velocity commands with columns v,w[,dt] (differential drive)")
    p.add_argument("--rows", metavar="rows.json|toml",
                   help="row boxes for 'aisles' (default: from the layout or the surfels)")
    p.add_argument("--speed", type=float, default=0.5, help="m/s along waypoints and aisles")
    p.add_argument("--aisle-margin", type=float, default=1.0, help="metres past the row ends where the robot turns")
    p.add_argument("--dt", type=float, default=0.1, help="seconds per velocity command (when the file has no dt)")
    p.add_argument("--robot", metavar="robot.toml", help="robot dimensions and sensor mounts (see sim/robot.py)")


def load_robot(path: str | None):
    """The robot of a robot.toml ([robot] table), or the default Jackal-sized one."""
    from ghsplat_jax.sim.robot import robot_from_config

    return robot_from_config(tomllib.loads(Path(path).read_text()).get("robot", {}) if path else None)


def load_trajectory(args: argparse.Namespace, scene, robot):
    """The trajectory `--trajectory` names: aisles of the scene's rows, waypoints, or velocity
    commands clamped to `robot`'s limits."""
    from ghsplat_jax.sim import scene_io
    from ghsplat_jax.sim import trajectory as tj

    if args.trajectory == "aisles":
        rows = tj.load_row_boxes(args.rows) if args.rows else scene_io.scene_rows(scene)
        return tj.from_waypoints(tj.aisle_waypoints(rows, margin=args.aisle_margin), speed=args.speed)
    if tj.is_twist_file(args.trajectory):
        return tj.load_twist(args.trajectory, args.dt, robot.max_speed, robot.max_yaw_rate)
    return tj.load_waypoints(args.trajectory, speed=args.speed)
