"""Train Table 1 segments side by side on one lent GPU inside one command's time limit.

    python benchmarks/analysis/device_table1.py --segments row0_x1,row2_x0 --end EPOCH_SECONDS --out DIR
    python benchmarks/analysis/device_table1.py --summarize DIR --name NAME   # here, on what came back

Each run is one `ghsplat run EXPERIMENT --preset gpu --only SEG/VARIANT` process. `--parallel`
of the segments' default variants start at once (all by default): one training step at 192x144
leaves much of a GPU idle, so several share it. Every 10 s the script reads each run's
stats.jsonl. When the runs going cannot all finish by `--end` at their measured rates (rescaled
by SHARE_EXPONENT for the runs that would share), it pauses (SIGSTOP) the one furthest from done;
when there is room again it resumes the paused run nearest to done. A run that exits frees its
share for the next waiting run, a remaining default or the compact variant of a finished default
(whose surfel cap comes from that default's final count), when the exited run's own wall time
still fits. At `--end` every process still going is killed: a run that did not finish is
recorded by its stats alone, since its checkpoint is too large to bring back.

DIR gets one SEG.tar.gz per segment (its run folders without checkpoints or PLY files, plus each
process's log) and status.json (machine, decisions, final state), refreshed every minute.
`--summarize` unpacks nothing: point it at the unpacked segment folders and it writes
benchmarks/results/NAME.json, each run's steps per second in 30-s windows of its training time.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tarfile
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from analysis.run_progress import read_jsonl  # noqa: E402
from record import RESULTS, machine_record  # noqa: E402

from ghsplat_jax.train.run_dir import is_evaluated

TICK_S = 10.0
PACK_EVERY_S = 60.0
DECIDE_EVERY_S = 30.0
EVAL_MARGIN_S = 45.0  # evaluation after the last step (renders every view, compiles once)
FINAL_MARGIN_S = 25.0  # packing after the processes are killed
SLOWDOWN = 1.15  # a step got about this much slower from 200k to 300k surfels (fern on an H100)
# Runs sharing one GPU each go (1/k) ** SHARE_EXPONENT as fast as alone: on an H200 at 192x144 a
# default went 86-91 steps/s alone and 33-36 with five sharing (about 41 with four, 50 with three).
SHARE_EXPONENT = 0.55


@dataclass
class Run:
    segment: str
    variant: str
    folder: Path
    proc: subprocess.Popen
    started: float
    paused: bool = False
    done: bool = False
    last_step: int = 0
    history: list = field(default_factory=list)  # (time, step) since it last started or resumed
    rate: float | None = None  # steps per second at the last decision
    sharers: int = 1  # runs going when `rate` was measured

    @property
    def name(self) -> str:
        return f"{self.segment}/{self.variant}"

    def step(self) -> int:
        return self.last_step


def last_stats(path: Path) -> dict | None:
    try:
        with path.open("rb") as f:
            f.seek(max(0, path.stat().st_size - 8192))
            lines = f.read().decode(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        try:
            return json.loads(line)
        except ValueError:
            continue
    return None


def measured_rate(run: Run) -> float | None:
    """Median steps/s over the last three ticks: one recompile stall does not set it."""
    h = run.history[-4:]
    rates = [(b[1] - a[1]) / (b[0] - a[0]) for a, b in zip(h, h[1:]) if b[0] > a[0]]
    return statistics.median(rates) if len(rates) >= 3 else None


def launch(args, segment: str, variant: str) -> Run:
    folder = Path(args.runs) / segment / variant
    logs = Path(args.runs) / segment
    logs.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-c", "import sys; from ghsplat_jax.cli import main; sys.exit(main())", "run",
           args.experiment, "--preset", args.preset, "--only", f"{segment}/{variant}"]
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false", PYTHONUNBUFFERED="1")
    with (logs / f"{variant}.log").open("ab") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    return Run(segment, variant, folder, proc, time.time())


def signal_run(run: Run, sig: int) -> None:
    try:
        os.killpg(run.proc.pid, sig)
    except ProcessLookupError:
        pass


def projected_seconds(runs: list[Run], steps: int) -> float:
    """Time for `runs` to finish if they alone share the GPU: each run's measured rate scaled by
    (sharers then / sharers now) ** SHARE_EXPONENT, and slowed by SLOWDOWN as the surfel count
    still grows."""
    worst = 0.0
    for r in runs:
        rate = r.rate * (r.sharers / len(runs)) ** SHARE_EXPONENT if r.rate else None
        worst = max(worst, SLOWDOWN * (steps - r.step()) / rate + EVAL_MARGIN_S if rate else float("inf"))
    return worst


def decide(going: list[Run], paused: list[Run], left: float, steps: int) -> tuple[str, Run] | None:
    """("pause", run) when the runs going cannot all finish in `left` seconds: the one furthest from
    done; ("resume", run) when the paused run nearest to done fits beside them with 10% to spare."""
    if not going or any(r.rate is None for r in going):
        return None
    if len(going) > 1 and projected_seconds(going, steps) > left:
        return "pause", max(going, key=lambda r: (steps - r.step()) / r.rate)
    if paused:
        nearest = max(paused, key=Run.step)
        if projected_seconds(going + [nearest], steps) < 0.9 * left:
            return "resume", nearest
    return None


def pack(args) -> None:
    """One SEG.tar.gz per segment, written beside and then renamed, so DIR never holds half a file."""
    root = Path(args.runs)
    for seg in sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []:
        tmp = Path(args.out) / f".{seg.name}.tar.gz.tmp"
        with tarfile.open(tmp, "w:gz", compresslevel=6) as tar:
            tar.add(seg, arcname=seg.name,
                    filter=lambda ti: None if ti.name.endswith((".npz", ".ply")) or ".scratch" in ti.name else ti)
        os.replace(tmp, Path(args.out) / f"{seg.name}.tar.gz")


def write_status(args, runs: list[Run], events: list, machine: dict) -> None:
    state = [{"run": r.name, "step": r.step(), "paused": r.paused, "done": r.done,
              "returncode": r.proc.poll(), "rate": r.rate,
              "finished": is_evaluated(r.folder),
              "surfels": (last_stats(r.folder / "stats.jsonl") or {}).get("num_surfels")} for r in runs]
    tmp = Path(args.out) / ".status.json.tmp"
    tmp.write_text(json.dumps({"machine": machine, "runs": state, "events": events}, indent=1))
    os.replace(tmp, Path(args.out) / "status.json")


def machine_facts() -> dict:
    """The machine record with the GPUs nvidia-smi lists; JAX's backend stays unstarted here, so
    this process never claims the GPU its training children use."""
    try:
        gpu = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=20).stdout.strip()
    except (OSError, subprocess.SubprocessError) as exc:
        gpu = f"nvidia-smi failed: {exc}"
    return machine_record(start_backend=False, gpu=gpu)


def rate_windows(stats: Path, window_s: float = 30.0) -> list[dict]:
    """Steps per second in consecutive windows of a run's training time, with its surfel count."""
    rows = read_jsonl(stats)
    out, start = [], 0
    for i, row in enumerate(rows):
        if row["elapsed_s"] >= rows[start]["elapsed_s"] + window_s or i == len(rows) - 1:
            dt = row["elapsed_s"] - rows[start]["elapsed_s"]
            if i - start >= 2 and dt > 0:
                out.append({"from_s": round(rows[start]["elapsed_s"], 1), "to_s": round(row["elapsed_s"], 1),
                            "steps_per_s": round((row["step"] - rows[start]["step"]) / dt, 1),
                            "step": row["step"], "surfels": row["num_surfels"]})
            start = i
    return out


