"""Training accuracy benchmark: lego at 400x400 (target test PSNR >= 32 dB) and llff_fern
images_8 at 504x378 (target >= 25 dB); training time, peak memory, final surfel count, and
the budgeted strategy against the default at a fifth of the default's count.

    python benchmarks/analysis/train_accuracy.py                      # full 30k-step schedule (GPU-sized)
    python benchmarks/analysis/train_accuracy.py --steps 2000         # short schedule (scaled 2DGS shape)
    python benchmarks/analysis/train_accuracy.py --scenes fern --steps 1000 --no-budget
    python benchmarks/analysis/train_accuracy.py --until 2000 --no-budget   # first 2000 steps of the 30k run

A short --steps run compresses the whole schedule (densification every 10 steps, opacity
resets every 100): on real scenes that is a different, worse method. --until N instead runs
the first N steps of the unchanged 30k schedule and evaluates that snapshot (as 3DGS reports
its 7k-step numbers); the checkpoint can be resumed to 30k later.

Each run trains in its own process (`ghsplat train`), so peak memory is per run; results go
to benchmarks/results/train_<scene>.json (and the run folders under --runs).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, ROOT, machine_record  # noqa: E402

from ghsplat_jax.io_utils import write_json

SCENES = {
    # name: (dataset folder, overrides, target test PSNR)
    "lego": ("nerf_synthetic_lego", {"downscale": 2.0, "background": [1.0, 1.0, 1.0]}, 32.0),
    "fern": ("llff_fern", {"downscale": 8.0}, 25.0),
}


def run_training(name: str, data: str, overrides: dict, steps: int, out: Path, extra: dict,
                 until: int | None = None) -> dict:
    import tomli_w

    from ghsplat_jax.io_utils import atomic_write

    out.mkdir(parents=True, exist_ok=True)
    # 30 test-curve points over the run (its PSNR against training time); --set overrides it
    cfg = dict(overrides, data=data, steps=steps, progress=False, scale_schedule=steps < 30_000,
               test_curve_every=max(steps // 30, 1)) | extra
    cfg_path = out / "bench_config.toml"
    with atomic_write(cfg_path, "w") as fh:
        fh.write(tomli_w.dumps(cfg))
    cli = [sys.executable, "-m", "ghsplat_jax.cli"]
    cmd = cli + ["train", "--out", str(out), "--config", str(cfg_path)]
    if until is not None:
        cmd += ["--until", str(until)]
    if (out / "checkpoint.npz").exists() and not (out / "metrics.json").exists():
        cmd.append("--resume")
    metrics = out / "metrics.json" if until is None else out / "snapshots" / f"step_{until:06d}" / "metrics.json"
    if not metrics.exists():
        t = time.perf_counter()
        print(f"[{name}] {' '.join(cmd)}", flush=True)
        subprocess.run(cmd, check=True, cwd=ROOT, env=dict(os.environ))
        if until is not None:  # a snapshot: evaluate the checkpoint in a fresh process
            subprocess.run(cli + ["eval", "--no-progress", str(out)], check=True, cwd=ROOT, env=dict(os.environ))
        print(f"[{name}] done in {time.perf_counter() - t:.0f} s", flush=True)
    return json.loads(metrics.read_text())


def summary(m: dict) -> dict:
    return {"test_psnr": m["test"]["psnr"], "test_l1": m["test"]["l1"], "test_ssim": m["test"]["ssim"],
            "train_psnr": m["train"]["psnr"], "num_gaussians": m["num_gaussians"],
            "train_seconds": m["train_seconds"], "steps": m["steps"], "peak_rss_mb": m.get("peak_rss_mb"),
            "render_seconds_per_view": m.get("render_seconds_per_view"), "image_size": m.get("image_size")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="lego,fern", help="comma-separated: " + ",".join(SCENES))
    ap.add_argument("--steps", type=int, default=30_000, help="training steps (a short run scales the schedule)")
    ap.add_argument("--until", type=int, help="stop the (unscaled) run after this step and evaluate that snapshot")
    ap.add_argument("--no-budget", action="store_true", help="skip the budgeted-strategy comparison")
    ap.add_argument("--budget-fraction", type=float, default=0.2, help="budget = this x the default run's count")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra TrainConfig overrides")
    ap.add_argument("--runs", default=str(ROOT / "runs" / "bench"), help="run folders")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)

    import tomllib

    import jax

    from ghsplat_jax.paths import datasets_root

    extra = {k: tomllib.loads(f"v = {v}")["v"] for k, v in (s.split("=", 1) for s in args.set)}
    for name in args.scenes.split(","):
        data, overrides, target = SCENES[name]
        if not (datasets_root() / data).is_dir():
            print(f"[{name}] skipped: {datasets_root() / data} not found")
            continue
        runs = Path(args.runs) / f"{name}_{args.steps}"
        default = run_training(name, data, overrides, args.steps, runs / "default", extra, args.until)
        if args.until is not None:
            schedule = f"the first {args.until} steps of the {args.steps}-step 2DGS schedule"
        elif args.steps >= 30_000:
            schedule = "2DGS"
        else:
            schedule = f"2DGS scaled by {args.steps}/30000"
        result = {
            "scene": name, "dataset": data, "steps": args.steps, "schedule": schedule, "target_test_psnr": target,
            "overrides": overrides | extra,
            "default": summary(default), "meets_target": default["test"]["psnr"] >= target,
            "machine": machine_record(devices=[str(d) for d in jax.devices()]),
            "measured_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        deviations = []
        if args.until is not None and args.until < args.steps:
            deviations.append(f"evaluated at step {args.until} of {args.steps} (the target is for the finished run)")
        if args.steps < 30_000:
            deviations.append(f"{args.steps} steps instead of 30000 (schedule scaled), "
                              "so the PSNR target does not apply")
        for k, v in extra.items():
            if k in overrides and overrides[k] != v:
                deviations.append(f"{k} = {v} instead of {overrides[k]} (the target's resolution)")
            elif k not in ("checkpoint_every", "progress"):
                deviations.append(f"{k} = {v}")
        result["protocol_deviations"] = deviations
        if not args.no_budget:
            cap = max(int(default["num_gaussians"] * args.budget_fraction), 1)
            budget = run_training(name, data, overrides, args.steps, runs / f"budget_{cap}",
                                  dict(extra, strategy={"name": "budget", "max_surfels": cap}), args.until)
            result["budget"] = summary(budget) | {"max_surfels": cap, "fraction_of_default": args.budget_fraction}
            result["budget_minus_default_psnr"] = budget["test"]["psnr"] - default["test"]["psnr"]
        suffix = "" if args.steps >= 30_000 and args.until is None else (
            f"_until{args.until}" if args.until is not None else f"_scaled{args.steps}")
        out = Path(args.results) / f"train_{name}{suffix}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        write_json(out, result)
        print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
