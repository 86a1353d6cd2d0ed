"""Write benchmarks/results/table1_greenhouse/README.md from the committed results files: every
number in it is computed here from results.json, segments.json, table1.md (the paper's ranges),
pareto.json, device_h200_sharing.json, ../fusion_profile_step.json, the runs' progress records
(progress/SEGMENT[_compact][_run2].json) and notes.json (the facts no results file records).

    python benchmarks/analysis/table1_readme.py            # rewrite README.md
    python benchmarks/analysis/table1_readme.py --check    # exit 1 with a diff if README.md differs

Statistics: the rank correlation is Spearman's rho with an exact two-sided permutation p-value
(every ordering of the gains), so no statistics package is needed. Imports no JAX unless writing
(ghsplat_jax.io_utils.atomic_write), so the check is quick.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: readme_check.py
sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/analysis/: auto_recipe.py
from auto_recipe import fmt_spread, is_seed, prior_steps, spread  # noqa: E402
from readme_check import text_diff, write_or_check  # noqa: E402

from ghsplat_jax.io_utils import one_machine  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"
NAME = "table1_greenhouse"
SCRIPT = "benchmarks/analysis/table1_readme.py"


# ---------------------------------------------------------------- reading


def load(results: Path = RESULTS) -> dict:
    """Every file the README is made from, parsed."""
    folder = results / NAME
    read = lambda p: json.loads(p.read_text())  # noqa: E731
    progress = {path.stem: read(path) for path in sorted((folder / "progress").glob("*.json"))}
    paper = re.search(r"paper[^:]*: L1 ([\d.]+)-([\d.]+), PSNR ([\d.]+)-([\d.]+) dB, ([\d,]+)-([\d,]+) Gaussians",
                      (folder / "table1.md").read_text())
    if paper is None:
        raise ValueError(f"{folder / 'table1.md'}: no line with the paper's ranges")
    p = paper.groups()
    return {
        "results": read(folder / "results.json"),
        "real": read(real) if (real := results / "auto_recipe" / "real" / "results.json").is_file() else None,
        "full_size": read(f) if (f := results / "auto_recipe" / "table1_384" / "results.json").is_file() else None,
        "auto": read(f) if (f := results / "auto_recipe" / "results.json").is_file() else None,
        "segments": read(folder / "segments.json"),
        "notes": read(folder / "notes.json"),
        "pareto": read(folder / "pareto.json"),
        "sharing": read(folder / "device_h200_sharing.json"),
        "profile": read(results / "fusion_profile_step.json"),
        "progress": progress,
        "compact_configs": sorted(p.name.split("_compact")[0] for p in folder.glob("*_compact_config.toml")),
        "device_time_charts": {read(p)["device"]: p.with_suffix(".png").name
                               for p in sorted(folder.glob("psnr_vs_time_*.json"))},
        "paper": {"l1": (float(p[0]), float(p[1])), "psnr": (float(p[2]), float(p[3])),
                  "num_gaussians": (int(p[4].replace(",", "")), int(p[5].replace(",", "")))},
    }


def run_progress(data: dict, row: dict) -> tuple[str, dict] | tuple[None, None]:
    """The progress record of the run in the table: same run folder and final count."""
    for name, p in data["progress"].items():
        if p.get("run") == row["run_dir"] and p.get("surfels") == row["num_gaussians"] and p.get("finished"):
            return name, p
    return None, None


def train_metrics(data: dict, row: dict) -> dict | None:
    """The training-view metrics of the run in the table, or None when no file records them (its
    progress record must carry the same test PSNR as results.json, so it is the same evaluation)."""
    _, p = run_progress(data, row)
    m = (p or {}).get("metrics") or {}
    if m.get("train") and m.get("test", {}).get("psnr") == row["psnr"]:
        return m["train"]
    return None


def spearman(a: list[float], b: list[float]) -> tuple[float, float]:
    """Spearman's rho (no ties) and its exact two-sided permutation p-value."""
    def ranks(x):
        order = sorted(range(len(x)), key=x.__getitem__)
        r = [0] * len(x)
        for k, i in enumerate(order):
            r[i] = k
        return r

    n, ra = len(a), ranks(a)
    rho = lambda rb: 1 - 6 * sum((p - q) ** 2 for p, q in zip(ra, rb)) / (n * (n * n - 1))  # noqa: E731
    observed = rho(ranks(b))
    perms = list(itertools.permutations(range(n)))
    extreme = sum(abs(rho(p)) >= abs(observed) - 1e-12 for p in perms)
    return observed, extreme / len(perms)


# ---------------------------------------------------------------- formatting


def rng(values, spec: str, sep: str = "-") -> str:
    lo, hi = format(min(values), spec), format(max(values), spec)
    return lo if lo == hi else f"{lo}{sep}{hi}"


def k(n: int) -> str:
    return f"{n / 1000:.0f}k"


def table(heads: list[str], rows: list[list]) -> list[str]:
    return ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)] + [
        "| " + " | ".join(str(c) for c in r) + " |" for r in rows]


def names(xs: list[str]) -> str:
    return xs[0] if len(xs) == 1 else ", ".join(xs[:-1]) + " and " + xs[-1]


def signed(x: float, spec: str) -> str:
    s = format(x, spec)
    return s if s.startswith("-") else "+" + s


def mean_sd(values: list[float], spec: str) -> str:
    """'mean ± sample sd' of the values that are there ('-' for none; one value: no spread)."""
    return fmt_spread(spread(values), spec)


