"""Seconds per training step in windows of the real 30k schedule, old rasterizer settings against new.

    python benchmarks/speed/train_speed.py --checkpoint runs/snap/fern_step1250.npz --config runs/fern30k/config.toml
    python benchmarks/speed/train_speed.py --scene fern            # from initialisation (step 0)
    python benchmarks/speed/train_speed.py --config C --checkpoint K --compare WHAT [...]  # two variants, below

    --compare pool                                # pool as grown vs compacted
    --compare malloc                              # glibc's policy vs host_memory's
    --compare skip                                # backward walks every chunk vs the live pairs
    --compare pairs                               # the checkpoint's pair buffer vs refitted
    --compare pairskip                            # backward walks live chunks vs live pairs
    --compare rev --rev HEAD~2 --rounds 4         # older code vs this
    --compare rev-interleaved --rev HEAD          # the same, one process
    --compare xla --xla-flags="--xla_cpu_..." --rounds 4
    --compare threads                             # one program vs two threads
    --compare partbatch                           # threads' batches of 128 vs 32

Each variant runs real training steps (render, losses, gradients, Adam, densification statistics)
from the same state and views, after a warm-up step that compiles; times are medians. The
"previous" variant is the rasterizer as it trained before this change: the two-pass logspace
compositor, 3-sigma boxes, every output computed, 16-chunk batches. With `--compare pool` both
variants use the current rasterizer and "previous" keeps the checkpoint's surfel pool as it grew
(doubling, before pool buckets), while "current" is compacted to the smallest pool bucket that
holds the live surfels, as the default strategy now does. With `--compare malloc` both use the
same settings and "previous" runs under glibc's default allocation policy, "current" under
`host_memory.reuse_freed_memory` (what the `ghsplat` command sets). The policy is process-wide
and cannot be switched back and forth (a trimmed heap faults in again as it regrows), so each
policy runs in its own child processes (`--rounds`, alternating); the rows pool their steps.
With `--compare skip` and `--compare pairskip` "previous" sets `raster.backward_skip` to "none"
(the carried backward walks every used chunk) or "chunks" (the chunks holding alpha > 0 at a
pixel open at their start, as before pairs were skipped); "current" skips pairs. With `--compare
rev` "previous" runs the code of git revision `--rev` (checked out into a temporary worktree)
and "current" this tree's, in child processes as for malloc: a change's whole effect on the step,
forward and backward. `--compare rev-interleaved` does the same in one process, the revision's
package imported beside this one's (`rev_session`) and the two steps interleaved, so the
machine's drift hits both alike. With `--compare pairs` "current" refits the pair buffer as the trainer
does after an epoch (the bucket of the most pairs a training view needs). With `--compare xla`
"current" adds `--xla-flags` to XLA_FLAGS (compiler options are process-wide: child processes as
for malloc), "previous" runs without them. With `--compare threads` "previous" runs the step as
one program (`step_threads = 1`), "current" with its compositor in two threads. With `--compare
partbatch` both run in two threads, "previous" with the one-program batch (`raster.part_batch_chunks`
= `raster.batch_chunks`), "current" with the config's own part batch. Every row also counts
the page faults per step. The same process also measures the machine's fused exp rate, so
throughputs can be read against it. Writes
benchmarks/results/train_speed.json (results are appended by window) and train_speed.png.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, ROOT, machine_record  # noqa: E402
from speed.raster_speed import exp_rate  # noqa: E402

from ghsplat_jax import host_memory
from ghsplat_jax.io_utils import save_figure, write_json
from ghsplat_jax.paths import datasets_root
from ghsplat_jax.train import trainer
from ghsplat_jax.train.config import TrainConfig, load_config, save_config
from ghsplat_jax.train.run_dir import load_training_data
from ghsplat_jax.train.state import fit_pool

SCENES = {"fern": TrainConfig(data="llff_fern", downscale=8.0),
          "lego": TrainConfig(data="nerf_synthetic_lego", downscale=2.0).replace(background=(1.0, 1.0, 1.0))}
PREVIOUS = dict(compositor="logspace", bounds="box3", batch_chunks=16)  # how training rendered before


def compact_pool(session) -> None:
    session.state = fit_pool(session.state)


def refit_pairs(session) -> None:
    """The pair buffer the trainer refits to after an epoch: the bucket of the most pairs any
    training view needs, with the trainer's headroom."""
    from ghsplat_jax.core.camera import Camera
    from ghsplat_jax.raster.render import count_pairs
    from ghsplat_jax.train.state import render_params

    s, needed = session.state, 0
    for K, w2c in zip(session.Ks, session.w2cs):
        cam = Camera(K, w2c, session.width, session.height)
        surfels = render_params(s.params, s.active, cam.world_to_cam)
        needed = max(needed, int(count_pairs(surfels, cam, session.config.raster)[0]))
    session.pair_capacity = trainer.pair_bucket(needed)


