"""Exposure compensation against none, on a capture whose photos the exposure check flags (every
number below is read from the runs' files, none typed).

    python benchmarks/analysis/exposure.py --runs runs/exposure_real --out benchmarks/results/exposure_real
    python benchmarks/analysis/exposure.py --check    # OUT/README.md against OUT/results.json

Reads every finished RUNS/SCENE/VARIANT folder (metrics.json, config.toml, per_view.json and,
with compensation, exposure_corrections.json) and the scene's photos as the exposure check sees
them (`data/exposure.py`: the photos more than 1.3x from the median, fitted in linear light on the
SfM tracks). Runs already in OUT/results.json whose folder is gone are kept from there. Writes
OUT/results.json (every run with its test views' PSNR and colour-corrected PSNR, the learnt gains,
the mean and spread per setting, the machine record) and OUT/README.md (generated). --check needs
no run folders and imports no JAX.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tomllib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: readme_check.py
from readme_check import report, text_diff  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "benchmarks" / "results" / "exposure_real"


def run_record(run: Path) -> dict:
    """One finished run: its setting, test scores (mean and per view), count, time and record."""
    m = json.loads((run / "metrics.json").read_text())
    cfg = tomllib.loads((run / "config.toml").read_text())
    views = json.loads((run / "per_view.json").read_text())
    test = m.get("test") or {}
    corrections = run / "exposure_corrections.json"
    gains = {}
    if corrections.is_file():
        from ghsplat_jax.train.exposure import mid_grey_change

        gains = {r["name"]: statistics.fmean(mid_grey_change(r)) for r in json.loads(corrections.read_text())["views"]}
    return {"scene": run.parent.name, "variant": run.name, "seed": cfg.get("seed", 0),
            "compensation": bool(cfg.get("exposure_compensation", False)),
            **{k: test.get(k) for k in ("psnr", "psnr_cc", "ssim", "lpips")},
            "train_psnr": (m.get("train") or {}).get("psnr"), "num_gaussians": m.get("num_gaussians"),
            "train_seconds": m.get("train_seconds"), "steps": m.get("steps"),
            "stop_reason": (m.get("stop") or {}).get("reason"),
            "test_views": [{"name": r["name"], "psnr": r["psnr"], "psnr_cc": r.get("psnr_cc")}
                           for r in views if r["split"] == "test"],
            "gains": gains, "machine": m.get("machine"), "code_revision": m.get("code_revision")}


def exposure_check(config: Path) -> list[dict] | None:
    """The photos the exposure check flags in the data of the run whose config.toml is `config`
    (as it loaded them): name, split, ratio to the median (linear light); None where the check
    cannot tell (no SfM tracks)."""
    from ghsplat_jax.data.exposure import exposure_outliers
    from ghsplat_jax.train.config import load_config
    from ghsplat_jax.train.run_dir import load_training_data

    odd = exposure_outliers(load_training_data(load_config(config)))
    return None if odd is None else [{"name": name, "split": split, "ratio": ratio} for split, name, ratio in odd]


def spread(values: list) -> dict:
    vals = [v for v in values if v is not None]
    return {"mean": statistics.fmean(vals) if vals else None,
            "std": statistics.stdev(vals) if len(vals) > 1 else 0.0, "n": len(vals)}


def summarize(runs: list[dict]) -> list[dict]:
    """Per scene and setting (compensation on or off): mean and spread over its runs, overall and
    per test view."""
    out = []
    for scene in sorted({r["scene"] for r in runs}):
        for on in (False, True):
            group = [r for r in runs if r["scene"] == scene and r["compensation"] == on]
            if not group:
                continue
            names = sorted({v["name"] for r in group for v in r["test_views"]})
            per_view = {n: {k: spread([v[k] for r in group for v in r["test_views"] if v["name"] == n])
                            for k in ("psnr", "psnr_cc")} for n in names}
            out.append({"scene": scene, "compensation": on, "runs": len(group),
                        **{k: spread([r[k] for r in group]) for k in ("psnr", "psnr_cc", "lpips", "num_gaussians",
                                                                      "train_seconds")},
                        "test_views": per_view})
    return out


def fmt(x, spec=".2f") -> str:
    return "-" if x is None else format(x, spec)


def pm(s: dict, spec=".2f") -> str:
    if s["mean"] is None:
        return "-"
    return fmt(s["mean"], spec) + (f" ± {fmt(s['std'], spec)}" if s["n"] > 1 else "")


def readme(res: dict) -> str:
    runs, summary, flagged = res["runs"], res["summary"], res["flagged"]
    lines = ["# Exposure compensation on a capture with auto-exposed photos", "",
             "Generated by `benchmarks/analysis/exposure.py` from `results.json`; do not edit. Runs: "
             "`experiments/exposure_real.toml` (the auto recipe, with `exposure_compensation` on and off).", "",
             "The photos the exposure check flags (ratio to the median photo, linear light):", ""]
    for scene, rows in flagged.items():
        listed = ("not checked (the data has no SfM tracks)" if rows is None else
                  ", ".join(f"{r['name']} ({r['split']}) {r['ratio']:.2f}x" for r in rows) or "none")
        lines.append(f"- {scene}: {listed}")
    lines += ["", "## Per setting (mean ± sd over runs)", "",
              "| scene | compensation | runs | test PSNR | colour-corrected PSNR | LPIPS | surfels | train s |",
              "|---|---|---|---|---|---|---|---|"]
    for s in summary:
        lines.append(f"| {s['scene']} | {'on' if s['compensation'] else 'off'} | {s['runs']} | {pm(s['psnr'])} | "
                     f"{pm(s['psnr_cc'])} | {pm(s['lpips'], '.3f')} | {pm(s['num_gaussians'], ',.0f')} | "
                     f"{pm(s['train_seconds'], '.0f')} |")
    lines += ["", "## Per test view (PSNR / colour-corrected PSNR, mean over runs)", ""]
    for s in summary:
        cells = [f"{n}: {fmt(v['psnr']['mean'])} / {fmt(v['psnr_cc']['mean'])}" for n, v in s["test_views"].items()]
        lines.append(f"- {s['scene']}, compensation {'on' if s['compensation'] else 'off'}: " + "; ".join(cells))
    lines += ["", "## Every run", "",
              "| scene | variant | seed | compensation | test PSNR | colour-corrected | LPIPS | train PSNR | surfels | "
              "train s | steps | learnt gains: flagged training views | the other views | code | load at the end |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        names = [f["name"] for f in flagged.get(r["scene"]) or [] if f["split"] == "train"]
        gains = ", ".join(f"{n} {r['gains'][n]:.2f}" for n in names if n in r["gains"]) or "-"
        others = [g for n, g in r["gains"].items() if n not in names]
        others_cell = f"{min(others):.2f}-{max(others):.2f}" if others else "-"
        load = (r.get("machine") or {}).get("load_average")
        lines.append(f"| {r['scene']} | {r['variant']} | {r['seed']} | {'on' if r['compensation'] else 'off'} | "
                     f"{fmt(r['psnr'])} | {fmt(r['psnr_cc'])} | {fmt(r['lpips'], '.3f')} | {fmt(r['train_psnr'])} | "
                     f"{r['num_gaussians']:,} | {fmt(r['train_seconds'], '.0f')} | {r['steps']} | {gains} | "
                     f"{others_cell} | {(r['code_revision'] or '-')[:10]} | {fmt(load[0] if load else None)} |")
    lines += ["", f"Report made at {res['report']['code_revision'][:10]}. A learnt gain is what a view's "
              "correction makes of a mid-grey (0.5), as a ratio, the mean over its three channels: gain and offset "
              "share an exposure change. It is in display values; the check's ratios are in linear light (about "
              "the display ratio to the power 2.2).", ""]
    return "\n".join(lines)


def check(out: Path = OUT) -> str:
    return text_diff(out / "README.md", readme(json.loads((out / "results.json").read_text())))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, default=ROOT / "runs" / "exposure_real")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--check", action="store_true", help="write nothing: exit 1 if OUT/README.md differs")
    args = ap.parse_args(argv)
    if args.check:
        return report(args.out / "README.md", check(args.out), "what exposure.py renders from results.json")
    sys.path.insert(0, str(ROOT / "benchmarks"))  # record.py
    from record import machine_record

    from ghsplat_jax.io_utils import atomic_write, code_revision, write_json

    runs = [run_record(p.parent) for p in sorted(args.runs.glob("*/*/metrics.json"))]
    previous = json.loads((args.out / "results.json").read_text()) if (args.out / "results.json").is_file() else {}
    present = {(r["scene"], r["variant"]) for r in runs}
    runs += [r for r in previous.get("runs", []) if (r["scene"], r["variant"]) not in present]
    if not runs:
        print(f"no finished runs under {args.runs}", file=sys.stderr)
        return 1
    runs.sort(key=lambda r: (r["scene"], r["compensation"], r["seed"]))
    flagged = dict(previous.get("flagged", {}))
    for scene in sorted({r["scene"] for r in runs} - set(flagged)):  # one check per scene: its first run's data
        config = next(iter(sorted(args.runs.glob(f"{scene}/*/config.toml"))), None)
        if config is not None:
            flagged[scene] = exposure_check(config)
    res = {"report": {"machine": machine_record(start_backend=False), "code_revision": code_revision()},
           "summary": summarize(runs), "flagged": flagged, "runs": runs}
    write_json(args.out / "results.json", res)
    with atomic_write(args.out / "README.md", "w") as fh:
        fh.write(readme(res))
    print(f"wrote {args.out}/results.json and README.md ({len(runs)} runs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
