"""A training process killed with SIGKILL at seeded random moments, some of them in the middle
of a checkpoint write, always leaves a run folder that `ghsplat train --resume` continues to the
end (benchmarks/robustness/crash_resume.py: the real `ghsplat train` in a subprocess; the full benchmark
kills it 20 times)."""

from __future__ import annotations

import pytest
from benchmark_scripts import load_benchmark

pytestmark = pytest.mark.slow  # a real `ghsplat train` killed and resumed in subprocesses: `make test-all`


def _benchmark():
    return load_benchmark("crash_resume")


def test_sigkill_at_random_moments_always_resumes(tmp_path):
    bench = _benchmark()
    data, config = bench.tiny_run_inputs(tmp_path, steps=40, checkpoint_every=4)
    res = bench.kill_and_resume(data, config, tmp_path / "run",
                                ["any", "checkpoint", "training", "checkpoint"], 40, 4)
    assert res["resumed_to_the_end"]
    assert sum(k["mid_checkpoint_write"] for k in res["kills"]) >= 2
    assert any(k["checkpoint_step"] > 0 for k in res["kills"])  # some kills landed after a checkpoint
