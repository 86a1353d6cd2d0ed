"""Image metrics (PSNR, L1, SSIM, LPIPS-VGG, the structure PSNR and L1 and, for images with alpha,
the background cover) of one rendered view, their per-split summary, and the checks evaluation
warns with: views far below their split, a train-test gap, a render that misses what the photos
show."""

from __future__ import annotations

import jax
import numpy as np

from ghsplat_jax.eval.geometry import GEOMETRY_METRICS
from ghsplat_jax.train import losses

METRICS = ("psnr", "l1", "ssim")
# Per view only where evaluation computes them: the test views (LPIPS where its weights are installed).
OPTIONAL_METRICS = ("lpips", "psnr_cc")


@jax.jit
def _image_metrics(rendered, target):
    return {"psnr": losses.psnr(rendered, target), "l1": losses.l1(rendered, target),
            "ssim": losses.ssim(rendered, target)}


def image_metrics(rendered, target) -> dict[str, float]:
    """PSNR (dB), mean absolute error and SSIM of (H,W,3) images in [0, 1]; the render is
    clipped to [0, 1] as it would be saved."""
    rendered = np.clip(np.asarray(rendered, np.float32), 0.0, 1.0)
    target = np.asarray(target, np.float32)
    if rendered.shape != target.shape:
        raise ValueError(f"render {rendered.shape} and target {target.shape} differ in shape")
    return {k: float(v) for k, v in _image_metrics(rendered, target).items()}


def colour_corrected_metrics(rendered, target) -> dict[str, float]:
    """{"psnr_cc": PSNR after the per-channel gain and offset that best fit the render to the
    photo (least squares; the render clipped to [0, 1] before and after)}: what is left when a
    photo's exposure or white balance, which no model of the scene can know, is taken out (the
    "colour-corrected" metric of mip-NeRF 360's evaluation, with a gain and offset per channel in
    place of its 3x3 matrix). The gap to `psnr` is the part of the error a view's exposure explains."""
    rendered = np.clip(np.asarray(rendered, np.float64), 0.0, 1.0).reshape(-1, 3)
    target = np.asarray(target, np.float64)[..., :3].reshape(-1, 3)
    fitted = np.empty_like(rendered)
    for c in range(3):
        design = np.stack([rendered[:, c], np.ones(len(rendered))], axis=1)
        coef = np.linalg.lstsq(design, target[:, c], rcond=None)[0]
        fitted[:, c] = design @ coef
    return {"psnr_cc": float(losses.psnr(np.clip(fitted, 0.0, 1.0), target))}


def lpips_metrics(rendered, target) -> dict[str, float]:
    """{"lpips": LPIPS-VGG} of (H,W,3) images in [0, 1] (eval/lpips.py: the papers' definition and
    where its weights come from); {} when those weights are not installed or the image is too
    small for VGG's pools."""
    from ghsplat_jax.eval.lpips import MIN_SIZE, lpips_vgg

    if min(np.shape(target)[:2]) < MIN_SIZE:
        return {}
    value = lpips_vgg(rendered, target)
    return {} if value is None else {"lpips": value}


# Images with alpha (object captures): how much of their empty background the render covers.
BACKGROUND_METRICS = ("background_alpha", "background_covered")
EMPTY_BELOW = 0.01  # image alpha below this is empty background
COVERED_ABOVE = 0.05  # rendered alpha above this over it is a visible cover


def background_cover(rendered_alpha, image_alpha) -> dict[str, float]:
    """Mean rendered alpha over the pixels the image leaves empty, and the fraction of them
    covered visibly; {} when the image has no alpha or no empty pixel. Surfels of the background
    colour there cost nothing on the training views and hide the object from new ones."""
    if image_alpha is None:
        return {}
    empty = np.asarray(image_alpha) < EMPTY_BELOW
    if not empty.any():
        return {}
    over = np.asarray(rendered_alpha, np.float32)[empty]
    return {"background_alpha": float(over.mean()), "background_covered": float((over > COVERED_ABOVE).mean())}


def summarize(rows: list[dict]) -> dict:
    """Mean of each metric over views (PSNR averaged per view, as the 3DGS papers do); LPIPS and
    the background metrics when every view has them; the structure metrics over the views that
    have them (`structure_views` of them), and so the depth and normal errors against ground
    truth (`geometry_views`; eval/geometry.py)."""
    if not rows:
        return {k: None for k in METRICS} | {"num_views": 0}
    keys = METRICS + tuple(k for k in OPTIONAL_METRICS + BACKGROUND_METRICS if all(k in r for r in rows))
    out = {k: float(np.mean([r[k] for r in rows])) for k in keys} | {"num_views": len(rows)}
    structured = [r for r in rows if all(k in r for k in STRUCTURE_METRICS)]
    if structured:  # views of a flat photo have none: the mean over those that have
        out |= {k: float(np.mean([r[k] for r in structured])) for k in STRUCTURE_METRICS}
        out["structure_views"] = len(structured)
    for key in GEOMETRY_METRICS:  # a view the model leaves uncovered has none; the count says how many had
        values = [r[key] for r in rows if key in r]
        if values:
            out[key] = float(np.mean(values))
    if any(k in r for r in rows for k in GEOMETRY_METRICS):
        out["geometry_views"] = sum(any(k in r for k in GEOMETRY_METRICS) for r in rows)
    return out


