"""`ghsplat localize`: AprilTag localization along a trajectory on rendered frames, with a
report (markdown + JSON + plot): detection rate against distance and viewing angle,
robot position and yaw error against ground truth, availability.

    ghsplat localize greenhouse.toml --trajectory aisles --out loc/
"""

from __future__ import annotations

import argparse
import sys
import tomllib

from ghsplat_jax.sim import motion_args

HELP = "Detect AprilTags in rendered frames along a trajectory and report localization accuracy."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", metavar="LAYOUT_OR_PLY", help="layout .toml or scene .ply (tags beside it or --tags)")
    p.add_argument("--tags", metavar="tags.json", help="marker ground truth (default: <stem>.tags.json beside a PLY)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="report folder (report.md, localization.json, localization.png)")
    motion_args.add_arguments(p)
    p.add_argument("--rate", type=float, default=2.0, help="frames per simulated second")
    p.add_argument("--max-frames", type=int, help="evaluate at most this many frames")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fov", type=float, default=70.0)


def main(args) -> int:
    from ghsplat_jax.localize import apriltag
    from ghsplat_jax.localize.report import write_report
    from ghsplat_jax.sim import scene_io
    from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer
    from ghsplat_jax.train.run_dir import raster_settings

    try:
        robot = motion_args.load_robot(args.robot)
        scene = scene_io.load_scene(args.scene, args.tags)
        if not scene.tags:
            raise ValueError(f"{args.scene}: no tags (give --tags or put <stem>.tags.json beside the PLY)")
        traj = motion_args.load_trajectory(args, scene, robot)
        camera = CameraModel.from_fov(robot.optical_frame, args.width, args.height, args.fov)
    except (ValueError, FileNotFoundError, tomllib.TOMLDecodeError, OSError) as exc:
        print(f"ghsplat localize: error: {exc}", file=sys.stderr)
        return 2
    tags = {t.id: t for t in scene.tags}
    renderer = CameraRenderer(raster_config=raster_settings(scene.path))  # a trained run's own settings
    frames = apriltag.frames_along(scene.surfels, robot, traj, camera, renderer, args.rate, args.max_frames)
    result = apriltag.evaluate(frames, tags, robot)
    result["config"] = {"scene": str(scene.path), "tags": len(tags), "width": args.width, "height": args.height,
                        "fov_deg": args.fov, "rate_hz": args.rate, "camera_mount_xyz": list(robot.camera.xyz),
                        "camera_mount_rpy": list(robot.camera.rpy), "compilations": renderer.traces}
    out = write_report(result, args.out, f"AprilTag localization: {scene.path.name}")
    s = result["summary"]
    pe = s["position_error_m"]["median"]
    print(f"ghsplat localize: {s['frames']} frames, availability {s['availability']:.0%}, "
          f"detection rate {'n/a' if s['detection_rate'] is None else format(s['detection_rate'], '.0%')}, "
          f"median position error {'n/a' if pe is None else format(pe, '.3f') + ' m'}; report in {out}",
          file=sys.stderr)
    return 0
