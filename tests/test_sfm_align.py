"""Greenhouse alignment on synthetic rows with known up and row axes (no pycolmap needed)."""

from __future__ import annotations

import numpy as np
import pytest

from ghsplat_jax.core.camera import look_at
from ghsplat_jax.sfm.align import (
    AlignOptions,
    angle_deg,
    camera_centres,
    camera_up_hint,
    estimate_alignment,
    transform_points,
    transform_world_to_cam,
)


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def greenhouse_scene(rng, end_on=True, pitch_deg=20.0, ground=True, outliers=0.05):
    """A row along x (open end at +x) in the greenhouse frame: (world_to_cam, points)."""
    parts = []
    if ground:
        n = 1500
        parts.append(np.c_[rng.uniform(-5, 5, n), rng.uniform(-1.5, 1.5, n), rng.normal(0, 0.005, n)])
    n = 3000
    side = rng.choice([-0.7, 0.7], n)
    parts.append(np.c_[rng.uniform(-4.5, 4.5, n), side + rng.normal(0, 0.15, n), rng.uniform(0.1, 2.0, n)])
    points = np.concatenate(parts)
    k = int(outliers * len(points))
    points = np.concatenate([points, rng.uniform([-6, -3, -1], [6, 3, 3], (k, 3))])

    cams = []
    drop = np.tan(np.radians(pitch_deg))
    for x in np.linspace(-4.5, 4.5, 24):  # walking toward the open end
        for side in (-1.0, 1.0):
            eye = np.array([x, 0.0, 1.4]) + rng.normal(0, 0.02, 3)
            target = eye + np.array([0.0, side, -drop]) + rng.normal(0, 0.03, 3)
            cams.append(look_at(eye, target))
    if end_on:
        for y in (-0.3, 0.0, 0.3):
            eye = np.array([5.5, y, 1.5])
            cams.insert(0, look_at(eye, eye + np.array([-1.0, 0.0, -0.15])))
    return np.stack(cams).astype(float), points


def _disturb(rng, world_to_cam, points):
    """Move the scene by a random similarity; return its pieces and the moved scene."""
    rot, scale, shift = _random_rotation(rng), rng.uniform(0.2, 5.0), rng.normal(0, 10, 3)
    new_points = scale * points @ rot.T + shift
    new_w2c = world_to_cam.copy()
    new_w2c[:, :3, :3] = world_to_cam[:, :3, :3] @ rot.T
    new_w2c[:, :3, 3] = scale * world_to_cam[:, :3, 3] - np.einsum(
        "nij,j->ni", new_w2c[:, :3, :3], shift
    )
    return rot, scale, new_w2c, new_points


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_up_and_row_with_end_on_views(seed):
    rng = np.random.default_rng(seed)
    w2c, pts = greenhouse_scene(rng)
    rot, _, w2c_old, pts_old = _disturb(rng, w2c, pts)
    al = estimate_alignment(w2c_old, pts_old)
    assert al.up_source == "ground_plane" and al.sign_rule == "end_on_views"
    assert angle_deg(al.up, rot @ [0, 0, 1]) < 2.0
    assert angle_deg(al.row, rot @ [1, 0, 0]) < 2.0
    # The ground ends up at z = 0 and the plants above it.
    aligned = transform_points(al, pts_old)
    assert abs(np.median(aligned[:1500, 2])) < 0.02 * al.scale * 5
    assert np.median(aligned[1500:4500, 2]) > 0


def test_ground_plane_beats_pitched_cameras():
    """Cameras all pitched 30 degrees down: their up hint is off, the ground fit is not."""
    rng = np.random.default_rng(3)
    w2c, pts = greenhouse_scene(rng, pitch_deg=30.0)
    w2c = w2c[3::2]  # one side only, no end-on views: every camera pitched the same way
    rot, _, w2c_old, pts_old = _disturb(rng, w2c, pts)
    assert angle_deg(camera_up_hint(w2c_old), rot @ [0, 0, 1]) > 20.0
    al = estimate_alignment(w2c_old, pts_old)
    assert angle_deg(al.up, rot @ [0, 0, 1]) < 2.0
    assert angle_deg(al.row, rot @ [1, 0, 0]) < 2.0
    assert al.sign_rule == "capture_direction"


def test_capture_direction_sets_sign_and_reversal_flips_it():
    rng = np.random.default_rng(4)
    w2c, pts = greenhouse_scene(rng, end_on=False)
    rot, _, w2c_old, pts_old = _disturb(rng, w2c, pts)
    forward = estimate_alignment(w2c_old, pts_old)
    backward = estimate_alignment(w2c_old[::-1], pts_old)
    assert forward.sign_rule == backward.sign_rule == "capture_direction"
    assert angle_deg(forward.row, rot @ [1, 0, 0]) < 2.0
    assert angle_deg(backward.row, rot @ [-1, 0, 0]) < 2.0
    # End-on views from both ends (a loop round the row) are no evidence either way.
    w2c_loop, _ = greenhouse_scene(rng, end_on=False)
    eye_open, eye_closed = np.array([5.5, 0, 1.5]), np.array([-5.5, 0, 1.5])
    ends = [look_at(eye_open, eye_open + [-1, 0, -0.15])] * 3
    ends += [look_at(eye_closed, eye_closed + [1, 0, -0.15])] * 3
    loop = np.concatenate([w2c_loop, np.stack(ends)])
    assert estimate_alignment(loop, pts).sign_rule == "capture_direction"


