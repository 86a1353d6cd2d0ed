"""Speed of the procedural greenhouse ground-truth renderer (ghsplat_jax.synth).

Target (issue 5): a 40-view 640x480 capture of one row renders in under two minutes on
the 2-core CPU. Measures, on the default scene:
- scene generation and embree BVH build;
- the full `write_dataset` of a 40-view hand-held capture (render + PNG/EXR/mask writes +
  COLMAP/transforms/points3D + meshes), median of --repeats runs, wall and CPU seconds;
- per-view render time of the renderer's options (shadows off, default, soft shadows,
  2x2 supersampling) on a few views.

Writes benchmarks/results/synth_speed.json and .png. The CPU is shared: the load average
at start and end is recorded, and CPU seconds are reported beside wall seconds.

    JAX_PLATFORMS=cpu .venv/bin/python benchmarks/speed/synth_speed.py [--repeats 3] [--views 40]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

BUDGET_S = 120.0

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402


def timed(fn, *args, **kwargs):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - wall, time.process_time() - cpu


def versions() -> dict:
    import embreex
    import numpy
    import OpenImageIO
    import trimesh

    return {"python": platform.python_version(), "numpy": numpy.__version__, "trimesh": trimesh.__version__,
            "embreex": getattr(embreex, "__version__", "?"), "OpenImageIO": OpenImageIO.__version__}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--views", type=int, default=40)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--option-views", type=int, default=3, help="views per renderer option")
    args = parser.parse_args()

    from ghsplat_jax.synth import capture, dataset, render
    from ghsplat_jax.synth import scene as synth_scene
    from ghsplat_jax.synth.config import SceneConfig

    load_start = os.getloadavg()
    cfg = SceneConfig()
    world, gen_s, _ = timed(synth_scene.generate_scene, cfg)
    _, bvh_s, _ = timed(lambda: world.intersector._scene)
    cams = capture.capture_path(world, "handheld", args.views, row=1, width=args.width, height=args.height)
    print(f"scene: {len(world.faces)} faces, generated in {gen_s:.2f} s, BVH {bvh_s:.2f} s")

    captures = []
    for r in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            # a fresh scene each repeat: the timed pipeline is what `ghsplat synth` runs
            def run():
                w = synth_scene.generate_scene(cfg)
                c = capture.capture_path(w, "handheld", args.views, row=1, width=args.width, height=args.height)
                return dataset.write_dataset(w, c, Path(tmp) / "ds")
            _, wall, cpu = timed(run)
        captures.append({"wall_s": wall, "cpu_s": cpu})
        print(f"capture {r + 1}/{args.repeats}: {wall:.1f} s wall, {cpu:.1f} s CPU")

    options = {
        "no shadows": dict(shadows=False),
        "default (hard shadows)": dict(),
        "soft shadows x4": dict(world=synth_scene.generate_scene(cfg.replace(
            render=dataclasses.replace(cfg.render, shadow_samples=4)))),
        "supersample 2x2": dict(supersample=2),
    }
    per_view = {}
    for name, kw in options.items():
        w = kw.pop("world", world)
        times = [timed(render.render_view, w, cams[k * len(cams) // args.option_views], **kw)[1]
                 for k in range(args.option_views)]
        per_view[name] = statistics.median(times)
        print(f"render one view, {name}: {per_view[name]:.2f} s")

    median_wall = statistics.median(c["wall_s"] for c in captures)
    result = {
        "benchmark": "synth_speed",
        "task": f"{args.views}-view {args.width}x{args.height} hand-held capture of one row, write_dataset",
        "budget_s": BUDGET_S,
        "scene_faces": int(len(world.faces)),
        "generate_s": gen_s, "bvh_s": bvh_s,
        "capture_runs": captures,
        "capture_median_wall_s": median_wall,
        "capture_median_cpu_s": statistics.median(c["cpu_s"] for c in captures),
        "within_budget": median_wall < BUDGET_S,
        "per_view_render_s": per_view,
        "machine": machine_record(loadavg_start=load_start, loadavg_end=os.getloadavg()),
        "versions": versions(),
    }
    from ghsplat_jax.io_utils import write_json

    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / "synth_speed.json", result)
    chart(result, RESULTS / "synth_speed.png")
    print(f"median capture {median_wall:.1f} s (budget {BUDGET_S:.0f} s) -> {RESULTS / 'synth_speed.json'}")


def chart(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ghsplat_jax.io_utils import atomic_write

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    walls = [c["wall_s"] for c in result["capture_runs"]]
    cpus = [c["cpu_s"] for c in result["capture_runs"]]
    a.bar(["wall (median)", "CPU (median)"], [statistics.median(walls), statistics.median(cpus)], color=["C0", "C1"])
    a.scatter([0] * len(walls) + [1] * len(cpus), walls + cpus, color="k", s=12, zorder=3)
    a.axhline(result["budget_s"], color="r", ls="--", label=f"budget {result['budget_s']:.0f} s")
    a.set_ylabel("seconds")
    a.set_title(result["task"], fontsize=8)
    a.legend()
    names = list(result["per_view_render_s"])
    b.barh(names, [result["per_view_render_s"][n] for n in names], color="C2")
    b.set_xlabel("seconds per view (render only, median)")
    b.set_title(f"renderer options, {result['scene_faces']} faces", fontsize=9)
    fig.suptitle(f"ghsplat synth speed (load avg {result['machine']['loadavg_start'][0]:.1f} "
                 f"on {result['machine']['cpu_count']} CPUs)", fontsize=10)
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