def summarize(folder: Path, name: str) -> Path:
    status = folder / "status.json"
    report = {"status": json.loads(status.read_text()) if status.is_file() else None, "runs": {}}
    for stats in sorted(folder.glob("*/*/stats.jsonl")):
        report["runs"][f"{stats.parent.parent.name}/{stats.parent.name}"] = rate_windows(stats)
    out = RESULTS / f"{name}.json"
    out.write_text(json.dumps(report, indent=1) + "\n")
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--summarize", metavar="DIR", help="write rate windows of the unpacked runs in DIR and stop")
    p.add_argument("--name", default="device_table1", help="--summarize: results file name")
    p.add_argument("--segments", help="comma-separated scene names, e.g. row0_x1,row2_x0")
    p.add_argument("--end", type=float, help="epoch seconds by which the output is packed")
    p.add_argument("--out")
    p.add_argument("--experiment", default="experiments/table1_greenhouse.toml")
    p.add_argument("--preset", default="gpu")
    p.add_argument("--runs", default="runs/table1_greenhouse_gpu", help="the preset's output folder")
    p.add_argument("--steps", type=int, default=30000)
    p.add_argument("--no-compact", action="store_true", help="train the default variants only")
    p.add_argument("--warmup", type=float, default=150.0, help="seconds before the first pause decision")
    p.add_argument("--parallel", type=int, default=0,
                   help="runs started at once (0: every segment); the rest start as runs finish")
    args = p.parse_args()
    if args.summarize:
        print(summarize(Path(args.summarize), args.name))
        return 0
    if not (args.segments and args.end and args.out):
        p.error("--segments, --end and --out are required to train")
    Path(args.out).mkdir(parents=True, exist_ok=True)
    machine = machine_facts()
    t0 = time.time()
    events: list = []

    def note(text: str) -> None:
        events.append({"t": round(time.time() - t0, 1), "event": text})
        print(f"[{time.time() - t0:6.1f}s] {text}", flush=True)

    pending = [(seg, "default") for seg in args.segments.split(",")]
    runs = [launch(args, *pending.pop(0)) for _ in range(min(args.parallel or len(pending), len(pending)))]
    note(f"started {', '.join(r.name for r in runs)}; waiting: {', '.join('/'.join(x) for x in pending) or 'none'}")
    last_pack = last_decision = time.time()
    while time.time() < args.end - FINAL_MARGIN_S:
        time.sleep(TICK_S)
        now = time.time()
        for r in [r for r in runs if not r.done]:
            stats = last_stats(r.folder / "stats.jsonl")
            if stats:
                r.last_step = int(stats["step"])
                if not r.paused:
                    r.history.append((now, r.last_step))
            if r.proc.poll() is None:
                continue
            r.done = True
            ok = is_evaluated(r.folder)
            note(f"{r.name} exited {r.proc.returncode} at step {r.step()} after {now - r.started:.0f} s"
                 f"{'' if ok else ' WITHOUT metrics.json'}")
            if ok and r.variant == "default" and not args.no_compact:
                pending.append((r.segment, "compact"))  # its cap needs this run's final count
            # the next run gets the freed share when a run like this one still fits
            if pending and args.end - FINAL_MARGIN_S - now > 1.1 * (now - r.started):
                runs.append(launch(args, *pending.pop(0)))
                note(f"started {runs[-1].name}")
        going = [r for r in runs if not r.done and not r.paused]
        if now - last_decision >= DECIDE_EVERY_S and now - t0 >= args.warmup and going:
            last_decision = now
            for r in going:
                rate = measured_rate(r)
                if rate is not None:
                    r.rate, r.sharers = rate, len(going)
            left = args.end - FINAL_MARGIN_S - now
            action = decide(going, [r for r in runs if r.paused and not r.done], left, args.steps)
            if action and action[0] == "pause":
                signal_run(action[1], signal.SIGSTOP)
                action[1].paused = True
                note(f"paused {action[1].name} at step {action[1].step()}: {len(going)} runs need "
                     f"{projected_seconds(going, args.steps):.0f} s, {left:.0f} s left")
            elif action:
                signal_run(action[1], signal.SIGCONT)
                action[1].paused, action[1].history = False, []
                note(f"resumed {action[1].name}")
        if all(r.done for r in runs) and not pending:
            note("every run exited")
            break
        if now - last_pack >= PACK_EVERY_S:
            pack(args)
            write_status(args, runs, events, machine)
            last_pack = now
    for r in runs:
        if not r.done:
            signal_run(r, signal.SIGKILL)
            note(f"killed {r.name} at step {r.step()}{' (paused)' if r.paused else ''}")
    time.sleep(1.0)
    pack(args)
    write_status(args, runs, events, machine)
    return 0


if __name__ == "__main__":
    sys.exit(main())
