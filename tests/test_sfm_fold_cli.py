"""`ghsplat sfm` refuses a folded model: exit status 4, advice, diagnostics in sfm_report.json.

The fast test forces the fold check's verdict on llff_fern (wiring: exit code, report,
advice); the slow one lets plain pycolmap fold a real row of identical plants and checks
that the fold check catches it.
"""

from __future__ import annotations

import dataclasses
import json

import pytest

from ghsplat_jax import cli
from ghsplat_jax.paths import datasets_root

pycolmap = pytest.importorskip("pycolmap")
FERN = datasets_root() / "llff_fern" / "images_8"


def _row(out, plants: int, views: int, width: int, height: int, identical: bool = True):
    pytest.importorskip("trimesh")
    pytest.importorskip("embreex")
    from ghsplat_jax.synth import capture, config, dataset, scene

    cfg = config.SceneConfig(seed=0)
    cfg = cfg.replace(
        layout=dataclasses.replace(cfg.layout, rows=1, plants_per_row=plants, identical_plants=identical),
        ground=dataclasses.replace(cfg.ground, margin=1.5, texture_tile=3.0),
        render=dataclasses.replace(cfg.render, texture_size=512),
    )
    world = scene.generate_scene(cfg)
    cams = capture.capture_path(world, "handheld", views, row=0, width=width, height=height, seed=0)
    return dataset.write_dataset(world, cams, out, n_points=200, meshes=False)


@pytest.mark.skipif(not FERN.exists(), reason=f"shared dataset not found at {FERN} (set GHSPLAT_DATASETS)")
def test_a_flagged_model_exits_4_with_advice(tmp_path, capsys, monkeypatch):
    from ghsplat_jax.sfm import folds

    images = tmp_path / "images"
    images.mkdir()
    for src in sorted(FERN.glob("*.png"))[:12]:
        (images / src.name).symlink_to(src)  # link, never copy, the dataset
    real = folds.diagnose

    def flag(*args, **kwargs):
        report = real(*args, **kwargs)
        return {**report, "fold_suspected": True, "reasons": ["forced by the test"]}

    monkeypatch.setattr(folds, "diagnose", flag)
    out = tmp_path / "sfm"
    code = cli.main(["sfm", "--images", str(images), "--out", str(out), "--max-size", "320",
                     "--no-undistort", "--align", "none", "--disambiguate", "none", "--quiet"])
    captured = capsys.readouterr()
    assert code == 4
    assert "looks folded (forced by the test)" in captured.err and "do not train on it" in captured.err
    report = json.loads((out / "sfm_report.json").read_text())
    assert report["status"] == "folded"
    assert any("folded" in tip for tip in report["advice"])
    diagnostics = report["fold_diagnostics"]
    assert {"neighbour_pairs", "order_jumps", "rotation_chain", "long_range_pairs", "opposite_tracks",
            "match_graph_components", "num_models", "reasons"} <= set(diagnostics)
    assert report["disambiguation"] == {"method": "none"}

    # --no-fold-check: the same diagnostics, reported, do not fail the run
    code = cli.main(["sfm", "--images", str(images), "--out", str(out), "--max-size", "320",
                     "--no-undistort", "--align", "none", "--disambiguate", "none", "--quiet",
                     "--no-fold-check", "--min-registered-fraction", "0"])
    assert code == 0
    assert json.loads((out / "sfm_report.json").read_text())["fold_diagnostics"]["fold_suspected"]


def test_order_needs_a_capture_order(tmp_path, capsys):
    code = cli.main(["sfm", "--images", str(tmp_path), "--out", str(tmp_path / "out"),
                     "--disambiguate", "order", "--capture-order", "none"])
    assert code == 1
    assert "--disambiguate order needs the capture order" in capsys.readouterr().err


@pytest.mark.slow
def test_identical_plants_fold_is_caught(tmp_path, capsys):
    """Five identical plants, 36 hand-held views: plain pycolmap folds the row (about 40% of the
    extent off); the fold check must say so, and --disambiguate auto must not report ok with
    a wrong model."""
    from ghsplat_jax.sfm.evaluate import compare_models

    data = _row(tmp_path / "data", plants=5, views=36, width=480, height=360)
    truth = pycolmap.Reconstruction(str(data / "sparse" / "0"))
    out = tmp_path / "plain"
    code = cli.main(["sfm", "--images", str(data / "images"), "--out", str(out), "--max-size", "480",
                     "--no-undistort", "--align", "none", "--disambiguate", "none", "--quiet"])
    report = json.loads((out / "sfm_report.json").read_text())
    error = compare_models(pycolmap.Reconstruction(str(out / "distorted" / "sparse" / "0")), truth)
    if error["centre_error_max_rel"] > 0.05:
        assert code == 4 and report["status"] == "folded"
        assert report["fold_diagnostics"]["neighbour_pairs"]["num_contradicted"] > 0
    # auto: the plain model, re-mapped through the order filter when flagged; never ok-but-wrong
    out = tmp_path / "auto"
    code = cli.main(["sfm", "--images", str(data / "images"), "--out", str(out), "--max-size", "480",
                     "--no-undistort", "--align", "none", "--quiet"])
    report = json.loads((out / "sfm_report.json").read_text())
    error = compare_models(pycolmap.Reconstruction(str(out / "distorted" / "sparse" / "0")), truth)
    assert report["disambiguation"]["method"] == "auto"
    assert code == 0 or report["status"] in ("folded", "partial")
    if report["status"] == "ok":
        assert error["centre_error_max_rel"] < 0.05
