"""`ghsplat run --stop-at N` and the reports of stopped runs; reported runs are not trained
again without --retrain; metrics.json names the evaluation's checks."""

from __future__ import annotations

import json
import shutil

import numpy as np
from test_train_loop import CONFIG

from ghsplat_jax.eval.lpips import weights_path
from ghsplat_jax.experiments import runner
from ghsplat_jax.experiments.report import table1_markdown
from ghsplat_jax.experiments.runner import collect, load_experiment, run_experiment
from ghsplat_jax.train.run_dir import has_checkpoint, read_metrics
from ghsplat_jax.train.synthetic import cached_synthetic_dataset, write_transforms

TWO = '''name = "e"
output = "{out}"
[[scenes]]
name = "a"
data = "da"
[[scenes]]
name = "b"
data = "db"
'''


def _fake_checkpoint(folder, step):
    folder.mkdir(parents=True, exist_ok=True)
    meta = np.frombuffer(json.dumps({"step": step}).encode(), np.uint8)
    np.savez(folder / "checkpoint.npz", meta_json=meta)


def _fake_metrics(folder, psnr):
    folder.mkdir(parents=True, exist_ok=True)
    split = {"psnr": psnr, "l1": 0.02, "ssim": 0.9, "num_views": 3}
    (folder / "metrics.json").write_text(json.dumps({"train": split, "test": split, "num_gaussians": 1000,
                                                     "train_seconds": 10.0, "steps": 300}))


def test_a_stopped_run_keeps_a_marked_row_in_every_report(tmp_path):
    f = tmp_path / "e.toml"
    f.write_text(TWO.format(out=(tmp_path / "runs").as_posix()) + "[train]\nsteps = 300\n")
    exp = load_experiment(f)
    a, b = exp.runs
    _fake_metrics(a.out_dir, 30.0)
    _fake_checkpoint(b.out_dir, 120)  # stopped by --stop-at 120 (or interrupted)
    rows, reports = collect(exp)
    assert [(r["scene"], r["status"]) for r in rows] == [("a", "finished"), ("b", "stopped at step 120 of 300")]
    assert rows[1]["steps"] == 120 and rows[1]["psnr"] is None
    md = (exp.results / "results.md").read_text()
    assert "stopped at step 120 of 300" in md and "1 of 2 runs have not finished" in md
    assert "stopped at step 120 of 300" in (exp.results / "results.csv").read_text()
    saved = json.loads((exp.results / "results.json").read_text())["rows"]
    assert saved[1]["status"] == "stopped at step 120 of 300"
    t1 = (exp.results / "table1.md").read_text()
    assert "| b | - | - | - | - | 120 | stopped at step 120 of 300 |" in t1 and "not final" in t1
    assert "PSNR 30.00-30.00 dB" in t1  # the ranges hold finished runs only
    # its folder lost, the row kept from the report stays marked
    shutil.rmtree(b.out_dir)
    assert [r["status"] for r in collect(exp)[0]] == ["finished", "stopped at step 120 of 300"]
    # a report of finished runs only has no status column in Table 1
    assert "status" not in table1_markdown(rows[:1])


def test_reported_runs_are_not_trained_again_unless_retrain(tmp_path, monkeypatch, caplog):
    f = tmp_path / "e.toml"
    f.write_text(TWO.format(out=(tmp_path / "runs").as_posix()))
    exp = load_experiment(f)
    exp.results.mkdir(parents=True, exist_ok=True)
    (exp.results / "results.json").write_text(json.dumps({"rows": [
        {"scene": "a", "variant": "default", "psnr": 30.0, "steps": 30000},                 # before statuses: finished
        {"scene": "b", "variant": "default", "psnr": None, "status": "stopped at step 5 of 300"}]}))
    trained = []
    monkeypatch.setattr(runner, "train_and_evaluate",
                        lambda config, out_dir, resume, **kw: trained.append((out_dir.parent.name, kw)))
    monkeypatch.setattr(runner, "collect", lambda exp: ([], []))
    with caplog.at_level("INFO", logger="ghsplat.run"):
        run_experiment(exp)
    assert trained == [("b", {})]  # a stopped row is not a finished one
    assert "a/default: no metrics.json or checkpoint" in caplog.text and "--retrain" in caplog.text
    trained.clear()
    run_experiment(exp, retrain=True, until=7)
    assert trained == [("a", {"until": 7}), ("b", {"until": 7})]


