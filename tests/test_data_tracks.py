"""The checks of a dataset against its SfM points' tracks: cameras (data/tracks.py): exact poses
agree, poses moved after the SfM are flagged with the views named, a large SfM residual of its
own is not, and datasets it cannot read stay unjudged; exposure (data/exposure.py): photos
brighter or darker than the rest where they see the same points are named, with their ratio."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ghsplat_jax.core.camera import Camera, intrinsics, look_at, project_points
from ghsplat_jax.data import load_dataset
from ghsplat_jax.data.exposure import exposure_outliers, exposure_warning
from ghsplat_jax.data.images import read_image, write_image
from ghsplat_jax.data.perturb import perturb_poses
from ghsplat_jax.data.tracks import POSE_DISAGREEMENT_DEG, pose_disagreement, track_agreement

pytest.importorskip("pycolmap")

W, H = 64, 48


def _write_model(root, views=8, points=60, error=0.0, seed=0):
    """A COLMAP text model whose tracks are the points' exact projections (ERROR `error` px)."""
    from ghsplat_jax.synth.dataset import write_colmap_text

    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-1, 1, (points, 3))
    K = intrinsics(W, H, 60.0)
    cams, names, tracks = [], [], []
    for i in range(views):
        a = 2 * np.pi * i / views
        cam = Camera(K, look_at([4 * np.cos(a), 4 * np.sin(a), 1.0], [0, 0, 0]), W, H)
        xy, z = project_points(xyz, cam.K, cam.world_to_cam)
        idx = np.flatnonzero((z > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < W) & (xy[:, 1] >= 0) & (xy[:, 1] < H))
        cams.append(cam)
        names.append(f"{i:03d}.png")
        tracks.append((idx, xy[idx]))
        write_image(root / "images" / names[-1], np.full((H, W, 3), 128, np.uint8))
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    write_colmap_text(model, cams, names, xyz, np.full((points, 3), 128, np.uint8), tracks)
    if error:
        text = (model / "points3D.txt").read_text().replace(" 128 128 128 0.0 ", f" 128 128 128 {error} ")
        (model / "points3D.txt").write_text(text)
    return root


def test_exact_poses_agree_and_moved_ones_are_named(tmp_path):
    ds = load_dataset(_write_model(tmp_path / "scene"), split="all")
    exact = track_agreement(ds)
    assert exact.views == 8 and exact.median_deg < 1e-4 and not exact.disagrees
    assert pose_disagreement(ds, "scene") is None
    moved = perturb_poses(ds, 0.02, seed=1)
    a = track_agreement(moved)
    assert a.disagrees and a.median_deg > POSE_DISAGREEMENT_DEG and a.stored_deg == 0
    message = pose_disagreement(moved, "scene")
    assert message.startswith("scene: the cameras disagree with the dataset's SfM points")
    assert a.worst[0][0] in message and "--pose-refine" in message


def test_a_large_residual_of_the_sfm_itself_is_not_flagged(tmp_path):
    """Poses moved by an angle the SfM's own residual matches: not a disagreement."""
    ds = load_dataset(_write_model(tmp_path / "scene", error=3.0), split="all")
    moved = perturb_poses(ds, 0.02, seed=1)
    a = track_agreement(moved)
    assert a.median_deg > POSE_DISAGREEMENT_DEG and a.stored_deg > a.median_deg / 3 and not a.disagrees


def test_datasets_it_cannot_judge_stay_unjudged(tmp_path):
    ds = load_dataset(_write_model(tmp_path / "scene"), split="all")
    assert track_agreement(dataclasses.replace(ds, format="transforms")) is None
    renamed = dataclasses.replace(ds, train=[dataclasses.replace(v, name="x" + v.name) for v in ds.train])
    assert track_agreement(renamed) is None  # no view of the model
    distorted = tmp_path / "scene" / "sparse" / "0" / "cameras.txt"
    lines = distorted.read_text().splitlines()
    cid, _, w, h, fx, fy, cx, cy = lines[-1].split()
    distorted.write_text("\n".join(lines[:-1] + [f"{cid} OPENCV {w} {h} {fx} {fy} {cx} {cy} 0.01 0 0 0"]) + "\n")
    assert track_agreement(ds) is None  # tracks in distorted pixels: not comparable with undistorted views


def _paint_points(root, gains: dict[int, float], seed=0):
    """Rewrite the model's photos: each point a 3x3 patch of its own grey level (the same in every
    view) on a grey background, photo i exposed `gains[i]` times brighter in linear light."""
    from ghsplat_jax.data.exposure import linear_luminance

    ds = load_dataset(root, split="all")
    albedo = np.random.default_rng(seed).uniform(0.1, 0.4, len(ds.points))  # linear light
    for i, view in enumerate(ds.train):
        xy, z = project_points(ds.points, view.camera.K, view.camera.world_to_cam)
        linear = np.full((H, W), 0.05)
        for (x, y), a in zip(np.floor(xy[z > 0]).astype(int), albedo[z > 0]):
            linear[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2] = a
        linear *= gains.get(i, 1.0)
        srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
        pixels = np.repeat(np.round(255 * np.clip(srgb, 0, 1)), 3).reshape(H, W, 3)
        write_image(view.image_path, pixels.astype(np.uint8))
        assert abs(linear_luminance(read_image(view.image_path)[0]).mean() / linear.mean() - 1) < 0.05
    return root


def test_photos_exposed_unlike_the_rest_are_named_with_their_ratio(tmp_path, monkeypatch):
    even = load_dataset(_paint_points(_write_model(tmp_path / "even", points=120), {}), split="all")
    assert exposure_outliers(even) == [] and exposure_warning(even, "scene") is None
    odd = load_dataset(_paint_points(_write_model(tmp_path / "odd", points=120), {2: 1.5, 3: 1.4}), split="all")
    found = exposure_outliers(odd)
    assert [name for _, name, _ in found] == ["002.png", "003.png"]
    assert [round(ratio, 1) for _, _, ratio in found] == [1.5, 1.4]
    message = exposure_warning(odd, "scene")
    assert message.startswith("scene: 2 photo(s) exposed unlike the rest") and "002.png (train) 1.4" in message
    assert exposure_outliers(dataclasses.replace(odd, format="transforms")) is None  # no tracks: not told
    # Where the config asks for it, a flagged training photo switches exposure compensation on.
    from ghsplat_jax.train.config import TrainConfig
    from ghsplat_jax.train.trainer import with_flagged_exposure

    asked = TrainConfig(exposure_compensation_when_flagged=True)
    assert with_flagged_exposure(asked, odd).exposure_compensation
    assert not with_flagged_exposure(asked, even).exposure_compensation
    assert not with_flagged_exposure(TrainConfig(), odd).exposure_compensation  # not asked: as it was
    test_only = dataclasses.replace(odd, train=[v for v in odd.train if v.name not in ("002.png", "003.png")],
                                    test=[v for v in odd.train if v.name in ("002.png", "003.png")])
    assert not with_flagged_exposure(asked, test_only).exposure_compensation  # flagged test photos only
    assert "Exposure compensation is on" in exposure_warning(odd, "scene", compensating=True)
    # A run asks twice (whether to compensate, then to warn); the exposures are fitted once.
    from ghsplat_jax.data import exposure

    fits = []
    monkeypatch.setattr(exposure, "fit_exposures", lambda *a, **k: fits.append(1) or np.zeros(k["num_views"]))
    again = dataclasses.replace(odd)
    assert with_flagged_exposure(asked, again) is asked and exposure_warning(again, "scene") is None
    assert len(fits) == 1
