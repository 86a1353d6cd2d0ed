"""The verified match graph of a COLMAP database, and checks of its pairs against camera poses.

Pair filters (disambiguate.py) and fold diagnostics (folds.py) both read the database
once into a `MatchGraph`: images in capture order, their keypoints, and the inlier
matches of every verified pair. A pair "agrees" with a set of poses when most of its
inlier matches triangulate in front of both cameras and reproject within a small angle:
epipolar distance alone is blind to a camera placed behind instead of ahead.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np


@dataclasses.dataclass
class MatchGraph:
    names: list[str]                      # images in capture order (index = position)
    image_ids: list[int]                  # database image id of each name
    camera_ids: list[int]                 # database camera id of each name
    keypoints: list[np.ndarray]           # (K_i, 2) pixel positions per image
    pairs: dict[tuple[int, int], np.ndarray]  # (i, j), i < j -> (M, 2) inlier keypoint indices

    def num_inliers(self) -> dict[tuple[int, int], int]:
        return {pair: len(m) for pair, m in self.pairs.items()}

    def order_distance(self, i: int, j: int, cyclic: bool = False) -> int:
        d = abs(i - j)
        return min(d, len(self.names) - d) if cyclic else d


def read_match_graph(database: Path, names: list[str], min_inliers: int = 15) -> MatchGraph:
    """Verified pairs with at least `min_inliers` inliers, indexed by position in `names`."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        images = {image.name: image for image in db.read_all_images()}
        present = [n for n in names if n in images]
        index_of_id = {images[n].image_id: k for k, n in enumerate(present)}
        keypoints = [np.asarray(db.read_keypoints(images[n].image_id))[:, :2].astype(float)
                     for n in present]
        pair_ids, geometries = db.read_two_view_geometries()
        pairs = {}
        for pair_id, geometry in zip(pair_ids, geometries):
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            matches = np.asarray(geometry.inlier_matches, np.int64).reshape(-1, 2)
            if len(matches) < min_inliers or id1 not in index_of_id or id2 not in index_of_id:
                continue
            i, j = index_of_id[id1], index_of_id[id2]
            pairs[(i, j) if i < j else (j, i)] = matches if i < j else matches[:, ::-1]
    finally:
        db.close()
    return MatchGraph(present, [images[n].image_id for n in present],
                      [images[n].camera_id for n in present], keypoints, pairs)


def copy_keeping_pairs(source: Path, target: Path, wanted: set[tuple[int, int]]) -> tuple[int, int]:
    """Copy database `source` to `target` without the verified pairs outside `wanted` (image ids,
    smaller first); (pairs kept, pairs removed). Features and raw matches stay."""
    import pycolmap

    for suffix in ("", "-wal", "-shm"):
        Path(f"{target}{suffix}").unlink(missing_ok=True)
    shutil.copyfile(source, target)
    db = pycolmap.Database.open(str(target))
    kept = removed = 0
    try:
        pair_ids, _ = db.read_two_view_geometries()
        for pair_id in pair_ids:
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            if (min(id1, id2), max(id1, id2)) in wanted:
                kept += 1
            else:
                db.delete_two_view_geometry(id1, id2)
                removed += 1
    finally:
        db.close()
    return kept, removed


def keep_pairs(source: Path, target: Path, graph: MatchGraph, keep: set[tuple[int, int]],
               narrowed: dict[tuple[int, int], np.ndarray] | None = None) -> int:
    """Copy database `source` to `target` without the verified pairs outside `keep`; returns
    how many were removed. Features and raw matches stay, so the mapper sees only `keep`.
    `narrowed` {pair: (M, 2) keypoint indices, as in `graph.pairs`} replaces those pairs'
    inlier matches, so the mapper sees only the matches kept there."""
    import pycolmap

    wanted = {tuple(sorted((graph.image_ids[i], graph.image_ids[j]))) for i, j in keep}
    _, removed = copy_keeping_pairs(source, target, wanted)
    if narrowed:
        db = pycolmap.Database.open(str(target))
        try:
            for (i, j), matches in narrowed.items():
                # read and written in capture order (i, j): pycolmap swaps the stored pair as needed
                geometry = db.read_two_view_geometry(graph.image_ids[i], graph.image_ids[j])
                geometry.inlier_matches = np.ascontiguousarray(matches, np.uint32)
                db.update_two_view_geometry(graph.image_ids[i], graph.image_ids[j], geometry)
        finally:
            db.close()
    return removed


