"""Depth and normal error against the ground truth of a synth scene (eval/geometry.py): surfels
laid on the ray-cast surface of a view and rendered by the rasterizer score near zero, the same
surfels pushed off it score what they were moved by, and datasets without ground truth have none."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import ghsplat_jax as gs
from ghsplat_jax.data.dataset import load_dataset
from ghsplat_jax.eval.geometry import geometry_errors, ground_truth
from ghsplat_jax.eval.metrics import summarize
from ghsplat_jax.raster.render import render
from ghsplat_jax.synth import capture, config, dataset, scene

W, H = 64, 48


@pytest.fixture(scope="module")
def synth_view(tmp_path_factory):
    cfg = config.SceneConfig(seed=3)
    cfg = cfg.replace(layout=dataclasses.replace(cfg.layout, rows=1, plants_per_row=2),
                      plant=dataclasses.replace(cfg.plant, leaves=(4, 5)),
                      render=dataclasses.replace(cfg.render, texture_size=32))
    s = scene.generate_scene(cfg)
    cams = capture.capture_path(s, "handheld", 2, row=0, width=W, height=H, seed=2)
    root = dataset.write_dataset(s, cams, tmp_path_factory.mktemp("synth") / "row", n_points=100, fps=None)
    view = load_dataset(root, split="all").train[0]
    return root, view, ground_truth(root, view.name, W, H)


def _surfels_on(view, depth, normal, push=0.0, tilt_deg=0.0):
    """One opaque surfel per surface pixel, at its ray-cast point moved `push` along the camera
    axis, facing its true normal turned by `tilt_deg` towards the camera, a pixel wide."""
    K, w2c = np.asarray(view.camera.K, np.float64), np.asarray(view.camera.world_to_cam, np.float64)
    i, j = np.nonzero(depth > 0)
    z = depth[i, j].astype(np.float64) + push
    cam_pts = np.stack([(j + 0.5 - K[0, 2]) / K[0, 0] * z, (i + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1)
    c2w = np.linalg.inv(w2c)
    means = cam_pts @ c2w[:3, :3].T + c2w[:3, 3]
    n = normal[i, j].astype(np.float64)
    to_camera = c2w[:3, 3] - means
    across = to_camera - np.sum(to_camera * n, axis=1, keepdims=True) * n  # perpendicular to n: the turn is
    across /= np.linalg.norm(across, axis=1, keepdims=True) + 1e-12       # exactly tilt_deg, and never away
    t = np.radians(tilt_deg)
    n = n * np.cos(t) + across * np.sin(t)
    q = np.stack([1 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], 1)  # turns +z onto n
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    scale = np.log(z / K[0, 0])[:, None].repeat(2, 1)
    return gs.make_surfels(means, q, scale, np.full(len(z), 6.0))


def _errors(view, truth, **moved):
    out = render(_surfels_on(view, *truth, **moved), view.camera)
    return geometry_errors(np.asarray(out.median_depth), np.asarray(out.normal), np.asarray(out.alpha), *truth)


def test_the_truth_is_found_at_the_loaded_size_and_only_in_a_synth_folder(synth_view, tmp_path):
    root, view, (depth, normal) = synth_view
    assert depth.shape == (H, W) and normal.shape == (H, W, 3) and (depth > 0).mean() > 0.3
    hit = depth > 0
    assert np.allclose(np.linalg.norm(normal[hit], axis=-1), 1.0, atol=1e-3) and not normal[~hit].any()
    small = ground_truth(root, view.name, W // 2, H // 2)
    assert small[0].shape == (H // 2, W // 2) and np.array_equal(small[0], depth[1::2, 1::2])
    assert ground_truth(tmp_path, view.name, W, H) is None and ground_truth(None, view.name, W, H) is None


def test_surfels_on_the_true_surface_score_near_zero_and_moved_ones_score_the_move(synth_view):
    _, view, truth = synth_view
    exact = _errors(view, truth)
    assert exact["geometry_covered"] > 0.9
    # Where two surfaces meet, a pixel blends both surfels' normals: a few degrees on average.
    assert exact["depth_abs_err"] < 1e-3 and exact["normal_err_deg"] < 6.0, exact
    pushed = _errors(view, truth, push=0.1)
    assert pushed["depth_abs_err"] == pytest.approx(0.1, abs=0.01), pushed
    tilted = _errors(view, truth, tilt_deg=20.0)  # within the blends' share of 20 degrees per pixel
    assert abs(tilted["normal_err_deg"] - 20.0) < exact["normal_err_deg"] + 1.0, (tilted, exact)


def test_errors_of_given_maps_and_their_summary():
    depth = np.full((4, 4), 2.0, np.float32)
    depth[0] = 0  # sky
    normal = np.zeros((4, 4, 3), np.float32)
    normal[..., 2] = 1
    alpha = np.ones((4, 4), np.float32)
    alpha[1] = 0.2  # uncovered surface
    tilted = normal.copy()
    tilted[..., 1], tilted[..., 2] = np.sin(np.radians(30)), np.cos(np.radians(30))
    e = geometry_errors(depth + 0.25, 0.5 * tilted, alpha, depth, normal)  # alpha-weighted normal: any length
    assert e == pytest.approx({"geometry_covered": 2 / 3, "depth_abs_err": 0.25, "normal_err_deg": 30.0}, abs=1e-4)
    assert "depth_abs_err" not in geometry_errors(None, normal, alpha, depth, normal)
    assert geometry_errors(depth, normal, np.zeros_like(alpha), depth, normal) == {}
    base = {"psnr": 20, "l1": 0.1, "ssim": 0.5}
    s = summarize([base | e, base])  # a view the model leaves uncovered has no geometry errors
    assert s["geometry_views"] == 1 and s["depth_abs_err"] == pytest.approx(0.25)
    assert "geometry_views" not in summarize([base])


def test_evaluation_reports_the_errors_of_a_synth_scene(synth_view, tmp_path):
    from ghsplat_jax.eval.evaluate import evaluate
    from ghsplat_jax.train.config import TrainConfig

    root, view, truth = synth_view
    data = load_dataset(root, split="every", test_every=2)  # 00000 (the laid view) tests, 00001 trains
    assert [v.name for v in data.test] == [view.name]
    cfg = TrainConfig(data=str(root), progress=False, save_test_renders=False, eval_lpips=False)
    m = evaluate(_surfels_on(view, *truth, push=0.1), data, cfg, tmp_path)
    assert m["test"]["geometry_views"] == 1 and m["test"]["depth_abs_err"] == pytest.approx(0.1, abs=0.01)
    assert m["train"]["geometry_views"] == 1 and 0 < m["train"]["geometry_covered"] <= 1
    assert {"depth_abs_err", "normal_err_deg"} <= set(m["train"])


def test_a_model_in_its_own_frame_is_scored_in_the_scenes_through_the_recorded_similarity(synth_view, tmp_path):
    """An SfM model of a synth folder's photos has its own frame and scale: with the similarity
    onto the exact cameras in its sfm_report.json, its depth and normals are carried into the
    scene's frame and score as the same surfels do there (metres and degrees, not model units)."""
    import json
    import os

    from ghsplat_jax.eval.geometry import truth_source
    from ghsplat_jax.scene.transform import similarity, transform_camera

    root, view, truth = synth_view
    scale, angle = 2.5, np.radians(70.0)
    rot = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    shift = np.array([0.3, -1.0, 0.2])
    sfm = tmp_path / "sfm"
    (sfm / "sparse" / "0").mkdir(parents=True)
    assert truth_source(sfm) is None  # no report: no ground truth
    (sfm / "sfm_report.json").write_text(json.dumps({"accuracy": {
        "reference": os.path.relpath(root / "sparse" / "0", sfm / "sparse" / "0"),  # as compare_model_dirs
        "to_reference": {"scale": scale, "rotation": rot.tolist(), "translation": shift.tolist()}}}))
    found, s, r = truth_source(sfm)
    assert found == root and s == scale and np.allclose(r, rot)
    assert ground_truth(sfm, view.name, W, H)[0].shape == (H, W)
    # The same surfels and camera in the model's frame: x_model = R^T (x_scene - t) / scale.
    inverse = dict(scale=1.0 / scale, M=rot.T, t=-rot.T @ shift / scale)
    surfels = similarity(_surfels_on(view, *truth), **inverse)
    cam = gs.Camera(K=view.camera.K, world_to_cam=transform_camera(view.camera.world_to_cam, **inverse),
                    width=W, height=H)
    out = render(surfels, cam)
    exact = _errors(view, truth)
    carried = geometry_errors(np.asarray(out.median_depth), np.asarray(out.normal), np.asarray(out.alpha), *truth,
                              scale=s, rotation=r)
    assert carried["depth_abs_err"] < 2e-3 and abs(carried["normal_err_deg"] - exact["normal_err_deg"]) < 0.5
    raw = geometry_errors(np.asarray(out.median_depth), np.asarray(out.normal), np.asarray(out.alpha), *truth)
    assert raw["depth_abs_err"] > 0.5 and raw["normal_err_deg"] > exact["normal_err_deg"] + 5.0  # read as it is: wrong
