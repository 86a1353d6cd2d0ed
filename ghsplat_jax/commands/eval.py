"""`ghsplat eval RUN_DIR`: re-evaluate a training run (metrics per view and split, renders)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "evaluate a training run: PSNR / L1 / SSIM per view and split, render time, depth and normal maps"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", nargs="+", help="run folder(s) written by ghsplat train")
    p.add_argument("--report", help="also write a Table-1 report of these runs to this folder")
    p.add_argument("--no-progress", action="store_true")


def main(args) -> int:
    from ghsplat_jax.eval.evaluate import evaluate_run
    from ghsplat_jax.train.run_dir import PLY_NAME

    status = 0
    for run in args.run_dir:
        try:
            m = evaluate_run(run, progress=not args.no_progress)
        except (FileNotFoundError, ValueError) as exc:
            print(f"ghsplat eval: {exc}", file=sys.stderr)
            status = 2
            continue
        t = m["test"] if m["test"].get("num_views") else m["train"]
        which = "test" if m["test"].get("num_views") else "train"
        at = f" (snapshot at step {m['steps']})" if not Path(run, PLY_NAME).is_file() else ""
        lpips = f", LPIPS {t['lpips']:.4f}" if "lpips" in t else ""  # test views, weights installed
        print(f"{run}{at}: {which} PSNR {t['psnr']:.2f} dB, L1 {t['l1']:.4f}, SSIM {t['ssim']:.4f}{lpips}, "
              f"{m['num_gaussians']} surfels, {m['render_seconds_per_view']:.3f} s/view")
    if args.report:
        from ghsplat_jax.experiments.report import collect_runs, write_table1

        paths = write_table1(collect_runs(args.run_dir), args.report)
        print("report:", ", ".join(str(p) for p in paths))
    return status
