"""Image metrics (PSNR, L1, SSIM and, for images with alpha, the background cover) of one
rendered view and their per-split summary."""

from __future__ import annotations

import jax
import numpy as np

from ghsplat_jax.train import losses

METRICS = ("psnr", "l1", "ssim")


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
    """Mean of each metric over views (PSNR averaged per view, as the 3DGS papers do); the
    background metrics when every view has them."""
    if not rows:
        return {k: None for k in METRICS} | {"num_views": 0}
    keys = METRICS + tuple(k for k in BACKGROUND_METRICS if all(k in r for r in rows))
    return {k: float(np.mean([r[k] for r in rows])) for k in keys} | {"num_views": len(rows)}
