"""End to end on a tiny transforms.json folder: `ghsplat train` writes every output,
`ghsplat eval` re-evaluates it, `ghsplat run` trains a scenes x variants set once."""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest
import tomli_w
from test_train_loop import CONFIG

from ghsplat_jax import cli
from ghsplat_jax.data.images import read_pixels
from ghsplat_jax.train.synthetic import cached_synthetic_dataset, write_transforms


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    ds = cached_synthetic_dataset(num_views=6, width=32, height=24, num_surfels=40, test_every=3, num_points=200)
    return write_transforms(ds, tmp_path_factory.mktemp("data") / "tiny")


def _config_file(path, **changes):
    values = {k: v for k, v in CONFIG.replace(**changes).to_dict().items() if k != "data"}
    path.write_text(tomli_w.dumps(values))
    return path


def _check_metrics(m, steps=30):
    for split in ("train", "test"):
        assert set(m[split]) >= {"psnr", "l1", "ssim", "num_views"}
        assert np.isfinite(m[split]["psnr"]) and 0 <= m[split]["l1"] <= 1 and -1 <= m[split]["ssim"] <= 1
    assert m["test"]["num_views"] == 2 and m["train"]["num_views"] == 4
    assert isinstance(m["num_gaussians"], int) and m["num_gaussians"] > 0
    assert m["train_seconds"] > 0 and m["steps"] == steps


def test_train_and_eval_commands(data_dir, tmp_path, capsys):
    out = tmp_path / "run"
    cfg = _config_file(tmp_path / "c.toml", background=(1.0, 1.0, 1.0))  # overridden below
    rc = cli.main(["train", "--data", str(data_dir), "--out", str(out), "--config", str(cfg), "--no-progress",
                   "--set", "background=[0.0, 0.0, 0.0]"])
    assert rc == 0
    outputs = ("config.toml", "stats.jsonl", "checkpoint.npz", "point_cloud.ply", "metrics.json", "per_view.json")
    for name in outputs:
        assert (out / name).is_file(), name
    m = json.loads((out / "metrics.json").read_text())
    _check_metrics(m)
    saved = tomllib.loads((out / "config.toml").read_text())
    assert saved["raster"]["background"] == [0.0, 0.0, 0.0]  # --set beats --config, in the run's one raster section
    renders = sorted(p.name for p in (out / "renders" / "test").iterdir())
    assert len(renders) == 2 * 4 and any(r.endswith("_depth.exr") for r in renders)
    # `ghsplat render` of the run's PLY uses the run's raster settings: the pixels eval wrote
    assert cli.main(["render", str(out / "point_cloud.ply"), "--out", str(tmp_path / "r"), "--data", str(data_dir),
                     "--split", "test"]) == 0
    rendered = sorted((tmp_path / "r").glob("*_rgb.png"))
    assert len(rendered) == 2
    for path in rendered:
        evaluated, = (out / "renders" / "test").glob("*" + path.name.replace("_rgb.png", ".png"))
        assert np.array_equal(read_pixels(path), read_pixels(evaluated)), path.name
    per_view = json.loads((out / "per_view.json").read_text())
    assert len(per_view) == 6 and all(v["render_seconds"] > 0 for v in per_view)
    # `ghsplat eval` reproduces the metrics from the saved files, and keeps what training recorded
    assert cli.main(["eval", str(out), "--no-progress"]) == 0
    again = json.loads((out / "metrics.json").read_text())
    assert again["code_revision"] == m["code_revision"] and again["machine"] == m["machine"]
    assert again["evaluated"]["code_revision"] and again["test"]["psnr"] == pytest.approx(m["test"]["psnr"], abs=0.05)
    (out / "metrics.json").unlink()
    assert cli.main(["eval", str(out), "--no-progress", "--report", str(tmp_path / "rep")]) == 0
    m2 = json.loads((out / "metrics.json").read_text())
    assert m2["test"]["psnr"] == pytest.approx(m["test"]["psnr"], abs=0.05)
    assert m2["num_gaussians"] == m["num_gaussians"] and m2["steps"] == 30
    assert (tmp_path / "rep" / "table1.md").is_file()
    # bad input: a clear message, not a traceback
    assert cli.main(["train", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x"), "--steps", "2"]) == 2
    assert "nowhere" in capsys.readouterr().err


def test_eval_of_a_stopped_run_writes_a_snapshot(data_dir, tmp_path, capsys):
    out = tmp_path / "run"
    cfg = _config_file(tmp_path / "c.toml")
    assert cli.main(["train", "--data", str(data_dir), "--out", str(out), "--config", str(cfg), "--no-progress",
                     "--until", "12"]) == 0
    assert not (out / "point_cloud.ply").exists() and not (out / "metrics.json").exists()
    assert cli.main(["eval", str(out), "--no-progress"]) == 0
    assert "snapshot at step 12" in capsys.readouterr().out
    snap = out / "snapshots" / "step_000012"
    m = json.loads((snap / "metrics.json").read_text())
    _check_metrics(m, steps=12)
    from ghsplat_jax.train.checkpoint import read_meta

    assert m["peak_rss_mb"] >= read_meta(out / "checkpoint.npz")["peak_rss_mb"] > 0  # training's peak counts
    assert m["device"] == "cpu"  # the tests run on the CPU (conftest), and a report tells a GPU's times apart
    assert (snap / "renders" / "test").is_dir()
    assert not (out / "metrics.json").exists()  # the run still counts as unfinished
    # a folder that has not started training: a clear error naming it
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "config.toml").write_text((out / "config.toml").read_text())
    assert cli.main(["eval", str(tmp_path / "empty"), "--no-progress"]) == 2
    assert "point_cloud.ply: missing and no checkpoint.npz" in capsys.readouterr().err


def test_run_command_skips_finished_runs(data_dir, tmp_path):
    values = {k: v for k, v in CONFIG.to_dict().items() if k != "data"}
    exp = tmp_path / "exp.toml"
    exp.write_text(tomli_w.dumps({
        "name": "tiny", "description": "test", "train": values, "scenes": [{"name": "tiny", "data": str(data_dir)}],
        "variants": [{"name": "default"}, {"name": "budget", "train": {"strategy": "budget", "max_surfels": 2048}}]}))
    out = tmp_path / "runs"
    assert cli.main(["run", str(exp), "--output", str(out), "--steps", "12"]) == 0
    for v in ("default", "budget"):
        _check_metrics(json.loads((out / "tiny" / v / "metrics.json").read_text()), steps=12)
    assert json.loads((out / "tiny" / "budget" / "metrics.json").read_text())["strategy"] == "budget"
    for name in ("results.md", "results.csv", "table1.md", "table1.csv", "psnr_vs_time.png", "psnr_vs_count.png"):
        assert (out / name).is_file(), name
    stamp = (out / "tiny" / "default" / "metrics.json").stat().st_mtime_ns
    assert cli.main(["run", str(exp), "--output", str(out), "--steps", "12"]) == 0  # all finished: no retraining
    assert (out / "tiny" / "default" / "metrics.json").stat().st_mtime_ns == stamp
    assert "| tiny | budget |" in (out / "results.md").read_text()
