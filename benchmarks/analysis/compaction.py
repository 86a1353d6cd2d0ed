"""Compaction applied to finished runs: how many surfels a trained model can lose for how much
held-out PSNR (train/compaction.py; the auto strategy compacts at its end).

    python benchmarks/analysis/compaction.py runs/table1_greenhouse/row2_x1/auto [RUN ...] \
        --out benchmarks/results/auto_recipe/compaction.json

For each run folder (config.toml and point_cloud.ply): the run's own validation split (carved
from its training views as training carved it) judges the compaction at each --max-loss-db;
the test views, which neither training nor compaction saw, score the model before and after.
A run that compacted itself (metrics.json has `compaction`) is scored as it is: compacting it
again would report a second pass. Results accumulate by run folder in OUT (one record per run,
with the machine and code revision); the compacted models are not written.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/
from record import RESULTS, ROOT, machine_record  # noqa: E402

DEFAULT_OUT = RESULTS / "auto_recipe" / "compaction.json"


def compact_run(run: Path, losses: list[float]) -> dict:
    """The run's model compacted at each allowed validation loss: counts, validation and test PSNR."""
    from ghsplat_jax.data.ply import load_ply
    from ghsplat_jax.eval.evaluate import test_curve_metrics
    from ghsplat_jax.io_utils import code_revision
    from ghsplat_jax.raster.render import capacity_for_views
    from ghsplat_jax.train.compaction import compact_model
    from ghsplat_jax.train.config import load_config
    from ghsplat_jax.train.run_dir import load_training_data
    from ghsplat_jax.train.state import new_state, pad_params
    from ghsplat_jax.train.strategies import accumulated_weights
    from ghsplat_jax.train.trainer import TrainingSession

    config = load_config(run / "config.toml").replace(progress=False)
    if not config.val_every:
        raise SystemExit(f"{run}: trained without a validation split (val_every = 0): nothing to judge by")
    dataset = load_training_data(config)
    with tempfile.TemporaryDirectory() as scratch:
        session = TrainingSession(config, Path(scratch), dataset, resume=False)
    surfels = load_ply(run / "point_cloud.ply")
    params, active = pad_params(surfels, surfels.num)
    state = new_state(params, active, session.optimizers, None)
    session.state = state
    ctx = session.context()
    t = time.perf_counter()
    weight = accumulated_weights(ctx, state)
    weight_s = time.perf_counter() - t
    measure, cameras = test_curve_metrics(dataset, config), [v.camera for v in dataset.test]

    def test_psnr(s) -> float:  # as metrics.json's test PSNR (the render clipped), from an exact pair buffer
        return measure(s.params, s.active, capacity_for_views(s.active_surfels(), cameras, config.raster))["psnr"]

    metrics = json.loads((run / "metrics.json").read_text()) if (run / "metrics.json").is_file() else {}
    row = {"run": str(run), "surfels": surfels.num, "test_psnr": test_psnr(state),
           "weights_seconds": round(weight_s, 2), "code_revision": code_revision(),
           "run_code_revision": metrics.get("code_revision"), "compacted": []}
    if "compaction" in metrics:
        row["self_compacted"] = metrics["compaction"]
        return row
    for loss in losses:
        t = time.perf_counter()
        small, rec = compact_model(state, weight, ctx.validate, loss)
        rec |= {"seconds": round(time.perf_counter() - t, 2), "test_psnr": test_psnr(small)}
        row["compacted"].append(rec)
        print(f"{run}: max loss {loss} dB: {rec['before']} -> {rec['after']} surfels, val "
              f"{rec['val_psnr_before']:.3f} -> {rec['val_psnr_after']:.3f}, test {row['test_psnr']:.3f} -> "
              f"{rec['test_psnr']:.3f} dB", flush=True)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    ap.add_argument("--max-loss-db", type=float, nargs="+", default=[0.02, 0.05, 0.1, 0.2])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    from ghsplat_jax.host_memory import release_compiled_programs
    from ghsplat_jax.io_utils import write_json

    previous = json.loads(args.out.read_text())["runs"] if args.out.is_file() else []
    rows = {r["run"]: r for r in previous}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for run in args.runs:
        release_compiled_programs()  # many models in one process (see host_memory)
        row = compact_run(run.resolve().relative_to(ROOT) if run.resolve().is_relative_to(ROOT) else run,
                          args.max_loss_db)
        rows[row["run"]] = row
        write_json(args.out, {"machine": machine_record(), "runs": sorted(rows.values(), key=lambda r: r["run"])})
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
