"""Tables of runs: the paper's Table 1 (L1, PSNR and Gaussian count per segment) and the
full results table of an experiment, as markdown and CSV."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from ghsplat_jax.io_utils import atomic_write, code_revision, host_label, machine_info, write_json
from ghsplat_jax.train.run_dir import kept_step, median_step_seconds, normal_loss_steps, read_metrics

# GreenhouseSplat Table 1 (8 row segments, 2DGS 30k steps): the ranges our runs are compared with.
PAPER_TABLE1 = {"l1": (0.013, 0.023), "psnr": (27.9, 32.1), "num_gaussians": (273_000, 479_000)}

RESULTS_NAME = "results.json"  # an experiment's report of every row (what a later report keeps rows from)
RESULT_COLUMNS = ("experiment", "scene", "variant", "split", "psnr", "psnr_cc", "structure_psnr", "l1", "ssim", "lpips",
                  "depth_abs_err", "normal_err_deg", "num_gaussians", "train_seconds", "step_seconds", "steps",
                  "render_seconds_per_view", "device", "host", "code_revision", "status", "run_dir")


def run_row(run_dir, scene: str | None = None, variant: str | None = None, experiment: str = "") -> dict | None:
    """One table row from RUN_DIR/metrics.json (test metrics, or train when there is no test split)."""
    run_dir = Path(run_dir)
    m = read_metrics(run_dir)
    if m is None:
        return None
    has_test = bool((m.get("test") or {}).get("num_views"))
    kept = kept_step(m)
    split = "test" if has_test else "train"
    s = m[split]
    return {
        "experiment": experiment, "scene": scene or run_dir.name, "variant": variant or "", "split": split,
        "psnr": s.get("psnr"), "psnr_cc": s.get("psnr_cc"), "structure_psnr": s.get("structure_psnr"),
        "l1": s.get("l1"), "ssim": s.get("ssim"),
        "lpips": s.get("lpips"), "depth_abs_err": s.get("depth_abs_err"), "normal_err_deg": s.get("normal_err_deg"),
        "num_gaussians": m.get("num_gaussians"),
        "train_seconds": m.get("train_seconds"), "step_seconds": median_step_seconds(run_dir), "steps": m.get("steps"),
        # the step of the model kept (a self-stopped run's best check), and its steps under the normal prior
        "kept_step": kept, "normal_loss_steps": normal_loss_steps(run_dir, kept),
        "render_seconds_per_view": m.get("render_seconds_per_view"), "device": m.get("device"),
        # where and with what code the run trained, as its training recorded it (None where it did not)
        "machine": m.get("machine"), "host": host_label(m.get("machine")), "code_revision": m.get("code_revision"),
        "run_dir": str(run_dir),
    }


def collect_runs(run_dirs) -> list[dict]:
    rows = [run_row(d) for d in run_dirs]
    return [r for r in rows if r is not None]


_FORMATS = {"l1": "{:.4f}", "psnr": "{:.2f}", "psnr_cc": "{:.2f}", "structure_psnr": "{:.2f}", "ssim": "{:.3f}",
            "lpips": "{:.3f}",
            "num_gaussians": "{:,}",
            "train_seconds": "{:.0f}",
            "step_seconds": "{:.3f}",
            "render_seconds_per_view": "{:.3f}"}


def short_revision(revision: str) -> str:
    """A code revision as a table names it: the sha's first 7 digits, "+dirty" kept."""
    return revision[:7] + revision[40:]


def _fmt(key: str, v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if key == "code_revision":
        return short_revision(v)
    if key == "num_gaussians":
        v = int(v)
    return _FORMATS.get(key, "{}").format(v)


def markdown_table(rows: list[dict], columns, headers=None) -> str:
    headers = headers or columns
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join(" --- " for _ in columns) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(c, r.get(c)) for c in columns) + " |")
    return "\n".join(lines) + "\n"


def csv_text(rows: list[dict], columns) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: ("" if r.get(c) is None else r.get(c)) for c in columns})
    return buf.getvalue()


def table1_rows(rows: list[dict]) -> list[dict]:
    """Table 1 layout: one row per segment (scene, and variant unless every row is the default
    variant: a table holding only the compact runs must say so)."""
    plain = {r.get("variant") for r in rows} <= {"default", "", None}
    out = []
    for r in rows:
        seg = r["scene"] if plain else f"{r['scene']} ({r['variant']})"
        out.append({"segment": seg, "l1": r["l1"], "psnr": r["psnr"], "num_gaussians": r["num_gaussians"],
                    "split": r["split"], "steps": r["steps"], "status": r.get("status") or "finished"})
    return out


