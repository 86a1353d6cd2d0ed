"""Turn render outputs into viewable images (colour maps for depth and normals)."""

from __future__ import annotations

import numpy as np


def depth_to_rgb(depth: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """Turbo-coloured depth between its 2nd and 98th percentiles; black where empty."""
    from matplotlib import colormaps

    depth = np.asarray(depth, np.float64)
    mask = depth > 0 if alpha is None else np.asarray(alpha) > 0.5
    if not mask.any():
        return np.zeros(depth.shape + (3,), np.float32)
    lo, hi = np.percentile(depth[mask], [2, 98])
    t = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    rgb = colormaps["turbo"](t)[..., :3]
    return np.where(mask[..., None], rgb, 0.0).astype(np.float32)


def normal_to_rgb(normal: np.ndarray) -> np.ndarray:
    """World normals n in [-1,1] shown as (n + 1) / 2."""
    return np.clip((np.asarray(normal) + 1) / 2, 0, 1).astype(np.float32)
