"""README of the rasterizer ablation at protocol size (raster_ablation, preset auto_cpu).

    python benchmarks/analysis/ablation_readme.py          # writes RESULTS/raster_ablation/auto_cpu/README.md
    python benchmarks/analysis/ablation_readme.py --check  # exit 1 with a diff when the README differs

Reads only committed files: the ablation's results.json (and step_timing.json once
benchmarks/speed/ablation_timing.py has re-timed the steps), the variants' settings in
experiments/raster_ablation.toml, and the seed spread of the auto recipe on the same segment from
benchmarks/results/table1_greenhouse/results.json. Every variant trains with seed 0, so one run
per variant: a difference from the default counts only where it exceeds the noise of two single
runs, 2 * sqrt(2) * the recipe's seed sd on that segment.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tomllib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: readme_check.py
sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/analysis/: the other READMEs' scripts
from auto_recipe import flat, fmt, is_seed, spread  # noqa: E402
from readme_check import text_diff, write_or_check  # noqa: E402
from table1_readme import names, signed, table  # noqa: E402

from ghsplat_jax.experiments.charts import pareto_front  # noqa: E402
from ghsplat_jax.experiments.report import short_revision  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"
EXPERIMENT = ROOT / "experiments" / "raster_ablation.toml"
PRESET = "auto_cpu"
SCRIPT = "benchmarks/analysis/ablation_readme.py"
BASE = "default"
SAME_SPEED = 0.10  # step times within this fraction of the default's are not told apart from it
SAME_GRADIENTS = ("skip_chunks", "skip_none")  # the backward walks pairs that add zero: the same sums


def load(results: Path = RESULTS, experiment: Path = EXPERIMENT) -> dict:
    """Every file the README is made from, parsed."""
    folder = results / "raster_ablation" / PRESET
    timing = folder / "step_timing.json"
    config = tomllib.loads(experiment.read_text())
    return {"rows": [r for r in json.loads((folder / "results.json").read_text())["rows"] if r["split"] == "test"],
            "timing": json.loads(timing.read_text()) if timing.is_file() else None,
            "variants": {v["name"]: flat(v.get("train", {})) for v in config["variants"]},
            "preset": config["presets"][PRESET], "prepare": config["prepare"],
            "table1": json.loads((results / "table1_greenhouse" / "results.json").read_text())["rows"]}


def seed_noise(table1_rows: list[dict], scene: str) -> dict:
    """The auto recipe's test PSNR over its seeds on `scene` (Table 1, same size and recipe)."""
    return spread([r.get("psnr") for r in table1_rows
                   if r["scene"] == scene and r["split"] == "test" and is_seed(r["variant"])])


def revision_named(revision: str | None) -> str:
    """A code revision as the README prints it: `abc1234`, `abc1234+dirty` or not recorded."""
    return f"`{short_revision(revision)}`" if revision else "not recorded"


def setting(overrides: dict) -> str:
    return ", ".join(f"`{k} = {json.dumps(v)}`" for k, v in overrides.items()) or "(the defaults)"


def verdict(delta: float, noise: float) -> str:
    if abs(delta) <= noise:
        return "no"
    return "better" if delta > 0 else "worse"


def pass_ratios(timed: dict, name: str) -> list[float] | None:
    """A variant's step time over the default's in each timing pass (None without two passes of both)."""
    mine, base = timed.get(name, {}).get("pass_seconds_per_step"), timed.get(BASE, {}).get("pass_seconds_per_step")
    if not mine or not base or len(mine) != len(base) or len(mine) < 2:
        return None
    return [a / b for a, b in zip(mine, base)]


