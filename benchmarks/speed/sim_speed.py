"""Simulation speed: camera frames per second (640x480 by default) and LiDAR scans per
second (VLP-16 from four 90-degree faces) for greenhouse-like scenes of N surfels.

Poses change every frame (the robot drives down an aisle), the functions compile once
(warm-up, then `traces` must stay 1: no recompilation per frame), and we report the
median of several repeats. Writes benchmarks/results/sim_speed.json and .png.

    JAX_PLATFORMS=cpu python benchmarks/speed/sim_speed.py --sizes 100000 400000 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402


def greenhouse_surfels(n: int, seed: int = 0):
    """n surfels: four 1.2 m-high rows of leaf-like splats (random orientations, 1-3 cm)
    along +x, 1.6 m apart, on a floor. About 85% of the surfels are in the rows."""
    import ghsplat_jax as gs
    from ghsplat_jax.core.quaternions import safe_normalize

    rng = np.random.default_rng(seed)
    n_rows = int(n * 0.85)
    n_floor = n - n_rows
    row = rng.integers(0, 4, n_rows)
    rows = np.c_[rng.uniform(0, 20, n_rows), (row - 1.5) * 1.6 + rng.normal(0, 0.15, n_rows),
                 rng.uniform(0.05, 1.2, n_rows)]
    floor = np.c_[rng.uniform(-2, 22, n_floor), rng.uniform(-4, 4, n_floor), np.zeros(n_floor)]
    means = np.concatenate([rows, floor]).astype(np.float32)
    quats = np.concatenate([rng.normal(size=(n_rows, 4)), np.tile([1.0, 0, 0, 0], (n_floor, 1))])
    quats = np.asarray(safe_normalize(quats)[0], np.float32)
    scales = np.concatenate([np.log(rng.uniform(0.01, 0.03, (n_rows, 2))),
                             np.full((n_floor, 2), np.log(np.sqrt(24 * 8 / max(n_floor, 1)) * 0.7))])
    colour = np.concatenate([np.c_[rng.uniform(-0.3, 0.0, n_rows), rng.uniform(0.0, 0.3, n_rows),
                                   rng.uniform(-0.4, -0.2, n_rows)],
                             np.tile([0.0, -0.1, -0.2], (n_floor, 1))]) / 0.2820948
    return gs.make_surfels(means, quats, scales.astype(np.float32), np.full(n, 2.0, np.float32),
                           colour.astype(np.float32))


def bench(n: int, repeats: int, width: int, height: int, lidar_name: str, face_width: int | None,
          variants=("beams/map",)) -> dict:
    """Camera and LiDAR timings; LiDAR `variants` are "sampling/batching" (the first is the headline)."""
    import jax

    from ghsplat_jax.sim import beams
    from ghsplat_jax.sim import robot as robot_mod
    from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer
    from ghsplat_jax.sim.lidar import Lidar

    s = jax.device_put(greenhouse_surfels(n))
    r = robot_mod.Robot()
    cam = CameraModel.from_fov(r.optical_frame, width, height, 70.0)
    renderer = CameraRenderer()
    poses = [(-1.0 + 0.05 * i, 0.8, 0.0) for i in range(repeats + 1)]  # down the aisle between rows 2 and 3

    t0 = time.perf_counter()
    renderer.render(s, cam, r.map_from_optical(*poses[0]))
    cam_first = time.perf_counter() - t0
    cam_warm_traces = renderer.traces  # includes one pair-buffer growth if the first guess was small
    cam_times = []
    for p in poses[1:]:
        t0 = time.perf_counter()
        f = renderer.render(s, cam, r.map_from_optical(*p))
        cam_times.append(time.perf_counter() - t0)
    lidars = {}
    for variant in variants:
        sampling, batching = variant.split("/")
        lidar = Lidar(beams.get_pattern(lidar_name), face_width=face_width, depth="median", batching=batching,
                      sampling=sampling)
        t0 = time.perf_counter()
        lidar.scan(s, r.map_from_lidar(*poses[0]))
        lidar_first = time.perf_counter() - t0
        lidar_warm_traces = lidar.traces
        lidar_times = []
        for i, p in enumerate(poses[1:]):
            t0 = time.perf_counter()
            scan = lidar.scan(s, r.map_from_lidar(*p), seed=i)
            lidar_times.append(time.perf_counter() - t0)
        lidars[variant] = {
            "pattern": lidar.pattern.name, "sampling": sampling, "batching": batching,
            "face": [lidar.geom.width, lidar.geom.height],
            "first_call_s": lidar_first, "median_s": float(np.median(lidar_times)),
            "scans_per_s": float(1 / np.median(lidar_times)), "compilations_warmup": lidar_warm_traces,
            "compilations_timed": lidar.traces - lidar_warm_traces,
            "pair_capacity": lidar.pair_capacity, "returns": int(scan.valid.sum()), "beams": int(scan.valid.size)}
    return {
        "surfels": n, "camera": {"width": width, "height": height, "first_call_s": cam_first,
                                  "median_s": float(np.median(cam_times)), "fps": float(1 / np.median(cam_times)),
                                  "compilations_warmup": cam_warm_traces,
                                  "compilations_timed": renderer.traces - cam_warm_traces,
                                  "pair_capacity": renderer.pair_capacity,
                                  "coverage": float(np.mean(f.alpha > 0.5))},
        "lidar": lidars[variants[0]], "lidar_variants": lidars,
        "repeats": repeats,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 400_000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--lidar", default="vlp16")
    ap.add_argument("--face-width", type=int, default=None, help="LiDAR face width (default: columns/pi)")
    ap.add_argument("--lidar-variants", nargs="+", default=["beams/map", "faces/map", "beams/vmap"],
                    choices=["beams/map", "faces/map", "beams/vmap", "faces/vmap"],
                    help="LiDAR sampling/batching variants to time (the first, the Lidar default, is the headline)")
    ap.add_argument("--out", default=str(RESULTS / "sim_speed"))
    args = ap.parse_args(argv)

    import jax

    from ghsplat_jax.io_utils import atomic_write, write_json

    runs = []
    for n in args.sizes:
        load_before = os.getloadavg()
        res = bench(n, args.repeats, args.width, args.height, args.lidar, args.face_width, tuple(args.lidar_variants))
        res["load_average_before_after"] = [load_before[0], os.getloadavg()[0]]
        runs.append(res)
        print(json.dumps(res), flush=True)
        if res["camera"]["compilations_timed"] or any(v["compilations_timed"] for v in res["lidar_variants"].values()):
            print("warning: a timed frame recompiled (pair buffer grew)", file=sys.stderr)
    out = {"benchmark": "sim_speed", "machine": machine_record(devices=[str(d) for d in jax.devices()]), "runs": runs,
           "notes": "median of repeats after a warm-up call (first_call_s includes compilation); "
                    "poses change every frame; compilations_timed == 0 proves no per-frame recompilation "
                    "(compilations_warmup counts the first trace plus at most a pair-buffer growth); "
                    "load_average_before_after shows how busy the shared machine was"}
    write_json(args.out + ".json", out)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ns = [r["surfels"] / 1000 for r in runs]
    ax[0].bar([str(int(n)) + "k" for n in ns], [r["camera"]["fps"] for r in runs])
    ax[0].set_title(f"camera {args.width}x{args.height} (frames/s)")
    variants = list(runs[0]["lidar_variants"])
    width = 0.8 / len(variants)
    for k, v in enumerate(variants):
        ax[1].bar(np.arange(len(runs)) + (k - (len(variants) - 1) / 2) * width,
                  [r["lidar_variants"][v]["scans_per_s"] for r in runs], width, label=v, color=f"C{k + 1}")
    ax[1].set_xticks(np.arange(len(runs)), [str(int(n)) + "k" for n in ns])
    ax[1].legend()
    ax[1].set_title(f"LiDAR {runs[0]['lidar']['pattern']} (scans/s)")
    for a in ax:
        a.set_xlabel("surfels")
    fig.suptitle(f"sim speed on {jax.default_backend()} ({jax.devices()[0].device_kind})")
    fig.tight_layout()
    with atomic_write(args.out + ".png", "wb") as fh:
        fig.savefig(fh, format="png", dpi=100)
    print(f"wrote {args.out}.json and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
