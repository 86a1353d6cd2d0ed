"""Image metrics (PSNR, L1, SSIM) of one rendered view and their per-split summary."""

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


def summarize(rows: list[dict]) -> dict:
    """Mean of each metric over views (PSNR averaged per view, as the 3DGS papers do)."""
    if not rows:
        return {k: None for k in METRICS} | {"num_views": 0}
    return {k: float(np.mean([r[k] for r in rows])) for k in METRICS} | {"num_views": len(rows)}
