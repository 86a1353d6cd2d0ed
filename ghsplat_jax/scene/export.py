"""Export: merge Gaussian PLYs, clean them (non-finite, crops, opacity, floaters), rescale /
mirror / rotate / translate them (SH bands rotated too), write 2DGS or 3DGS-viewer PLY and,
on request, a mesh. `ghsplat export` (commands/export.py) is its command line.

    info = export(["a.ply", "b.ply"], "out.ply", ExportOptions(min_opacity=0.05, scale=2.0))
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ghsplat_jax.scene import edit, merge, stats, transform


@dataclasses.dataclass(frozen=True)
class ExportOptions:
    """What `export` does, in its order: cleaning, then the transform x' = R (s x) + t, then output."""
    crop_box: tuple[float, ...] | None = None       # X0 Y0 Z0 X1 Y1 Z1: keep surfels inside this box
    crop_sphere: tuple[float, ...] | None = None    # CX CY CZ R: keep surfels inside this sphere
    crop_hull: str | None = None                    # points file (x y z lines, or a PLY): keep inside their hull
    crop_remove: bool = False                       # remove what is inside the crop shapes instead
    min_opacity: float = 0.0                        # drop surfels below this opacity
    remove_floaters: bool = False                   # drop k-NN outliers and small disconnected clusters
    floater_std: float = 3.0                        # outlier threshold in std devs
    cluster_radius: float | None = None             # cluster link distance (m; None: 4x median 8-NN distance)
    min_cluster_fraction: float = 0.01              # drop clusters smaller than this share of the largest
    removed_mask: str | None = None                 # save a boolean .npy, one per input surfel, True = removed
    scale: float | None = None                      # uniform scale s
    scale_from_length: tuple[float, float] | None = None  # (measured, true): s = true / measured
    rotate: tuple[float, float, float] | None = None  # degrees, extrinsic x then y then z
    translate: tuple[float, float, float] | None = None
    mirror: str | None = None                       # x, y or z: reflect across that plane (before rotate)
    sh_degree: int | None = None                    # output SH degree (None: from sh_policy)
    sh_policy: str = "pad"                          # inputs of different degree: pad to highest, or truncate
    allow_3dgs_mix: bool = False                    # allow merging 3DGS files with 2DGS files
    viewer_compatible: bool = False                 # 3DGS-viewer layout: scale_2 = log(1e-6)
    mesh: str | None = None                         # also extract a mesh here (TSDF of orbit renders)
    mesh_voxel: float | None = None                 # TSDF voxel (m; None: extent / 200)
    mesh_views: int = 12                            # views per orbit ring (three rings)
    input_stats: bool = False                       # statistics of every input in the result
    stats_out: str | None = None                    # write the statistics JSON here


def _hull_points(path: str) -> np.ndarray:
    if path.lower().endswith(".ply"):
        from ghsplat_jax.data.ply import read_vertices

        v = read_vertices(path)
        return np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    try:
        return np.loadtxt(path, ndmin=2)[:, :3]
    except (OSError, ValueError, IndexError) as exc:
        raise ValueError(f"{path}: cannot read hull points ({exc})") from None


def export(inputs: list[str], out, opts: ExportOptions = ExportOptions()) -> dict:
    """Merge `inputs` in order, clean, transform, write `out` (and the mesh, removed mask and
    statistics file when asked); returns the statistics dict."""
    from ghsplat_jax.data.ply import save_ply

    # non-finite surfels are loaded here only to be dropped below, with a warning
    parts, names = merge.load_many(inputs, allow_mixed_3dgs=opts.allow_3dgs_mix, finite=False)
    s = merge.merge(parts, opts.sh_policy, names, degree=opts.sh_degree)
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
    inside = lambda m: ~m if opts.crop_remove else m
    if opts.crop_box:
        step(lambda x: inside(edit.box_mask(x, opts.crop_box[:3], opts.crop_box[3:])), "crop box")
    if opts.crop_sphere:
        step(lambda x: inside(edit.sphere_mask(x, opts.crop_sphere[:3], opts.crop_sphere[3])), "crop sphere")
    if opts.crop_hull:
        pts = _hull_points(opts.crop_hull)
        step(lambda x: inside(edit.hull_mask(x, pts)), "convex-hull crop")
    if opts.min_opacity > 0:
        step(lambda x: edit.opacity_mask(x, opts.min_opacity), f"opacity threshold {opts.min_opacity}")
    if opts.remove_floaters:
        step(lambda x: edit.statistical_outlier_mask(x, std_ratio=opts.floater_std), "outlier removal")
        step(lambda x: edit.small_cluster_mask(x, opts.cluster_radius, min_fraction=opts.min_cluster_fraction),
             "small-cluster removal")
    scale = opts.scale if opts.scale is not None else (
        transform.scale_from_length(*opts.scale_from_length) if opts.scale_from_length else 1.0)
    M = transform.mirror_matrix(opts.mirror) if opts.mirror else np.eye(3)
    if opts.rotate:
        M = transform.rotation_from_euler(opts.rotate) @ M
    if scale != 1.0 or opts.mirror or opts.rotate or opts.translate:
        s = transform.similarity(s, scale, M, opts.translate)
    info = stats.statistics(s)
    info["removed"] = int((~keep).sum())
    if opts.input_stats or opts.stats_out:
        info["inputs"] = [{"path": n, **stats.statistics(p)} for n, p in zip(names, parts)]
    else:
        info["inputs"] = names
    mesh = None
    if opts.mesh:  # before any write, so a failure leaves no output at all
        from ghsplat_jax.scene.tsdf import mesh_from_surfels, save_mesh
        from ghsplat_jax.train.run_dir import raster_settings

        voxel = opts.mesh_voxel or float(np.ptp(np.percentile(s.means, [1, 99], axis=0), axis=0).max() / 200)
        # One input from a training run renders its mesh views with that run's settings.
        run = raster_settings(inputs[0]) if len(inputs) == 1 else None
        mesh = mesh_from_surfels(s, voxel, views_per_ring=opts.mesh_views, config=run)
        info["mesh"] = {"path": str(opts.mesh), "vertices": len(mesh.vertices), "faces": len(mesh.faces),
                        "voxel": voxel}
    save_ply(s, out, viewer_compatible=opts.viewer_compatible)
    if mesh is not None:
        save_mesh(mesh, opts.mesh)
    if opts.removed_mask:
        from ghsplat_jax.io_utils import atomic_write

        with atomic_write(opts.removed_mask) as fh:
            np.save(fh, ~keep)
    if opts.stats_out:
        from ghsplat_jax.io_utils import write_json

        write_json(opts.stats_out, info)
    return info