# ---------------------------------------------------------------------------- poses


@dataclasses.dataclass
class ModelPoses:
    """Registered cameras of a reconstruction, by capture-order index."""
    world_to_cam: dict[int, np.ndarray]   # index -> (3, 4)
    normalise: dict[int, object]          # index -> f(pixels (N,2)) -> normalised coords (N,2)
    focal: dict[int, float]               # index -> mean focal length in pixels


def model_poses(reconstruction, graph: MatchGraph) -> ModelPoses:
    index = {name: k for k, name in enumerate(graph.names)}
    w2c, normalise, focal = {}, {}, {}
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.images[image_id]
        if image.name not in index:
            continue
        k = index[image.name]
        camera = reconstruction.cameras[image.camera_id]
        w2c[k] = np.asarray(image.cam_from_world().matrix(), float)
        normalise[k] = camera.cam_from_img
        focal[k] = float(np.mean([camera.focal_length_x, camera.focal_length_y]))
    return ModelPoses(w2c, normalise, focal)


def ray_agreement(xa: np.ndarray, xb: np.ndarray, w2c_a: np.ndarray, w2c_b: np.ndarray,
                  max_angle: float) -> np.ndarray:
    """(M,) bool: normalised matches (xa, xb) triangulate in front of both cameras and each ray
    passes within `max_angle` radians of the midpoint (a match whose rays are near-parallel
    only needs the two ray directions within `max_angle`: a far point)."""
    ra, rb = w2c_a[:3, :3], w2c_b[:3, :3]
    ca, cb = -ra.T @ w2c_a[:3, 3], -rb.T @ w2c_b[:3, 3]
    da = np.column_stack([xa, np.ones(len(xa))]) @ ra  # world directions, camera z = 1
    db = np.column_stack([xb, np.ones(len(xb))]) @ rb
    ua = da / np.linalg.norm(da, axis=1, keepdims=True)
    ub = db / np.linalg.norm(db, axis=1, keepdims=True)
    parallel = np.einsum("ij,ij->i", ua, ub)
    # closest points: ca + s ua, cb + t ub
    w = ca - cb
    p, q = ua @ w, ub @ w
    denom = 1.0 - parallel**2
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (parallel * q - p) / denom
        t = (q - parallel * p) / denom
    mid = 0.5 * ((ca + s[:, None] * ua) + (cb + t[:, None] * ub))

    def angle_to(c, u):
        v = mid - c
        cos = np.einsum("ij,ij->i", v, u) / np.maximum(np.linalg.norm(v, axis=1), 1e-12)
        return np.arccos(np.clip(cos, -1.0, 1.0))

    far = denom < (0.5 * max_angle) ** 2  # near-parallel rays: the point is at infinity
    with np.errstate(invalid="ignore"):
        near_ok = (s > 0) & (t > 0) & (angle_to(ca, ua) < max_angle) & (angle_to(cb, ub) < max_angle)
    far_ok = np.arccos(np.clip(parallel, -1.0, 1.0)) < max_angle
    return np.where(far, far_ok, near_ok)


def agreeing_matches(graph: MatchGraph, poses: ModelPoses, pair: tuple[int, int],
                     max_angle_deg: float) -> np.ndarray | None:
    """(M,) bool: which of the pair's inlier matches agree with the poses (None: not both posed)."""
    i, j = pair
    if i not in poses.world_to_cam or j not in poses.world_to_cam:
        return None
    matches = graph.pairs[pair]
    xa = np.asarray(poses.normalise[i](graph.keypoints[i][matches[:, 0]]), float)
    xb = np.asarray(poses.normalise[j](graph.keypoints[j][matches[:, 1]]), float)
    return ray_agreement(xa, xb, poses.world_to_cam[i], poses.world_to_cam[j], np.radians(max_angle_deg))


def pair_agreement(graph: MatchGraph, poses: ModelPoses, pair: tuple[int, int],
                   max_angle_deg: float) -> float | None:
    """Fraction of the pair's inlier matches that agree with the poses (None: not both posed)."""
    ok = agreeing_matches(graph, poses, pair, max_angle_deg)
    return float(ok.mean()) if ok is not None and len(ok) else None
