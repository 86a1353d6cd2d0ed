"""Initial points inside a subject's silhouettes (train/carve.py): on a plain background they
fill the subject's visual hull, coloured by its pixels; a textured background gets none."""

from __future__ import annotations

import dataclasses

import numpy as np

from ghsplat_jax.train.carve import subject_mask, subject_points
from ghsplat_jax.train.synthetic import cached_synthetic_dataset


def test_points_fill_the_subjects_hull_on_a_plain_background():
    ds = cached_synthetic_dataset(num_views=12, width=64, height=48, num_surfels=12, test_every=6, num_points=0)
    rng = np.random.default_rng(0)
    points, colors = subject_points(ds.train, np.zeros(3), 2.5, 4000, rng)
    assert len(points) == 4000 and colors.shape == (4000, 3) and np.isfinite(points).all()
    # The scene: surfels with centres in [-1, 1] x [-1, 1] x [-0.6, 0.6], each up to 0.25 across;
    # the hull of ten views around it stays near that box: 16% of the 5 m cube searched holds 85%+.
    inside = (np.abs(points[:, :2]) < 1.5).all(axis=1) & (np.abs(points[:, 2]) < 1.1)
    assert inside.mean() > 0.85, inside.mean()
    assert colors.max() > 0.2 and colors.min() >= 0.0  # the subject's colours, not the black background
    # Each kept point lands on the subject in the views that see it.
    mask, plain = subject_mask(ds.train[0].image)
    assert plain and 0.02 < mask.mean() < 0.6


def test_a_textured_background_gets_no_carving():
    ds = cached_synthetic_dataset(num_views=12, width=64, height=48, num_surfels=40, test_every=6, num_points=0)
    rng = np.random.default_rng(1)
    noisy = [dataclasses.replace(v, image=rng.uniform(0, 1, np.shape(v.image)).astype(np.float32)) for v in ds.train]
    assert subject_points(noisy, np.zeros(3), 2.5, 1000, rng) is None
    alpha = np.zeros(np.shape(ds.train[0].image)[:2], np.float32)
    alpha[10:20, 10:30] = 1.0
    mask, plain = subject_mask(noisy[0].image, alpha)  # an alpha channel decides, whatever the colours
    assert plain and mask[15, 20] and not mask[40, 60]