def _unfinished(rows: list[dict]) -> list[dict]:
    return [r for r in rows if (r.get("status") or "finished") != "finished"]


def table1_markdown(rows: list[dict], title: str = "Table 1") -> str:
    t1 = table1_rows(rows)
    cols, heads = ("segment", "l1", "psnr", "num_gaussians", "split", "steps"), ("Segment", "L1", "PSNR (dB)",
                                                                                 "Gaussians", "split", "steps")
    stopped = _unfinished(t1)
    if stopped:  # a stopped run keeps its row, marked, never silently left out
        cols, heads = cols + ("status",), heads + ("status",)
    text = [f"# {title}\n", markdown_table(t1, cols, heads)]
    if stopped:
        text.append(f"\n{len(stopped)} of {len(t1)} runs have not finished: their numbers (if any) are not final "
                    "and are left out of the ranges below.\n")
    vals = [r for r in t1 if r["psnr"] is not None and r not in stopped]
    if vals:
        rng = lambda k: (min(r[k] for r in vals), max(r[k] for r in vals))  # noqa: E731
        (l1a, l1b), (pa, pb), (na, nb) = rng("l1"), rng("psnr"), rng("num_gaussians")
        text.append(f"\nThese runs: L1 {l1a:.4f}-{l1b:.4f}, PSNR {pa:.2f}-{pb:.2f} dB, {na:,}-{nb:,} Gaussians.\n")
    p = PAPER_TABLE1
    text.append(f"GreenhouseSplat paper (8 greenhouse row segments, 2DGS, 30k steps): L1 {p['l1'][0]}-{p['l1'][1]}, "
                f"PSNR {p['psnr'][0]}-{p['psnr'][1]} dB, {p['num_gaussians'][0]:,}-{p['num_gaussians'][1]:,} "
                "Gaussians.\n")
    return "".join(text)


def write_table1(rows: list[dict], folder, title: str = "Table 1") -> list[Path]:
    folder = Path(folder)
    md, csv_path = folder / "table1.md", folder / "table1.csv"
    with atomic_write(md, "w") as fh:
        fh.write(table1_markdown(rows, title))
    with atomic_write(csv_path, "w") as fh:
        fh.write(csv_text(table1_rows(rows), ("segment", "l1", "psnr", "num_gaussians", "split", "steps", "status")))
    return [md, csv_path]


def write_results(rows: list[dict], folder, title: str = "Results") -> list[Path]:
    folder = Path(folder)
    md, csv_path = folder / "results.md", folder / "results.csv"
    cols = ("scene", "variant", "split", "psnr", "psnr_cc", "structure_psnr", "l1", "ssim", "lpips", "num_gaussians",
            "train_seconds", "step_seconds", "steps", "render_seconds_per_view", "device", "host", "code_revision",
            "status")
    rows = [dict(r, status=r.get("status") or "finished") for r in rows]
    stopped = _unfinished(rows)
    note = (f"\n{len(stopped)} of {len(rows)} runs have not finished (status): their numbers are not final.\n"
            if stopped else "")
    if any(r.get("code_revision") is None for r in rows):
        note += ("\nmachine and code revision: as each run's metrics.json records them; '-' where a run trained "
                 "before runs recorded them.\n")
    heads = ("scene", "variant", "split", "PSNR (dB)", "colour-corrected PSNR", "structure PSNR", "L1", "SSIM",
             "LPIPS", "Gaussians", "train s", "median step s", "steps", "render s/view", "device", "machine",
             "code revision", "status")
    if all(r.get("psnr_cc") is None for r in rows):  # runs evaluated before the metric existed
        cols, heads = zip(*[(c, h) for c, h in zip(cols, heads) if c != "psnr_cc"])
    with atomic_write(md, "w") as fh:
        fh.write(f"# {title}\n\n" + markdown_table(rows, cols, heads) + note)
    with atomic_write(csv_path, "w") as fh:
        fh.write(csv_text(rows, RESULT_COLUMNS))
    # Each row names the machine and code it trained with; `report` names those that wrote this file.
    js = write_json(folder / RESULTS_NAME, {"title": title, "report": {"machine": machine_info(),
                                                                        "code_revision": code_revision()},
                                            "rows": rows})
    return [md, csv_path, js]
