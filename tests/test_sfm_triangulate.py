"""Points triangulated from known cameras (sfm/triangulate.py): a rendered scene with exact
cameras and its points dropped gets points on the surfaces its depth maps show; `ghsplat
train`'s path writes them beside the run, reuses them, and falls back when they are too few."""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest

pytest.importorskip("pycolmap")

from ghsplat_jax.data import load_dataset
from ghsplat_jax.data.images import read_pixels
from ghsplat_jax.sfm import triangulate as tri
from ghsplat_jax.synth import capture, config
from ghsplat_jax.synth import dataset as synth_dataset
from ghsplat_jax.synth import scene as synth_scene

VIEWS, W, H = 12, 320, 240


@pytest.fixture(scope="module")
def pointless(tmp_path_factory):
    """A rendered row end with exact cameras and no SfM points (its COLMAP model removed, so
    transforms.json is read)."""
    cfg = config.SceneConfig()
    world = synth_scene.generate_scene(cfg)
    cams = capture.capture_path(world, "handheld", VIEWS, row=0, width=W, height=H, seed=cfg.seed,
                                config=capture.PathConfig(end="x0"))
    out = synth_dataset.write_dataset(world, cams, tmp_path_factory.mktemp("syn") / "row", n_points=500,
                                      meshes=False)
    shutil.rmtree(out / "sparse")
    ds = load_dataset(out, split="all")
    assert ds.format == "transforms" and len(ds.points) == 0
    return ds


def _depth_errors(ds, points) -> np.ndarray:
    """Per point, the smallest |camera depth - rendered depth| over the views that see it."""
    best = np.full(len(points), np.inf)
    for i, v in enumerate(ds.train):
        depth = np.asarray(read_pixels(ds.root / "depth" / f"{i:05d}.exr"), np.float32)
        depth = depth[..., 0] if depth.ndim == 3 else depth
        w2c, K = np.asarray(v.camera.world_to_cam), np.asarray(v.camera.K)
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        uv = (cam @ K.T)[:, :2] / cam[:, 2:3]
        u, r = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        idx = np.flatnonzero((cam[:, 2] > 0) & (u >= 0) & (r >= 0) & (u < depth.shape[1]) & (r < depth.shape[0]))
        d = depth[r[idx], u[idx]]
        seen = d > 0
        best[idx[seen]] = np.minimum(best[idx[seen]], np.abs(cam[idx[seen], 2] - d[seen]))
    return best


def test_points_triangulated_from_known_cameras_lie_on_the_surface(pointless, tmp_path):
    points, colors, info = tri.triangulate_known_cameras(pointless.train, tmp_path / "tri")
    assert len(points) >= 40 and info["points"] == len(points) and info["views"] == VIEWS
    assert colors.shape == points.shape and 0.0 <= colors.min() and colors.max() <= 1.0
    assert info["mean_reprojection_px"] < 1.5
    # Verified pairs: those with at least 15 inlier matches, not every pair COLMAP tried (it keeps
    # an entry with 0 inliers for each).
    import pycolmap

    db = pycolmap.Database.open(str(tmp_path / "tri" / "database.db"))
    try:
        _, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    inliers = [len(np.asarray(g.inlier_matches).reshape(-1, 2)) for g in geometries]
    assert 0 < info["verified_pairs"] == sum(n >= 15 for n in inliers) <= len(inliers)
    err = _depth_errors(pointless, points)
    # scene extent ~2 m: half the points within 1 cm of the rendered surface, 80% within 10 cm
    assert np.median(err) < 0.01 and np.mean(err < 0.1) > 0.8, (np.median(err), np.mean(err < 0.1))


def test_train_path_writes_reuses_and_falls_back(pointless, tmp_path, monkeypatch, caplog):
    run = tmp_path / "run"
    with caplog.at_level(logging.INFO, logger="ghsplat.sfm"):
        ds = tri.with_triangulated_points(pointless, 20, run)
    assert len(ds.points) >= 20 and ds.point_colors.shape == ds.points.shape and ds.train is pointless.train
    assert (run / tri.TRIANGULATED_NAME).is_file() and "training starts from the" in caplog.text
    points, colors = tri.read_points_ply(run / tri.TRIANGULATED_NAME)
    np.testing.assert_allclose(points, ds.points)
    assert np.abs(colors - ds.point_colors).max() <= 1 / 255 + 1e-6

    def fail(*a, **k):
        raise AssertionError("matched again")

    monkeypatch.setattr(tri, "triangulate_known_cameras", fail)
    again = tri.with_triangulated_points(pointless, 20, run)  # a restarted run reuses the points
    np.testing.assert_allclose(again.points, ds.points)
    assert tri.with_triangulated_points(ds, 20, tmp_path / "other") is ds  # enough points already
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="ghsplat.sfm"):
        assert tri.with_triangulated_points(pointless, 10**6, run) is pointless
    assert "too few to start from" in caplog.text and "random points" in caplog.text

    def broken(views, work_dir, options=None):
        raise tri.TriangulationError(f"{work_dir}: no matches")

    monkeypatch.setattr(tri, "triangulate_known_cameras", broken)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="ghsplat.sfm"):
        assert tri.with_triangulated_points(pointless, 20, tmp_path / "fresh") is pointless
    assert "no matches" in caplog.text and "random points" in caplog.text


def test_ghsplat_train_triangulates_a_dataset_without_enough_points(tmp_path, monkeypatch):
    import argparse

    from ghsplat_jax.commands import train as train_cmd
    from ghsplat_jax.train.synthetic import cached_synthetic_dataset, write_transforms

    data = write_transforms(cached_synthetic_dataset(num_views=6, width=32, height=24, num_surfels=40, test_every=3,
                                                     num_points=200), tmp_path / "tiny")
    seen = {}
    monkeypatch.setattr(tri, "with_triangulated_points",
                        lambda dataset, min_points, run_dir: seen.update(points=len(dataset.points), min=min_points,
                                                                         run=run_dir) or dataset)
    import ghsplat_jax.eval.evaluate as ev

    monkeypatch.setattr(ev, "train_and_evaluate",
                        lambda config, out, **kw: seen.update(dataset=kw["dataset"]) or {"finished": False, "steps": 1})
    p = argparse.ArgumentParser()
    train_cmd.add_arguments(p)
    out = tmp_path / "run"
    assert train_cmd.main(p.parse_args(["--data", str(data), "--out", str(out), "--set", "init_min_points=500"])) == 0
    assert seen["min"] == 500 and seen["run"] == str(out) and seen["dataset"] is not None
    seen.clear()
    assert train_cmd.main(p.parse_args(["--data", str(data), "--out", str(out), "--no-triangulate"])) == 0
    assert "min" not in seen and seen["dataset"] is None