def timed_seconds(rows: list[dict], main_kind: str, among: list[dict]) -> str:
    """'mean ± sd' of the training seconds of the rows on one kind of machine (one_machine, the
    kinds read over `among`), with the kind named where rows on another are left out."""
    kind, timed = one_machine(rows, main_kind, among)
    note = "" if len(timed) == len(rows) else f" ({len(timed)} of {len(rows)} runs: {kind})"
    return mean_sd([r["train_seconds"] for r in timed], ",.0f") + note


# The metrics beyond PSNR (seed_table's columns, quality_against_compact's comparison): key, column,
# words, format; lower is better for each.
QUALITY = (("lpips", "LPIPS", "LPIPS", ".3f"), ("depth_abs_err", "depth err (m)", "depth error", ".4f"),
           ("normal_err_deg", "normal err (deg)", "normal error", ".1f"))


def seed_table(rows: list[dict], first: str) -> list[str]:
    """One row per scene of a variant's seeds: mean ± sd of the test metrics over the seeds that
    record each (how many, where not all do), and of the training seconds of the seeds on one kind
    of machine (one_machine)."""
    body, main_kind = [], one_machine(rows)[0]
    for s in sorted({r["scene"] for r in rows}):
        rs = [r for r in rows if r["scene"] == s]

        def cell(key: str, spec: str) -> str:  # over the seeds that record it, named when not all do
            values = [r.get(key) for r in rs]
            n = sum(v is not None for v in values)
            return mean_sd(values, spec) + ("" if n in (0, len(rs)) else f" ({n} of {len(rs)} seeds)")

        body.append([s, len(rs), cell("psnr", ".2f"), cell("ssim", ".3f")]
                    + [cell(key, spec) for key, _, _, spec in QUALITY]
                    + [cell("num_gaussians", ",.0f"), timed_seconds(rs, main_kind, rows)])
    return table([first, "seeds", "test PSNR (dB)", "SSIM"] + [column for _, column, _, _ in QUALITY]
                 + ["Gaussians", "training s"], body)


def finished_seeds(rows: list[dict], base: str = "auto") -> list[dict]:
    """The rows of `base`'s seeds (by default the auto recipe's) that have a test PSNR (a finished,
    evaluated run)."""
    return [r for r in rows if is_seed(r.get("variant", ""), base) and r.get("psnr") is not None]


def several_seeds(rows: list[dict]) -> list[dict]:
    """The rows of the segments that have more than one of them."""
    return [r for r in rows if sum(x["scene"] == r["scene"] for x in rows) > 1]


def default_seeds_section(rows: list[dict], conditions: dict | None = None) -> list[str]:
    """The 2DGS default over its seeds ("default", "default_seedN") on the segments with more than
    one: its own spread, the LPIPS and geometry errors only its later seeds record, and those
    against the compact variant's seeds. `conditions`: notes.json's, how the machine was shared."""
    runs = several_seeds(finished_seeds(rows, "default"))
    if not runs:
        return []
    known = {k: c for r in runs if (c := (conditions or {}).get(k := f"{r['scene']}/{r['variant']}"))}
    alone = len(known) == len(runs) and all(c.get("alone") for c in known.values())
    how = "; ".join(f"{k}: {c['text']}" for k, c in known.items())
    intro = ("The Table 1 protocol (`default`, seed 0) and `default_seedN`, the same settings with `seed = N`, on the "
             "segments where more than one has finished (mean ± sample sd). The seed-0 runs trained before LPIPS and "
             "the geometry errors were measured and their models were not kept, so those columns are over the other "
             "seeds, as their counts say. Code revisions: " + revision_list(runs) + ". Training seconds are as each "
             "run recorded them" + (f" ({how})" if how else "")
             + ("." if alone else ", so their spread is the machine's as much as the method's."))
    return (["## The 2DGS default over seeds", "", intro, ""] + seed_table(runs, "segment") + [""]
            + quality_against_compact(runs, finished_seeds(rows, "compact")))


def quality_against_compact(defaults: list[dict], compacts: list[dict]) -> list[str]:
    """The metrics beyond PSNR, the default's seeds against the compact variant's on the segments
    where both record them: whether the compact's PSNR gain holds in the perceptual and geometric
    errors too (each a mean over the seeds that record it, their count named)."""
    body, worse = [], []  # worse: "segment (metrics where the compact's mean is higher)"
    for seg in sorted({r["scene"] for r in defaults}):
        d = [r for r in defaults if r["scene"] == seg]
        c = [r for r in compacts if r["scene"] == seg]
        pairs = [(spread([r.get(key) for r in d]), spread([r.get(key) for r in c]), words, spec)
                 for key, _, words, spec in QUALITY]
        if not all(sd["n"] and sc["n"] for sd, sc, _, _ in pairs):
            continue
        body.append([seg] + [f"{fmt_spread(x, spec)} ({x['n']})" for sd, sc, _, spec in pairs for x in (sd, sc)])
        if higher := [words for sd, sc, words, _ in pairs if sc["mean"] > sd["mean"]]:
            worse.append(f"{seg} ({names(higher)})")
    if not body:
        return []
    heads = ["segment"] + [f"{column}: {v}" for _, column, _, _ in QUALITY for v in ("default", "compact")]
    verdict = (f"The compact variant's mean is worse on {names(worse)}: its PSNR gain does not hold in every "
               "metric." if worse else "The compact variant's mean is as good or better in each.")
    return ["Against the compact variant's seeds, in the metrics beyond PSNR (lower is better; mean ± sample sd "
            "over the seeds that record each, their count in brackets). " + verdict, ""] + table(heads, body) + [""]


