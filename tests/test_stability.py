"""The stability study (experiments/stability.toml, ghsplat_jax/experiments/stability.py) and the
pose-noise perturbation it trains from, on tiny inputs."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from ghsplat_jax.data.perturb import perturb_poses
from ghsplat_jax.experiments import stability
from ghsplat_jax.experiments.runner import load_experiment
from ghsplat_jax.io_utils import json_safe
from ghsplat_jax.train.config import ConfigError, TrainConfig
from ghsplat_jax.train.synthetic import cached_synthetic_dataset

ROOT = Path(__file__).resolve().parent.parent
TOML = ROOT / "experiments" / "stability.toml"


def _centres(views):
    return np.stack([np.asarray(v.camera.center, np.float64) for v in views])


@pytest.mark.parametrize("fraction", [0.005, 0.01, 0.02])
def test_pose_noise_moves_every_training_camera_by_the_exact_fraction(fraction):
    ds = cached_synthetic_dataset(num_views=8, width=16, height=12, num_surfels=10)
    noisy = perturb_poses(ds, fraction, seed=3)
    moved = np.linalg.norm(_centres(noisy.train) - _centres(ds.train), axis=1)
    np.testing.assert_allclose(moved, fraction * ds.scene_extent, rtol=1e-4)
    for a, b in zip(noisy.train, ds.train):  # translation only: orientation and intrinsics kept
        np.testing.assert_allclose(np.asarray(a.camera.rotation), np.asarray(b.camera.rotation), atol=1e-6)
        np.testing.assert_array_equal(np.asarray(a.camera.K), np.asarray(b.camera.K))
    assert noisy.test is ds.test and noisy.scene_extent == ds.scene_extent
    again = perturb_poses(ds, fraction, seed=3)
    np.testing.assert_array_equal(_centres(again.train), _centres(noisy.train))  # seeded
    other = perturb_poses(ds, fraction, seed=4)
    assert not np.allclose(_centres(other.train), _centres(noisy.train))
    assert perturb_poses(ds, 0.0) is ds


def test_pose_noise_rotation_is_the_exact_angle():
    ds = cached_synthetic_dataset(num_views=8, width=16, height=12, num_surfels=10)
    noisy = perturb_poses(ds, 0.0, seed=0, rotation_deg=2.0)
    for a, b in zip(noisy.train, ds.train):
        r = np.asarray(a.camera.rotation, np.float64) @ np.asarray(b.camera.rotation, np.float64).T
        angle = np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))
        assert angle == pytest.approx(2.0, abs=0.02)
        np.testing.assert_allclose(np.asarray(a.camera.center), np.asarray(b.camera.center), atol=1e-5)


def test_pose_noise_config_field(tmp_path):
    from ghsplat_jax.train.run_dir import load_training_data
    from ghsplat_jax.train.synthetic import write_transforms

    with pytest.raises(ConfigError, match="pose_noise"):
        TrainConfig(pose_noise=-0.01)
    folder = write_transforms(cached_synthetic_dataset(num_views=8, width=16, height=12, num_surfels=10),
                              tmp_path / "ds")
    clean = load_training_data(TrainConfig(data=str(folder)))
    noisy = load_training_data(TrainConfig(data=str(folder), pose_noise=0.01, seed=1))
    moved = np.linalg.norm(_centres(noisy.train) - _centres(clean.train), axis=1)
    np.testing.assert_allclose(moved, 0.01 * clean.scene_extent, rtol=1e-4)
    np.testing.assert_array_equal(_centres(noisy.test), _centres(clean.test))


def test_both_presets_load_and_the_quick_one_covers_every_family():
    full = load_experiment(TOML)
    quick = load_experiment(TOML, preset="quick")
    assert full.kind == quick.kind == "stability"
    assert quick.results == Path("benchmarks/results/stability/quick")
    for exp in (full, quick):
        cases = stability.check_cases(exp.spec["cases"])
        assert {c["family"] for c in cases} == set(stability.FAMILIES)
    quick_train = [c for c in quick.spec["cases"] if c["family"] == "train"]
    assert any(c.get("pose_noise") for c in quick_train) and any(c.get("views") for c in quick_train)
    assert any(c.get("init") for c in quick_train) and quick.spec["train"]["steps"] <= 300
    assert quick.spec["prepare"]["width"] <= 64


def test_case_entries_are_checked():
    with pytest.raises(stability.StudyError, match="unknown keys"):
        stability.check_cases([{"family": "raster", "name": "x", "scene": "opaque", "colour": 1}])
    with pytest.raises(stability.StudyError, match="family"):
        stability.check_cases([{"family": "nope", "name": "x"}])
    with pytest.raises(stability.StudyError, match="twice"):
        stability.check_cases([{"family": "raster", "name": "x"}] * 2)


def test_a_silent_sfm_failure_is_a_fail_marked_not_detected():
    case = {"family": "sfm", "name": "c"}
    wrong = {"method": "none", "status": "ok", "registered": 40, "views": 40, "centre_rmse_pct": 12.0}
    row = stability._sfm_row(case, wrong, "test")
    assert row["result"] == "fail" and row["detection"].startswith("NOT DETECTED") and row["exit_code"] == 0
    folded = dict(wrong, status="folded", fold_reasons=["r1"])
    row = stability._sfm_row(case, folded, "test")
    assert row["result"] == "fail" and "exit 4" in row["detection"] and "looks folded (r1)" in row["message"]
    partial = dict(wrong, status="partial", registered=10, centre_rmse_pct=0.1)
    row = stability._sfm_row(case, partial, "test")
    assert row["result"] == "fail" and "exit 3" in row["detection"] and "only 10 of 40" in row["message"]
    good = dict(wrong, centre_rmse_pct=0.5)
    assert stability._sfm_row(case, good, "test")["result"] == "pass"


@pytest.mark.slow  # a recorded SfM row and render cases through the whole study: the file's longest test
def test_study_runs_cases_and_writes_one_table(tmp_path):
    """Recorded SfM rows and two render cases through run_study: reports written, a broken case is a
    fail row naming the error, never a pass."""
    exp = dataclasses.replace(load_experiment(TOML, preset="quick"), output=tmp_path / "runs",
                              results=tmp_path / "results")
    # the file names the recorded rows relative to the repository root, where `ghsplat run` starts
    assert (ROOT / exp.spec["sfm_recorded"]).is_file()
    exp.spec["sfm_recorded"] = str(ROOT / exp.spec["sfm_recorded"])
    exp.spec["cases"] = [
        {"family": "sfm_recorded", "name": "ident", "recorded": "identical-5-handheld-s0", "methods": ["none"]},
        {"family": "raster", "name": "sparse", "scene": "sparse", "compositor": "carried", "width": 24,
         "height": 16},
        {"family": "raster", "name": "broken", "scene": "no-such-scene"},
    ]
    result = stability.run_study(exp)
    rows = {r["case"]: r for r in result["rows"]}
    assert rows["ident"]["result"] == "fail" and "exit 4" in rows["ident"]["detection"]
    assert rows["ident"]["source"].startswith("recorded:")
    assert rows["sparse"]["result"] == "pass" and rows["sparse"]["max_abs_rgb"] < 1e-3
    assert rows["broken"]["result"] == "fail" and "no-such-scene" in rows["broken"]["error"]
    assert [name for name, _ in result["failed"]] == ["broken"]
    md = (tmp_path / "results" / "stability.md").read_text()
    assert "| family | case | method | result | error | detection | message | source |" in md
    import json

    report = json.loads((tmp_path / "results" / "stability.json").read_text())
    assert report["machine"]["cpu_count"] and len(report["rows"]) == 3
    assert report["code_revision"] and {r["code_revision"] for r in report["rows"]} == {report["code_revision"]}
    assert f"the code revision each case ran at: {report['code_revision']} (3 rows)" in md
    assert (tmp_path / "results" / "stability.csv").read_text().count("\n") == 4

    # a partial rerun (ghsplat run --only) replaces its case's rows and keeps the others'
    exp.spec["cases"][1]["width"] = 32
    rerun = stability.run_study(exp, only={"sparse"})
    assert [r["case"] for r in rerun["rows"]] == ["ident", "sparse", "broken"]
    assert rerun["rows"][1]["seconds"] != rows["sparse"]["seconds"]  # computed again (new key)
    assert rerun["rows"][0] == json.loads(json.dumps(json_safe(rows["ident"])))
    assert len(json.loads((tmp_path / "results" / "stability.json").read_text())["rows"]) == 3


@pytest.mark.slow  # test_raster_robustness.py checks culling and test_raster_reference.py exactness in make test
def test_degenerate_scene_matches_the_reference_and_counts_the_culled():
    # 64x48 shows the surfel whose 3-sigma ellipse crosses the camera plane on the horizon rows:
    # there the filter centre is the projected mean in both renderers
    case = {"family": "raster", "name": "d", "scene": "degenerate", "compositor": "carried"}
    (row,) = stability.run_raster(case, None)
    assert row["finite"] and row["num_invalid"] == 3 and row["num_culled_near"] >= 1
    assert "num_invalid = 3" in row["detection"]
    assert row["result"] == "pass" and row["max_abs_alpha"] < 1e-3, row["error"]


def test_cached_sfm_rows_follow_their_source(tmp_path, monkeypatch):
    """A case's cached rows are reused only while what they came from is unchanged: the
    recorded benchmark file for sfm_recorded, the SfM defaults for live SfM cases."""
    recorded = tmp_path / "results.json"
    recorded.write_text('{"rows": []}')
    ctx = stability.Context(tmp_path, tmp_path, None, recorded=recorded)
    case = {"family": "sfm_recorded", "name": "r", "recorded": "x"}
    before = stability._key(case, ctx)
    assert stability._key(case, ctx) == before
    recorded.write_text('{"rows": [1]}')
    assert stability._key(case, ctx) != before
    live = {"family": "sfm", "name": "s"}
    from ghsplat_jax.sfm import pipeline

    default = stability._key(live, None)
    import functools

    monkeypatch.setattr(pipeline, "SfmOptions", functools.partial(pipeline.SfmOptions, sift_peak_threshold=0.002))
    assert stability._key(live, None) != default