def compiled_session(config: TrainConfig, dataset, checkpoint: Path | None, transform=None):
    """A training session at `checkpoint` (or initialisation), `transform(session)` applied, compiled."""
    session = trainer.TrainingSession(config, Path(tempfile.mkdtemp()), dataset, resume=False)
    return _compiled(session, checkpoint, transform)


def session_class(trainer_module):
    """The trainer's session class in this tree or in an older revision's (which named it _Session,
    and its restore _restore): the benchmark compares revisions."""
    return getattr(trainer_module, "TrainingSession", None) or trainer_module._Session


def _compiled(session, checkpoint: Path | None, transform=None):
    """`session` at `checkpoint` (or as it is), `transform(session)` applied, its step compiled."""
    if checkpoint is not None:
        (getattr(session, "restore", None) or session._restore)(checkpoint)
    if transform is not None:
        transform(session)
    state0 = session.state
    session.step(int(state0.step))  # compile
    session.state = state0
    return session


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _minor_faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def time_steps(configs: dict, dataset, checkpoint: Path | dict | None, steps: int, transforms=None,
               contexts=None) -> dict:
    """Median wall and CPU seconds and page faults per training step for each config, from the
    same checkpoint (or step 0; or {name: checkpoint}, one per config; `transforms` {name: f(session)}
    applied after loading; `contexts` {name: context manager factory} around its compile and
    steps), the configs' steps interleaved (A, B, A, B, ...) so drifting load hits them alike.
    Each row keeps its raw samples."""
    checkpoints = checkpoint if isinstance(checkpoint, dict) else dict.fromkeys(configs, checkpoint)
    transforms, contexts = transforms or {}, contexts or {}
    within = lambda name: contexts.get(name, contextlib.nullcontext)()
    sessions = {}
    for name, cfg in configs.items():
        with within(name):
            sessions[name] = compiled_session(cfg, dataset, checkpoints[name], transforms.get(name))
    return time_sessions(sessions, steps, within)


def time_sessions(sessions: dict, steps: int, within=lambda name: contextlib.nullcontext()) -> dict:
    """`time_steps` for compiled sessions {name: session}, interleaved."""
    starts = {name: int(session.state.step) for name, session in sessions.items()}
    samples = {name: [] for name in sessions}
    for k in range(steps):
        for name, session in sessions.items():
            t0, c0, f0 = time.perf_counter(), time.process_time(), _minor_faults()
            with within(name):
                m = session.step(starts[name] + k)
            samples[name].append((time.perf_counter() - t0, time.process_time() - c0, m["num_pairs"],
                                  _minor_faults() - f0))
    rows = {}
    for name, session in sessions.items():
        rows[name] = step_row(dict(step=starts[name], surfels=int(jnp.sum(session.state.active)),
                               pool=session.state.capacity, pair_capacity=session.pair_capacity),
                          [list(map(float, sample)) for sample in samples[name]])
        print(name, rows[name], flush=True)
    return rows