def auto_recipe_settings() -> dict:
    """The auto recipe's settings as the code sets them (train/recipes.py, read on its own: the
    train package would import JAX)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("recipes", ROOT / "ghsplat_jax" / "train" / "recipes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.RECIPES["auto"]


def prior_note(auto: dict | None, readme: str) -> str:
    """How many of the recipe's seeds in an auto_recipe results.json kept a model that never trained
    under the normal prior, and where the README groups the geometry by it ('' without records)."""
    seeds = [r for r in finished_seeds((auto or {}).get("runs", [])) if r.get("normal_err_deg") is not None]
    steps = [prior_steps(r) for r in seeds]
    if not seeds or None in steps:
        return ""
    share = f"All {len(seeds)}" if steps.count(0) == len(seeds) else f"{steps.count(0)} of the {len(seeds)}"
    settle = auto_recipe_settings().get("normal_settle")
    before = [r for r in seeds if not (r.get("settings") or {}).get("normal_settle")]
    return (f" {share} runs kept a model from before the normal-consistency loss "
            "started (their best validation check came before it), so their normal errors are those of a model "
            f"without it: [{readme}]({readme}#geometry-against-the-normal-priors-steps-in-the-kept-model)."
            + (f" {'These' if len(before) == len(seeds) else f'{len(before)} of them'} trained before the recipe "
               f"kept only a model with {settle:,} steps of it (`normal_settle`; its `auto_settle` rows there)."
               if settle and before else ""))


def auto_section(rows: list[dict], auto: dict | None = None) -> list[str]:
    """The auto recipe's rows, per segment: mean ± sd over its seeds of the test metrics."""
    auto_rows = finished_seeds(rows)
    if not auto_rows:
        return []
    return ["## The auto recipe (self-sizing, self-stopping)", "",
            "`recipe = \"auto\"` on the same segments at the same size, one row per segment over the seeds that "
            "finished (mean ± sample sd); LPIPS (VGG), median depth error and mean normal error on the test views, "
            "the geometry against the procedural scene's ray-cast depth and normals (the model carried into the "
            "scene's frame by its SfM's similarity onto the exact cameras, so the SfM's pose error is in them). "
            "Curves, ablations and the equal-time comparison: [../auto_recipe/README.md](../auto_recipe/README.md)."
            + prior_note(auto, "../auto_recipe/README.md"), ""] + seed_table(auto_rows, "segment") + [""]


def full_size_section(full: dict | None) -> list[str]:
    """The auto recipe at the photos' own 384x288 (benchmarks/results/auto_recipe/table1_384/results.json)."""
    runs = finished_seeds((full or {}).get("runs", []))
    if not runs:
        return []
    return ["## The auto recipe at the photos' own 384x288", "",
            "The same recipe on the same segments' photos at their own size, 4x the pixels of the tables above "
            "(`ghsplat run experiments/table1_greenhouse.toml --preset auto_384`). No default or compact rows: each "
            "would need a default run at 384x288 first, hours a segment on this CPU. One row per segment with a "
            "finished run; mean ± sample sd over the seeds that finished; per-run rows and curves: "
            "[../auto_recipe/table1_384/README.md](../auto_recipe/table1_384/README.md)."
            + prior_note(full, "../auto_recipe/table1_384/README.md"), ""] + seed_table(runs, "segment") + [""]


def real_section(real: dict | None) -> list[str]:
    """The auto recipe on real captures (benchmarks/results/auto_recipe/real/results.json), per scene."""
    runs = finished_seeds((real or {}).get("runs", []))
    if not runs:
        return []
    machines = sorted({(r.get("machine") or {}).get("processor", "unrecorded") for r in runs})
    return ["## Real captures (the auto recipe)", "",
            "The same recipe, unchanged, on real photos (`experiments/auto_real.toml`: shared captures, and a real "
            "plant fetched from a public repository with its provenance by `benchmarks/data/fetch_capture.py`, "
            "posed by `ghsplat sfm`). One row per capture with a finished run; mean ± sample sd over the seeds that "
            "finished; no geometric ground truth, so no depth or normal error. Every run records its machine and "
            f"code revision ({', '.join(machines)}); per-run rows, curves and goals: "
            "[../auto_recipe/real/README.md](../auto_recipe/real/README.md).", ""] + seed_table(runs, "capture") + [""]


def revision_list(rows: list[dict]) -> str:
    """The code revisions `rows` trained at (first 7 digits), and how many recorded none."""
    known = sorted({r["code_revision"][:7] for r in rows if r.get("code_revision")})
    missing = sum(not r.get("code_revision") for r in rows)
    return ", ".join(known + ([f"{missing} not recorded"] if missing else []))


