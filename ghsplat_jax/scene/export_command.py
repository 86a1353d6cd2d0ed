"""`ghsplat export`: clean, rescale, transform, merge and write Gaussian PLYs."""

from __future__ import annotations

import argparse
import json
import sys
import warnings

import numpy as np

HELP = "clean, crop, rescale, rotate (SH included) and merge Gaussian PLYs; write 2DGS or 3DGS-viewer PLY, optionally a mesh"


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
    t.add_argument("--mirror", choices=["x", "y", "z"], help="reflect across the plane normal to this axis (before rotate)")
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


def _hull_points(path: str) -> np.ndarray:
    if path.lower().endswith(".ply"):
        from ghsplat_jax.data.ply import read_vertices

        v = read_vertices(path)
        return np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    try:
        return np.loadtxt(path, ndmin=2)[:, :3]
    except (OSError, ValueError, IndexError) as exc:
        raise ValueError(f"{path}: cannot read hull points ({exc})") from None


def run(args) -> dict:
    """Everything but argument parsing; returns the statistics dict."""
    from ghsplat_jax.scene import edit, merge, stats, transform
    from ghsplat_jax.data.ply import save_ply

    # non-finite surfels are loaded here only to be dropped below, with a warning
    parts, names = merge.load_many(args.inputs, allow_mixed_3dgs=args.allow_3dgs_mix, finite=False)
    s = merge.merge(parts, args.sh_policy, names, degree=args.sh_degree)
    keep = np.ones(s.num, bool)

    def step(mask_fn, what):
        nonlocal s
        mask = mask_fn(s)
        s, _ = edit.apply(s, mask, what)
        keep[np.flatnonzero(keep)] = mask

    bad = int((~edit.finite_mask(s)).sum())
    if bad:
        warnings.warn(f"dropped {bad} surfels with non-finite (NaN/Inf) values", stacklevel=2)
    step(edit.finite_mask, "non-finite removal")
    inside = lambda m: ~m if args.crop_remove else m
    if args.crop_box:
        step(lambda x: inside(edit.box_mask(x, args.crop_box[:3], args.crop_box[3:])), "crop box")
    if args.crop_sphere:
        step(lambda x: inside(edit.sphere_mask(x, args.crop_sphere[:3], args.crop_sphere[3])), "crop sphere")
    if args.crop_hull:
        pts = _hull_points(args.crop_hull)
        step(lambda x: inside(edit.hull_mask(x, pts)), "convex-hull crop")
    if args.min_opacity > 0:
        step(lambda x: edit.opacity_mask(x, args.min_opacity), f"opacity threshold {args.min_opacity}")
    if args.remove_floaters:
        step(lambda x: edit.statistical_outlier_mask(x, std_ratio=args.floater_std), "outlier removal")
        step(lambda x: edit.small_cluster_mask(x, args.cluster_radius, min_fraction=args.min_cluster_fraction),
             "small-cluster removal")
    scale = args.scale if args.scale is not None else (
        transform.scale_from_length(*args.scale_from_length) if args.scale_from_length else 1.0)
    M = transform.mirror_matrix(args.mirror) if args.mirror else np.eye(3)
    if args.rotate:
        M = transform.rotation_from_euler(args.rotate) @ M
    if scale != 1.0 or args.mirror or args.rotate or args.translate:
        s = transform.similarity(s, scale, M, args.translate)
    info = stats.statistics(s)
    info["removed"] = int((~keep).sum())
    if args.stats or args.stats_out:
        info["inputs"] = [{"path": n, **stats.statistics(p)} for n, p in zip(names, parts)]
    else:
        info["inputs"] = names
    mesh = None
    if args.mesh:  # before any write, so a failure leaves no output at all
        from ghsplat_jax.scene.tsdf import mesh_from_surfels, save_mesh

        voxel = args.mesh_voxel or float(np.ptp(np.percentile(s.means, [1, 99], axis=0), axis=0).max() / 200)
        from ghsplat_jax.train.run_dir import raster_settings

        # One input from a training run renders its mesh views with that run's settings.
        run = raster_settings(args.inputs[0]) if len(args.inputs) == 1 else None
        mesh = mesh_from_surfels(s, voxel, views_per_ring=args.mesh_views, config=run)
        info["mesh"] = {"path": str(args.mesh), "vertices": len(mesh.vertices), "faces": len(mesh.faces),
                        "voxel": voxel}
    save_ply(s, args.out, viewer_compatible=args.viewer_compatible)
    if mesh is not None:
        save_mesh(mesh, args.mesh)
    if args.removed_mask:
        from ghsplat_jax.io_utils import atomic_write

        with atomic_write(args.removed_mask) as fh:
            np.save(fh, ~keep)
    if args.stats_out:
        from ghsplat_jax.io_utils import write_json

        write_json(args.stats_out, info)
    return info


def main(args) -> int:
    from ghsplat_jax.data.ply import PlyError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = lambda msg, *a, **k: print(f"ghsplat export: warning: {msg}", file=sys.stderr)
            info = run(args)
    except (PlyError, ValueError, FileNotFoundError) as exc:
        print(f"ghsplat export: error: {exc}", file=sys.stderr)
        return 2
    print(f"ghsplat export: wrote {args.out} ({info['count']} surfels, SH degree {info['sh_degree']}, "
          f"{info['removed']} removed)", file=sys.stderr)
    if args.stats:
        print(json.dumps(info, indent=2))
    return 0
