"""Evaluation's checks: views far below their split, the train-test gap and the structure
score that a missing subject cannot hide (no rendering)."""

from __future__ import annotations

import logging

import numpy as np

from ghsplat_jax.eval.evaluate import diagnose
from ghsplat_jax.eval.metrics import (
    colour_corrected_metrics,
    image_metrics,
    psnr_outliers,
    structure_mask,
    structure_metrics,
    summarize,
)


def _plant(h=48, w=64):
    """A thin green stem on black: the subject covers a few percent of the photo."""
    img = np.zeros((h, w, 3), np.float32)
    img[4:44, 30, 1] = 0.8
    img[20, 20:44, 1] = 0.6
    return img


def test_structure_psnr_exposes_a_missing_thin_subject():
    photo = _plant()
    empty = np.zeros_like(photo)  # the model rendered only the background
    whole = image_metrics(empty, photo)["psnr"]
    s = structure_metrics(empty, photo)
    assert whole > 20.0 and s["structure_psnr"] < 13.0 and whole - s["structure_psnr"] > 10.0
    assert s["structure_gain_db"] == 0.0  # the empty render is exactly the background: nothing gained
    # A render of the plant that is off by 0.1 everywhere on it gains, however small the plant is;
    # its whole-image PSNR minus structure PSNR is as large as the missing plant's.
    rough = np.where(photo > 0, photo - 0.1, 0.0).astype(np.float32)
    r = structure_metrics(rough, photo)
    assert r["structure_gain_db"] > 10.0 and image_metrics(rough, photo)["psnr"] - r["structure_psnr"] > 10.0
    assert s["structure_l1"] > 10 * image_metrics(empty, photo)["l1"] * 0.5
    mask = structure_mask(photo)
    assert mask[10, 30] and mask[10, 29] and not mask[10, 27] and not mask[2, 2]  # the stem and its edge
    assert (structure_mask(photo, dilate=1)[10, 28:33]).all()
    assert structure_metrics(photo, photo)["structure_psnr"] > 100.0  # a perfect render
    assert structure_metrics(empty, empty) == {}  # a flat photo has no structure
    alpha = np.zeros(photo.shape[:2], np.float32)
    alpha[:, 30] = 1.0
    assert (structure_mask(photo, alpha) == (alpha >= 0.5)).all()  # the foreground where alpha is given
    rows = [image_metrics(empty, photo) | s, image_metrics(empty, empty)]
    summary = summarize(rows)
    assert summary["structure_views"] == 1 and summary["structure_psnr"] == s["structure_psnr"]


def test_psnr_outliers_name_the_views_far_below_their_split():
    rows = [{"name": f"v{i}", "psnr": p} for i, p in enumerate([30.0, 30.4, 29.7, 30.2, 22.5, 29.9, 31.0])]
    out = psnr_outliers(rows)
    assert [o["name"] for o in out] == ["v4"] and abs(out[0]["below_median_db"] - 7.5) < 1e-9
    assert psnr_outliers(rows[:4]) == []  # within 3 dB: none
    spread = [{"name": f"v{i}", "psnr": p} for i, p in enumerate([20.0, 24.0, 28.0, 32.0, 36.0, 27.0])]
    assert psnr_outliers(spread) == []  # a wide split: 4 x MAD is the margin
    clean = [{"name": f"v{i}", "psnr": p} for i, p in enumerate([46.0, 46.2, 45.9, 46.1, 41.7, 43.0])]
    assert psnr_outliers(clean) == []  # far under the median, but rendered within 1.8% RMS of the photo
    assert [o["name"] for o in psnr_outliers(clean, clean_db=50.0)] == ["v4"]


def test_diagnose_warns_of_outliers_overfitting_and_a_missing_subject(caplog):
    rows = ([{"split": "train", "name": f"t{i}", "psnr": 36.0 + 0.1 * i} for i in range(5)]
            + [{"split": "train", "name": "bad_pose.jpg", "psnr": 25.0}]
            + [{"split": "test", "name": f"s{i}", "psnr": 26.0} for i in range(3)])
    metrics = {"train": {"psnr": 34.3, "structure_psnr": 30.0, "structure_gain_db": 14.0},
               "test": {"psnr": 26.0, "structure_psnr": 12.0, "structure_gain_db": 0.5}}
    with caplog.at_level(logging.WARNING, logger="ghsplat.eval"):
        out = diagnose(metrics, rows, where="RUN")
    assert out["outlier_views"]["train"][0]["name"] == "bad_pose.jpg" and out["outlier_views"]["test"] == []
    assert abs(out["train_test_gap_db"] - 8.3) < 1e-9
    assert out["missing_structure_db"] == {"test": 0.5}
    text = caplog.text
    assert "bad_pose.jpg (25.00 dB)" in text and "bad pose" in text
    assert "over-fits" in text and "--recipe auto" in text
    assert "misses what the photos show" in text
    assert len(out["warnings"]) == 3
    # A self-stopping run's advice names its held-out views' score instead of the recipe it already used.
    stopped = diagnose(metrics | {"stop": {"best_val_psnr": 40.09}}, rows, where="RUN")
    assert "held out to stop the run scored 40.09 dB" in stopped["warnings"][1]
    assert "--recipe auto" not in stopped["warnings"][1]
    # One whose checks read the training views (too few to hold some out) says that is why it missed it.
    blind = diagnose(metrics | {"stop": {"best_val_psnr": 40.09, "validation_views": []}}, rows, where="RUN")
    assert "too few training views to hold some out" in blind["warnings"][1]
    assert "held out to stop the run scored" not in blind["warnings"][1]
    calm = diagnose({"train": {"psnr": 30.0}, "test": {"psnr": 28.0}}, rows[:5])
    assert calm["warnings"] == [] and calm["train_test_gap_db"] == 2.0


def test_colour_corrected_psnr_takes_out_a_views_exposure_and_nothing_else():
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.05, 0.6, (24, 32, 3)).astype(np.float32)
    exposed = np.clip(photo * np.array([1.6, 1.5, 1.7]) + 0.02, 0, 1).astype(np.float32)  # brighter and tinted
    assert image_metrics(photo, exposed)["psnr"] < 15.0
    assert colour_corrected_metrics(photo, exposed)["psnr_cc"] > 50.0  # a gain and offset explain all of it
    # An error of the scene itself stays: noise no gain or offset can fit. Never below plain PSNR.
    noisy = np.clip(photo + rng.normal(0, 0.05, photo.shape), 0, 1).astype(np.float32)
    plain, corrected = image_metrics(noisy, photo)["psnr"], colour_corrected_metrics(noisy, photo)["psnr_cc"]
    assert plain <= corrected < plain + 0.5
    assert set(summarize([{"psnr": 20.0, "l1": 0.1, "ssim": 0.8, "psnr_cc": 22.0}])) >= {"psnr_cc"}