def compact_seeds_section(rows: list[dict]) -> list[str]:
    """The compact variant over its seeds ("compact", "compact_seedN"), on the segments with more
    than one, against the default's seeds there: does its gain lie outside the seeds' spread?"""
    done = finished_seeds(rows, "compact")
    main_kind = one_machine(done, among=rows)[0]
    defaults = finished_seeds(rows, "default")
    body, judged = [], []
    for seg in sorted({r["scene"] for r in done}):
        rs = [r for r in done if r["scene"] == seg]
        base = spread([r["psnr"] for r in defaults if r["scene"] == seg])
        if len(rs) < 2 or not base["n"]:
            continue
        judged += rs
        compact = spread([r["psnr"] for r in rs])
        gain, sd = compact["mean"] - base["mean"], (compact["std"] ** 2 + base["std"] ** 2) ** 0.5
        smallest = compact["min"] - base["max"]
        outside = smallest > 0 and gain > 2 * sd
        body.append([seg, f"{len(rs)} and {base['n']}", fmt_spread(compact, ".2f"),
                     fmt_spread(base, ".2f"), f"{gain:+.2f} ± {sd:.2f}",
                     f"{smallest:+.2f}", "yes" if outside else "no", mean_sd([r["num_gaussians"] for r in rs], ",.0f"),
                     timed_seconds(rs, main_kind, rows), revision_list(rs)])
    if not body:
        return []
    return ["## The compact variant over seeds", "",
            "The compact variant (`compact`, seed 0, and `compact_seedN`: the same settings with `seed = N`) on the "
            "segments where it has more than one seed, against the default's seeds there (`default` and any "
            "`default_seedN`; with one, its own spread is not in these numbers). The gain is the difference of the "
            "means, ± the two sample sds combined; the smallest gain is the worst compact seed against the best "
            "default seed. The gain lies outside the spread when every compact seed beats every default seed and "
            "the mean gain exceeds twice that sd. The compact seeds trained at different code revisions where the "
            "last column names more than one (a row whose run trained before rows recorded it: \"not recorded\"); "
            "seeds trained after the MCMC pool grew with the count use the same relocation, growth and noise with "
            "other random draws.", ""] + table(
        ["segment", "seeds (compact and default)", "compact test PSNR (dB)", "default test PSNR (dB)", "gain (dB)",
         "smallest gain", "outside the spread", "Gaussians", "training s", "code revisions"], body) + [
        "", "The same compact seeds' test metrics (mean ± sample sd; LPIPS and the geometry errors over the seeds "
        "that record them, as the counts say: the seed-0 runs trained before they were measured):", ""] + (
        seed_table(judged, "segment") + [""])


# ---------------------------------------------------------------- the README


def crosscheck_note(path: Path = RESULTS / "sfm_crosscheck" / "results.json") -> str:
    """What the SfM's leave-one-out cross-check makes of row3_x0's photos (its committed results),
    or that the segments' models predate it."""
    rows = json.loads(path.read_text())["rows"] if path.is_file() else []
    after = next((r for r in rows if r["case"] == "row3_x0" and r["variant"] == "after"), None)
    if after is None:
        return "No check of the segments' SfM caught that."
    dropped = ", ".join(d.split(" (")[0] for d in after["cross_check_dropped"] or []) or "nothing"
    return (f"The segments' models predate the SfM's leave-one-out cross-check, which on these photos drops "
            f"{dropped} and leaves {after['centre_error_max_pct']:.2f}% max centre error and "
            f"{after['rotation_error_max_deg']:.2f} degrees (`../sfm_crosscheck/README.md`).")


