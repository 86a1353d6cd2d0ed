"""Progress of a training run (finished or not) from its stats.jsonl: steps done, seconds per step
by window, surfel count, the training-view PSNR against wall time and the normal loss by step.

    python benchmarks/analysis/run_progress.py runs/fern30k --name train_fern_progress
    python benchmarks/analysis/run_progress.py runs/table1_greenhouse/row2_x1/default \
        --name table1_greenhouse/progress/row2_x1        # a Table 1 run's record

Training PSNR is of the one view each step trains on (smoothed over 100 steps), not a test
metric: a run trained with `--set test_curve_every=N` also has the test views' PSNR every N
steps (test_curve.jsonl), charted against the same training time; a finished run's metrics.json
is copied in. Stalls are the steps that took over STALL_S (compiles, densification rounds,
checkpoints). Writes benchmarks/results/NAME.json and NAME.png (NAME may name a folder there).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402

from ghsplat_jax.io_utils import read_jsonl, save_figure, write_json
from ghsplat_jax.train.run_dir import STATS_NAME, TEST_CURVE_NAME

WINDOWS = [(0, 500), (500, 1000), (1000, 1500), (1500, 3000), (3000, 7000), (7000, 7100), (15000, 15100),
           (29000, 29100)]
STALL_S = 1.0


def summarize(records: list[dict], schedule_steps: int) -> dict:
    step = np.array([r["step"] for r in records])
    elapsed = np.array([r["elapsed_s"] for r in records])
    psnr = np.array([r.get("psnr") or np.nan for r in records], float)
    dt = np.diff(elapsed, prepend=elapsed[0])
    windows = {}
    for lo, hi in WINDOWS:
        inside = (step > lo + 1) & (step <= hi)  # the first step of a window may carry a compile
        if inside.sum() >= 10:
            windows[f"{lo}-{hi}"] = dict(median_seconds_per_step=float(np.median(dt[inside])),
                                         surfels=int(np.median([r["num_surfels"]
                                                                for r, m in zip(records, inside) if m])),
                                         steps_measured=int(inside.sum()))
    stall = dt > STALL_S
    stalls = dict(count=int(stall.sum()), seconds=round(float(dt[stall].sum()), 1),
                  steps=step[stall].tolist(), step_seconds=[round(float(v), 1) for v in dt[stall]])
    k = 100

    def smoothed(values):
        values = np.nan_to_num(np.asarray(values, float))
        s = np.convolve(values, np.ones(k) / k, mode="valid") if len(values) >= k else values
        return [round(float(v), 4) for v in s[::50]]

    return dict(steps_done=int(step[-1]), schedule_steps=schedule_steps, finished=int(step[-1]) >= schedule_steps,
                elapsed_s=float(elapsed[-1]), surfels=int(records[-1]["num_surfels"]), windows=windows,
                first_step_seconds=float(elapsed[0]), stalls=stalls,
                curve=dict(step=step[k - 1:].tolist()[::50], elapsed_s=elapsed[k - 1:].tolist()[::50],
                           train_psnr_smoothed=smoothed(psnr),
                           normal_loss_smoothed=smoothed([r.get("normal") or 0.0 for r in records]),
                           surfels=[r["num_surfels"] for r in records[k - 1:]][::50]))


def chart(summary: dict, title: str, path: Path) -> None:
    from matplotlib.figure import Figure

    c = summary["curve"]
    fig = Figure(figsize=(14, 4))
    ax1, ax2, ax3 = fig.subplots(1, 3)
    ax1.plot(np.array(c["elapsed_s"]) / 3600, c["train_psnr_smoothed"], label="training view (100-step mean)")
    if summary.get("test_curve"):
        t = summary["test_curve"]
        ax1.plot(np.array(t["elapsed_s"]) / 3600, t["psnr"], "o-", ms=3, label="test views")
    ax1.legend()
    ax1.set_xlabel("training time (h)")
    ax1.set_ylabel("PSNR (dB)")
    ax2.plot(c["step"], c["surfels"])
    ax2.set_xlabel("step")
    ax2.set_ylabel("surfels")
    ax3.plot(c["step"], c["normal_loss_smoothed"])
    if summary.get("lambda_normal") == 0:
        ax3.set_title("lambda_normal = 0: the normal term is not computed", fontsize=8)
    ax3.set_xlabel("step")
    ax3.set_ylabel("normal loss, unweighted (100-step mean)")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def main(argv=None) -> int:
    import tomllib

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--name", required=True, help="results file name (without extension)")
    ap.add_argument("--machine", help="where the run ran, when not on this machine (recorded as given)")
    args = ap.parse_args(argv)
    records = read_jsonl(args.run / STATS_NAME)
    config = tomllib.loads((args.run / "config.toml").read_text())
    summary = summarize(records, int(config.get("steps", 30000)))
    summary.update(run=str(args.run), data=config.get("data"), downscale=config.get("downscale"),
                   raster=config.get("raster"), lambda_normal=config.get("lambda_normal"),
                   machine=args.machine or machine_record(start_backend=False))
    curve = read_jsonl(args.run / TEST_CURVE_NAME)
    if curve:
        keys = ("step", "elapsed_s", "psnr", "l1", "num_surfels", "background_alpha")
        summary["test_curve"] = {k: [p.get(k) for p in curve] for k in keys}
    if (args.run / "metrics.json").is_file():
        summary["metrics"] = json.loads((args.run / "metrics.json").read_text())
    (RESULTS / args.name).parent.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / f"{args.name}.json", summary)
    state = "finished" if summary["finished"] else f"{summary['steps_done']} of {summary['schedule_steps']} steps"
    title = f"{args.run.name}: {state}, {summary['surfels']} surfels, {summary['elapsed_s'] / 3600:.2f} h"
    if "metrics" in summary:
        title += f", test PSNR {summary['metrics']['test']['psnr']:.2f} dB"
    chart(summary, title, RESULTS / f"{args.name}.png")
    print(json.dumps({k: summary[k] for k in ("steps_done", "elapsed_s", "surfels", "windows", "stalls")}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
