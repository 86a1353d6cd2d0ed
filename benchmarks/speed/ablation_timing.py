"""Re-time an experiment's variants in one process, interleaved, and redraw its Pareto charts.

    python benchmarks/speed/ablation_timing.py benchmarks/results/raster_ablation/quick [--steps 32] [--passes 2]

`ghsplat run` records each run's median step time as it trained, so runs trained at different
times (or beside other jobs) carry different machine loads. Here every variant's training step is
timed from the run's own final checkpoint (its own surfels, settings and pair buffer), one step of
each variant in turn, so drifting load hits them alike; medians of wall and process CPU time.
With --passes N the interleaved timing runs N times over the same compiled steps: each variant's
median is over every pass's steps, and each pass's own median is kept (`pass_seconds_per_step`),
so the spread between passes is on record.
Writes RESULTS/step_timing.json and, with these times as the cost, pareto_interleaved.json and
pareto_interleaved_SCENE.png beside the experiment's own charts.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import machine_record  # noqa: E402
from speed.train_speed import compiled_session, step_row, time_sessions  # noqa: E402

from ghsplat_jax.experiments.charts import write_pareto_charts
from ghsplat_jax.io_utils import code_revision, write_json
from ghsplat_jax.train.config import load_config
from ghsplat_jax.train.run_dir import CHECKPOINT_NAME, CONFIG_NAME, load_training_data


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="an experiment's results folder (with results.json)")
    ap.add_argument("--steps", type=int, default=32,  # 8 steps' medians moved by up to a fifth between passes
                    help="timed steps per variant")
    ap.add_argument("--passes", type=int, default=2, help="interleaved timings of the same compiled steps")
    ap.add_argument("--split", default="test", help="whose PSNR the charts show")
    ap.add_argument("--redraw", action="store_true",
                    help="time nothing: redraw the charts and table from RESULTS/step_timing.json")
    args = ap.parse_args(argv)
    rows = [r for r in json.loads((args.results / "results.json").read_text())["rows"] if r["split"] == args.split]
    if args.redraw:  # the charts and table again, from the times on record
        recorded = json.loads((args.results / "step_timing.json").read_text())
        timing, steps = recorded["scenes"], recorded["steps_timed"]
    else:
        if args.steps < 1 or args.passes < 1:
            ap.error(f"--steps and --passes must be >= 1, got {args.steps} and {args.passes}")
        timing, steps = {scene: time_scene([r for r in rows if r["scene"] == scene], args.steps, args.passes)
                         for scene in sorted({r["scene"] for r in rows})}, args.steps
        write_json(args.results / "step_timing.json", {"machine": machine_record(), "code_revision": code_revision(),
                                                       "steps_timed": steps, "passes": args.passes,
                                                       "split": args.split, "scenes": timing})
    charted = [dict(r, interleaved_step_seconds=timing[r["scene"]][r["variant"]]["seconds_per_step"],
                    interleaved_cpu_seconds=timing[r["scene"]][r["variant"]]["cpu_seconds_per_step"])
               for r in rows if r["variant"] in timing.get(r["scene"], {})]
    write_pareto_charts(charted, args.results, cost="interleaved_step_seconds", stem="pareto_interleaved",
                        title="step time re-measured interleaved")
    write_markdown(args.results / "step_timing.md", charted, steps)
    print(json.dumps({s: {v: round(t["seconds_per_step"], 3) for v, t in tt.items()} for s, tt in timing.items()},
                     indent=1))
    return 0


def time_scene(rows: list[dict], steps: int, passes: int = 1) -> dict:
    """{variant: step timing} of one scene's runs that kept a checkpoint, interleaved
    (time_sessions), `passes` times over the same compiled sessions (pooled_passes)."""
    runs = {r["variant"]: r for r in rows if (Path(r["run_dir"]) / CHECKPOINT_NAME).is_file()}
    configs = {v: dataclasses.replace(load_config(Path(r["run_dir"]) / CONFIG_NAME), progress=False,
                                      checkpoint_every=0) for v, r in runs.items()}
    dataset = load_training_data(next(iter(configs.values())))  # the variants share the scene's data
    sessions = {v: compiled_session(cfg, dataset, Path(runs[v]["run_dir"]) / CHECKPOINT_NAME)
                for v, cfg in configs.items()}
    return pooled_passes([time_sessions(sessions, steps) for _ in range(passes)])


def pooled_passes(passes: list[dict]) -> dict:
    """{variant: row} over the passes' rows ({variant: row} each, with raw samples): the medians over
    every pass's steps, the first pass's facts, and each pass's own median step time."""
    return {v: step_row({k: x for k, x in first.items() if k in ("step", "surfels", "pool", "pair_capacity")},
                        [s for p in passes for s in p[v]["samples"]])
            | {"pass_seconds_per_step": [p[v]["seconds_per_step"] for p in passes]}
            for v, first in passes[0].items()}


def write_markdown(path: Path, rows: list[dict], steps: int) -> None:
    from ghsplat_jax.experiments.report import markdown_table
    from ghsplat_jax.io_utils import atomic_write

    table = [dict(r, logged=f"{r['step_seconds']:.3f}", wall=f"{r['interleaved_step_seconds']:.3f}",
                  cpu=f"{r['interleaved_cpu_seconds']:.3f}") for r in rows]
    with atomic_write(path, "w") as fh:
        fh.write(f"# Step time re-measured interleaved ({steps} steps per variant, medians)\n\n"
                 "Each variant's step from its own final checkpoint, one step of each in turn in one process "
                 "(benchmarks/speed/ablation_timing.py); `logged` is the median the run logged while it trained.\n\n"
                 + markdown_table(table, ("scene", "variant", "psnr", "num_gaussians", "logged", "wall", "cpu"),
                                  ("scene", "variant", "test PSNR (dB)", "surfels", "logged step s",
                                   "interleaved step s", "interleaved CPU s")))


if __name__ == "__main__":
    raise SystemExit(main())
