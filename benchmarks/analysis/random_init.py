"""Random initialisation: tile-surfel pairs (the cost of a step) and training PSNR over the
first steps of the real schedule, for several `random_init_scale` factors.

    python benchmarks/analysis/random_init.py --data nerf_synthetic_lego --downscale 4 --steps 600 --scales 1.0 0.5

Each factor trains `ghsplat train --until STEPS` in RUNS/scale_F (a finished run is reused) on a
white background, from the same seed. Pairs are counted by the rasterizer at every step, so they
do not depend on the machine's load; PSNR is the training view's, averaged over windows of 100
steps (the views rotate). Writes benchmarks/results/random_init.json and .png.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402


def train(data: str, downscale: float, steps: int, scale: float, out: Path) -> None:
    stats = out / "stats.jsonl"
    if stats.is_file() and sum(1 for _ in stats.open()) >= steps:
        return
    subprocess.run([sys.executable, "-m", "ghsplat_jax.cli", "train", "--data", data, "--downscale", str(downscale),
                    "--white", "--out", str(out), "--until", str(steps), "--no-eval", "--no-progress",
                    "--set", f"random_init_scale={scale}"], check=True)


def windows(stats: Path, size: int = 100) -> list[dict]:
    rows = [json.loads(line) for line in stats.open()]
    out = []
    for start in range(0, rows[-1]["step"] + 1, size):
        w = [r for r in rows if start <= r["step"] < start + size]
        if w:
            out.append(dict(steps=[start, start + size], psnr=float(np.mean([r["psnr"] for r in w])),
                            pairs=float(np.mean([r["num_pairs"] for r in w])), surfels=int(w[-1]["num_surfels"]),
                            count=len(w)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="nerf_synthetic_lego")
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.5])
    ap.add_argument("--runs", default="runs/random_init", help="folder of the training runs")
    ap.add_argument("--results", default=str(RESULTS))
    ap.add_argument("--summarise-only", action="store_true", help="read the runs as they are (train nothing)")
    args = ap.parse_args(argv)

    from ghsplat_jax.io_utils import save_figure, write_json

    result = {"data": args.data, "downscale": args.downscale, "steps": args.steps,
              "machine": machine_record(start_backend=False),
              "note": "train-view PSNR and rasterizer pairs per 100-step window; pairs do not depend on load",
              "runs": {}}
    for scale in args.scales:
        out = Path(args.runs) / f"scale_{scale:g}"
        if not args.summarise_only:
            train(args.data, args.downscale, args.steps, scale, out)
        result["runs"][f"{scale:g}"] = windows(out / "stats.jsonl")
    write_json(Path(args.results) / "random_init.json", result)

    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.5))
    a, b = fig.subplots(1, 2)
    for scale, ws in result["runs"].items():
        mid = [np.mean(w["steps"]) for w in ws]
        a.plot(mid, [w["pairs"] / 1e3 for w in ws], "o-", label=f"random_init_scale {scale}")
        b.plot(mid, [w["psnr"] for w in ws], "o-", label=f"random_init_scale {scale}")
    a.set(xlabel="step", ylabel="tile-surfel pairs (thousands)", title="cost of a step")
    b.set(xlabel="step", ylabel="train PSNR (dB)", title="accuracy")
    b.legend()
    fig.suptitle(f"{args.data} /{args.downscale:g}, random initialisation, first {args.steps} steps")
    fig.subplots_adjust(top=0.82, wspace=0.3)
    save_figure(fig, Path(args.results) / "random_init.png")
    print(json.dumps(result["runs"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
