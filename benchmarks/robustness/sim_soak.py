"""Simulation soak: resident memory over a long run (10,000 camera frames by default) of a
small scene, with the sinks of a real session attached (a bag being recorded, optionally a
Foxglove server). Memory must stay flat: growth of at most 5% after warm-up.

Samples RSS (psutil) every few frames; growth = (largest RSS after warm-up - RSS at the end of
warm-up) / RSS at the end of warm-up. Writes benchmarks/results/sim_soak.json and .png.

    JAX_PLATFORMS=cpu python benchmarks/robustness/sim_soak.py --frames 10000
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402


def small_scene(n: int = 5_000, seed: int = 0):
    """Two rows of leaf-like surfels beside an aisle at y = 0, on a floor (sim_speed's recipe, smaller)."""
    from speed.sim_speed import greenhouse_surfels

    return greenhouse_surfels(n, seed)


def aisle_trajectory(duration: float, speed: float = 0.5):
    """Back and forth along the aisle between two rows, long enough for `duration` seconds."""
    from ghsplat_jax.sim.trajectory import from_waypoints

    legs = math.ceil(duration * speed / 18.0) + 1
    xs = [0.0 if i % 2 == 0 else 18.0 for i in range(legs + 1)]
    return from_waypoints(np.array([[x, 0.8] for x in xs]), speed=speed)


def soak(frames: int = 10_000, rate: float = 100.0, surfels=None, width: int = 64, height: int = 48,
         lidar_face_width: int = 64, record: bool = True, foxglove: bool = False, sample_every: int = 50,
         warmup: int | None = None, render_fn=None) -> dict:
    """Run `frames` camera frames (and a LiDAR scan every tenth) and sample RSS; returns the figures.
    `render_fn` replaces the rasterizer (tests use an analytic one)."""
    import psutil

    from ghsplat_jax.sim import beams, simulate
    from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer
    from ghsplat_jax.sim.lidar import Lidar
    from ghsplat_jax.sim.robot import Robot
    from ghsplat_jax.transport.recorder import BagRecorder

    warmup = warmup if warmup is not None else max(frames // 10, 1)
    robot = Robot()
    camera = CameraModel.from_fov(robot.optical_frame, width, height, 70.0)
    lidar = Lidar(beams.get_pattern("vlp16"), face_width=lidar_face_width, render_fn=render_fn)
    renderer = CameraRenderer(render_fn=render_fn)
    duration = (frames - 1) / rate
    cfg = simulate.SimConfig(camera_rate=rate, lidar_rate=rate / 10, duration=duration)
    process = psutil.Process()
    samples, counts = [], {}
    with tempfile.TemporaryDirectory(prefix="sim_soak.") as tmp:
        sinks, closers = [], []
        if record:
            bag = BagRecorder(Path(tmp) / "soak.mcap").__enter__()
            sinks.append(lambda topic, msg, t, payload: bag.write(topic, msg, t))
            closers.append(lambda: bag.__exit__(None, None, None))
        if foxglove:
            from ghsplat_jax.transport.foxglove_sink import FoxgloveSink

            fox = FoxgloveSink(port=0)
            sinks.append(fox.sink)
            closers.append(fox.close)
        t0 = time.perf_counter()
        try:
            for topic, msg, t, payload in simulate.run(surfels, robot, aisle_trajectory(duration), cfg, camera,
                                                       lidar, renderer):
                for sink in sinks:
                    sink(topic, msg, t, payload)
                counts[topic] = counts.get(topic, 0) + 1
                n = counts.get("/render", 0)
                if topic == "/render" and (n % sample_every == 0 or n == 1):
                    samples.append((n, time.perf_counter() - t0, process.memory_info().rss))
        finally:
            for close in closers:
                close()
        bag_bytes = sum(p.stat().st_size for p in Path(tmp).rglob("*") if p.is_file())
    seconds = time.perf_counter() - t0
    after = [rss for n, _, rss in samples if n >= warmup]
    baseline = after[0]
    return {
        "frames": counts.get("/render", 0), "lidar_scans": counts.get("/lidar", 0), "messages": sum(counts.values()),
        "seconds": seconds, "frames_per_s": counts.get("/render", 0) / seconds, "warmup_frames": warmup,
        "rss_mb_at_warmup": baseline / 2**20, "rss_mb_max_after_warmup": max(after) / 2**20,
        "rss_mb_final": after[-1] / 2**20, "growth": (max(after) - baseline) / baseline,
        "bag_mb": bag_bytes / 2**20, "camera_compilations": renderer.traces, "lidar_compilations": lidar.traces,
        "samples": [{"frame": n, "seconds": round(s, 3), "rss_mb": round(r / 2**20, 2)} for n, s, r in samples],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--rate", type=float, default=100.0, help="camera Hz of simulated time (LiDAR at a tenth)")
    ap.add_argument("--surfels", type=int, default=5_000)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--foxglove", action="store_true", help="also serve the topics with a Foxglove server")
    ap.add_argument("--out", default=str(RESULTS / "sim_soak"))
    args = ap.parse_args(argv)

    import jax

    from ghsplat_jax.io_utils import save_figure, write_json

    res = soak(args.frames, args.rate, jax.device_put(small_scene(args.surfels)), args.width, args.height,
               foxglove=args.foxglove)
    res.update(surfels=args.surfels, width=args.width, height=args.height, foxglove=args.foxglove, limit=0.05,
               passed=res["growth"] <= 0.05)
    out = {"benchmark": "sim_soak", "machine": machine_record(), "result": res,
           "notes": "RSS sampled every 50 camera frames while a rosbag2 (MCAP) is recorded; growth is the largest "
                    "RSS after warm-up relative to the RSS at the end of warm-up (the first 10% of frames)"}
    write_json(args.out + ".json", out)
    print({k: v for k, v in res.items() if k != "samples"})

    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 3.5))
    ax = fig.subplots()
    ax.plot([s["frame"] for s in res["samples"]], [s["rss_mb"] for s in res["samples"]], lw=1.2)
    ax.axvline(res["warmup_frames"], color="grey", ls=":", label="end of warm-up")
    ax.axhline(res["rss_mb_at_warmup"] * 1.05, color="C3", ls="--", label="+5% limit")
    ax.set_xlabel("camera frame")
    ax.set_ylabel("resident memory (MiB)")
    ax.set_title(f"sim soak: {res['frames']} frames, {res['lidar_scans']} LiDAR scans, "
                 f"growth {100 * res['growth']:.2f}%")
    ax.legend(loc="lower right")
    fig.tight_layout()
    save_figure(fig, args.out + ".png")
    print(f"wrote {args.out}.json and .png")
    return 0 if res["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