def front_summary(by: dict, timed: dict, threshold: float) -> list[str]:
    """Which variants no other beats in interleaved step time and test PSNR together, which cost
    more than SAME_SPEED a step over the default, which differ from it by more than the noise, and
    which it cannot be told from (step times within SAME_SPEED, PSNR within the noise)."""
    runs = [v for v in by if v in timed]
    step = {v: timed[v]["seconds_per_step"] for v in runs}
    gain = {v: by[v]["psnr"] - by[BASE]["psnr"] for v in runs}
    front = [v for v, f in zip(runs, pareto_front([(step[v], by[v]["psnr"]) for v in runs])) if f]
    slower = sorted((v for v in runs if step[v] > (1 + SAME_SPEED) * step[BASE]), key=step.__getitem__)
    beyond = [v for v in runs if v != BASE and abs(gain[v]) > threshold]
    alike = [v for v in runs if v != BASE and v not in beyond and abs(step[v] / step[BASE] - 1) <= SAME_SPEED]
    band = f"{SAME_SPEED:.0%}"

    def listed(xs: list[str]) -> str:
        return names(xs) if xs else "none"

    return ["## Speed against accuracy", "",
            f"- On the front of interleaved step time against test PSNR: {listed([f'`{v}`' for v in front])}.",
            f"- More than {band} slower a step than the default: " + listed(
                [f"`{v}` ({step[v] / step[BASE]:.2f}x, {signed(gain[v], '.2f')} dB)" for v in slower]) + ".",
            f"- Beyond the noise ({threshold:.2f} dB) in PSNR: " + listed(
                [f"`{v}` ({signed(gain[v], '.2f')} dB)" for v in beyond]) + ".",
            f"- Within {band} of the default's step time and within the PSNR noise, so not told apart from the default "
            "by this single-seed run: " + listed([f"`{v}`" for v in alike]) + "."]