def render(data: dict) -> str:
    rows = data["results"]["rows"]
    notes = data["notes"]
    by = {(r["scene"], r["variant"]): r for r in rows}
    finished = [r for r in rows if r.get("psnr") is not None and r["steps"] == max(x["steps"] for x in rows)]
    segs = sorted({r["scene"] for r in finished})
    both = [s for s in segs if (s, "default") in by and (s, "compact") in by]
    d = {s: by[s, "default"] for s in both}
    c = {s: by[s, "compact"] for s in both}
    steps = max(r["steps"] for r in finished)
    cap = data["segments"]["capture"]
    seginfo = {s["segment"]: s for s in data["segments"]["segments"]}
    down = {p["downscale"] for p in data["progress"].values()}
    (downscale,) = down
    w, h = int(cap["width"] / downscale), int(cap["height"] / downscale)
    gpu_rows = [r for r in finished if r.get("device") not in (None, "cpu")]
    gpu_seg = gpu_rows[0]["scene"] if len(gpu_rows) == 1 and gpu_rows[0]["variant"] == "default" else None
    gpu_name = gpu_rows[0]["device"] if gpu_rows else None
    gpu_short = gpu_name.replace("NVIDIA ", "") if gpu_name else None
    train = {(s, v): train_metrics(data, by[s, v]) for s in both for v in ("default", "compact")}  # the table's runs
    out = ["# Table 1 on a greenhouse: where the runs stand", "",
           f"Generated by `{SCRIPT}` from the committed results files; do not edit by hand (numbers are computed "
           "from the results files; the facts no results file records are in `notes.json`). "
           "`notebooks/results.ipynb` draws these results (tables, fronts, curves) from the same files.", "",
           f"`experiments/{NAME}.toml`: a procedural four-row cucumber greenhouse, both ends of every row "
           f"photographed hand-held ({len(seginfo)} segments, {cap['views']} photos of {cap['width']}x{cap['height']} "
           f"each), SfM on each segment (`segments.md`), then 2DGS training at {w}x{h} (downscale {downscale:g}) for "
           f"{steps:,} steps. Everything was measured on one 2-core CPU"
           + (f", except {gpu_seg}'s default run, which trained on a lent {gpu_short} (below)." if gpu_seg else "."),
           ""]

    # -------- Table of finished runs
    all_done = len(both) == len(seginfo)
    out += [f"## Finished: both variants of {'all ' if all_done else ''}{len(both)} segments", ""]
    label = {"default": "default (the Table 1 protocol)", "compact": "compact (mcmc, a fifth of the count)"}
    trs = []
    for s in both:
        for v in ("default", "compact"):
            r = by[s, v]
            lab = label[v] if r.get("device") in (None, "cpu") else label[v][:-1] + f"; trained on an {gpu_short})"
            t = train[s, v]
            trs.append([s, lab, f"{r['steps']:,}", f"{r['psnr']:.2f}", f"{r['l1']:.4f}", f"{r['ssim']:.3f}",
                        f"{r['num_gaussians']:,}", "not recorded" if t is None else f"{t['psnr']:.2f}"])
    out += table(["segment", "variant", "steps", "test PSNR (dB)", "test L1", "test SSIM", "Gaussians",
                  "train PSNR (dB)"], trs)
    missing_train = sorted({s for (s, v), t in train.items() if t is None})
    out.append("")

    # held-out split: every 8th registered view (cross-checked with the recorded view counts)
    n_test = {s: len(range(0, seginfo[s]["registered"], 8)) for s in both}
    n_train = {s: seginfo[s]["registered"] - n_test[s] for s in both}
    for (s, _), t in train.items():
        if t is not None and t.get("num_views") not in (None, n_train[s]):
            raise ValueError(f"{s}: {t['num_views']} training views recorded, {n_train[s]} expected")

    def groups(counts):
        vals = sorted(set(counts.values()))
        return vals, {v: [s for s in both if counts[s] == v] for v in vals}

    tv, tg = groups(n_test)
    test_txt = ", ".join(f"{v} for {names(tg[v])}" for v in tv[:-1]) + f", {tv[-1]} for the others" \
        if len(tv) > 1 else f"{tv[0]} for each"
    rv, rgp = groups(n_train)
    train_txt = ", ".join(f"{v} for {names(rgp[v])}" for v in rv)
    out.append(f"- **Evaluation.** Test metrics are means over the segment's held-out views (every 8th registered "
               f"photo: {test_txt}); the models trained on the other registered views ({train_txt}). "
               "`table1.md` has the paper's layout and `results.md` every column."
               + (f" The training-view PSNR of {names(missing_train)} is not recorded: its run folders are gone "
                  "and no progress record carries its final evaluation." if missing_train else "")
               + (" These rows have no LPIPS or depth and normal errors: they trained before those were measured, "
                  "and their models were not kept. A variant's other seeds carry them where it has some (\"over "
                  "seeds\", below)." if any(by[s, v].get("lpips") is None for s in both for v in ("default", "compact"))
                  else ""))

    # -------- compact against default
    gap = {s: train[s, "default"]["psnr"] - d[s]["psnr"] for s in both if train[s, "default"] is not None}
    gain = {s: c[s]["psnr"] - d[s]["psnr"] for s in both}
    dl1 = {s: c[s]["l1"] - d[s]["l1"] for s in both}
    dssim = {s: c[s]["ssim"] - d[s]["ssim"] for s in both}
    higher = [s for s in both if gain[s] > 0]
    within = [s for s in both if gain[s] >= -0.2]
    worse_l1 = [s for s in both if round(dl1[s], 4) > 0]
    worse_ssim = [s for s in both if round(dssim[s], 3) < 0]
    frac = {s: c[s]["num_gaussians"] / d[s]["num_gaussians"] for s in both}
    n_all = "all " + str(len(both)) if len(higher) == len(both) else f"{len(higher)} of {len(both)}"
    sent = [f"- **Compact against default, segment by segment.** The default over-fits: it fits its training views "
            f"{rng(gap.values(), '.0f')} dB better than the held-out ones"
            + (f" (on the {len(gap)} segments whose training PSNR is recorded)" if len(gap) < len(both) else "")
            + f". At {rng(frac.values(), '.1%')} of the surfels, the compact variant's held-out PSNR is higher on "
            f"{n_all} segments"]
    sent.append(", so every one meets the compactness goal (within 0.2 dB of the default at a fifth of the count)."
                if len(within) == len(both) else f"; {len(within)} meet the compactness goal (within 0.2 dB of the "
                "default at a fifth of the count).")
    if worse_l1:
        sent.append(f" Its L1 is slightly worse on {len(worse_l1)} ({names(worse_l1)}, by "
                    f"{rng([dl1[s] for s in worse_l1], '.4f')})")
    if worse_ssim:
        sent.append(f" and its SSIM on {len(worse_ssim)} ({names(worse_ssim)}, by "
                    f"{rng([-dssim[s] for s in worse_ssim], '.3f')})")
    sent.append(". The table below holds only these differences, each computed from the unrounded values in "
                "`results.json` (and the progress records) and then rounded, so a difference can differ by 0.01 "
                "from one taken between the rounded numbers above.")
    out.append("".join(sent))
    out.append("")
    out += table(["segment", "default: training minus held-out PSNR (dB)", "compact gain in held-out PSNR (dB)",
                  "compact minus default L1", "compact minus default SSIM"],
                 [[s + (f" (default on an {gpu_short})" if s == gpu_seg else ""),
                   "not recorded" if s not in gap else f"{gap[s]:.2f}", signed(gain[s], ".2f"),
                   signed(dl1[s], ".4f"), signed(dssim[s], ".3f")] for s in both])
    out.append("")

    # -------- rank correlation
    corr = [s for s in both if s in gap]
    rho, p = spearman([gap[s] for s in corr], [gain[s] for s in corr])
    left = [s for s in both if s not in gap]
    verdict = ("no finding. The gain is positive everywhere; these points do not show that its size follows the "
               "default's over-fit." if p >= 0.05 else "the gain grows with the default's over-fit at the 5% level.")
    out.append(f"- **Does the gain grow with over-fitting?** Spearman's rank correlation between the default's gap "
               f"and the compact gain over the {len(corr)} segments whose gap is recorded"
               + (f" ({names(left)}'s is not)" if left else "")
               + f" is **{rho:.2f} (exact two-sided permutation p = {p:.2f})**: {verdict}")

    # -------- paper
    def span(rs, key, spec):
        return rng([r[key] for r in rs], spec)
    pp = data["paper"]
    out.append(f"- **Compared with the paper.** Here the defaults gave L1 {span(d.values(), 'l1', '.4f')}, PSNR "
               f"{span(d.values(), 'psnr', '.2f')} dB and {span(d.values(), 'num_gaussians', ',')} Gaussians; the "
               f"compact runs L1 {span(c.values(), 'l1', '.4f')}, PSNR {span(c.values(), 'psnr', '.2f')} dB and "
               f"{span(c.values(), 'num_gaussians', ',')} Gaussians. The paper's 8 real segments gave L1 "
               f"{pp['l1'][0]}-{pp['l1'][1]}, PSNR {pp['psnr'][0]}-{pp['psnr'][1]} dB and "
               f"{k(pp['num_gaussians'][0])}-{k(pp['num_gaussians'][1])} Gaussians, at full photo resolution. "
               f"These are procedural segments at {w}x{h}: the numbers sit side by side, and they are not a "
               "like-for-like comparison.")
    out.append("")

    # -------- training time
    sharing = data["sharing"]
    pauses = [e["t"] for e in sharing["status"]["events"] if e["event"].startswith("paused")]
    shared_until = max(pauses)
    cond = {}
    for s in both:
        for v in ("default", "compact"):
            r, n = by[s, v], notes["conditions"].get(f"{s}/{v}", {})
            text = n.get("text", "conditions not recorded")
            if r.get("device") not in (None, "cpu"):
                text = f"on an {r['device']}; the first {shared_until:.0f} s shared with {len(pauses)} other runs"
            _, prog = run_progress(data, r)
            st = (prog or {}).get("stalls")
            if n.get("estimate_without_stalls") and st:
                text += (f"; about {(prog['elapsed_s'] - st['seconds']) / 3600:.1f} h without its "
                         f"{st['seconds']:,.0f} s of stalls")
            cond[s, v] = text

    def window_range(r):
        _, prog = run_progress(data, r)
        if prog is None:
            return "-"
        ws = [x["median_seconds_per_step"] for x in prog["windows"].values() if x["surfels"] == prog["surfels"]]
        spec = ".3f"
        return rng(ws, spec) if ws else "-"

    out += ["## Training time", "",
            "Wall seconds and the median step time are `results.json`'s; the step time at the full count is the "
            "range of the median step times of the 100-step windows the progress record took once the count had "
            "reached its final value; how the machine was shared is from `notes.json`.", ""]
    tt = []
    for s in both:
        cells = [s]
        for v in ("default", "compact"):
            r = by[s, v]
            wall = f"{r['train_seconds']:,.0f} ({cond[s, v]})"
            cells += ["**" + wall + "**" if notes["conditions"].get(f"{s}/{v}", {}).get("text", "").endswith(
                "measured whole") or r.get("device") not in (None, "cpu") else wall,
                      f"{r['step_seconds']:.3f}", window_range(r)]
        tt.append(cells)
    out += table(["segment", "default: training wall s", "default: median s a step", "default: s a step at the "
                  "full count", "compact: training wall s", "compact: median s a step",
                  "compact: s a step at the full count"], tt)
    out.append("")

    alone = lambda v: [by[s, v]["train_seconds"] for s in both  # noqa: E731
                       if notes["conditions"].get(f"{s}/{v}", {}).get("alone")
                       and by[s, v].get("device") in (None, "cpu")]
    last_change = []
    for s in both:
        _, prog = run_progress(data, d[s])
        if prog:
            cs, st = prog["curve"]["surfels"], prog["curve"]["step"]
            last_change.append(max(st[i] for i in range(1, len(cs)) if cs[i] != cs[i - 1]))
    out.append(f"- A default segment takes about {rng([x / 3600 for x in alone('default')], '.1f')} h of this 2-core "
               f"CPU alone, a compact one {rng([x / 60 for x in alone('compact')], '.0f')} min (the runs marked alone "
               f"above). The surfel count, not the pixel count, sets the step time: 2DGS's densification reaches "
               f"{rng([k(r['num_gaussians']) for r in d.values()], 's')} surfels at {w}x{h}, and the count stops "
               f"changing by step {max(last_change):,} in every default's progress curve.")
    share = notes["concurrency"]["machine_share"]
    out.append(f"- Two segments trained at once buy nothing on two cores: each run's share of its own alone speed "
               f"adds up to {share[0]:.2f}-{share[1]:.2f} of the machine (45 s windows, row0_x0 and row0_x1 alone and "
               "together, twice), so segments run one after another.")
    key = next(k_ for k_ in data["profile"] if k_.startswith("t1_row1_x1_final"))
    prof = data["profile"][key]
    thr = prof["thread_ms_per_step"]
    by_file = prof["rest_of_step_ms_by_file"]
    sorts = sum(op["ms_per_step"] for op in prof["top_ops"] if op["region"] == "rest of the step"
                and any("sort" in src for src in op["source"]) and op["op"].startswith("pure_callback"))
    prof_seg = prof["run"].split("/")[-2]
    out.append(f"- Profiled from {prof_seg}'s final checkpoint (one program, {prof['steps']} steps; "
               f"`../fusion_profile_step.json`, window `{key}`): {prof['step_wall_s'] * 1000:.0f} ms a step, and "
               f"{thr['rest of the step']:.0f} ms of its {sum(thr.values()):.0f} ms of op thread time lie outside the "
               f"compositor's loops (binning {by_file['binning.py']:.0f} ms, of which the two sorts {sorts:.0f}; "
               f"projection {by_file['project.py']:.0f}; SH colour {by_file['sh.py']:.0f}; Adam and the rest of the "
               f"update {by_file['step.py'] + by_file['transform.py']:.0f}): at this count per-surfel work, not the "
               "pixels, sets the step.")
    first_pause = min(pauses)
    runs = sharing["runs"]
    shared_rates = [x["steps_per_s"] for ws in runs.values() for x in ws if x["to_s"] <= first_pause]
    gpu_run = next(r for r in sharing["status"]["runs"] if r["finished"])["run"]
    alone_rates = sorted(x["steps_per_s"] for x in runs[gpu_run] if x["from_s"] >= shared_until)
    med = lambda xs: (sorted(xs)[(len(xs) - 1) // 2] + sorted(xs)[len(xs) // 2]) / 2  # noqa: E731
    per_run_shared = [med([x["steps_per_s"] for x in ws if x["to_s"] <= first_pause]) for ws in runs.values()]
    out.append(f"- On a GPU, `ghsplat bench device_table1 --preset gpu` trains segments with the surfel pool, pair "
               f"buffer and batches sized up front (the result does not depend on these sizes). {len(runs)} runs "
               f"sharing one {gpu_short} went {rng(shared_rates, '.0f')} steps/s each (30 s windows before the first "
               f"pause), about {sum(per_run_shared) / med(alone_rates):.1f}x one run alone in total "
               f"(`device_h200_sharing.json`); a run alone went a median {med(alone_rates):.0f} steps/s "
               f"({rng(alone_rates, '.0f')} over its {len(alone_rates)} windows alone). A default needs about "
               f"{notes['gpu_default_seconds_alone']['seconds']} s of a GPU to itself.")
    no_device = [f"{r['scene']}/{r['variant']}" for r in finished if r.get("device") is None]
    left_out = [s for s, v in data["pareto"]["scenes"].items() if "left_out" in v]
    out.append("- Each run's `metrics.json` names its device (`\"cpu\"`, or the accelerator's kind); `results.md` has "
               "a device column. A time axis draws one kind of machine: `psnr_vs_time.png` the CPU's runs"
               + "".join(f", `{png}` the {device}'s" for device, png in data["device_time_charts"].items())
               + ". A Pareto chart leaves out a scene whose runs "
               f"ran on different devices (`pareto.json` says so for {names(left_out) if left_out else 'none'}). "
               f"Rows evaluated before metrics named the device show none ({len(no_device)} of {len(finished)}); all "
               "of them ran on the CPU.")
    run2 = sorted({n.split("_run")[0] for n in data["progress"] if "_run" in n})
    out.append("- The PSNR-against-time curve of each run is in `progress/SEGMENT[_compact].{json,png}` "
               f"(the default run in the table is `SEGMENT_run2` for {names(run2)}).")
    out.append("")

    # -------- compact variant
    reach = []
    for s in both:
        _, prog = run_progress(data, c[s])
        if prog:
            cs, st = prog["curve"]["surfels"], prog["curve"]["step"]
            reach.append(next(st[i] for i in range(len(cs)) if cs[i] >= prog["surfels"]))
    fr = {r["count_fraction"] for r in c.values()}
    (fraction,) = fr
    out += ["## Compact variant", "",
            f"The compact variant uses `strategy = \"{names(sorted({r['strategy'] for r in c.values()}))}\"` with "
            f"`max_surfels` at a fifth of the same segment's default count (`count_fraction = {fraction:g}`), "
            f"everything else as the default ({steps:,} steps, {w}x{h}). Its cap is reached by steps "
            f"{rng(reach, ',')} (progress curves).", ""]
    out += table(["segment", "steps", "test PSNR (dB)", "test L1", "test SSIM", "Gaussians", "training wall s"],
                 [[f"{s} (compact)", f"{c[s]['steps']:,}", f"{c[s]['psnr']:.2f}", f"{c[s]['l1']:.4f}",
                   f"{c[s]['ssim']:.3f}", f"{c[s]['num_gaussians']:,}", f"{c[s]['train_seconds']:,.0f}"] for s in both])
    out.append("")
    first = data["progress"].get("row1_x0")  # the first default run's record
    if first and "row1_x0" in both:
        r0 = first["surfels"]
        cap_ = c["row1_x0"]["num_gaussians"]
        out.append(f"- **row1_x0's cap** came from a first default run whose final count was {r0:,} (max_surfels = "
                   f"{cap_:,}); that run's folder was lost, and the default in the table, a second run, finished at "
                   f"{d['row1_x0']['num_gaussians']:,}, so this compact run has {frac['row1_x0']:.1%} of its count.")
    configs = data["compact_configs"]
    out.append(f"- **{names([f'{s}' + chr(39) + 's' for s in configs])} compact runs** were started through the "
               "runner's `train_and_evaluate` with the experiment's resolved config and their cap, because the "
               "default's `metrics.json` was not available at the time. Their configs are committed beside this file: "
               f"`ghsplat train --config benchmarks/results/{NAME}/{configs[0]}_compact_config.toml --out "
               f"runs/{NAME}/{configs[0]}/compact` reproduces one (the segment's SfM data must first exist at "
               f"`{seginfo[configs[0]]['data']}`; any `ghsplat run` of this experiment makes it).")
    out.append("- **row1_x0's run folders are gone**, so its two rows live only in `results.json`. A report keeps a "
               "planned run's row from there when its folder has no `metrics.json` (with a warning), so such rows stay "
               "in the table as other segments finish.")
    out.append("")

    out += default_seeds_section(rows, notes["conditions"])
    out += compact_seeds_section(rows)
    out += auto_section(rows, data.get("auto"))
    out += full_size_section(data.get("full_size"))
    out += real_section(data.get("real"))

    # -------- SfM
    ok = [s for s in seginfo.values() if s["status"] == "ok"]
    plain = notes["sfm_plain_mapping"]
    fixes = [f"{s} ({plain[s]['registered']} -> {seginfo[s]['registered']} of {seginfo[s]['views']} views, "
             f"{seginfo[s]['centre_error_max_pct_extent']:.2f}% max centre error) needed {plain[s]['fix']}"
             for s in sorted(k_ for k_ in plain if k_ != "about")]
    other = notes["sfm_row3_x0_other_host"]
    r3 = seginfo["row3_x0"]
    out += ["## SfM of the segments", "",
            f"- {'All ' + str(len(ok)) if len(ok) == len(seginfo) else str(len(ok)) + ' of ' + str(len(seginfo))} "
            f"segments are status ok (`segments.md`), so the runner trains every one. " + " and ".join(
                [fixes[0]] + [f.replace(" needed ", " ") for f in fixes[1:]])
            + "; with plain mapping they came out partial.",
            "- row3_x0 is ok with a "
            f"{rng([r3['centre_error_max_pct_extent'], other['centre_error_max_pct_extent']], '.1f')}"
            "% max centre error (two hosts): its first two photos are off by several degrees. " + crosscheck_note(),
            f"- **Remaking a segment does not always give the same model on another machine.** The {cap['views']} "
            f"photos of row3_x0 come out byte-identical each time (sha256 of `cat images/*.png`: "
            f"{other['images_sha256']}), and one machine repeats its SfM exactly, yet two hosts gave "
            f"{r3['reprojection_px']:.3f} px, {r3['centre_error_max_pct_extent']:.3f}% max centre error, "
            f"{r3['rotation_error_max_deg']:.3f} degrees (`segments.json`) and {other['reprojection_px']:.3f} px, "
            f"{other['centre_error_max_pct_extent']:.3f}%, {other['rotation_error_max_deg']:.3f} degrees, both with "
            f"pycolmap {r3['pycolmap']}, the first pass unflagged, with this code and with the code of "
            f"{other['also_with_code']}. Neither load nor the disambiguation path explains it; SIFT's floats can "
            "follow the CPU's vector code paths. Each segment's `sfm_report.json` now records its machine (CPU model "
            "and vector extensions), so a difference can be tied to a machine or ruled out. `segments.{json,md}` list "
            "the data every run here trained on.",
            f"- The \"SfM s\" column of `segments.md` is the reports' own time "
            f"({rng([s['sfm_seconds'] for s in seginfo.values()], '.1f')} s a segment on an idle machine); photo "
            f"rendering takes {notes['photo_render_seconds'][0]}-{notes['photo_render_seconds'][1]} s a segment.", ""]

    # -------- running it again
    out += ["## Running it again", "",
            f"`ghsplat run experiments/{NAME}.toml` makes the photos and SfM of every segment whose folder is missing "
            "and trains every run whose folder has no `metrics.json`, each default followed by its compact one (the "
            "compact run takes its cap from the finished default's count, so it cannot go first); `--only "
            "SEG/VARIANT` picks runs, `--prepare-only` makes the segments and trains nothing. On a lent GPU, "
            "`ghsplat bench device_table1 --parallel 1` trains one default within a device command's time limit "
            f"(about {notes['gpu_default_seconds_alone']['seconds']} s alone plus the machine's start); see "
            "[docs/performance.md](../../../docs/performance.md#table-1-segments-on-a-gpu).", ""]
    return "\n".join(out)


def generate(results: Path = RESULTS) -> str:
    """The README text, from the committed results files under `results`."""
    return render(load(results))


def check(readme: Path, results: Path = RESULTS) -> str:
    """'' when `readme` is what the results files give, else a unified diff (committed -> generated)."""
    return text_diff(readme, generate(results))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=RESULTS, help="the benchmarks/results folder to read")
    ap.add_argument("--readme", type=Path, help=f"the README to write or check (default: RESULTS/{NAME}/README.md)")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 with a diff if the README differs")
    args = ap.parse_args(argv)
    readme = args.readme or args.results / NAME / "README.md"
    return write_or_check(readme, generate(args.results), args.check, SCRIPT)


if __name__ == "__main__":
    sys.exit(main())