def test_falls_back_to_camera_up_without_ground():
    rng = np.random.default_rng(5)
    w2c, pts = greenhouse_scene(rng, ground=False, pitch_deg=0.0, outliers=0.0)
    rot, _, w2c_old, pts_old = _disturb(rng, w2c, pts)
    al = estimate_alignment(w2c_old, pts_old)
    assert al.up_source == "camera_up"
    assert angle_deg(al.up, rot @ [0, 0, 1]) < 2.0
    assert angle_deg(al.row, rot @ [1, 0, 0]) < 2.0


def test_metric_scale_from_camera_height_and_known_distance():
    rng = np.random.default_rng(6)
    w2c, pts = greenhouse_scene(rng, outliers=0.0)
    _, _, w2c_old, pts_old = _disturb(rng, w2c, pts)
    true_height = np.median(camera_centres(w2c)[:, 2])
    al = estimate_alignment(w2c_old, pts_old, AlignOptions(camera_height=true_height))
    assert al.scale_source == "camera_height"
    aligned = transform_points(al, pts_old)
    # Back in metres: distances between points match the original scene.
    i, j = rng.integers(0, len(pts), (2, 200))
    ratio = np.linalg.norm(aligned[i] - aligned[j], axis=1) / np.linalg.norm(pts[i] - pts[j], axis=1)
    assert np.allclose(ratio, 1.0, atol=0.01)

    true_gap = np.linalg.norm(camera_centres(w2c)[3] - camera_centres(w2c)[40])
    al = estimate_alignment(w2c_old, pts_old, AlignOptions(known_distance=(3, 40, true_gap)))
    aligned_c = camera_centres(transform_world_to_cam(al, w2c_old))
    assert np.linalg.norm(aligned_c[3] - aligned_c[40]) == pytest.approx(true_gap, rel=1e-6)


def test_manual_rotation_yaw_and_flip():
    rng = np.random.default_rng(7)
    w2c, pts = greenhouse_scene(rng)
    rot, _, w2c_old, pts_old = _disturb(rng, w2c, pts)
    al = estimate_alignment(w2c_old, pts_old, AlignOptions(rotation=rot.T))
    assert al.up_source == "manual" and np.allclose(al.rotation, rot.T)
    turned = estimate_alignment(w2c_old, pts_old, AlignOptions(yaw_deg=90.0))
    assert angle_deg(turned.row, rot @ [0, -1, 0]) < 2.0  # old -y is the new +x
    flipped = estimate_alignment(w2c_old, pts_old, AlignOptions(flip=True))
    assert angle_deg(flipped.row, rot @ [-1, 0, 0]) < 2.0
    assert angle_deg(flipped.up, rot @ [0, 0, 1]) < 2.0


def test_cameras_and_points_move_together():
    """A point projects to the same pixel before and after the similarity."""
    rng = np.random.default_rng(8)
    w2c, pts = greenhouse_scene(rng)
    _, _, w2c_old, pts_old = _disturb(rng, w2c, pts)
    al = estimate_alignment(w2c_old, pts_old, AlignOptions(scale=2.5))
    w2c_new, pts_new = transform_world_to_cam(al, w2c_old), transform_points(al, pts_old)
    def project(cams, p):
        cam = np.einsum("nij,mj->nmi", cams[:, :3, :3], p) + cams[:, None, :3, 3]
        return cam[..., :2] / cam[..., 2:]
    assert np.allclose(project(w2c_old, pts_old[:50]), project(w2c_new, pts_new[:50]), atol=1e-6)
    assert np.allclose(np.linalg.det(w2c_new[:, :3, :3]), 1.0)


def test_rejects_bad_overrides():
    rng = np.random.default_rng(9)
    w2c, pts = greenhouse_scene(rng)
    with pytest.raises(ValueError, match="rotation"):
        estimate_alignment(w2c, pts, AlignOptions(rotation=np.diag([1.0, 1.0, -1.0])))
    with pytest.raises(ValueError, match="at most one"):
        estimate_alignment(w2c, pts, AlignOptions(scale=2.0, camera_height=1.0))
    with pytest.raises(ValueError, match="indices"):
        estimate_alignment(w2c, pts, AlignOptions(known_distance=(0, 999, 1.0)))


def test_robust_plane_refinement_ignores_outliers():
    """optimistix LM with a Cauchy loss: a 4-degree-off start lands on the true plane."""
    from ghsplat_jax.sfm.align import refine_plane

    rng = np.random.default_rng(10)
    normal = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    e1 = np.cross(normal, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    uv = rng.uniform(-3, 3, (800, 2))
    on_plane = uv[:, :1] * e1 + uv[:, 1:] * e2 + 2.0 * normal + rng.normal(0, 0.003, (800, 1)) * normal
    outliers = on_plane[:200] + rng.uniform(0.05, 0.3, (200, 1)) * normal  # low leaves, clutter
    points = np.concatenate([on_plane, outliers])
    start = normal + np.array([0.07, 0.0, 0.0])
    start /= np.linalg.norm(start)
    refined, offset = refine_plane(points, start, 2.0, loss_scale=0.02)
    assert angle_deg(refined, normal) < 0.2
    assert offset == pytest.approx(2.0, abs=0.01)
    # A plain least-squares fit on the same points is pulled up by the clutter.
    plain = np.linalg.svd(points - points.mean(0))[2][2]
    plain *= np.sign(plain @ normal)
    assert points.mean(0) @ plain - 2.0 > 0.02
