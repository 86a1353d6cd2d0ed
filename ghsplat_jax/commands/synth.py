"""`ghsplat synth`: generate a procedural greenhouse and render a ground-truth dataset."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HELP = "generate a procedural greenhouse scene and render a dataset with ground truth"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, default=None, help="scene TOML (default: built-in defaults)")
    parser.add_argument("--preset", default=None,
                        help="a named scene under --config's values (thin-plant: one thin plant on black, no ground)")
    parser.add_argument("--out", type=Path, required=True, help="output dataset folder")
    parser.add_argument("--views", type=int, default=40, help="number of views (default 40)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--path", "--capture", dest="path", choices=("handheld", "robot", "orbit"), default="handheld",
                        help="capture path kind; orbit: a turntable-like ring round one plant (a closed loop)")
    parser.add_argument("--row", type=int, default=0, help="row to capture (default 0)")
    parser.add_argument("--end", choices=("x0", "x1"), default=None,
                        help="handheld: walk round this end of the row only (one row segment)")
    parser.add_argument("--segment-fraction", type=float, default=0.5,
                        help="with --end: share of the row's length the walk covers (default 0.5)")
    parser.add_argument("--plant", type=int, default=None,
                        help="orbit: the plant along the row to circle (default the middle one)")
    parser.add_argument("--orbit-radius", type=float, default=0.7, help="orbit: ring radius in metres")
    parser.add_argument("--fov", type=float, default=65.0, help="horizontal field of view, degrees")
    parser.add_argument("--fps", type=float, default=2.0, help="frame rate of the capture (time stamps)")
    parser.add_argument("--seed", type=int, default=None, help="override the config's seed")
    parser.add_argument("--points", type=int, default=20000,
                        help="surface samples for points3D (0: cameras only, an empty points3D.txt)")
    parser.add_argument("--no-mesh", action="store_true", help="skip mesh.ply / mesh.glb")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset in --out")


def main(args: argparse.Namespace) -> int:
    from ghsplat_jax.synth import capture, config, dataset, scene

    try:
        if args.config:
            cfg = config.load_config(args.config, preset=args.preset)
        else:
            cfg = config.preset_config(args.preset) if args.preset else config.SceneConfig()
    except (FileNotFoundError, ValueError) as exc:
        print(f"ghsplat synth: {exc}", file=sys.stderr)
        return 2
    if args.seed is not None:
        cfg = cfg.replace(seed=args.seed)
    if args.views < 1 or args.width < 8 or args.height < 8 or not 1 < args.fov < 179 or args.fps <= 0:
        print("ghsplat synth: need --views >= 1, --width/--height >= 8, 1 < --fov < 179, --fps > 0", file=sys.stderr)
        return 2
    start = time.perf_counter()
    world = scene.generate_scene(cfg)
    try:
        cameras = capture.capture_path(world, args.path, args.views, row=args.row, width=args.width,
                                       height=args.height, seed=cfg.seed,
                                       config=capture.PathConfig(fov_x_deg=args.fov, fps=args.fps, end=args.end,
                                                                 segment_fraction=args.segment_fraction,
                                                                 plant=args.plant, orbit_radius=args.orbit_radius))
        out = dataset.write_dataset(world, cameras, args.out, n_points=args.points, fps=args.fps,
                                    meshes=not args.no_mesh, overwrite=args.overwrite, progress=True)
    except (ValueError, FileExistsError) as exc:
        print(f"ghsplat synth: {exc}", file=sys.stderr)
        return 2
    print(f"ghsplat synth: {len(cameras)} views of a {len(world.faces)}-face scene written to {out} "
          f"in {time.perf_counter() - start:.1f} s")
    return 0
