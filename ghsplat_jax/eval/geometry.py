"""Depth and normal error against ground truth, for the procedural scenes of ghsplat_jax.synth.

`ghsplat synth` writes, beside each image, the ray-cast z-depth (camera z, 0 where the ray hits
nothing) and the world-frame unit normal facing the camera (synth/dataset.py). The model's median
depth and normal renders follow the same conventions (raster/config.py RenderOutput), so the
errors compare them pixel by pixel where the scene has a surface and the model covers it:

- `depth_abs_err`: median absolute depth error (scene units, metres for synth scenes);
- `normal_err_deg`: mean angle between the rendered and the true normal, in degrees;
- `geometry_covered`: the fraction of the surface pixels that the model covers (alpha > 0.5),
  the pixels the two errors are taken over.

Only a synth dataset folder (one with scene.toml) is trusted to hold ground truth: other datasets
may keep estimated depth under the same folder names. A model `ghsplat sfm` made from a synth
folder's photos has its own frame and scale: when its sfm_report.json records the similarity
onto the exact cameras (`accuracy.to_reference`, from the experiments that know them), the
model's depth and normals are carried into the scene's frame by it, so the errors, in metres
and degrees, include the SfM's own pose error."""

from __future__ import annotations

from pathlib import Path

import numpy as np

GEOMETRY_METRICS = ("depth_abs_err", "normal_err_deg", "geometry_covered")
COVERED_ALPHA = 0.5  # the median depth is defined where accumulated opacity crosses this


def _nearest(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixels sampled at the centres of a (height, width) grid over the same image: identity at
    equal size; nearest, not averaged, so depth edges stay on one surface or the other."""
    h, w = pixels.shape[:2]
    if (h, w) == (height, width):
        return pixels
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(int), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(int), w - 1)
    return pixels[rows][:, cols]


def truth_source(root) -> tuple[Path, float, np.ndarray] | None:
    """(synth folder, scale, rotation) taking the dataset `root`'s frame onto the scene's
    (x_scene = scale R x + t): a synth folder itself (1, I), or an SfM model of one's photos whose
    sfm_report.json records that similarity; None for any other dataset."""
    import json

    if root is None:
        return None
    root = Path(root)
    if (root / "scene.toml").is_file():
        return root, 1.0, np.eye(3)
    try:
        report = json.loads((root / "sfm_report.json").read_text())
        acc = report["accuracy"]
        frame = acc["to_reference"]
        # The reference (SYNTH/sparse/0) is recorded relative to the model compared, ROOT/sparse/0.
        synth = (root / "sparse" / "0" / acc["reference"]).resolve().parent.parent
        scale, rotation = float(frame["scale"]), np.asarray(frame["rotation"], np.float64).reshape(3, 3)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return (synth, scale, rotation) if (synth / "scene.toml").is_file() else None


def ground_truth(root, name: str, width: int, height: int) -> tuple[np.ndarray, np.ndarray] | None:
    """((H,W) z-depth, (H,W,3) world normals), in the scene's frame, of the view `name` at the
    loaded size, from the synth folder of `truth_source(root)` (depth/STEM.exr,
    normals/STEM.exr); None for any other dataset or a view without both files."""
    from ghsplat_jax.data.images import read_pixels

    source = truth_source(root)
    if source is None:
        return None
    root = source[0]
    stem = Path(name).stem
    depth_file, normal_file = root / "depth" / f"{stem}.exr", root / "normals" / f"{stem}.exr"
    if not (depth_file.is_file() and normal_file.is_file()):
        return None
    depth = np.asarray(read_pixels(depth_file), np.float32)
    normal = np.asarray(read_pixels(normal_file), np.float32)[..., :3]
    return _nearest(depth, width, height), _nearest(normal, width, height)


def geometry_errors(depth, normal, alpha, true_depth, true_normal, scale: float = 1.0,
                    rotation=None) -> dict[str, float]:
    """The errors above of one view from its (H,W) median depth (None: not rendered), (H,W,3)
    alpha-weighted normal and (H,W) alpha against the ground truth, the model's depth times
    `scale` and its normals turned by `rotation` into the scene's frame first (truth_source);
    {} when the view shows no surface or the model covers none of it."""
    alpha = np.asarray(alpha, np.float32)
    depth = None if depth is None else np.asarray(depth, np.float64) * scale
    normal = np.asarray(normal, np.float64)
    if rotation is not None:
        normal = normal @ np.asarray(rotation, np.float64).T
    surface = np.asarray(true_depth) > 0
    covered = surface & (alpha > COVERED_ALPHA)
    if not covered.any():
        return {}
    out = {"geometry_covered": float(covered.sum() / surface.sum())}
    if depth is not None:
        out["depth_abs_err"] = float(np.median(np.abs(np.asarray(depth, np.float64)[covered]
                                                      - np.asarray(true_depth, np.float64)[covered])))
    n = np.asarray(normal, np.float64)[covered]
    length = np.linalg.norm(n, axis=-1)
    ok = length > 1e-6  # a covered pixel whose weighted normals cancel has no direction to compare
    if ok.any():
        cos = np.sum(n[ok] / length[ok, None] * np.asarray(true_normal, np.float64)[covered][ok], axis=-1)
        out["normal_err_deg"] = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).mean())
    return out