def step_row(facts: dict, samples: list) -> dict:
    """`facts` and the medians of the timed steps' samples (wall s, CPU s, candidate pairs, page faults)."""
    wall, cpu, pairs, faults = (np.array(v) for v in zip(*samples))
    return facts | dict(candidate_pairs=float(np.median(pairs)), seconds_per_step=float(np.median(wall)),
                        cpu_seconds_per_step=float(np.median(cpu)), page_faults_per_step=int(np.median(faults)),
                        load_average=os.getloadavg()[0], samples=samples)


def time_children(args, variants: dict, rounds: int = 2) -> dict:
    """Rows per variant {name: (source tree, extra environment)}, each from `rounds` child
    processes that time `args.steps` steps of the config with that tree's code, alternating."""
    samples, facts = {name: [] for name in variants}, {}
    for _ in range(rounds):
        for name, (tree, env) in variants.items():
            script = next(p for p in (Path(tree) / "benchmarks" / "speed" / "train_speed.py",
                                      Path(tree) / "benchmarks" / "train_speed.py") if p.is_file())  # older trees
            cmd = [sys.executable, str(script), "--child", "--steps",
                   str(args.steps), "--scene", args.scene]
            cmd += [flag for flag, value in (("--config", args.config), ("--checkpoint", args.checkpoint)) if value
                    for flag in (flag, str(Path(value).resolve()))]
            child_env = dict(os.environ, PYTHONPATH=str(tree), GHSPLAT_DATASETS=str(datasets_root()), **env)
            # In this directory, where a config's relative data path points.
            out = subprocess.run(cmd, env=child_env, cwd=os.getcwd(), check=True, capture_output=True,
                                 text=True).stdout
            row = json.loads(out.strip().splitlines()[-1])
            samples[name] += row.pop("samples")
            facts[name] = {k: row[k] for k in ("step", "surfels", "pool", "pair_capacity")} | dict(
                peak_rss_mb=max(row["peak_rss_mb"], facts.get(name, {}).get("peak_rss_mb", 0.0)))
    return {name: step_row(facts[name], samples[name]) for name in samples}


def time_policies(args) -> dict:
    """Rows "previous" (glibc's default policy) and "current" (host_memory's), this tree's code."""
    return time_children(args, {"previous": (ROOT, {host_memory.OPT_OUT: "1"}),
                                "current": (ROOT, {host_memory.OPT_OUT: "0"})}, args.rounds)


def rev_session(tree: Path, args, checkpoint: Path | None):
    """A compiled training session of the code in `tree`, imported beside this tree's as the
    package `ghsplat_rev` (its source copied with the package name rewritten), so both run in one
    process and their steps interleave: this machine's speed drifts by up to 2x within minutes,
    which child processes one after the other cannot separate from a change's effect."""
    import importlib

    copy = Path(tempfile.mkdtemp(prefix="ghsplat_rev_"))
    for src in (tree / "ghsplat_jax").rglob("*.py"):
        dst = copy / "ghsplat_rev" / src.relative_to(tree / "ghsplat_jax")
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_text(src.read_text().replace("ghsplat_jax", "ghsplat_rev"))
    sys.path.insert(0, str(copy))
    os.environ["GHSPLAT_DATASETS"] = str(datasets_root())  # the copy would look beside itself
    rev = lambda name: importlib.import_module(f"ghsplat_rev.{name}")
    path = args.config
    if not path:  # a scene preset is this tree's TrainConfig: the revision reads it from a file
        path = save_config(SCENES[args.scene], Path(tempfile.mkdtemp()) / "config.toml")
    config = dataclasses.replace(rev("train.config").load_config(path), progress=False, checkpoint_every=0)
    dataset = rev("train.run_dir").load_training_data(config)
    session = session_class(rev("train.trainer"))(config, Path(tempfile.mkdtemp()), dataset, resume=False)
    return _compiled(session, checkpoint)


