"""`ghsplat localize`: AprilTag localization along a trajectory on rendered frames, with a
report (markdown + JSON + plot): detection rate against distance and viewing angle,
robot position and yaw error against ground truth, availability.

    ghsplat localize greenhouse.toml --trajectory aisles --out loc/
"""

from __future__ import annotations

import argparse
import sys
import tomllib
from pathlib import Path

HELP = "Detect AprilTags in rendered frames along a trajectory and report localization accuracy."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", metavar="LAYOUT_OR_PLY", help="layout .toml or scene .ply (tags beside it or --tags)")
    p.add_argument("--tags", metavar="tags.json", help="marker ground truth (default: <stem>.tags.json beside a PLY)")
    p.add_argument("--out", required=True, metavar="DIR", help="report folder (report.md, localization.json, localization.png)")
    p.add_argument("--trajectory", default="aisles", metavar="aisles|FILE", help="as for `ghsplat simulate`")
    p.add_argument("--rows", metavar="rows.json|toml", help="row boxes for 'aisles'")
    p.add_argument("--speed", type=float, default=0.5)
    p.add_argument("--aisle-margin", type=float, default=1.0)
    p.add_argument("--dt", type=float, default=0.1)
    p.add_argument("--robot", metavar="robot.toml", help="robot dimensions and camera mount")
    p.add_argument("--rate", type=float, default=2.0, help="frames per simulated second")
    p.add_argument("--max-frames", type=int, help="evaluate at most this many frames")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fov", type=float, default=70.0)


def main(args) -> int:
    from ghsplat_jax.io_utils import atomic_write, write_json
    from ghsplat_jax.sim import localize, robot as robot_mod, scene_io, simulate
    from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer
    from ghsplat_jax.sim.command import _trajectory

    try:
        args._robot = robot_mod.robot_from_config(tomllib.loads(Path(args.robot).read_text()).get("robot", {})
                                                  if args.robot else None)
        scene = scene_io.load_scene(args.scene, args.tags)
        if not scene.tags:
            raise ValueError(f"{args.scene}: no tags (give --tags or put <stem>.tags.json beside the PLY)")
        traj = _trajectory(args, scene)
        camera = CameraModel.from_fov(args._robot.optical_frame, args.width, args.height, args.fov)
    except (ValueError, FileNotFoundError, tomllib.TOMLDecodeError, OSError) as exc:
        print(f"ghsplat localize: error: {exc}", file=sys.stderr)
        return 2
    tags = {t.id: t for t in scene.tags}
    cfg = simulate.SimConfig(camera_rate=args.rate, lidar_rate=0.0, max_events=args.max_frames)
    renderer = CameraRenderer()
    robot = args._robot

    def frames_iter():
        for ev in simulate.schedule(traj, cfg):
            x, y, yaw = ev.pose
            yield ev.t, (x, y, yaw), renderer.render(scene.surfels, camera, robot.map_from_optical(x, y, yaw), ev.t)

    result = localize.evaluate(frames_iter(), tags, robot)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result["config"] = {"scene": str(scene.path), "tags": len(tags), "width": args.width, "height": args.height,
                        "fov_deg": args.fov, "rate_hz": args.rate, "camera_mount_xyz": list(robot.camera.xyz),
                        "camera_mount_rpy": list(robot.camera.rpy), "compilations": renderer.traces}
    write_json(out / "localization.json", result)
    localize.plot(result, out / "localization.png")
    with atomic_write(out / "report.md", "w") as fh:
        fh.write(localize.markdown(result, f"AprilTag localization: {scene.path.name}", "localization.png"))
    s = result["summary"]
    pe = s["position_error_m"]["median"]
    print(f"ghsplat localize: {s['frames']} frames, availability {s['availability']:.0%}, "
          f"detection rate {'n/a' if s['detection_rate'] is None else format(s['detection_rate'], '.0%')}, "
          f"median position error {'n/a' if pe is None else format(pe, '.3f') + ' m'}; report in {out}",
          file=sys.stderr)
    return 0
