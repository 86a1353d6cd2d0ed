"""benchmarks/analysis/run_progress.py: a run's windows, stalls, test curve and (when finished) its test metrics."""

import json

from benchmark_scripts import load_benchmark


def test_stalls_windows_and_metrics(tmp_path, monkeypatch):
    rp = load_benchmark("run_progress")
    monkeypatch.setattr(rp, "RESULTS", tmp_path / "results")
    run = tmp_path / "run"
    run.mkdir()
    elapsed, lines = 5.0, []  # a 5 s first step, 10 ms steps, a 3 s compile at step 1,200
    for step in range(1, 1501):
        elapsed += 3.0 if step == 1200 else 0.01 if step > 1 else 0.0
        lines.append(json.dumps(dict(step=step, elapsed_s=elapsed, num_surfels=100 + step, psnr=20.0)))
    (run / "stats.jsonl").write_text("\n".join(lines) + "\n{\"step\": 15")  # a line cut short by a stop
    (run / "config.toml").write_text('data = "x"\nsteps = 1500\n')
    (run / "metrics.json").write_text(json.dumps({"test": {"psnr": 25.0}}))
    (run / "test_curve.jsonl").write_text("".join(json.dumps(dict(step=s, elapsed_s=s / 100, psnr=20.0 + s / 500,
                                                                 l1=0.1, num_surfels=100 + s)) + "\n"
                                                  for s in (500, 1000, 1500)))
    assert rp.main([str(run), "--name", "p"]) == 0
    out = json.loads((tmp_path / "results" / "p.json").read_text())
    assert out["finished"] and out["first_step_seconds"] == 5.0
    assert out["stalls"] == dict(count=1, seconds=3.0, steps=[1200], step_seconds=[3.0])
    assert abs(out["windows"]["1000-1500"]["median_seconds_per_step"] - 0.01) < 1e-9
    assert out["metrics"]["test"]["psnr"] == 25.0 and (tmp_path / "results" / "p.png").is_file()
    assert out["test_curve"]["step"] == [500, 1000, 1500] and out["test_curve"]["psnr"] == [21.0, 22.0, 23.0]
