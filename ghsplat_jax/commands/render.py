"""`ghsplat render`: render a Gaussian PLY from a camera or a dataset's views to images."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

HELP = "render a PLY to rgb/depth/normal images from a look-at camera or a dataset's views"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("ply", type=Path, help="2DGS (or 3DGS) Gaussian PLY")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--data", type=Path, help="render the views of this dataset instead of --eye")
    p.add_argument("--split", choices=["train", "test"], default="test")
    p.add_argument("--downscale", type=float, default=1.0)
    p.add_argument("--eye", type=float, nargs=3, default=(0.0, -3.0, 1.0))
    p.add_argument("--target", type=float, nargs=3, default=(0.0, 0.0, 0.0))
    p.add_argument("--fov", type=float, default=60.0, help="horizontal field of view, degrees")
    p.add_argument("--size", default="640x480", help="WIDTHxHEIGHT for --eye cameras")
    p.add_argument("--config", type=Path, help="a run's config.toml whose [raster] settings to use "
                   "(default: the one beside the PLY, if any)")
    p.add_argument("--background", type=float, nargs=3, help="overrides the run's background (default black)")
    p.add_argument("--sh-degree", type=int, default=None)


def _cameras(args):
    import ghsplat_jax as gs

    if args.data is not None:
        from ghsplat_jax.data import load_dataset

        ds = load_dataset(args.data, downscale=args.downscale)
        return [(v.name, v.camera) for v in (ds.test if args.split == "test" else ds.train)]
    width, height = (int(v) for v in args.size.lower().split("x"))
    return [("view", gs.Camera(K=gs.intrinsics(width, height, args.fov),
                                world_to_cam=gs.look_at(args.eye, args.target), width=width, height=height))]


def render_to_files(surfels, camera, cfg, out: Path, name: str) -> dict[str, Path]:
    """Render one view and write rgb PNG, depth EXR + PNG, normal PNG, alpha PNG."""
    import ghsplat_jax as gs
    from ghsplat_jax.data.images import write_image
    from ghsplat_jax.eval.evaluate import depth_colormap, normal_colormap

    o = gs.render(surfels, camera, cfg)
    rgb, alpha, depth = np.asarray(o.rgb), np.asarray(o.alpha), np.asarray(o.depth)
    return {
        "rgb": write_image(out / f"{name}_rgb.png", rgb),
        "alpha": write_image(out / f"{name}_alpha.png", alpha),
        "depth": write_image(out / f"{name}_depth.exr", depth),
        "depth_vis": write_image(out / f"{name}_depth.png", depth_colormap(depth, alpha)),
        "normal": write_image(out / f"{name}_normal.png", normal_colormap(o.normal, alpha)),
    }


def main(args) -> int:
    import ghsplat_jax as gs
    from ghsplat_jax.train.run_dir import raster_settings

    surfels = gs.load_ply(args.ply)
    cfg = raster_settings(args.config or args.ply) or gs.RasterConfig()
    overrides = dict(background=args.background and tuple(args.background), sh_degree=args.sh_degree)
    cfg = dataclasses.replace(cfg, pair_capacity=None, on_overflow="raise",
                              **{k: v for k, v in overrides.items() if v is not None})
    for name, cam in _cameras(args):
        files = render_to_files(surfels, cam, cfg, args.out, Path(name).stem)
        print(f"{name}: {', '.join(str(p) for p in files.values())}")
    return 0
