"""The pycolmap pipeline end to end on the shared datasets (small images to stay fast)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ghsplat_jax import cli
from ghsplat_jax.paths import datasets_root
from ghsplat_jax.sfm.evaluate import compare_models, umeyama

pycolmap = pytest.importorskip("pycolmap")

FERN = datasets_root() / "llff_fern" / "images_8"
LUND = datasets_root() / "lund_door"
needs = lambda path: pytest.mark.skipif(  # noqa: E731
    not path.exists(), reason=f"shared dataset not found at {path} (set GHSPLAT_DATASETS)"
)


def _noise_image(path, seed):
    import cv2

    rng = np.random.default_rng(seed)
    cv2.imwrite(str(path), rng.integers(0, 256, (300, 400, 3), dtype=np.uint8))


def _no_nans(obj):
    if isinstance(obj, float):
        assert math.isfinite(obj)
    elif isinstance(obj, dict):
        for v in obj.values():
            _no_nans(v)
    elif isinstance(obj, list):
        for v in obj:
            _no_nans(v)


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.linalg.det(q)
    scale, rot, t = umeyama(src, 2.5 * src @ q.T + [1.0, -2.0, 3.0])
    assert scale == pytest.approx(2.5) and np.allclose(rot, q) and np.allclose(t, [1, -2, 3])


@pytest.mark.slow
@needs(FERN)
def test_fern_registers_all_and_reports_partial_runs(tmp_path, capsys):
    """All 20 fern images register; two noise images do not, and the run says so."""
    images = tmp_path / "images"
    images.mkdir()
    for src in sorted(FERN.glob("*.png")):
        (images / src.name).symlink_to(src)  # link, never copy, the dataset
    _noise_image(images / "zz_noise_a.png", 1)
    _noise_image(images / "zz_noise_b.png", 2)
    out = tmp_path / "out"
    code = cli.main([
        "sfm", "--images", str(images), "--out", str(out), "--max-size", "320",
        "--min-registered-fraction", "0.95", "--quiet",
    ])
    captured = capsys.readouterr()
    assert code == 3  # 20 of 22 is below 0.95
    assert "Registered 20 of 22" in captured.out
    assert "zz_noise_a.png" in captured.out and "--matching sequential" in captured.out
    # the refusal says why: pycolmap could not read the two noise images
    assert "Likely cause:\n  - unreadable: pycolmap could not read 2 photos (zz_noise_a.png, zz_noise_b.png)" \
        in captured.err
    assert "Why so few images registered:" in captured.out

    report = json.loads((out / "sfm_report.json").read_text())
    _no_nans(report)
    assert report["status"] == "partial"
    assert report["num_registered"] == 20 and report["num_images"] == 22
    assert report["unregistered_images"] == ["zz_noise_a.png", "zz_noise_b.png"]
    assert report["mean_reprojection_error_px"] < 1.5
    assert report["track_length"]["mean"] > 3
    assert set(report["timings_s"]) >= {"extraction", "matching", "mapping", "second_estimate", "alignment",
                                        "undistortion"}
    # the global mapper's second estimate of the forward-facing capture agrees with the model
    second = report["second_estimate"]
    assert second["verdict"] == "agree" and second["num_common"] == 20, second
    assert "Second estimate: the global mapper's second estimate agrees on 20 views" in captured.out

    # OUT is ready for training: PINHOLE model of the 20 undistorted images, aligned.
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert model.num_reg_images() == 20
    assert {cam.model.name for cam in model.cameras.values()} == {"PINHOLE"}
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(
        im.name for im in model.images.values()
    )
    assert max(report["cameras"][0]["width"], report["cameras"][0]["height"]) == 320
    points = np.array([p.xyz for p in model.points3D.values()])
    matrix = np.array(report["alignment"]["matrix"])
    assert np.allclose(matrix[3], [0, 0, 0, 1])
    assert np.allclose(np.median(points[:, :2], axis=0), 0.0, atol=1e-6)  # origin at the median


@pytest.mark.slow
@needs(LUND)
def test_lund_door_matches_reference_poses(tmp_path):
    from ghsplat_jax.sfm.pipeline import SfmOptions, run_sfm

    out = tmp_path / "out"
    options = SfmOptions(max_size=400, align="none", undistort=False, progress=False)
    report = run_sfm(LUND / "images", out, options)
    assert report["status"] == "ok" and report["num_registered"] == 12
    assert not (out / "sparse").exists()  # no undistortion asked for
    reference = pycolmap.Reconstruction(str(LUND / "colmap_ground_truth"))
    result = compare_models(pycolmap.Reconstruction(str(out / "distorted" / "sparse" / "0")), reference)
    print(f"lund_door: centre error max {100 * result['centre_error_max_rel']:.3f}% of extent, "
          f"rotation error max {result['rotation_error_max_deg']:.3f} deg")
    assert result["num_cameras"] == 12
    assert result["centre_error_max_rel"] < 0.01
    assert result["rotation_error_max_deg"] < 1.0


def test_bad_inputs_name_the_problem(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    assert cli.main(["sfm", "--images", str(missing), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert str(missing) in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli.main(["sfm", "--images", str(empty), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert "no image files" in capsys.readouterr().err
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    assert cli.main(["sfm", "--images", str(text), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert "not a folder of images or a video" in capsys.readouterr().err


def test_unmatchable_images_fail_plainly(tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    for k in range(3):
        _noise_image(images / f"noise_{k}.png", k)
    (images / "truncated.png").write_bytes(b"\x89PNG not really")
    out = tmp_path / "out"
    stale = out / "sparse" / "0"
    stale.mkdir(parents=True)  # an earlier run's model must not survive a failed run
    code = cli.main(["sfm", "--images", str(images), "--out", str(out), "--quiet", "--max-size", "400"])
    assert code == 3
    report = json.loads((out / "sfm_report.json").read_text())
    assert report["status"] == "failed" and report["num_registered"] == 0
    assert report["unregistered_images"] == ["noise_0.png", "noise_1.png", "noise_2.png", "truncated.png"]
    assert report["unreadable_images"] == ["truncated.png"]
    assert [d["cause"] for d in report["diagnosis"]] == ["unreadable", "too few matches"]
    assert report["diagnosis"][0]["images"] == ["truncated.png"]
    assert report["diagnosis"][1]["detail"] == "no two photos share a verified match"
    assert not stale.exists()
    assert report["advice"]
    assert "Registered 0 of 4" in capsys.readouterr().out


def test_align_config_file_and_flags(tmp_path):
    import argparse

    from ghsplat_jax.commands import sfm as command

    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    config = tmp_path / "align.toml"
    config.write_text("[align]\nrotation = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]\nflip = true\n"
                      "camera_height = 1.2\n")
    base = ["--images", "in", "--out", "out", "--align-config", str(config)]
    options = command.build_options(parser.parse_args(base))
    assert np.allclose(options.align_options.rotation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert options.align_options.flip and options.align_options.camera_height == 1.2
    # Flags override the file.
    options = command.build_options(parser.parse_args(base + ["--camera-height", "0.5", "--align-yaw", "30",
                                                              "--known-distance", "a.jpg", "b.jpg", "2.5"]))
    assert options.align_options.camera_height == 0.5 and options.align_options.yaw_deg == 30.0
    assert options.known_distance_names == ("a.jpg", "b.jpg", 2.5)
    config.write_text("roll = 3\n")
    with pytest.raises(ValueError, match="unknown keys"):
        command.build_options(parser.parse_args(base))


def test_sift_peak_threshold_flag():
    import argparse

    from ghsplat_jax.commands import sfm as command
    from ghsplat_jax.sfm.pipeline import SfmError, SfmOptions

    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    base = ["--images", "in", "--out", "out"]
    assert command.build_options(parser.parse_args(base)).sift_peak_threshold == SfmOptions().sift_peak_threshold
    options = command.build_options(parser.parse_args(base + ["--sift-peak-threshold", "0.002"]))
    assert options.sift_peak_threshold == 0.002
    with pytest.raises(SfmError, match="sift_peak_threshold"):
        SfmOptions(sift_peak_threshold=0.0).validate()


def test_spatial_matching_without_gps_says_so(tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    for k in range(2):
        _noise_image(images / f"noise_{k}.png", k)
    code = cli.main(["sfm", "--images", str(images), "--out", str(tmp_path / "out"), "--quiet",
                     "--matching", "spatial", "--max-size", "200"])
    assert code == 1
    assert "needs position priors (EXIF GPS)" in capsys.readouterr().err


@needs(FERN)
def test_global_mapper_registers_fern(tmp_path):
    """GLOMAP through pycolmap.global_mapping, on a quick subset at small size."""
    from ghsplat_jax.sfm.pipeline import SfmOptions, run_sfm

    images = tmp_path / "images"
    images.mkdir()
    for src in sorted(FERN.glob("*.png"))[:10]:
        (images / src.name).symlink_to(src)
    options = SfmOptions(mapper="global", max_size=300, align="none", undistort=False, progress=False)
    report = run_sfm(images, tmp_path / "out", options)
    assert report["status"] == "ok" and report["num_registered"] == 10
    assert report["mean_reprojection_error_px"] < 1.5
