"""A tiny synthetic scene for tests, demos and smoke runs: random surfels rendered from a
ring of cameras, returned as a Dataset (no files) or written as a transforms.json folder."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np


def random_scene(num: int = 80, seed: int = 0, radius: float = 1.0):
    """Opaque coloured surfels in a ball of `radius`, facing outwards."""
    from ghsplat_jax.core.surfels import make_surfels

    rng = np.random.default_rng(seed)
    means = rng.uniform(-radius, radius, (num, 3)) * np.array([1.0, 1.0, 0.6])
    quats = rng.normal(size=(num, 4))
    log_scales = np.log(rng.uniform(0.08, 0.25, (num, 2)) * radius)
    logits = np.full(num, 2.0)
    colors = rng.uniform(0.1, 0.9, (num, 3))
    from ghsplat_jax.core.sh import rgb_to_dc

    return make_surfels(means, quats, log_scales, logits, rgb_to_dc(colors), sh_degree=0)


def ring_cameras(num: int, width: int, height: int, distance: float = 3.5, fov: float = 50.0, seed: int = 0):
    from ghsplat_jax.core.camera import Camera, intrinsics, look_at

    rng = np.random.default_rng(seed + 1)
    cams = []
    for i in range(num):
        a = 2 * math.pi * i / num + rng.uniform(-0.1, 0.1)
        eye = [distance * math.cos(a), distance * math.sin(a), 0.8 + 0.3 * math.sin(3 * a)]
        cams.append(Camera(intrinsics(width, height, fov), look_at(eye, [0, 0, 0]), width, height))
    return cams


def synthetic_dataset(num_views: int = 8, width: int = 48, height: int = 32, num_surfels: int = 80, seed: int = 0,
                      background=(0.0, 0.0, 0.0), test_every: int = 4, num_points: int = 300):
    """A Dataset of rendered views; every `test_every`-th view is a test view; `points` are
    samples on the true surfels (a stand-in for SfM points) with their colours."""
    from ghsplat_jax.data import Dataset, View
    from ghsplat_jax.raster import RasterConfig, render

    scene = random_scene(num_surfels, seed)
    cfg = RasterConfig(background=tuple(background))
    views = []
    for i, cam in enumerate(ring_cameras(num_views, width, height, seed=seed)):
        out = render(scene, cam, cfg)
        views.append(View(f"view_{i:03d}", cam, np.asarray(out.rgb, np.float32), None))
    test = [v for i, v in enumerate(views) if i % test_every == 0]
    train = [v for i, v in enumerate(views) if i % test_every != 0]
    rng = np.random.default_rng(seed + 2)
    s = scene.to_numpy()
    idx = rng.integers(0, s.num, num_points)
    points = (s.means[idx] + rng.normal(0, 0.05, (num_points, 3))).astype(np.float32)
    from ghsplat_jax.core.sh import C0

    colors = np.clip(s.sh_dc[idx] * C0 + 0.5, 0, 1).astype(np.float32)
    centres = np.stack([np.asarray(v.camera.center) for v in train])
    center = centres.mean(0).astype(np.float32)
    extent = float(1.1 * np.max(np.linalg.norm(centres - center, axis=1)))
    return Dataset(root=Path("<synthetic>"), format="synthetic", train=train, test=test, points=points,
                   point_colors=colors, scene_extent=extent, scene_center=center,
                   background=tuple(float(b) for b in background), split="every", test_every=test_every)


def write_transforms(dataset, folder) -> Path:
    """Write a dataset's views as a NeRF-synthetic folder (transforms_{train,test}.json + PNGs)."""
    from ghsplat_jax.data.images import write_image
    from ghsplat_jax.io_utils import write_json

    folder = Path(folder)
    for split, views in (("train", dataset.train), ("test", dataset.test)):
        frames = []
        for v in views:
            (folder / split).mkdir(parents=True, exist_ok=True)
            write_image(folder / split / f"{v.name}.png", v.image)
            w2c = np.asarray(v.camera.world_to_cam, np.float64)
            c2w = np.linalg.inv(w2c)
            c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
            frames.append({"file_path": f"./{split}/{v.name}", "transform_matrix": c2w.tolist()})
        K = np.asarray(views[0].camera.K)
        angle = 2 * math.atan(0.5 * views[0].camera.width / float(K[0, 0]))
        write_json(folder / f"transforms_{split}.json", {"camera_angle_x": angle, "frames": frames})
    return folder


@functools.lru_cache(maxsize=4)
def cached_synthetic_dataset(**kwargs):
    """synthetic_dataset, memoised (tests share one; do not mutate it)."""
    return synthetic_dataset(**kwargs)
