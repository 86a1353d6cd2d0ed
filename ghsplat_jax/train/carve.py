"""Initial points for a subject on a plain background, where the dataset has cameras but no
points (and triangulation from the known cameras found too few): random points in the camera
box that every view seeing them shows on the subject, its visual hull (Laurentini 1994),
coloured by the pixels they land on.

A thin plant on black gives SIFT almost nothing to match (5-16 features a view at 128x96), so
triangulation finds no points and training would start from random points filling the whole
box, where the plant's few pixels pull on a handful of them. The hull puts the start on the plant.

    points, colors = subject_points(views, center, half, count, rng)   # None: no plain background

Only where most views have a plain background (the share of pixels near the median colour of the
image's border), or an alpha channel; anything else (a greenhouse row) gets None.
"""

from __future__ import annotations

import numpy as np

from ghsplat_jax.core.camera import project_points

BACKGROUND_TOLERANCE = 0.08  # colour distance (largest channel difference) that still counts as background
PLAIN_SHARE = 0.6  # a view's background is plain when at least this share of its pixels is background
PLAIN_VIEWS = 0.8  # ... and carving needs that of at least this share of the views
ON_SUBJECT = 0.9  # a point is kept when at least this share of the views that see it show it on the subject
SEEN_SHARE = 0.5  # ... and at least this share of all views see it (in front, in the frame): a subject on
# a plain background is in most views, and a point few views see is hardly constrained
BATCH = 200_000  # candidates drawn at a time
MAX_BATCHES = 25  # the most candidates drawn: MAX_BATCHES x BATCH


def _dilate(mask: np.ndarray) -> np.ndarray:
    """One-pixel square dilation (a pose or a pixel off still lands on a stem one pixel wide)."""
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, structure=np.ones((3, 3), bool))


def subject_mask(image, alpha=None) -> tuple[np.ndarray, bool]:
    """((H,W) subject pixels, whether the view has a plain background): its alpha where given
    (alpha >= 0.5), else the pixels farther than BACKGROUND_TOLERANCE from the median colour of the
    image's one-pixel border; both dilated by a pixel."""
    if alpha is not None:
        fg = np.asarray(alpha) >= 0.5
        return _dilate(fg), bool(fg.any() and not fg.all())
    rgb = np.asarray(image, np.float32)[..., :3]
    border = np.concatenate([rgb[0], rgb[-1], rgb[:, 0], rgb[:, -1]])
    distance = np.abs(rgb - np.median(border, axis=0)).max(axis=-1)
    fg = distance > BACKGROUND_TOLERANCE
    return _dilate(fg), bool(1.0 - fg.mean() >= PLAIN_SHARE)  # the share before dilation: thin stems stay thin


def _project(points: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row, column, inside) of each point's pixel in `camera` (inside: in front and in the image)."""
    uv, z = project_points(points, camera.K, camera.world_to_cam)
    front = z > 1e-6
    uv = np.where(front[:, None], uv, -1.0)  # behind the camera: outside (and never cast from inf)
    col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = front & (col >= 0) & (row >= 0) & (col < camera.width) & (row < camera.height)
    return np.where(inside, row, 0), np.where(inside, col, 0), inside


def subject_points(views, center, half: float, count: int, rng) -> tuple[np.ndarray, np.ndarray] | None:
    """Up to `count` points of the cube center +- half in the subject's visual hull, with the mean
    colour of the pixels they land on; None when the views have no plain background or no
    candidate survives."""
    masks = [subject_mask(v.image, getattr(v, "alpha", None)) for v in views]
    if not views or sum(plain for _, plain in masks) < PLAIN_VIEWS * len(views):
        return None
    kept_points, kept_colors = [], []
    total = 0
    for _ in range(MAX_BATCHES):
        cand = np.asarray(center, np.float64) + rng.uniform(-half, half, size=(BATCH, 3))
        seen = np.zeros(BATCH, np.int32)
        on = np.zeros(BATCH, np.int32)
        color = np.zeros((BATCH, 3), np.float64)
        for v, (mask, _) in zip(views, masks):
            row, col, inside = _project(cand, v.camera)
            hit = inside & mask[row, col]
            seen += inside
            on += hit
            color += np.where(hit[:, None], np.asarray(v.image, np.float64)[row, col, :3], 0.0)
        keep = (seen >= max(SEEN_SHARE * len(views), 2)) & (on >= ON_SUBJECT * seen)
        kept_points.append(cand[keep])
        kept_colors.append(color[keep] / np.maximum(on[keep], 1)[:, None])
        total += int(keep.sum())
        if total >= count:
            break
    if total == 0:
        return None
    points, colors = np.concatenate(kept_points)[:count], np.concatenate(kept_colors)[:count]
    return points.astype(np.float32), np.clip(colors, 0.0, 1.0).astype(np.float32)
