"""Rasterizer speed and memory: forward and forward+backward against the naive baseline.

    python benchmarks/speed/raster_speed.py [--quick] [--sizes 256x256 ...] [--counts 20000 ...]

Scenes are random surfels of typical trained size (3-sigma radius of a few pixels) in front
of the camera. Every variant is compiled and warmed up first; times are medians of repeats;
memory is XLA's buffer assignment for the compiled program (arguments + outputs + temporaries).
Writes benchmarks/results/raster_speed.json and .png.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402

import ghsplat_jax as gs
from ghsplat_jax.raster import rasterize
from ghsplat_jax.raster.render import binning_config, capacity_bucket, count_pairs

VARIANTS = {
    "carried, tight bounds (default)": gs.RasterConfig(),
    "carried, 3-sigma boxes": gs.RasterConfig(bounds="box3"),
    "logspace, 3-sigma boxes (previous)": gs.RasterConfig(compositor="logspace", bounds="box3", batch_chunks=32),
    "logspace autodiff, 3-sigma boxes": gs.RasterConfig(compositor="logspace", backward="autodiff", bounds="box3",
                                                        batch_chunks=32),
    "naive dense": gs.RasterConfig(backend="dense", tile_size=16, bounds="box3"),
}
DEFAULT, PREVIOUS, NAIVE = "carried, tight bounds (default)", "logspace, 3-sigma boxes (previous)", "naive dense"
DENSE_MEMORY_LIMIT = 6e9  # bytes: the naive baseline is skipped above this predicted size


def typical_scene(n: int, seed: int = 0) -> gs.Surfels:
    r = np.random.default_rng(seed)
    means = r.uniform([-1.2, -1.2, -0.6], [1.2, 1.2, 0.6], (n, 3))
    log_scales = r.uniform(np.log(0.004), np.log(0.03), (n, 2))
    opacity = r.uniform(0.2, 0.9, n)
    return gs.make_surfels(means, r.normal(size=(n, 4)), log_scales, np.log(opacity / (1 - opacity)),
                           r.normal(0, 0.5, (n, 3)), r.normal(0, 0.1, (n, 15, 3)), 3)


def once(fn, *args) -> tuple[float, float]:
    """(wall s, process CPU s) of one call."""
    start, start_cpu = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start, time.process_time() - start_cpu


def timed(fn, *args, repeats: int):
    """(compile wall s, median wall s, median process CPU s). CPU time counts the work done by
    all of this process's threads, so it stays comparable when other jobs share the machine."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - start
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return compile_s, float(np.median(wall)), float(np.median(cpu))


def exp_rate(n: int = 1 << 18, rounds: int = 20) -> float:
    """Fused exp evaluations per second on cache-resident planes (this machine, now)."""
    x = jnp.linspace(0.1, 2.0, n).reshape(-1, 64)
    f = jax.jit(lambda x: jax.lax.fori_loop(0, rounds, lambda i, c: jnp.exp(-c) + x, x))
    return n * rounds / timed(f, x, repeats=5)[1]


def memory_bytes(fn, *args) -> int | None:
    try:
        m = fn.lower(*args).compile().memory_analysis()
        return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes)
    except Exception:  # backends without buffer statistics
        return None


