"""`ghsplat run --executor ray`: the quick preset's two smallest runs (fern, default and budget)
as Ray tasks on a local 2-CPU Ray instance, retargeted at a tiny synthetic scene and a few steps
so the test stays quick. One run is interrupted beforehand and must resume from its checkpoint;
a second pass must skip both finished runs."""

from __future__ import annotations

from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

from test_train_loop import CONFIG

from ghsplat_jax.experiments.runner import load_experiment, run_experiment
from ghsplat_jax.train.run_dir import STATS_NAME, has_checkpoint, read_metrics
from ghsplat_jax.train.synthetic import cached_synthetic_dataset, write_transforms

QUICK = Path(__file__).parents[1] / "experiments" / "quick_cpu.toml"


@pytest.fixture
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR")
    yield
    ray.shutdown()


@pytest.mark.slow  # a local Ray cluster running training tasks
def test_quick_preset_runs_as_ray_tasks_skipping_and_resuming(tmp_path, local_ray):
    from ghsplat_jax.eval.evaluate import train_and_evaluate

    ds = cached_synthetic_dataset(num_views=6, width=32, height=24, num_surfels=40, test_every=3, num_points=200)
    data = write_transforms(ds, tmp_path / "tiny")
    # Everything but the variants' own strategy settings comes from the tiny test config.
    overrides = {k: v for k, v in CONFIG.to_dict().items() if k not in ("data", "strategy", "max_surfels")}
    overrides.update(data=str(data), steps=12, checkpoint_every=6, downscale=1.0)
    exp = load_experiment(QUICK, output=tmp_path / "runs", overrides=overrides)
    runs = {f"{r.scene}/{r.variant}": r for r in exp.runs if r.scene == "llff_fern"}
    assert sorted(runs) == ["llff_fern/budget", "llff_fern/default"]

    interrupted = runs["llff_fern/default"]
    train_and_evaluate(interrupted.config, interrupted.out_dir, until=6)
    assert has_checkpoint(interrupted.out_dir) and not interrupted.finished
    first_steps = (interrupted.out_dir / STATS_NAME).read_text().splitlines()
    assert len(first_steps) == 6

    result = run_experiment(exp, only={"llff_fern"}, executor="ray")
    assert result["failed"] == []
    for name, r in runs.items():
        metrics = read_metrics(r.out_dir)
        assert metrics is not None and metrics["steps"] == 12, name
    assert read_metrics(runs["llff_fern/budget"].out_dir)["strategy"] == "budget"
    # resumed, not restarted: the steps before the checkpoint are the ones trained before
    assert (interrupted.out_dir / STATS_NAME).read_text().splitlines()[:6] == first_steps
    assert (exp.output / "results.md").is_file()

    stamps = {name: (r.out_dir / "metrics.json").stat().st_mtime_ns for name, r in runs.items()}
    again = run_experiment(exp, only={"llff_fern"}, executor="ray")
    assert again["failed"] == [] and len(again["rows"]) == 2
    assert stamps == {name: (r.out_dir / "metrics.json").stat().st_mtime_ns for name, r in runs.items()}


def test_resources_of_a_run():
    from ghsplat_jax.experiments.ray_executor import resources

    assert resources({"CPU": 8.0}) == {"num_cpus": 1.0, "num_gpus": 0.0}
    assert resources({"CPU": 8.0, "GPU": 2.0}) == {"num_cpus": 1.0, "num_gpus": 1.0}
    assert resources({"CPU": 8.0}, cpus_per_run=4) == {"num_cpus": 4.0, "num_gpus": 0.0}


def test_ray_flags_need_the_ray_executor(capsys):
    from ghsplat_jax import cli

    assert cli.main(["run", str(QUICK), "--address", "auto"]) == 2
    assert "--executor ray" in capsys.readouterr().err