# ---------------------------------------------------------------- structure: what the photo shows
# Whole-image metrics of a thin plant on a black background stay high when the model renders
# only the background. The structure metrics score the pixels where the photo has something to
# show: its foreground where the image has alpha, else where its gradient is strong; and the
# structure gain, how much better the render does there than an empty one (the photo's own
# background colour everywhere). A missing subject gains ~0 dB, whatever the background's share:
# the whole-image PSNR minus the structure PSNR cannot tell, since a perfect background lifts the
# whole image by 10 log10(1 / the subject's share) for a good model and a missing one alike.
STRUCTURE_METRICS = ("structure_psnr", "structure_l1", "structure_gain_db")
STRUCTURE_PERCENTILE = 80.0  # gradient magnitude above this percentile of the image is structure
STRUCTURE_DILATE = 0  # pixels the structure mask grows by (the contrast already marks both sides of an edge)
STRUCTURE_MIN_GRADIENT = 1e-3  # a flat image has no structure, whatever its percentiles


def _dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Square dilation by `radius` pixels."""
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, structure=np.ones((2 * radius + 1,) * 2, bool))


def structure_mask(target, alpha=None, percentile: float = STRUCTURE_PERCENTILE,
                   dilate: int = STRUCTURE_DILATE) -> np.ndarray:
    """(H,W) bool: the pixels where the ground-truth photo has structure. With an alpha that
    has both foreground and empty pixels, its foreground (alpha >= 0.5); else the pixels whose
    grey-level contrast (the largest absolute difference to a 4-neighbour, so both sides of an
    edge and the whole of a one-pixel line count) is above the image's `percentile` (and not
    ~0), dilated by `dilate` pixels. All False for a flat image."""
    if alpha is not None:
        fg = np.asarray(alpha) >= 0.5
        if fg.any() and not fg.all():
            return fg
    grey = np.asarray(target, np.float32).mean(axis=-1)
    mag = np.zeros_like(grey)
    dy, dx = np.abs(np.diff(grey, axis=0)), np.abs(np.diff(grey, axis=1))
    mag[1:] = np.maximum(mag[1:], dy)
    mag[:-1] = np.maximum(mag[:-1], dy)
    mag[:, 1:] = np.maximum(mag[:, 1:], dx)
    mag[:, :-1] = np.maximum(mag[:, :-1], dx)
    threshold = max(float(np.percentile(mag, percentile)), STRUCTURE_MIN_GRADIENT)
    mask = mag > threshold
    return _dilate(mask, dilate) if dilate > 0 and mask.any() else mask


def structure_metrics(rendered, target, alpha=None) -> dict[str, float]:
    """PSNR and L1 over `structure_mask` (the render clipped to [0, 1]), and the structure gain:
    that PSNR minus the PSNR there of an empty render, the median colour of the photo's other
    pixels (its background); {} when the photo has no structure."""
    target = np.asarray(target, np.float32)
    mask = structure_mask(target, alpha)
    if not mask.any():
        return {}
    diff = np.clip(np.asarray(rendered, np.float32), 0.0, 1.0)[mask] - target[mask]
    mse = max(float(np.mean(diff ** 2)), 1e-20)
    rest = target[~mask]
    background = np.median(rest, axis=0) if len(rest) else np.zeros(target.shape[-1], np.float32)
    blank_mse = max(float(np.mean((target[mask] - background) ** 2)), 1e-20)
    return {"structure_psnr": float(-10.0 * np.log10(mse)), "structure_l1": float(np.mean(np.abs(diff))),
            "structure_gain_db": float(10.0 * np.log10(blank_mse / mse))}


# The render must remove at least a fifth of an empty render's squared error where the photos
# show structure: a model that misses the subject gains ~0 dB; the stability study's quick-preset
# greenhouse row, a blurred 13.5 dB model at 64x48, gains 1.5-2.3 dB and a Table 1 segment 8.4.
STRUCTURE_MIN_GAIN_DB = 1.0


def missing_structure(summary: dict, min_gain_db: float = STRUCTURE_MIN_GAIN_DB) -> float | None:
    """A split summary's structure gain when under `min_gain_db` (the model misses what the
    photos show), else None."""
    gain = summary.get("structure_gain_db")
    if gain is None or gain >= min_gain_db:
        return None
    return float(gain)


# ---------------------------------------------------------------- views far below their split
OUTLIER_MIN_DB = 3.0  # a view is an outlier when its PSNR is more than max(this, OUTLIER_MADS x MAD)
OUTLIER_MADS = 4.0    # under the median of its split
# ... and under this: a view rendered to within 1.8% RMS of its photo shows no bad pose or image,
# however far its split's median lies above it (a thin plant on black: training views of 41.7
# and 43.0 dB against a median of 46 were named).
OUTLIER_CLEAN_DB = 35.0


def psnr_outliers(rows: list[dict], min_db: float = OUTLIER_MIN_DB, mads: float = OUTLIER_MADS,
                  clean_db: float = OUTLIER_CLEAN_DB) -> list[dict]:
    """Views whose PSNR is far below the median of `rows` (one split): more than
    max(min_db, mads x the median absolute deviation) under it, and under `clean_db`; worst
    first, each {name, psnr, below_median_db}. Fewer than 3 views have no outlier."""
    values = np.array([r["psnr"] for r in rows], np.float64)
    if len(values) < 3:
        return []
    median = float(np.median(values))
    mad = float(np.median(np.abs(values - median)))
    margin = max(min_db, mads * mad)
    out = [{"name": r["name"], "psnr": float(r["psnr"]), "below_median_db": median - float(r["psnr"])}
           for r in rows if r["psnr"] < min(median - margin, clean_db)]
    return sorted(out, key=lambda o: o["psnr"])


TRAIN_TEST_GAP_DB = 6.0  # training views' PSNR this far above the test views': over-fitting