def test_stop_at_trains_to_the_step_then_the_run_resumes_and_evaluation_names_its_checks(tmp_path):
    ds = cached_synthetic_dataset(num_views=6, width=32, height=24, num_surfels=40, test_every=3, num_points=200)
    data = write_transforms(ds, tmp_path / "tiny")
    overrides = {k: v for k, v in CONFIG.to_dict().items() if k not in ("data", "strategy", "max_surfels")}
    overrides.update(data=str(data), steps=12, checkpoint_every=6, downscale=1.0, save_test_renders=False)
    f = tmp_path / "e.toml"
    f.write_text(f'name = "e"\noutput = "{(tmp_path / "runs").as_posix()}"\n[[scenes]]\nname = "s"\ndata = "x"\n')
    exp = load_experiment(f, overrides=overrides)
    (run,) = exp.runs
    result = run_experiment(exp, until=6)
    assert result["failed"] == [] and has_checkpoint(run.out_dir) and not run.finished
    assert [r["status"] for r in result["rows"]] == ["stopped at step 6 of 12"]
    result = run_experiment(exp)
    assert result["failed"] == [] and [r["status"] for r in result["rows"]] == ["finished"]
    assert result["rows"][0]["structure_psnr"] is not None  # the results table shows the structure score
    m = read_metrics(run.out_dir)
    assert m["steps"] == 12
    assert set(m["outlier_views"]) == {"train", "test"} and isinstance(m["warnings"], list)
    assert m["train_test_gap_db"] == m["train"]["psnr"] - m["test"]["psnr"]
    assert "structure_psnr" in m["test"] and "missing_structure_db" in m
    if weights_path() is not None:  # LPIPS on the test views only, and in the results table
        assert m["test"]["lpips"] > 0 and "lpips" not in m["train"] and result["rows"][0]["lpips"] == m["test"]["lpips"]


def test_a_run_without_enough_points_starts_from_triangulated_ones(tmp_path, monkeypatch):
    from ghsplat_jax.sfm import triangulate

    ds = cached_synthetic_dataset(num_views=6, width=32, height=24, num_surfels=40, test_every=3, num_points=200)
    data = write_transforms(ds, tmp_path / "tiny")
    f = tmp_path / "e.toml"
    f.write_text(f'name = "e"\noutput = "{(tmp_path / "runs").as_posix()}"\n[train]\ninit_min_points = 500\n'
                 f'[[scenes]]\nname = "s"\ndata = "{data.as_posix()}"\n')
    exp = load_experiment(f)
    calls, given = [], []
    monkeypatch.setattr(triangulate, "with_triangulated_points",
                        lambda dataset, n, out: calls.append((n, out)) or "triangulated")
    monkeypatch.setattr(runner, "train_and_evaluate", lambda config, out_dir, resume, **kw: given.append(kw))
    monkeypatch.setattr(runner, "collect", lambda exp: ([], []))
    run_experiment(exp)
    assert calls == [(500, exp.runs[0].out_dir)] and given == [{"dataset": "triangulated"}]
    _fake_checkpoint(exp.runs[0].out_dir, 3)  # resuming: the checkpoint holds the surfels
    run_experiment(exp)
    assert len(calls) == 1 and given[-1] == {}


def test_stop_at_needs_a_positive_step(tmp_path, capsys):
    from ghsplat_jax import cli

    f = tmp_path / "e.toml"
    f.write_text(TWO.format(out=(tmp_path / "runs").as_posix()))
    assert cli.main(["run", str(f), "--stop-at", "0"]) == 2
    assert "--stop-at must be a step >= 1" in capsys.readouterr().err


def test_list_names_a_reported_run_whose_folder_is_gone(tmp_path, capsys):
    from ghsplat_jax import cli

    f = tmp_path / "e.toml"
    f.write_text(TWO.format(out=(tmp_path / "runs").as_posix()))
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "results.json").write_text(json.dumps({"rows": [{"scene": "a", "variant": "default"}]}))
    assert cli.main(["run", str(f), "--list"]) == 0
    out = capsys.readouterr().out
    assert "a/default: reported (its folder is gone" in out and "b/default: todo" in out
