"""Rasterizer ablation on a trained scene: tile size x chunk size x backward, forward and
forward+backward time of real surfels seen from the dataset's test cameras.

    python benchmarks/speed/raster_ablation.py --run runs/bench/fern_30000/default [--views 3]

The run folder gives the surfels (point_cloud.ply, or the checkpoint of an unfinished run) and
its dataset. The chunk size and the backward do not change the image; the tile size changes
it only where a surfel's alpha still reaches 1/255 outside its 3-sigma box, in pixels of a
tile the box does not touch (the reference CUDA rasterizer behaves the same way). The
largest difference from the run's own settings is recorded per variant. Times are medians
after a warm-up, wall and process CPU time; the CPU time stays comparable when other jobs
share the machine. Writes benchmarks/results/raster_ablation.json
and .png.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, ROOT, machine_record  # noqa: E402
from speed.raster_speed import timed  # noqa: E402

import ghsplat_jax as gs
from ghsplat_jax.io_utils import save_figure, write_json
from ghsplat_jax.raster import rasterize
from ghsplat_jax.raster.render import binning_config, capacity_bucket, count_pairs
from ghsplat_jax.train.run_dir import load_run, load_training_data

# Changes of the run's settings timed beside the tile x chunk grid.
VARIANTS = {"batch32": dict(batch_chunks=32), "batch64": dict(batch_chunks=64), "box3": dict(bounds="box3"),
            "logspace": dict(compositor="logspace", bounds="box3", batch_chunks=16),
            "logspace-autodiff": dict(compositor="logspace", backward="autodiff", bounds="box3", batch_chunks=16),
            "xla-sort": dict(sort="xla"), "skip-chunks": dict(backward_skip="chunks"),
            "skip-none": dict(backward_skip="none")}


def bench_view(surfels, view, cfg: gs.RasterConfig, repeats: int):
    cam = view.camera
    pairs, fullest = (int(x) for x in count_pairs(surfels, cam, binning_config(cfg)))
    capacity = capacity_bucket(pairs)
    slots = max(32, 1 << max(fullest - 1, 0).bit_length())
    image = jnp.asarray(view.image)
    render = lambda s: rasterize(s, cam, cfg, capacity, tile_slots=slots)
    forward = jax.jit(lambda s: render(s).rgb)
    grad = jax.jit(jax.grad(lambda s: jnp.mean(jnp.abs(render(s).rgb - image))))
    _, fwd_wall, fwd_cpu = timed(forward, surfels, repeats=repeats)
    _, both_wall, both_cpu = timed(grad, surfels, repeats=repeats)
    out = render(surfels)
    kept, visible = int(out.stats.num_kept), max(int(out.stats.num_visible), 1)
    # A tile saturates when every pixel's transmittance fell below 1e-4 (early termination's gain).
    ts, a = cfg.tile_size, np.asarray(out.alpha)
    h, w = -(-a.shape[0] // ts) * ts, -(-a.shape[1] // ts) * ts
    tiles = np.pad(a, ((0, h - a.shape[0]), (0, w - a.shape[1])), constant_values=1.0).reshape(h // ts, ts, w // ts, ts)
    return dict(pairs=pairs, kept_pairs=kept, pairs_per_visible_surfel=kept / visible,
                pixel_evals_per_pixel=kept * ts**2 / a.size,
                saturated_tile_fraction=float(np.mean(np.min(tiles, axis=(1, 3)) >= 1 - 1e-4)),
                forward_s=fwd_wall, forward_cpu_s=fwd_cpu, forward_backward_s=both_wall,
                forward_backward_cpu_s=both_cpu, pixel_evals=kept * ts**2), np.asarray(out.rgb)


def _label(r: dict) -> str:
    sort = f", {r['sort']} sort" if r.get("sort", "auto") != "auto" else ""
    skip = f", skip {r['backward_skip']}" if r.get("backward_skip", "pairs") != "pairs" else ""
    return (f"{r['compositor']} {r['bounds']} {r['backward']}, tile {r['tile_size']}, "
            f"chunk {r['chunk_size']}x{r['batch_chunks']}{sort}{skip}")


def chart(rows: list[dict], title: str, path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 5))
    ax = fig.add_subplot()
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["forward_cpu_s"] for r in rows], 0.4, label="forward")
    ax.bar(x + 0.2, [r["forward_backward_cpu_s"] for r in rows], 0.4, label="forward + backward")
    ax.set_xticks(x, [_label(r) for r in rows], rotation=50, ha="right", fontsize=7)
    ax.set_ylabel("CPU seconds per view (median over views)")
    ax.set_title(title, fontsize=9)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default=str(ROOT / "runs" / "bench" / "fern_30000" / "default"), help="training run")
    ap.add_argument("--views", type=int, default=3, help="test views to time (evenly spaced)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--tiles", default="8,16,32")
    ap.add_argument("--chunks", default="16,32")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="other settings to time: " + ",".join(VARIANTS))
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)

    run = Path(args.run)
    config, surfels, meta, _ = load_run(run)
    surfels = jax.tree_util.tree_map(jnp.asarray, surfels)
    step = int(meta.get("step", config.steps))
    dataset = load_training_data(config)
    views = list(dataset.test) or list(dataset.train)
    views = [views[i] for i in np.unique(np.linspace(0, len(views) - 1, args.views).round().astype(int))]
    # The training run's own settings first: it is the reference image and the baseline time.
    base = dataclasses.replace(config.raster, pair_capacity=None, on_overflow="raise")
    grid = [dataclasses.replace(base, tile_size=t, chunk_size=c)
            for t, c in itertools.product((int(v) for v in args.tiles.split(",")),
                                          (int(v) for v in args.chunks.split(",")))]
    variants = [VARIANTS[name] for name in args.variants.split(",") if name]
    grid = [base] + [g for g in grid if g != base] + [dataclasses.replace(base, **v) for v in variants]
    reference = None
    rows = []
    for cfg in grid:
        per_view, images = [], []
        for v in views:
            r, rgb = bench_view(surfels, v, cfg, args.repeats)
            per_view.append(r)
            images.append(rgb)
        reference = images if reference is None else reference
        row = dict(compositor=cfg.compositor, bounds=cfg.bounds, tile_size=cfg.tile_size, chunk_size=cfg.chunk_size,
                   backward=cfg.backward, backward_skip=cfg.backward_skip, batch_chunks=cfg.batch_chunks, sort=cfg.sort,
                   load_average=os.getloadavg()[0],
                   **{k: float(np.median([p[k] for p in per_view])) for k in per_view[0]})
        row["max_abs_diff_vs_default"] = float(max(np.max(np.abs(a - b)) for a, b in zip(images, reference)))
        rows.append(row)
        print(json.dumps(row), flush=True)
    fastest = min(rows, key=lambda r: r["forward_backward_cpu_s"])
    default = rows[0]
    w, h = views[0].camera.width, views[0].camera.height
    result = {
        "run": str(run), "data": config.data, "step": step, "num_surfels": int(surfels.num),
        "image_size": [int(w), int(h)], "views": [v.name for v in views], "rows": rows,
        "default": _label(default), "fastest_forward_backward": _label(fastest),
        "default_over_fastest_cpu": default["forward_backward_cpu_s"] / fastest["forward_backward_cpu_s"],
        "machine": machine_record(),
        "measured_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "raster_ablation.json", result)
    chart(rows, f"{config.data} at step {step}: {surfels.num} surfels, {w}x{h}, {len(views)} test views",
          out / "raster_ablation.png")
    print(f"fastest fwd+bwd: {result['fastest_forward_backward']}; default is "
          f"{result['default_over_fastest_cpu']:.2f}x its CPU time")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
