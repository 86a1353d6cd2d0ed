"""The shared real datasets load with the expected views, splits, sizes and geometry.

Heavily downscaled to stay fast; skipped when ../shared/datasets is absent.
"""

from __future__ import annotations

import numpy as np
import pytest

from ghsplat_jax.data import DatasetWarning, load_dataset
from ghsplat_jax.data.dataset import read_scene
from ghsplat_jax.data.splits import split_indices
from ghsplat_jax.paths import datasets_root

ROOT = datasets_root()


def _require(name):
    if not (ROOT / name).is_dir():
        pytest.skip(f"shared dataset {name} not found under {ROOT} (set GHSPLAT_DATASETS)")
    return ROOT / name


def _check_views(ds, width, height):
    for view in ds.views:
        assert view.image.shape == (height, width, 3) and view.image.dtype == np.float32
        assert (view.camera.width, view.camera.height) == (width, height)
        assert 0.0 <= view.image.min() and view.image.max() <= 1.0 and view.image.std() > 0.02
        R = np.asarray(view.camera.world_to_cam, np.float64)[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)


def _visible_fraction(ds, view):
    """Fraction of the SfM points in front of the camera and inside its image."""
    cam = view.camera
    w2c, K = np.asarray(cam.world_to_cam, np.float64), np.asarray(cam.K, np.float64)
    x = ds.points.astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    front = x[:, 2] > 0
    uv = (x[front] @ K.T)[:, :2] / x[front, 2:]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height)
    return front.mean(), inside.mean()


def test_llff_fern():
    # images_8 (504x378) further downscaled by 2: hwf is for 4032x3024, so downscale 16
    ds = load_dataset(_require("llff_fern"), downscale=16)
    assert ds.format == "llff" and (len(ds.train), len(ds.test)) == (17, 3)
    assert [v.name for v in ds.test] == ["image000.png", "image008.png", "image016.png"]
    _check_views(ds, 252, 189)
    np.testing.assert_allclose(np.asarray(ds.train[0].camera.K)[0, 0], 3260.526 / 16, rtol=1e-4)
    assert len(ds.points) > 5000 and ds.point_colors.shape == ds.points.shape
    # the reordered LLFF axes agree with the COLMAP world of sparse/0/points3D.bin:
    # the points lie in front of every camera and project inside its image
    for view in ds.views:
        front, inside = _visible_fraction(ds, view)
        assert front > 0.99 and inside > 0.8, (view.name, front, inside)
    assert 1.0 < ds.scene_extent < 20.0


def test_nerf_synthetic_lego():
    root = _require("nerf_synthetic_lego")
    # the split is decided before any pixel is read: count it without decoding 125 PNGs
    spec = read_scene(root, "transforms", 8)
    train, test, rule = split_indices([f.name for f in spec.frames], spec.split)
    assert rule == "dataset" and (len(train), len(test)) == (100, 25)
    ds = load_dataset(root, downscale=8, max_views=13)
    assert ds.format == "transforms" and ds.split == "dataset"
    assert (len(ds.train), len(ds.test)) == (13, 13)
    assert ds.train[0].name == "train/r_0.png" and ds.test[0].name == "test/r_0.png"
    _check_views(ds, 100, 100)
    K = np.asarray(ds.train[0].camera.K)
    f = 0.5 * 100 / np.tan(0.6911112 / 2)
    np.testing.assert_allclose(K, [[f, 0, 50], [0, f, 50], [0, 0, 1]], rtol=1e-5)
    view = ds.train[0]
    assert view.alpha is not None and view.alpha.shape == (100, 100)
    assert np.allclose(view.image[view.alpha == 0], 1.0)  # transparent pixels show the white background
    # cameras sit on a sphere of radius ~4 around the object and look at its centre
    centres = np.array([np.asarray(v.camera.center) for v in ds.views])
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 4.03, atol=0.05)
    for v in ds.views:
        w2c = np.asarray(v.camera.world_to_cam, np.float64)
        origin = w2c[:3, 3]  # the world origin in camera coordinates: in front, near the image centre
        assert origin[2] > 3.5 and np.hypot(*(origin[:2] / origin[2])) < 0.05


def test_ngp_fox_skips_missing_frames_with_a_warning():
    root = _require("ngp_fox")
    with pytest.warns(DatasetWarning, match=r"skipping 17 frame\(s\).*images/0005.jpg.*images/0113.jpg"):
        spec = read_scene(root, "transforms", 8)
    names = [f.name for f in spec.frames]
    train, test, rule = split_indices(names, spec.split)
    assert len(names) == 50 and (len(train), len(test), rule) == (43, 7, "every")
    assert [names[i] for i in test][:2] == ["images/0001.jpg", "images/0012.jpg"]
    # decoding and undistorting 50 full-size JPEGs takes seconds: check the pixels of a few
    with pytest.warns(DatasetWarning):
        ds = load_dataset(root, downscale=8, max_views=3)
    assert ds.format == "transforms" and (len(ds.train), len(ds.test)) == (3, 3)
    _check_views(ds, 135, 240)
    # undistorted with k1, k2, p1, p2: a new pinhole K near fl_x / 8
    K = np.asarray(ds.test[0].camera.K, np.float64)
    assert abs(K[0, 0] - 1375.52 / 8) < 0.1 * 1375.52 / 8 and abs(K[0, 2] - 554.558 / 8) < 5


def test_lund_door_colmap_text_model():
    ds = load_dataset(_require("lund_door"), downscale=8)
    assert ds.format == "colmap" and (len(ds.train), len(ds.test)) == (10, 2)
    assert [v.name for v in ds.test] == ["DSC_0001.JPG", "DSC_0009.JPG"]
    _check_views(ds, 162, 242)
    assert len(ds.points) == 11384
    for view in ds.views:
        front, inside = _visible_fraction(ds, view)
        assert front > 0.99 and inside > 0.6, (view.name, front, inside)


def test_lund_door_matches_pycolmap():
    pycolmap = pytest.importorskip("pycolmap")
    root = _require("lund_door")
    rec = pycolmap.Reconstruction(str(root / "colmap_ground_truth"))
    ds = load_dataset(root, downscale=8, split="all", max_views=3)
    by_name = {im.name: im for im in rec.images.values()}
    for view in ds.train:
        expected = by_name[view.name].cam_from_world().matrix()
        np.testing.assert_allclose(np.asarray(view.camera.world_to_cam)[:3], expected, atol=1e-5)
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    np.testing.assert_allclose(np.sort(ds.points[:, 0]), np.sort(xyz[:, 0]), atol=1e-4)
