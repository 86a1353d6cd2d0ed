"""Crash and resume: a training process killed with SIGKILL at seeded random moments, some of
them in the middle of a checkpoint write, must always leave a run folder that
`ghsplat train --resume` continues, and the finished run must have every step exactly once.

Each round starts the real `ghsplat train --resume` in a subprocess and kills it: at any
moment from start-up on ("any"), while it trains ("training"), or while a checkpoint is
written but not yet renamed into place ("checkpoint"; the harness sleeps inside each
checkpoint write so that this window can be hit on purpose). After every kill the checkpoint
on disk must be whole (readable, at a checkpoint step). Writes benchmarks/results/crash_resume.json
and .png.

    JAX_PLATFORMS=cpu python benchmarks/robustness/crash_resume.py --kills 20
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHECKPOINT_SLEEP = 0.4  # seconds each checkpoint write stays unfinished (its temporary file exists)

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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, ROOT, machine_record  # noqa: E402


def tiny_run_inputs(folder: Path, steps: int, checkpoint_every: int) -> tuple[Path, Path]:
    """A tiny synthetic transforms.json scene and a small training config for it."""
    import tomli_w

    from ghsplat_jax.train.config import TrainConfig
    from ghsplat_jax.train.synthetic import cached_synthetic_dataset, write_transforms

    ds = cached_synthetic_dataset(num_views=6, width=32, height=24, num_surfels=40, test_every=3, num_points=200)
    data = write_transforms(ds, folder / "data")
    config = TrainConfig(steps=steps, checkpoint_every=checkpoint_every, sh_degree=1, sh_increase_every=10,
                         densify_from=4, densify_every=4, densify_until=max(steps - 15, 5), opacity_reset_every=1000,
                         initial_capacity=2048, init_random_points=200, progress=False).replace(pair_capacity=16384)
    path = folder / "config.toml"
    path.write_text(tomli_w.dumps({k: v for k, v in config.to_dict().items() if k != "data"}))
    return data, path


def launch(data: Path, config: Path, out: Path) -> subprocess.Popen:
    argv = [sys.executable, "-c", HARNESS, "train", "--data", str(data), "--config", str(config), "--out", str(out),
            "--resume", "--no-eval", "--no-progress"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)


def checkpoint_scratch(out: Path) -> set[str]:
    """The temporary folders of checkpoint writes in `out` (atomic_path names them .checkpoint.npz.*)."""
    from ghsplat_jax.train.run_dir import CHECKPOINT_NAME

    return {p.name for p in out.iterdir() if p.name.startswith(f".{CHECKPOINT_NAME}.")} if out.is_dir() else set()


def steps_logged(out: Path) -> int:
    from ghsplat_jax.train.run_dir import STATS_NAME

    path = out / STATS_NAME
    return len(path.read_text().splitlines()) if path.is_file() else 0


def _wait(proc: subprocess.Popen, condition, timeout: float = 180.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        if condition():
            return True
        time.sleep(0.005)
    return False


def kill_and_resume(data: Path, config: Path, out: Path, moments: list[str], steps: int, checkpoint_every: int,
                    seed: int = 15) -> dict:
    """Kill one `ghsplat train --resume` per moment, then let the last one finish; returns what
    every kill left behind and the finished run's checks. Raises AssertionError on a broken run."""
    from ghsplat_jax.train.checkpoint import read_meta
    from ghsplat_jax.train.run_dir import CHECKPOINT_NAME, PLY_NAME, STATS_NAME

    rng = np.random.default_rng(seed)
    kills = []
    for moment in moments:
        before = steps_logged(out)
        stale = checkpoint_scratch(out)  # left by the previous kill; the resumed run removes it
        writing = lambda: bool(checkpoint_scratch(out) - stale)  # noqa: E731 (a write of this process)
        t0 = time.monotonic()
        proc = launch(data, config, out)
        if moment == "any":
            time.sleep(rng.uniform(0.0, 4.0))
        elif moment == "training":
            assert _wait(proc, lambda: steps_logged(out) > before), _failure(proc)
            time.sleep(rng.uniform(0.0, 0.3))
        elif moment == "checkpoint":
            assert _wait(proc, writing), _failure(proc)
            time.sleep(rng.uniform(0.0, 0.5 * CHECKPOINT_SLEEP))
            assert writing(), "the checkpoint write ended before the kill"
        else:
            raise ValueError(f"unknown moment {moment!r}")
        mid_checkpoint = writing()
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert proc.returncode == -signal.SIGKILL, f"the run ended before the kill ({moment}): {_failure(proc)}"
        proc.stderr.close()
        step = read_meta(out / CHECKPOINT_NAME)["step"] if (out / CHECKPOINT_NAME).exists() else 0
        assert 0 <= step < steps and step % checkpoint_every == 0, f"torn checkpoint at step {step}"
        kills.append({"moment": moment, "killed_after_s": round(time.monotonic() - t0, 3),
                      "steps_logged": steps_logged(out), "checkpoint_step": step,
                      "mid_checkpoint_write": mid_checkpoint})
    t0 = time.monotonic()
    proc = launch(data, config, out)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    logged = [json.loads(line)["step"] for line in (out / STATS_NAME).read_text().splitlines()]
    assert read_meta(out / CHECKPOINT_NAME)["step"] == steps and (out / PLY_NAME).is_file()
    assert logged == list(range(1, steps + 1)), "a step is missing or repeated in stats.jsonl"
    leftovers = [p.name for p in out.iterdir() if p.name.startswith(".")]
    assert not leftovers, f"scratch left behind: {leftovers}"
    return {"kills": kills, "final_resume_s": round(time.monotonic() - t0, 3), "steps": steps,
            "checkpoint_every": checkpoint_every, "resumed_to_the_end": True}


def _failure(proc: subprocess.Popen) -> str:
    return proc.stderr.read() if proc.poll() is not None else "still running"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=15)
    ap.add_argument("--out", default=str(RESULTS / "crash_resume"))
    args = ap.parse_args(argv)

    from ghsplat_jax.io_utils import save_figure, write_json

    moments = [["any", "training", "checkpoint"][i % 3] for i in range(args.kills)]
    with tempfile.TemporaryDirectory(prefix="crash_resume.") as tmp:
        data, config = tiny_run_inputs(Path(tmp), args.steps, 4)
        res = kill_and_resume(data, config, Path(tmp) / "run", moments, args.steps, 4, args.seed)
    res.update(seed=args.seed)
    write_json(args.out + ".json", {"benchmark": "crash_resume", "machine": machine_record(start_backend=False),
                                    "result": res})
    print(json.dumps({k: v for k, v in res.items() if k != "kills"}))

    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 3.5))
    ax = fig.subplots()
    x = np.arange(1, len(res["kills"]) + 1)
    colours = {"any": "C0", "training": "C1", "checkpoint": "C3"}
    for moment, colour in colours.items():
        idx = [i for i, k in enumerate(res["kills"]) if k["moment"] == moment]
        ax.scatter(x[idx], [res["kills"][i]["steps_logged"] for i in idx], color=colour, marker="x",
                   label=f"killed: {moment} (steps logged)")
        ax.scatter(x[idx], [res["kills"][i]["checkpoint_step"] for i in idx], color=colour, marker="o",
                   facecolors="none", label=f"killed: {moment} (checkpoint on disk)")
    ax.set_xlabel("kill number (each followed by --resume)")
    ax.set_ylabel("training step")
    ax.set_title(f"{len(res['kills'])} SIGKILLs, every run resumed to step {res['steps']}")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    save_figure(fig, args.out + ".png")
    print(f"wrote {args.out}.json and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