def render(data: dict) -> str:
    rows, variants = data["rows"], data["variants"]
    scene_cfg = data["preset"]["scenes"][0]  # the preset's one scene
    scene = scene_cfg["name"]
    by = {r["variant"]: r for r in rows if r["scene"] == scene}
    base = by.get(BASE)
    noise = seed_noise(data["table1"], scene)
    threshold = 2 * math.sqrt(2) * noise["std"] if noise["n"] > 1 else None
    timed = (data["timing"] or {}).get("scenes", {}).get(scene, {})
    passes = (data["timing"] or {}).get("passes", 1)
    revisions = sorted({revision_named(r.get("code_revision")) for r in by.values()})
    hosts = sorted({r.get("host") or "a machine not recorded" for r in by.values()})

    prep, down = data["prepare"], scene_cfg.get("train", {}).get("downscale", 1.0)
    size = f"{round(prep['width'] / down)}x{round(prep['height'] / down)}"
    out = [f"# Rasterizer ablation at protocol size (raster_ablation, preset {PRESET})", "",
           "Every variant changes one rasterizer or loss choice of the defaults and trains with the auto recipe "
           "(self-sized, self-stopped), so a choice is judged by the PSNR, count and time of a whole run. Scene "
           f"{scene} at {size} (Table 1's size), seed 0 for every variant. Made by `ghsplat run "
           f"experiments/raster_ablation.toml --preset {PRESET}`; this README by `{SCRIPT}`.", "",
           f"- Runs: {len(by)} of {len(variants)} variants, on {names(hosts)}, at code {names(revisions)}."]
    if threshold is not None:
        out.append(f"- Noise: the auto recipe's {noise['n']} seeds on {scene} (Table 1) score {noise['mean']:.2f} ± "
                   f"{noise['std']:.2f} dB. The difference of two single runs then has an sd of "
                   f"{threshold / 2:.2f} dB (√2 times), so a variant's difference from the default counts as beyond "
                   f"noise only past twice that, {threshold:.2f} dB.")
    starts = {r["kept_step"] - r["normal_loss_steps"] for r in by.values() if r.get("normal_loss_steps")}
    start = f"step {starts.pop():,}" if len(starts) == 1 else "`normal_from`"
    out.append("- Geometry: depth and normal errors compare only between runs that trained alike under the "
               f"normal-consistency loss. It starts at {start} (2DGS's start, which the auto recipe keeps), and a "
               "self-stopped run returns the model of its best validation check, so a model kept before then has "
               "none of it (\"normal-prior steps\" 0) and the normals of a model without the prior, whatever the "
               "choice ablated.")
    out.append("- Step times: " + (
        f"re-measured interleaved in one process from each run's final checkpoint "
        f"({data['timing']['steps_timed']} steps each"
        + (f" in each of {passes} passes over the same compiled steps, medians over all of them and, in the last "
           "column, each pass's own" if passes > 1 else ", medians")
        + ", at code "
        f"{revision_named(data['timing'].get('code_revision'))}; `step_timing.json`), beside the median each run "
        "logged while it trained. The logged medians also count the early steps at reduced resolution and a "
        "smaller count, so a run that stopped early logs a lower median; the interleaved times are each run's "
        "step at its final count and full resolution, taken under one load, and are the ones to compare." if timed else
        "the median each run logged while it trained; `benchmarks/speed/ablation_timing.py` re-times them "
        "interleaved in one process once every variant has run."))
    out.append("")

    heads = ["variant", "setting", "test PSNR (dB)", "vs default (dB)", "beyond noise", "SSIM", "LPIPS",
             "depth err (m)", "normal err (deg)", "normal-prior steps", "Gaussians", "steps", "train s",
             "logged step s"]
    if timed:
        heads += ["interleaved step s", "vs default"] + (["vs default, each pass"] if passes > 1 else [])
    body = []
    for name, overrides in variants.items():
        r = by.get(name)
        if r is None:
            continue
        delta = r["psnr"] - base["psnr"] if base and name != BASE else None
        cells = [name, setting(overrides), f"{r['psnr']:.2f}", "" if delta is None else signed(delta, ".2f"),
                 "" if delta is None or threshold is None else verdict(delta, threshold),
                 f"{r['ssim']:.3f}", fmt(r.get("lpips"), ".3f"), fmt(r.get("depth_abs_err"), ".4f"),
                 fmt(r.get("normal_err_deg"), ".1f"), fmt(r.get("normal_loss_steps"), ","),
                 f"{r['num_gaussians']:,}", f"{r['steps']:,}", f"{r['train_seconds']:,.0f}",
                 f"{r['step_seconds']:.3f}"]
        if timed:
            step = timed.get(name, {}).get("seconds_per_step")
            ratio = step / timed[BASE]["seconds_per_step"] if step and BASE in timed and name != BASE else None
            cells += [fmt(step, ".3f"), "" if ratio is None else f"{ratio:.2f}x"]
            if passes > 1:
                each = pass_ratios(timed, name)
                cells.append(", ".join(f"{x:.2f}x" for x in each) if each and name != BASE else "")
        body.append(cells)
    out += table(heads, body) + [""]
    if base and BASE in timed and threshold is not None:
        out += front_summary(by, timed, threshold) + [""]

    same = [v for v in SAME_GRADIENTS if v in by and base]
    if same:
        out += ["## Variants that change speed only", "",
                "The default's backward pass walks only the tile-surfel pairs that can change an output; "
                "`skip_chunks` walks every chunk holding such a pair, `skip_none` every pair. The pairs skipped add "
                "exactly zero, so these variants change the time only, and any difference in their result comes "
                "from the order of floating-point additions, grown by the recipe's discrete decisions (when the "
                "count stops growing, when the run stops) into a different run. So it measures the recipe's own "
                "noise at a fixed seed:", ""]
        out += [f"- `{v}`: {signed(by[v]['psnr'] - base['psnr'], '.3f')} dB, {by[v]['num_gaussians']:,} against "
                f"{base['num_gaussians']:,} Gaussians, stopped at step {by[v]['steps']:,} against "
                f"{base['steps']:,}." for v in same]
        out.append("")

    missing = [v for v in variants if v not in by]
    if missing:
        out += ["## Not yet run", "",
                f"{names([f'`{v}`' for v in missing])}. Each trains alone with "
                f"`ghsplat run experiments/raster_ablation.toml --preset {PRESET} --only {scene}/VARIANT` (an "
                "interrupted run resumes from its checkpoint); the report keeps the committed rows of the others.",
                ""]
    return "\n".join(out)


def generate(results: Path = RESULTS) -> str:
    return render(load(results))


def check(readme: Path, results: Path = RESULTS) -> str:
    """'' when `readme` is what the results files give, else a unified diff (committed -> generated)."""
    return text_diff(readme, generate(results))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=RESULTS, help="the benchmarks/results folder to read")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 with a diff if the README differs")
    args = ap.parse_args(argv)
    readme = args.results / "raster_ablation" / PRESET / "README.md"
    return write_or_check(readme, generate(args.results), args.check, SCRIPT)


if __name__ == "__main__":
    sys.exit(main())
