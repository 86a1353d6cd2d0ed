"""Seeded pose noise for robustness studies: move every training camera by an exact fraction
of the scene extent (test views keep their true poses, so evaluation measures the damage).

    noisy = perturb_poses(dataset, 0.01, seed=0)   # each training centre moved 1% of the extent
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ghsplat_jax.core.camera import Camera


def perturb_poses(dataset, fraction: float, seed: int = 0, rotation_deg: float = 0.0):
    """A copy of `dataset` whose training cameras are moved by exactly `fraction` x
    `dataset.scene_extent` each, in a uniformly random direction (numpy Generator seeded by
    `seed`), and, when `rotation_deg` > 0, turned by exactly that angle about a random axis
    through their centre. Test views, points, extent and centre are left as they are."""
    if not fraction >= 0 or not rotation_deg >= 0:
        raise ValueError(f"pose noise must be >= 0, got fraction={fraction}, rotation_deg={rotation_deg}")
    if fraction == 0 and rotation_deg == 0:
        return dataset
    rng = np.random.default_rng([seed, 7919])  # its own stream: not the trainer's view order
    step = fraction * float(dataset.scene_extent)
    views = []
    for v in dataset.train:
        w2c = np.asarray(v.camera.world_to_cam, np.float64)
        R, t = w2c[:3, :3], w2c[:3, 3]
        centre = -R.T @ t
        d = rng.normal(size=3)
        centre = centre + step * d / np.linalg.norm(d)
        axis = rng.normal(size=3)
        if rotation_deg > 0:
            R = R @ _axis_angle(axis / np.linalg.norm(axis), np.deg2rad(rotation_deg)).T  # world-frame turn
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = R, -R @ centre
        cam = Camera(np.asarray(v.camera.K), out, v.camera.width, v.camera.height)
        views.append(dataclasses.replace(v, camera=cam))
    return dataclasses.replace(dataset, train=views)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
