"""The check of a dataset's cameras against its SfM points (data/tracks.py): exact poses agree,
poses moved after the SfM are flagged with the views named, a large SfM residual of its own is
not, and datasets it cannot read stay unjudged."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ghsplat_jax.core.camera import Camera, intrinsics, look_at, project_points
from ghsplat_jax.data import load_dataset
from ghsplat_jax.data.images import write_image
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
