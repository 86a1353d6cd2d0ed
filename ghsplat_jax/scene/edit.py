"""Cleaning edits: crops, opacity threshold, non-finite removal, floater removal.

Every `*_mask` function returns a boolean array, True = keep; `apply(s, mask)` selects and
refuses an empty result. Editing functions return (Surfels, kept_mask) so callers can
record what was removed (the mask indexes the input surfels).
"""

from __future__ import annotations

import numpy as np

from ghsplat_jax.core.surfels import Surfels


class EmptyResultError(ValueError):
    """An edit removed every surfel."""


def _means(s: Surfels) -> np.ndarray:
    return np.asarray(s.means, np.float64)


def apply(s: Surfels, keep: np.ndarray, what: str = "edit") -> tuple[Surfels, np.ndarray]:
    """(surfels where keep, keep); EmptyResultError when nothing is left."""
    keep = np.asarray(keep, bool)
    if keep.shape != (s.num,):
        raise ValueError(f"{what}: mask of shape {keep.shape} for {s.num} surfels")
    if s.num and not keep.any():
        raise EmptyResultError(f"{what} removed all {s.num} surfels")
    return s.to_numpy().take(np.flatnonzero(keep)), keep


def finite_mask(s: Surfels) -> np.ndarray:
    """Surfels whose every parameter is finite (NaN/Inf anywhere drops the surfel)."""
    s = s.to_numpy()
    ok = np.ones(s.num, bool)
    for a in (s.means, s.quats, s.log_scales, s.opacity_logits[:, None], s.sh_dc,
              s.sh_rest.reshape(s.num, -1)):
        ok &= np.all(np.isfinite(a), axis=1)
    return ok


def box_mask(s: Surfels, lo, hi, keep_inside: bool = True) -> np.ndarray:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if np.any(lo > hi):
        raise ValueError(f"crop box min {lo.tolist()} exceeds max {hi.tolist()}")
    inside = np.all((_means(s) >= lo) & (_means(s) <= hi), axis=1)
    return inside if keep_inside else ~inside


def sphere_mask(s: Surfels, center, radius: float, keep_inside: bool = True) -> np.ndarray:
    if not radius > 0:
        raise ValueError(f"crop sphere radius must be positive, got {radius}")
    inside = np.linalg.norm(_means(s) - np.asarray(center, np.float64), axis=1) <= radius
    return inside if keep_inside else ~inside


def hull_mask(s: Surfels, points, keep_inside: bool = True) -> np.ndarray:
    """Inside the convex hull of `points` (M,3), M >= 4 not coplanar (Delaunay test)."""
    from scipy.spatial import Delaunay, QhullError

    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise ValueError(f"convex-hull crop needs at least 4 points (M,3), got {points.shape}")
    try:
        tri = Delaunay(points)
    except QhullError as exc:
        raise ValueError(f"convex-hull crop: degenerate (coplanar?) points: {exc}") from None
    inside = tri.find_simplex(_means(s)) >= 0
    return inside if keep_inside else ~inside


def opacity_mask(s: Surfels, min_opacity: float) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(s.opacity_logits, np.float64))) >= min_opacity


def statistical_outlier_mask(s: Surfels, k: int = 16, std_ratio: float = 3.0) -> np.ndarray:
    """Keep surfels whose mean distance to their k nearest neighbours is within
    mean + std_ratio * std of that statistic over the whole set (Open3D's rule)."""
    from scipy.spatial import cKDTree

    x = _means(s)
    if len(x) <= k:
        return np.ones(len(x), bool)
    dist, _ = cKDTree(x).query(x, k=k + 1)
    mean_d = dist[:, 1:].mean(axis=1)  # column 0 is the point itself
    return mean_d <= mean_d.mean() + std_ratio * mean_d.std()


def cluster_labels(s: Surfels, radius: float, k: int = 16) -> np.ndarray:
    """Connected components of the graph linking each surfel to its (up to k) neighbours
    closer than `radius`. A bounded k-NN graph keeps memory at N x k even for dense scenes,
    where a full radius graph can hold hundreds of millions of pairs."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    x = _means(s)
    k = min(k, len(x) - 1)
    if k < 1:
        return np.zeros(len(x), int)
    dist, idx = cKDTree(x).query(x, k=k + 1, distance_upper_bound=radius)
    linked = np.isfinite(dist)
    rows = np.broadcast_to(np.arange(len(x))[:, None], idx.shape)[linked]
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, idx[linked])), shape=(len(x), len(x)))
    return connected_components(graph, directed=False)[1]


def default_cluster_radius(s: Surfels, k: int = 8, factor: float = 4.0) -> float:
    """`factor` x the median distance to the k-th neighbour: links a surface, not across gaps."""
    from scipy.spatial import cKDTree

    x = _means(s)
    k = min(k, len(x) - 1)
    if k < 1:
        return 1.0
    dist, _ = cKDTree(x).query(x, k=k + 1)
    return float(factor * np.median(dist[:, k]))


def small_cluster_mask(s: Surfels, radius: float | None = None, min_size: int | None = None,
                       min_fraction: float = 0.01) -> np.ndarray:
    """Drop connected clusters smaller than max(min_size, min_fraction x largest cluster)."""
    if s.num == 0:
        return np.ones(0, bool)
    radius = default_cluster_radius(s) if radius is None else radius
    labels = cluster_labels(s, radius)
    sizes = np.bincount(labels)
    threshold = max(min_size or 0, min_fraction * sizes.max())
    return sizes[labels] >= threshold


def remove_floaters(s: Surfels, k: int = 16, std_ratio: float = 3.0, radius: float | None = None,
                    min_size: int | None = None, min_fraction: float = 0.01
                    ) -> tuple[Surfels, np.ndarray]:
    """Statistical outliers first, then small disconnected clusters of what is left."""
    keep = statistical_outlier_mask(s, k, std_ratio)
    kept, _ = apply(s, keep, "floater removal (statistical)")
    cluster_keep = small_cluster_mask(kept, radius, min_size, min_fraction)
    keep[np.flatnonzero(keep)] = cluster_keep
    return apply(s, keep, "floater removal")


def remove_non_finite(s: Surfels) -> tuple[Surfels, np.ndarray]:
    return apply(s, finite_mask(s), "non-finite removal")


def crop_box(s: Surfels, lo, hi, keep_inside: bool = True) -> tuple[Surfels, np.ndarray]:
    return apply(s, box_mask(s, lo, hi, keep_inside), f"crop box {list(lo)}-{list(hi)}")


def crop_sphere(s: Surfels, center, radius: float, keep_inside: bool = True
                ) -> tuple[Surfels, np.ndarray]:
    return apply(s, sphere_mask(s, center, radius, keep_inside),
                 f"crop sphere {list(center)} r={radius}")


def crop_hull(s: Surfels, points, keep_inside: bool = True) -> tuple[Surfels, np.ndarray]:
    return apply(s, hull_mask(s, points, keep_inside), "convex-hull crop")


def threshold_opacity(s: Surfels, min_opacity: float) -> tuple[Surfels, np.ndarray]:
    return apply(s, opacity_mask(s, min_opacity), f"opacity threshold {min_opacity}")
