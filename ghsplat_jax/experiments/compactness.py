"""The compactness report of an experiment (experiments/compactness.toml): PSNR against surfel
count, training time and render time, one line per strategy, and the goal check of issue #14
("at a fifth of the count, within 0.2 dB of the default, with the step time and memory gain").
Ratios are against each scene's reference run: the variant the capped runs take their count
from (`count_of`: the 2DGS default, or the auto recipe's self-sized run in the CPU preset).

Per run it adds, from the run folder: the median step time (seconds per step over the second
half of training, from stats.jsonl: the count has settled there), the training state's size
(checkpoint.npz: parameters, Adam moments and statistics of every pool slot, the memory the
state takes in a training process) and the pool capacity. Peak RSS (metrics.json) is the
process's peak, so it only compares runs trained in separate processes.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ghsplat_jax.curves import psnr_at
from ghsplat_jax.io_utils import atomic_write, machine_info, read_jsonl, save_figure, write_json
from ghsplat_jax.train.run_dir import CHECKPOINT_NAME, TEST_CURVE_NAME, median_step_seconds, read_metrics

GOAL_FRACTION = 0.2
GOAL_DB = 0.2
X_AXES = (  # file stem, row key, axis label
    ("compactness_psnr_vs_count", "num_gaussians", "surfels"),
    ("compactness_psnr_vs_train_time", "train_seconds", "training time (s)"),
    ("compactness_psnr_vs_render_time", "render_seconds_per_view", "render time per view (s, median)"),
)


def run_facts(row: dict) -> dict:
    """The row with step_seconds, state_mib, capacity and peak_rss_mb of its run folder."""
    from ghsplat_jax.train.checkpoint import read_meta

    run = Path(row["run_dir"])
    ck = run / CHECKPOINT_NAME
    meta = read_meta(ck) if ck.is_file() else {}
    m = read_metrics(run) or {}
    return dict(row, step_seconds=median_step_seconds(run, last_fraction=0.5),
                state_mib=ck.stat().st_size / 2**20 if ck.is_file() else None,
                capacity=meta.get("capacity"), peak_rss_mb=m.get("peak_rss_mb"))


def series_name(row: dict) -> str:
    """The chart line of a run: its strategy, with contribution pruning named when it was on."""
    name = row.get("strategy") or row.get("variant") or ""
    return f"{name} + contrib prune" if row.get("contrib_prune") else name


def psnr_by(run_dir, seconds: float) -> float | None:
    """The test PSNR a run had reached after `seconds` of training: its test curve's last point
    at or before then (None without a curve, or before its first point)."""
    return psnr_at(read_jsonl(Path(run_dir) / TEST_CURVE_NAME), seconds)


def psnr_at_time(row: dict, seconds: float | None) -> float | None:
    """Equal time: the test PSNR a run offered after `seconds` of training, its result where it
    had finished by then (a stopped run's best check, not its last step), else its test curve."""
    if not seconds:
        return None
    if row.get("train_seconds") is not None and row["train_seconds"] <= seconds:
        return row["psnr"]
    return psnr_by(row["run_dir"], seconds) if row.get("run_dir") else None


def _ratio(a, b):
    return None if a is None or b in (None, 0) else a / b


def reference_variant(rows: list[dict]) -> str:
    """The variant the capped runs take their count from (their `count_of`), "default" when
    they name none or disagree."""
    named = {r.get("count_of") for r in rows if r.get("count_fraction") is not None} - {None}
    return named.pop() if len(named) == 1 else "default"


def compare(rows: list[dict]) -> list[dict]:
    """Every run beside its scene's reference run (`reference_variant`): PSNR difference and
    count, step-time and state-size ratios."""
    reference = reference_variant(rows)
    refs = {r["scene"]: r for r in rows if r["variant"] == reference}
    out = []
    for r in rows:
        ref = refs.get(r["scene"])
        d = dict(r)
        if ref is not None:
            d["dpsnr"] = None if r["psnr"] is None or ref["psnr"] is None else r["psnr"] - ref["psnr"]
            d["count_ratio"] = _ratio(r["num_gaussians"], ref["num_gaussians"])
            d["step_ratio"] = _ratio(r.get("step_seconds"), ref.get("step_seconds"))
            d["state_ratio"] = _ratio(r.get("state_mib"), ref.get("state_mib"))
            d["render_ratio"] = _ratio(r.get("render_seconds_per_view"), ref.get("render_seconds_per_view"))
            d["psnr_at_reference_time"] = psnr_at_time(r, ref.get("train_seconds"))
        out.append(d)
    return out


def _f(v, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)


def summary_markdown(rows: list[dict], title: str) -> str:
    reference = reference_variant(rows)
    lines = [f"# Compactness: {title}\n",
             "PSNR on the test split (train split where a scene has none), median render time over views, "
             "step time = median seconds per step over the second half of training, state = size of the "
             "training state (checkpoint.npz: every pool slot's parameters, Adam moments and statistics). "
             f"Ratios are against the same scene's `{reference}` run, whose final count the capped runs' "
             "fractions are of; the same seed for every run. "
             "`train s` includes XLA compilation, which JAX's persistent cache shares between runs whose "
             "programs are identical (the first run of a scene pays most of it): compare `step s`. Peak RSS "
             "(compactness.json) is a process peak: it only compares runs trained in separate processes.\n"]
    if reference != "default":  # the goal is stated against the 2DGS default's count
        lines.append(f"No goal check: the capped runs' counts are fractions of `{reference}`'s, not of the 2DGS "
                     "default's.\n")
    else:
        lines += _goal_check(rows)
    timed = any(r.get("psnr_at_reference_time") is not None for r in rows)  # runs that wrote a test curve
    lines.append("## All runs\n")
    if timed:
        lines.append(f"`PSNR at its time`: the test PSNR each run offered after `{reference}`'s training time, an "
                     "equal-time comparison: its result where it had finished by then, else its test curve's last "
                     "point by then.\n")
    lines.append("| scene | variant | strategy | fraction | surfels | PSNR | dPSNR | train s | "
                 + ("PSNR at its time | " if timed else "") + "step s | render s | state MiB | capacity |")
    lines.append("|" + " --- |" * (13 if timed else 12))
    for r in rows:
        at_time = f"{_f(r.get('psnr_at_reference_time'), '{:.2f}')} | " if timed else ""
        lines.append(f"| {r['scene']} | {r['variant']} | {series_name(r)} | "
                     f"{_f(r.get('count_fraction'), '{:.0%}')} | "
                     f"{_f(r['num_gaussians'], '{:,}')} | {_f(r['psnr'], '{:.2f}')} | "
                     f"{_f(r.get('dpsnr'), '{:+.2f}')} | "
                     f"{_f(r.get('train_seconds'), '{:.0f}')} | {at_time}{_f(r.get('step_seconds'), '{:.3f}')} | "
                     f"{_f(r.get('render_seconds_per_view'), '{:.3f}')} | {_f(r.get('state_mib'), '{:.1f}')} | "
                     f"{_f(r.get('capacity'), '{:,}')} |")
    return "\n".join(lines) + "\n"


def _goal_check(rows: list[dict]) -> list[str]:
    """The goal check's section: each run at GOAL_FRACTION of the default's count against it."""
    lines = [f"## Goal check: at {GOAL_FRACTION:.0%} of the default's count, within {GOAL_DB} dB\n"]
    goal = [r for r in rows if r.get("count_fraction") is not None and abs(r["count_fraction"] - GOAL_FRACTION) < 1e-9]
    if not goal:
        return lines + [f"No run at count_fraction = {GOAL_FRACTION} in this set.\n"]
    lines.append("| scene | strategy | surfels (ratio) | PSNR | dPSNR (dB) | within | step s (ratio) | "
                 "state MiB (ratio) | render s (ratio) |")
    lines.append("|" + " --- |" * 9)
    for r in goal:
        ok = None if r.get("dpsnr") is None else r["dpsnr"] >= -GOAL_DB
        lines.append(f"| {r['scene']} | {series_name(r)} | {_f(r['num_gaussians'], '{:,}')} "
                     f"({_f(r.get('count_ratio'), '{:.2f}')}) | {_f(r['psnr'], '{:.2f}')} | "
                     f"{_f(r.get('dpsnr'), '{:+.2f}')} | {'-' if ok is None else ('yes' if ok else 'no')} | "
                     f"{_f(r.get('step_seconds'), '{:.3f}')} ({_f(r.get('step_ratio'), '{:.2f}')}) | "
                     f"{_f(r.get('state_mib'), '{:.1f}')} ({_f(r.get('state_ratio'), '{:.2f}')}) | "
                     f"{_f(r.get('render_seconds_per_view'), '{:.3f}')} ({_f(r.get('render_ratio'), '{:.2f}')}) |")
    met = [r for r in goal if r.get("dpsnr") is not None and r["dpsnr"] >= -GOAL_DB]
    return lines + [f"\n{len(met)} of {len(goal)} runs at {GOAL_FRACTION:.0%} meet the goal.\n"]


def lines_figure(rows: list[dict], x: str, xlabel: str, title: str = ""):
    """One panel per scene, one line per strategy (points sorted by x), the reference run a star."""
    from matplotlib.figure import Figure

    reference = reference_variant(rows)
    scenes = sorted({r["scene"] for r in rows})
    strategies = sorted({series_name(r) for r in rows})
    fig = Figure(figsize=(4.4 * len(scenes), 4.0), dpi=120)
    axes = np.atleast_1d(fig.subplots(1, len(scenes), squeeze=False)[0])
    for ax, scene in zip(axes, scenes):
        for i, s in enumerate(strategies):
            pts = sorted((r[x], r["psnr"], r["variant"]) for r in rows
                         if r["scene"] == scene and series_name(r) == s and r.get(x) is not None
                         and r.get("psnr") is not None)
            if not pts:
                continue
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "-o", color=f"C{i}", label=s, ms=4)
            for p in pts:
                if p[2] == reference:
                    ax.plot([p[0]], [p[1]], "*", color=f"C{i}", ms=12)
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(scene, fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def write_compactness(rows: list[dict], folder, title: str = "") -> list[Path]:
    """compactness.{md,json,csv} and the three charts (each with its numbers as JSON beside it)."""
    from ghsplat_jax.experiments.report import csv_text

    folder = Path(folder)
    rows = compare([run_facts(r) for r in rows])
    made = []
    md = folder / "compactness.md"
    with atomic_write(md, "w") as fh:
        fh.write(summary_markdown(rows, title))
    made.append(md)
    made.append(write_json(folder / "compactness.json", {"title": title, "report": {"machine": machine_info()},
                                                         "rows": rows}))  # each row: its run's machine
    cols = ("scene", "variant", "strategy", "count_fraction", "num_gaussians", "psnr", "dpsnr", "count_ratio",
            "train_seconds", "psnr_at_reference_time", "step_seconds", "step_ratio", "render_seconds_per_view",
            "render_ratio", "state_mib", "state_ratio", "capacity", "peak_rss_mb", "steps", "host", "code_revision")
    with atomic_write(folder / "compactness.csv", "w") as fh:
        fh.write(csv_text(rows, cols))
    made.append(folder / "compactness.csv")
    for stem, x, xlabel in X_AXES:
        if not any(r.get(x) is not None for r in rows):
            continue
        write_json(folder / f"{stem}.json", {"x": x, "y": "psnr", "title": title, "rows": [
            {k: r.get(k) for k in ("scene", "variant", "strategy", x, "psnr")} for r in rows]})
        made.append(save_figure(lines_figure(rows, x, xlabel, title), folder / f"{stem}.png", dpi=120))
    return made
