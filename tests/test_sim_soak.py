"""The soak benchmark's property at small scale: resident memory stays flat over a long
simulation with a bag recorded and a Foxglove server attached (analytic renderer, so it is
quick). benchmarks/robustness/sim_soak.py measures the full 10,000 frames with the rasterizer."""

from __future__ import annotations

import importlib.util

import pytest

pytest.importorskip("psutil")

from benchmark_scripts import load_benchmark
from test_sim_fakes import box_room_renderer

pytestmark = pytest.mark.slow  # 1,500 simulated frames: `make test-all`


def _benchmark():
    return load_benchmark("sim_soak")


def test_memory_stays_flat_over_a_long_simulation():
    foxglove = importlib.util.find_spec("foxglove") is not None
    res = _benchmark().soak(frames=1500, rate=100.0, surfels=None, width=32, height=24, lidar_face_width=48,
                            foxglove=foxglove, sample_every=25, warmup=300,
                            render_fn=box_room_renderer(lo=(-10.0, -10.0, -1.0), hi=(30.0, 10.0, 3.0)))
    assert res["frames"] == 1500 and res["lidar_scans"] == 150
    assert res["camera_compilations"] == 1 and res["lidar_compilations"] == 1  # no per-frame recompilation
    assert res["growth"] <= 0.05, res["samples"]
