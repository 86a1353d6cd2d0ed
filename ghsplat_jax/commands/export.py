"""`ghsplat export`: clean, rescale, transform, merge and write Gaussian PLYs."""

from __future__ import annotations

import argparse
import json
import sys
import warnings

HELP = ("clean, crop, rescale, rotate (SH included) and merge Gaussian PLYs; "
        "write 2DGS or 3DGS-viewer PLY, optionally a mesh")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", nargs="+", metavar="IN.ply", help="2DGS (or 3DGS) PLY files, merged in order")
    p.add_argument("--out", required=True, metavar="OUT.ply", help="output PLY (written atomically)")
    g = p.add_argument_group("cleaning (applied in this order, before any transform)")
    g.add_argument("--crop-box", nargs=6, type=float, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                   help="keep surfels inside this axis-aligned box")
    g.add_argument("--crop-sphere", nargs=4, type=float, metavar=("CX", "CY", "CZ", "R"),
                   help="keep surfels inside this sphere")
    g.add_argument("--crop-hull", metavar="POINTS", help="keep surfels inside the convex hull of the "
                   "points in this file (text: x y z per line, or a PLY's vertices)")
    g.add_argument("--crop-remove", action="store_true",
                   help="remove what is inside the crop shapes instead of keeping it")
    g.add_argument("--min-opacity", type=float, default=0.0, help="drop surfels below this opacity")
    g.add_argument("--remove-floaters", action="store_true",
                   help="drop statistical outliers (k-NN distance) and small disconnected clusters")
    g.add_argument("--floater-std", type=float, default=3.0, help="outlier threshold in std devs")
    g.add_argument("--cluster-radius", type=float, default=None,
                   help="link distance for clusters (m; default 4x the median 8-NN distance)")
    g.add_argument("--min-cluster-fraction", type=float, default=0.01,
                   help="drop clusters smaller than this fraction of the largest")
    g.add_argument("--removed-mask", metavar="MASK.npy",
                   help="save a boolean array (one per input surfel, True = removed)")
    t = p.add_argument_group("transform: x' = R (s x) + t")
    sc = t.add_mutually_exclusive_group()
    sc.add_argument("--scale", type=float, default=None, help="uniform scale s")
    sc.add_argument("--scale-from-length", nargs=2, type=float, metavar=("MEASURED", "TRUE"),
                    help="s = TRUE / MEASURED (a length measured in the reconstruction, and its real length)")
    t.add_argument("--rotate", nargs=3, type=float, metavar=("RX", "RY", "RZ"),
                   help="rotation in degrees, extrinsic x then y then z (SH bands rotated too)")
    t.add_argument("--translate", nargs=3, type=float, metavar=("TX", "TY", "TZ"))
    t.add_argument("--mirror", choices=["x", "y", "z"],
                   help="reflect across the plane normal to this axis (before rotate)")
    o = p.add_argument_group("output")
    o.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], default=None,
                   help="output SH degree (default: from --sh-policy over the inputs)")
    o.add_argument("--sh-policy", choices=["pad", "truncate"], default="pad",
                   help="inputs of different SH degree: zero-pad to the highest or truncate to the lowest")
    o.add_argument("--allow-3dgs-mix", action="store_true",
                   help="allow merging 3DGS files (three scales, flattened) with 2DGS files")
    o.add_argument("--viewer-compatible", action="store_true",
                   help="3DGS-viewer layout: add scale_2 = log(1e-6)")
    o.add_argument("--mesh", metavar="MESH.ply", help="also extract a mesh (TSDF fusion of renders from "
                   "orbiting cameras, marching cubes); format from the suffix (.ply .obj .stl .glb)")
    o.add_argument("--mesh-voxel", type=float, default=None, help="TSDF voxel (m; default extent/200)")
    o.add_argument("--mesh-views", type=int, default=12, help="views per orbit ring (three rings)")
    o.add_argument("--stats", action="store_true", help="print statistics of the result as JSON")
    o.add_argument("--stats-out", metavar="STATS.json", help="write the statistics JSON here")


def options(args: argparse.Namespace):
    """ExportOptions from parsed arguments."""
    import dataclasses

    from ghsplat_jax.scene.export import ExportOptions

    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(ExportOptions) if hasattr(args, f.name)}
    return ExportOptions(**given, input_stats=args.stats)


def main(args) -> int:
    from ghsplat_jax.data.ply import PlyError
    from ghsplat_jax.scene.export import export

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = lambda msg, *a, **k: print(f"ghsplat export: warning: {msg}", file=sys.stderr)
            info = export(args.inputs, args.out, options(args))
    except (PlyError, ValueError, FileNotFoundError) as exc:
        print(f"ghsplat export: error: {exc}", file=sys.stderr)
        return 2
    print(f"ghsplat export: wrote {args.out} ({info['count']} surfels, SH degree {info['sh_degree']}, "
          f"{info['removed']} removed)", file=sys.stderr)
    if args.stats:
        print(json.dumps(info, indent=2))
    return 0
