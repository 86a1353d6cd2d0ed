"""Small random scenes and cameras shared by the rasterizer tests."""

import numpy as np

import ghsplat_jax as gs


def random_scene(n, seed=0, opacity=(0.05, 0.3), scale=(0.03, 0.15), degree=1):
    r = np.random.default_rng(seed)
    means = r.uniform(-1, 1, (n, 3)) * [1, 1, 0.5]
    op = r.uniform(*opacity, n)
    k = (degree + 1) ** 2 - 1
    return gs.make_surfels(means, r.normal(size=(n, 4)), np.log(r.uniform(*scale, (n, 2))),
                           np.log(op / (1 - op)), r.normal(0, 0.5, (n, 3)), r.normal(0, 0.2, (n, k, 3)),
                           degree)


def camera(width=48, height=32, eye=(0.0, -3.5, 1.0), target=(0.0, 0.0, 0.0), fov=60.0):
    return gs.Camera(K=gs.intrinsics(width, height, fov), world_to_cam=gs.look_at(eye, target),
                     width=width, height=height)


def psnr(a, b):
    return float(10 * np.log10(1.0 / max(np.mean((np.asarray(a, np.float64) - b) ** 2), 1e-30)))