def bench_case(width: int, height: int, n: int, repeats: int, variants) -> list[dict]:
    """Every variant compiled first, then timed in interleaved rounds (variant A, B, C, A, B, C,
    ...), so drifting load on a shared machine affects all of them alike; medians per variant."""
    cam = gs.Camera(K=gs.intrinsics(width, height, 60), world_to_cam=gs.look_at([0, -3.0, 0.8], [0, 0, 0]),
                    width=width, height=height)
    s = typical_scene(n)
    target = jax.random.uniform(jax.random.PRNGKey(0), (height, width, 3))
    rows, fns = [], {}
    for name in variants:
        cfg = VARIANTS[name]
        pairs, fullest = (int(x) for x in count_pairs(s, cam, binning_config(cfg)))
        capacity = capacity_bucket(pairs)
        slots = max(32, 1 << max(fullest - 1, 0).bit_length())
        row = dict(variant=name, width=width, height=height, surfels=n, tile_size=cfg.tile_size, pairs=pairs,
                   fullest_tile=fullest, capacity=capacity)
        rows.append(row)
        tiles = -(-width // cfg.tile_size) * -(-height // cfg.tile_size)
        if cfg.backend == "dense" and tiles * slots * cfg.tile_size**2 * 4 * 12 > DENSE_MEMORY_LIMIT:
            row["skipped"] = f"predicted dense block {tiles}x{slots}x{cfg.tile_size**2} exceeds memory"
            print(row)
            continue
        render = functools.partial(rasterize, cam=cam, cfg=cfg, capacity=capacity, tile_slots=slots)
        forward = jax.jit(lambda s, render=render: render(s).rgb)
        backward = jax.jit(jax.grad(lambda s, render=render: jnp.sum((render(s).rgb - target) ** 2)))
        row["forward_compile_s"] = once(forward, s)[0]
        row["backward_compile_s"] = once(backward, s)[0]
        row["kept_pairs"] = int(render(s).stats.num_kept)
        row["forward_memory_bytes"] = memory_bytes(forward, s)
        row["forward_backward_memory_bytes"] = memory_bytes(backward, s)
        fns[name] = (row, forward, backward)
    samples = {name: {"forward": [], "forward_backward": []} for name in fns}
    for _ in range(repeats):
        for name, (_row, forward, backward) in fns.items():
            for key, fn in (("forward", forward), ("forward_backward", backward)):
                samples[name][key].append(once(fn, s))
    for name, (row, _, _) in fns.items():
        for key, got in samples[name].items():
            row[f"{key}_s"] = float(np.median([w for w, _ in got]))
            row[f"{key}_cpu_s"] = float(np.median([c for _, c in got]))
        row["load_average"] = os.getloadavg()[0]
        # Work actually done: every composited pair against every pixel of its tile.
        evals = row["kept_pairs"] * row["tile_size"] ** 2
        row["pair_pixel_evals"] = evals
        row["forward_evals_per_s"] = evals / row["forward_s"]
        row["forward_backward_evals_per_s"] = evals / row["forward_backward_s"]
        print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return rows


def chart(rows, path: Path):
    from matplotlib.figure import Figure

    from ghsplat_jax.io_utils import save_figure

    fig = Figure(figsize=(12, 4.5))
    axes = fig.subplots(1, 2)
    for ax, key in zip(axes, ("forward_cpu_s", "forward_backward_cpu_s")):
        for name in VARIANTS:
            pts = [(r["width"] * r["height"] * r["surfels"], r[key]) for r in rows if r["variant"] == name and key in r]
            if pts:
                x, y = zip(*sorted(pts))
                ax.loglog(x, y, "o-", label=name)
        ax.set_xlabel("image pixels x surfels")
        ax.set_ylabel("process CPU seconds (median)")
        ax.set_title(key.replace("_cpu_s", "").replace("_", "+"))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"2DGS rasterizer on {platform.processor() or platform.machine()} ({jax.devices()[0].platform})")
    fig.tight_layout()
    save_figure(fig, path)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="*", default=["128x128", "256x256", "512x512", "1024x768"])
    parser.add_argument("--counts", nargs="*", type=int, default=[5000, 20000, 100000, 400000])
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS))
    parser.add_argument("--compare", nargs="*", default=["128x128/5000", "256x256/5000", "256x256/20000",
                                                          "512x512/20000"],
                        help="SIZE/COUNT cases that also run the other variants (the rest: first variant only)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="only 256x256 with 20k surfels")
    parser.add_argument("--out", default=str(RESULTS / "raster_speed"))
    args = parser.parse_args()
    if args.quick:
        args.sizes, args.counts = ["256x256"], [20000]
    rows = []
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        for n in args.counts:
            compare = args.quick or f"{size}/{n}" in args.compare
            rows += bench_case(width, height, n, args.repeats, args.variants if compare else args.variants[:1])
    summary = {}
    for r in rows:
        if r["variant"] != DEFAULT or "forward_s" not in r:
            continue
        case = f"{r['width']}x{r['height']}/{r['surfels']}"
        for label, base_name in (("naive", NAIVE), ("previous", PREVIOUS)):
            base = next((b for b in rows if b["variant"] == base_name and b["width"] == r["width"]
                         and b["height"] == r["height"] and b["surfels"] == r["surfels"] and "forward_s" in b), None)
            if base:
                summary.setdefault(case, {}).update({
                    f"forward_speedup_vs_{label}": base["forward_s"] / r["forward_s"],
                    f"forward_backward_speedup_vs_{label}": base["forward_backward_s"] / r["forward_backward_s"],
                    f"forward_cpu_speedup_vs_{label}": base["forward_cpu_s"] / r["forward_cpu_s"],
                    f"forward_backward_cpu_speedup_vs_{label}":
                        base["forward_backward_cpu_s"] / r["forward_backward_cpu_s"]})
    result = dict(machine=machine_record(exp_rate_per_s=exp_rate()),
                  rows=rows, speedups=summary)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from ghsplat_jax.io_utils import write_json
    write_json(out.with_suffix(".json"), result)
    chart(rows, out.with_suffix(".png"))
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