@contextlib.contextmanager
def checkout(rev: str):
    """A temporary detached worktree of this repository at `rev`."""
    where = Path(tempfile.mkdtemp(prefix="train_speed_rev_")) / "tree"
    subprocess.run(["git", "worktree", "add", "--detach", "-q", str(where), rev], cwd=ROOT, check=True)
    try:
        yield where
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(where)], cwd=ROOT, check=False)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="fern", choices=sorted(SCENES))
    ap.add_argument("--config", help="a run's config.toml (overrides --scene)")
    ap.add_argument("--checkpoint", help="start from this training checkpoint (else from initialisation)")
    ap.add_argument("--steps", type=int, default=10, help="timed steps per variant")
    ap.add_argument("--label", help="name of this window in the results (default: scene@step)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)  # --compare malloc's worker
    ap.add_argument("--compare", choices=("raster", "pool", "malloc", "skip", "pairskip", "pairs", "rev",
                                          "rev-interleaved", "xla", "threads", "partbatch"),
                    default="raster",
                    help="raster: previous rasterizer settings against current; pool: the checkpoint's pool "
                         "against the same state compacted to its live surfels; malloc: glibc's default "
                         "allocation policy against host_memory's; skip: the carried backward walking every "
                         "chunk against the live pairs; pairskip: the chunks holding a live pair against the "
                         "live pairs alone; pairs: the checkpoint's pair buffer against the one the trainer "
                         "refits to after an epoch; rev: the code of git revision --rev against this tree's, "
                         "in child processes; rev-interleaved: the same in one process, steps interleaved; "
                         "xla: XLA_FLAGS as set against with --xla-flags added; threads: the step as one "
                         "program against its compositor in two threads; partbatch: the threads' walks in the "
                         "one-program batch against raster.part_batch_chunks")
    ap.add_argument("--rev", default="HEAD", help="with --compare rev or rev-interleaved: the baseline revision "
                                                  "(default HEAD)")
    ap.add_argument("--xla-flags", default="", help="with --compare xla: the compiler flags to try")
    ap.add_argument("--rounds", type=int, default=2,
                    help="with --compare malloc, rev or xla: child processes per variant")
    args = ap.parse_args(argv)
    config = load_config(args.config) if args.config else SCENES[args.scene]
    config = dataclasses.replace(config, progress=False, checkpoint_every=0)
    dataset = load_training_data(config)
    checkpoint = Path(args.checkpoint) if args.checkpoint else None
    if args.child:  # one policy, set by the parent's environment; prints the row as JSON
        host_memory.reuse_freed_memory()
        row = time_steps({"current": config}, dataset, checkpoint, args.steps)["current"]
        print(json.dumps(row | dict(peak_rss_mb=_peak_rss_mb())))
        return 0
    if args.compare == "malloc":
        rows, previous = time_policies(args), "glibc's default allocation policy"
    elif args.compare == "rev":
        with checkout(args.rev) as tree:
            rev = subprocess.run(["git", "rev-parse", "--short", args.rev], cwd=ROOT, check=True, capture_output=True,
                                 text=True).stdout.strip()
            rows = time_children(args, {"previous": (tree, {}), "current": (ROOT, {})}, args.rounds)
        previous = f"the code of revision {rev} ({args.rev})"
    elif args.compare == "rev-interleaved":
        host_memory.reuse_freed_memory()  # as `ghsplat train` runs (process-wide: both variants)
        with checkout(args.rev) as tree:
            rev = subprocess.run(["git", "rev-parse", "--short", args.rev], cwd=ROOT, check=True, capture_output=True,
                                 text=True).stdout.strip()
            sessions = {"previous": rev_session(tree, args, checkpoint),
                        "current": compiled_session(config, dataset, checkpoint)}
        rows = time_sessions(sessions, args.steps)
        previous = f"the code of revision {rev} ({args.rev}), in the same process, steps interleaved"
    elif args.compare == "xla":
        if not args.xla_flags:
            ap.error("--compare xla needs --xla-flags")
        base = os.environ.get("XLA_FLAGS", "")
        rows = time_children(args, {"previous": (ROOT, {"XLA_FLAGS": base}),
                                    "current": (ROOT, {"XLA_FLAGS": f"{base} {args.xla_flags}".strip()})}, args.rounds)
        previous = f"XLA_FLAGS={base!r}; current adds {args.xla_flags!r}"
    elif args.compare == "pool":
        variants = {"previous": config, "current": config}
        rows = time_steps(variants, dataset, checkpoint, args.steps, {"current": compact_pool})
        previous = "the checkpoint's surfel pool as it grew"
    elif args.compare in ("skip", "pairskip"):
        skip = "none" if args.compare == "skip" else "chunks"
        variants = {"previous": config.replace(**{"raster.backward_skip": skip}), "current": config}
        rows = time_steps(variants, dataset, checkpoint, args.steps)
        previous = f"raster.backward_skip = {skip!r}"
    elif args.compare == "threads":
        variants = {"previous": config.replace(step_threads=1), "current": config.replace(step_threads=2)}
        rows = time_steps(variants, dataset, checkpoint, args.steps)
        previous = "step_threads = 1 (one program); current 2 (train/parted_step.py)"
    elif args.compare == "partbatch":
        same = config.raster.batch_chunks
        variants = {"previous": config.replace(step_threads=2, **{"raster.part_batch_chunks": same}),
                    "current": config.replace(step_threads=2)}
        rows = time_steps(variants, dataset, checkpoint, args.steps)
        previous = f"step_threads = 2 with raster.part_batch_chunks = {same} (the one-program batch)"
    elif args.compare == "pairs":
        variants = {"previous": config, "current": config}
        rows = time_steps(variants, dataset, checkpoint, args.steps, {"current": refit_pairs})
        previous = "the checkpoint's pair buffer"
    else:
        variants = {"previous": config.replace(**{f"raster.{k}": v for k, v in PREVIOUS.items()}), "current": config}
        rows, previous = time_steps(variants, dataset, checkpoint, args.steps), PREVIOUS
    window = dict(rows=rows, speedup=rows["previous"]["seconds_per_step"] / rows["current"]["seconds_per_step"],
                  cpu_speedup=rows["previous"]["cpu_seconds_per_step"] / rows["current"]["cpu_seconds_per_step"],
                  exp_rate_per_s=exp_rate(), peak_rss_mb=_peak_rss_mb(),
                  image=[dataset.train[0].camera.width, dataset.train[0].camera.height], steps_timed=args.steps,
                  compare=args.compare, previous_settings=previous, current_settings=dataclasses.asdict(config.raster))
    label = args.label or f"{Path(config.data).name}@{rows['current']['step']}"
    path = RESULTS / "train_speed.json"
    results = json.loads(path.read_text()) if path.is_file() else {}
    results.setdefault("windows", {})[label] = window
    results["machine"] = machine_record()
    write_json(path, results)
    chart(results["windows"], RESULTS / "train_speed.png")
    print(json.dumps({label: {k: window[k] for k in ("speedup", "cpu_speedup", "exp_rate_per_s")}}, indent=1))
    return 0


def chart(windows: dict, path: Path) -> None:
    from matplotlib.figure import Figure

    labels = list(windows)
    fig = Figure(figsize=(max(7.0, 2.0 * len(labels)), 4.5))
    ax = fig.add_subplot()
    x = np.arange(len(labels))
    for i, name in enumerate(("previous", "current")):
        ax.bar(x + (i - 0.5) * 0.38, [windows[k]["rows"][name]["seconds_per_step"] for k in labels], 0.38, label=name)
    ax.set_xticks(x, [textwrap.fill(k, 24) + f"\n{windows[k]['rows']['current']['surfels']} surfels" for k in labels],
                  fontsize=7)
    ax.set_ylabel("seconds per training step (median)")
    ax.set_title("Training step on a 2-core CPU: previous vs current (rasterizer, surfel pool or malloc policy)")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    raise SystemExit(main())
