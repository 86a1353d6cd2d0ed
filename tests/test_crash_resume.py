"""A training process killed with SIGKILL at random moments, some of them in the middle of a
checkpoint write, always leaves a run folder that `ghsplat train --resume` continues to the end.

The subprocess runs the real `ghsplat train`; the harness only slows each checkpoint write
down (a sleep inside the atomic write, before the rename) so that "during a checkpoint write"
is a moment the test can hit on purpose. Kill moments come from a seeded generator."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import tomli_w

from ghsplat_jax.train.checkpoint import read_meta
from ghsplat_jax.train.run_dir import CHECKPOINT_NAME, PLY_NAME, STATS_NAME
from ghsplat_jax.train.synthetic import cached_synthetic_dataset, write_transforms

from test_train_loop import CONFIG

STEPS = 40
CHECKPOINT_SLEEP = 0.4  # seconds each checkpoint write stays unfinished (the temp file exists)

HARNESS = f"""
import contextlib, sys, time
import ghsplat_jax.train.checkpoint as checkpoint
_atomic_write = checkpoint.atomic_write

@contextlib.contextmanager
def slow_atomic_write(path, mode="wb"):
    with _atomic_write(path, mode) as fh:
        yield fh
        fh.flush()
        time.sleep({CHECKPOINT_SLEEP})  # written, not yet renamed into place

checkpoint.atomic_write = slow_atomic_write
from ghsplat_jax.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _launch(data: Path, config: Path, out: Path) -> subprocess.Popen:
    argv = [sys.executable, "-c", HARNESS, "train", "--data", str(data), "--config", str(config), "--out", str(out),
            "--resume", "--no-eval", "--no-progress"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)


def _checkpoint_in_progress(out: Path) -> bool:
    return any(p.name.startswith(f".{CHECKPOINT_NAME}.") for p in out.iterdir()) if out.is_dir() else False


def _steps_done(out: Path) -> int:
    path = out / STATS_NAME
    return len(path.read_text().splitlines()) if path.is_file() else 0


def _wait(proc: subprocess.Popen, until, timeout: float = 120.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        if until():
            return True
        time.sleep(0.005)
    return False


def test_sigkill_at_random_moments_always_resumes(tmp_path):
    ds = cached_synthetic_dataset(num_views=6, width=32, height=24, num_surfels=40, test_every=3, num_points=200)
    data = write_transforms(ds, tmp_path / "data")
    values = {k: v for k, v in CONFIG.to_dict().items() if k != "data"}
    values.update(steps=STEPS, checkpoint_every=4)
    config = tmp_path / "config.toml"
    config.write_text(tomli_w.dumps(values))
    out = tmp_path / "run"
    rng = np.random.default_rng(15)
    kills = []
    for moment in ["any", "checkpoint", "training", "checkpoint", "training"]:
        before = _steps_done(out)
        proc = _launch(data, config, out)
        if moment == "any":  # anywhere from start-up on
            time.sleep(rng.uniform(0.0, 4.0))
        elif moment == "training":  # between steps or inside one, once this process trains
            assert _wait(proc, lambda: _steps_done(out) > before), proc.stderr.read() if proc.poll() else ""
            time.sleep(rng.uniform(0.0, 0.3))
        else:  # the checkpoint is written to its temporary name, not yet renamed
            assert _wait(proc, lambda: _checkpoint_in_progress(out)), proc.stderr.read() if proc.poll() else ""
            time.sleep(rng.uniform(0.0, 0.5 * CHECKPOINT_SLEEP))
            assert _checkpoint_in_progress(out)
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert proc.returncode == -signal.SIGKILL, f"the run ended before the kill ({moment}): {proc.stderr.read()}"
        proc.stderr.close()
        step = read_meta(out / CHECKPOINT_NAME)["step"] if (out / CHECKPOINT_NAME).exists() else 0
        kills.append((moment, _steps_done(out), step))
        assert 0 <= step < STEPS and step % 4 == 0  # a whole checkpoint, never a torn one

    proc = _launch(data, config, out)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert read_meta(out / CHECKPOINT_NAME)["step"] == STEPS and (out / PLY_NAME).is_file()
    steps = [json.loads(line)["step"] for line in (out / STATS_NAME).read_text().splitlines()]
    assert steps == list(range(1, STEPS + 1))  # every step once: redone steps replaced, none lost
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no scratch left behind
    assert any(step > 0 for _, _, step in kills), kills  # some kills did land after a checkpoint
