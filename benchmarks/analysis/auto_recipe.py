"""The auto recipe against the 2DGS default and the compact variant: held-out PSNR against training
time, per scene, from the runs' own records (every number below is read from files, none typed).

    python benchmarks/analysis/auto_recipe.py --runs runs/table1_greenhouse \
        --reference benchmarks/results/table1_greenhouse/results.json --out benchmarks/results/auto_recipe
    python benchmarks/analysis/auto_recipe.py --check    # OUT/README.md against OUT/results.json
    python benchmarks/analysis/auto_recipe.py --readme-only    # OUT/README.md again from OUT/results.json

Reads every RUNS/SCENE/VARIANT folder whose variant starts with "auto" (metrics.json, config.toml,
test_curve.jsonl: the test views scored while training, that time left out of the training seconds)
and the reference results' rows of the variants it draws (REFERENCE_STYLE). Variants "auto" and
"auto_seedN" are the recipe's seeds; any other "auto_X" is an ablation, compared with the same
scene's seed-0 run. A run interrupted before it finished (a test curve, no metrics.json) is listed
apart, with its last scored step. The variants "default_curve" and "compact_curve" (the reference
variants trained with a test curve, often only their first steps: --stop-at) and "mcmc_full" (the
control: MCMC at the default's count) give the reference curves: drawn beside the auto runs and read
at fixed training times (the equal-time table), finished or not, each with the step it reached. Runs
already in OUT/results.json whose folder is gone are kept from there (run folders do not outlive the
machine they ran on). Writes OUT/results.json (every run, the per-scene mean and spread over seeds,
the goal checks, the machine record of this report and of each run), OUT/README.md (generated:
tables) and OUT/psnr_vs_time_SCENE.png. --check needs no run folders: it renders the README from the
committed OUT/results.json and exits 1 with a diff when OUT/README.md differs (no JAX import).

The goal (self-sizing issue): per scene, the auto recipe's mean test PSNR over its seeds at least
the compact variant's, its mean count at most compact's, and each run at most 10 minutes of
training. Reference rows trained at other code revisions and often on other hosts: their times are
shown as they were recorded, with the device, not as a same-machine comparison; one trained on
another kind of device than the scene's auto runs (an H200 against a CPU) is drawn as its PSNR
level only, with no point on the time axis.
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

from ghsplat_jax.curves import psnr_at, time_to  # JAX-free modules: --check runs without JAX
from ghsplat_jax.io_utils import (
    atomic_write,
    code_revision,
    host_label,
    machine_kind,
    one_machine,
    read_jsonl,
    write_json,
)

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"

TIME_GOAL_S = 600.0
# Scenes with goals of their own (the self-sizing issue): (test PSNR at least, training seconds at most).
SCENE_GOALS = {"llff_fern": (26.0, 1200.0), "lego": (34.4, 3600.0)}
PSNR_LEVELS = (26.0, 27.0, 28.0, 29.0, 30.0)  # the time-to-PSNR table's levels (dB)


def is_seed(variant: str, base: str = "auto") -> bool:
    """Whether a variant is one of `base`'s seeds (`base`, "`base`_seedN"; by default the recipe's),
    not an ablation."""
    prefix = f"{base}_seed"
    return variant == base or (variant.startswith(prefix) and variant[len(prefix):].isdigit())


def carried_runs(previous: Path, present: list[dict], key: str = "runs") -> list[dict]:
    """Records under `key` in a previous results.json whose (scene, variant) is not among `present`."""
    if not previous.is_file():
        return []
    have = {(r["scene"], r["variant"]) for r in present}
    return [r for r in json.loads(previous.read_text()).get(key, []) if (r["scene"], r["variant"]) not in have]


# run folder -> reference variant; mcmc_full: the count-against-regularisation control (MCMC at the
# default's count), trained with a test curve under its own name
CURVE_VARIANTS = {"default_curve": "default", "compact_curve": "compact", "mcmc_full": "mcmc_full"}
EQUAL_TIMES_S = (120.0, 300.0, 600.0)  # the equal-time table's training times
REFERENCE_STYLE = {"default": ("s", "black"), "compact": ("D", "gray"), "mcmc_full": ("^", "saddlebrown")}


def curve_points(path: Path) -> list[dict]:
    """A test_curve.jsonl's points as the results keep them."""
    keys = ("elapsed_s", "psnr", "num_surfels", "step", "code_revision", "host", "load_average")
    return [{k: p.get(k) for k in keys} for p in read_jsonl(path)]


def reference_curves(runs_root: Path) -> list[dict]:
    """The reference variants' test curves (RUNS/SCENE/{default,compact}_curve), finished or stopped."""
    out = []
    for folder, variant in CURVE_VARIANTS.items():
        for path in sorted(runs_root.glob(f"*/{folder}/test_curve.jsonl")):
            curve = curve_points(path)
            if not curve:
                continue
            metrics = path.parent / "metrics.json"
            m = json.loads(metrics.read_text()) if metrics.is_file() else {}
            out.append({"scene": path.parent.parent.name, "variant": variant, "finished": bool(m),
                        "last_step": curve[-1]["step"], "num_surfels_then": curve[-1]["num_surfels"],
                        "machine": m.get("machine"), "host": curve[-1]["host"],
                        "code_revisions": sorted({p["code_revision"] or "unrecorded" for p in curve}),
                        "curve": curve})
    return out


def unfinished_runs(runs_root: Path) -> list[dict]:
    """Auto runs that have a test curve but no metrics.json (interrupted): listed with their last
    scored step, never counted in the summary or the goals."""
    out = []
    for curve_path in sorted(runs_root.glob("*/auto*/test_curve.jsonl")):
        run = curve_path.parent
        curve = curve_points(curve_path)
        if (run / "metrics.json").is_file() or not curve:
            continue
        last = curve[-1]
        out.append({"scene": run.parent.name, "variant": run.name, "last_scored_step": last["step"],
                    "psnr_then": last["psnr"], "num_surfels_then": last.get("num_surfels"),
                    "train_seconds_then": last["elapsed_s"], "host": last["host"], "curve": curve})
    return out


def auto_runs(runs_root: Path, defaults: dict | None = None) -> list[dict]:
    """One record per finished auto run under RUNS/SCENE/VARIANT. `defaults`: {dotted setting:
    value} of the settings a run's config.toml may predate (it trained with their defaults)."""
    out = []
    for metrics_path in sorted(runs_root.glob("*/auto*/metrics.json")):
        run = metrics_path.parent
        m = json.loads(metrics_path.read_text())
        cfg = tomllib.loads((run / "config.toml").read_text()) if (run / "config.toml").is_file() else {}
        test = m.get("test") or {}
        stop = m.get("stop") or {}
        curve = curve_points(run / "test_curve.jsonl")
        out.append({"scene": run.parent.name, "variant": run.name, "seed": cfg.get("seed"),
                    "settings": (defaults or {}) | flat(cfg),
                    **{k: test.get(k) for k in ("psnr", "psnr_cc", "l1", "ssim", "lpips", "depth_abs_err",
                                                 "normal_err_deg")},
                    "train_psnr": (m.get("train") or {}).get("psnr"), "num_gaussians": m.get("num_gaussians"),
                    "compacted_from": (m.get("compaction") or {}).get("before"),
                    "train_seconds": m.get("train_seconds"), "steps": m.get("steps"),
                    "best_step": stop.get("best_step"), "stop_reason": stop.get("reason"),
                    "device": m.get("device"), "machine": m.get("machine"), "code_revision": m.get("code_revision"),
                    "host": host_label(m.get("machine")) or (curve[-1]["host"] if curve else None), "curve": curve})
    return out


def reference_rows(path: Path) -> dict[tuple[str, str], dict]:
    """(scene, variant) -> the reference results' test row, for the reference variants."""
    if not path.is_file():
        return {}
    rows = json.loads(path.read_text())["rows"]
    return {(r["scene"], r["variant"]): r for r in rows
            if r.get("variant") in REFERENCE_STYLE and r.get("split", "test") == "test"}


def spread(values: list[float]) -> dict:
    vals = [v for v in values if v is not None]
    if not vals:
        return {"mean": None, "std": None, "min": None, "max": None, "n": 0}
    return {"mean": statistics.fmean(vals), "std": statistics.stdev(vals) if len(vals) > 1 else 0.0,
            "min": min(vals), "max": max(vals), "n": len(vals)}


def psnr_then(curve: list[dict], seconds: float, finished: bool) -> float | None:
    """The test PSNR of a run after `seconds` of training: its last point by then; None when
    nothing was scored by then, or when an unfinished curve ends before `seconds` (not reached)."""
    if not curve or (not finished and curve[-1]["elapsed_s"] < seconds):
        return None
    return psnr_at(curve, seconds)


def equal_time(scene: str, runs: list[dict], curves: list[dict], kind: str, among: list[dict] = ()) -> dict:
    """Test PSNR after each of EQUAL_TIMES_S of training: the auto seeds' mean, and each reference
    curve's trained on `kind` of machine (machine_kind over `among` and the curves)."""
    seeds = [r for r in runs if r["scene"] == scene and is_seed(r["variant"])]
    row = {"auto": {f"{t:g}": spread([psnr_then(r["curve"], t, True) for r in seeds]) for t in EQUAL_TIMES_S}}
    for c in curves:
        if c["scene"] == scene and machine_kind(c, [*among, *curves]) == kind:
            row[c["variant"]] = {f"{t:g}": psnr_then(c["curve"], t, c["finished"]) for t in EQUAL_TIMES_S}
    return row


# The recipe's seed-0 run, the previous recipe's, and the first run with normal_settle.
BASES = ("auto", "auto_normal2k", "auto_settle")
NOT_SETTINGS = {"seed", "test_curve_every", "progress", "checkpoint_every"}  # no part of the method


def flat(config: dict, prefix: str = "") -> dict:
    """A run's config.toml as {dotted key: value}."""
    out = {}
    for k, v in config.items():
        if isinstance(v, dict):
            out |= flat(v, f"{prefix}{k}.")
        elif k not in NOT_SETTINGS:
            out[prefix + k] = v
    return out


def differences(a: dict, b: dict) -> list[str]:
    """The settings two runs' configs differ in (auto_runs fills a setting a config predates with
    its default, as that run trained with it; a carried record may hold None for one: unrecorded)."""
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


def split_differences(a: dict, b: dict, names: list[str] | None = None) -> tuple[list[str], list[str]]:
    """The settings two runs differ in (`names`, or all of them): those both record and set apart, and
    those only one records (a setting added after the other trained is no evidence that they differ)."""
    names = differences(a, b) if names is None else names
    known = [k for k in names if a.get(k) is not None and b.get(k) is not None]
    return known, [k for k in names if k not in known]


def differs_cell(a: dict) -> str:
    """An ablation's "differs in" cell: the settings both runs record and set apart, then those only
    one of them records (a setting added after the other trained)."""
    base = a.get("base_settings") or {}
    names = a.get("differs_in") or []
    if not base:
        return ", ".join(names) or "-"
    known, unrecorded = split_differences(a.get("settings") or {}, base, names)
    only = f"; recorded by one run only (the other predates them): {', '.join(unrecorded)}" if unrecorded else ""
    return (", ".join(known) or "-") + only


def ablations(runs: list[dict]) -> list[dict]:
    """Each ablation run against the scene's base run (BASES) whose settings it differs least
    from (in settings both record, then in those one predates), with the settings they differ in:
    what the ablated part changes. A base run is compared with the bases listed before it."""
    out = []
    for r in runs:
        bases = [b for b in runs if b["scene"] == r["scene"] and b["variant"] in BASES
                 and BASES.index(b["variant"]) < (BASES.index(r["variant"]) if r["variant"] in BASES else len(BASES))]
        if is_seed(r["variant"]) or not bases:
            continue
        b = min(bases, key=lambda b: (*map(len, split_differences(r.get("settings") or {}, b.get("settings") or {})),
                                      BASES.index(b["variant"])))
        diff = differences(r.get("settings") or {}, b.get("settings") or {})
        out.append({"scene": r["scene"], "variant": r["variant"], "against": b["variant"], "psnr": r["psnr"],
                    "differs_in": diff, "settings": {k: (r.get("settings") or {}).get(k) for k in diff},
                    "base_settings": {k: (b.get("settings") or {}).get(k) for k in diff},
                    "num_gaussians": r["num_gaussians"], "train_seconds": r["train_seconds"],
                    "delta_psnr_db": r["psnr"] - b["psnr"], "delta_seconds": r["train_seconds"] - b["train_seconds"],
                    "count_ratio": r["num_gaussians"] / b["num_gaussians"],
                    "same_code": r.get("code_revision") == b.get("code_revision")})
    return out


def ablation_of(variant: str) -> str:
    """The ablation a run belongs to: its variant without a "_seedN" ending."""
    head, _, tail = variant.rpartition("_seed")
    return head if head and tail.isdigit() else variant


def seeded_ablations(runs: list[dict]) -> list[dict]:
    """Each ablation with more than one seed on a scene ("auto_X", "auto_X_seedN") or run on more than
    one scene: per scene, the mean and spread over its seeds beside the same scene's recipe seeds'."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in runs:
        if not is_seed(r["variant"]):
            groups.setdefault((r["scene"], ablation_of(r["variant"])), []).append(r)
    spans = {name: sum(n == name for _, n in groups) for _, name in groups}
    out = []
    for (scene, name), rs in sorted(groups.items(), key=lambda g: (g[0][1], g[0][0])):
        recipe = [r for r in runs if r["scene"] == scene and is_seed(r["variant"])]
        if (len(rs) < 2 and spans[name] < 2) or not recipe:
            continue
        out.append({"scene": scene, "variant": name, "seeds": len(rs), "recipe_seeds": len(recipe)}
                   | {k: spread([r.get(k) for r in rs]) for k in ("psnr", "lpips", "normal_err_deg", "num_gaussians",
                                                                  "train_seconds")}
                   | {f"recipe_{k}": spread([r.get(k) for r in recipe]) for k in ("psnr", "normal_err_deg",
                                                                                   "num_gaussians", "train_seconds")})
    return out


PRIOR_BINS = ((0, 0), (1, 500), (501, 1000), (1001, None))  # normal-prior steps of the kept model


def prior_steps(run: dict) -> int | None:
    """How many steps of the normal-consistency loss the run's kept model trained with (its best
    check's step past `normal_from`; 0 with the loss off); None where its record does not say."""
    settings = run.get("settings") or {}
    if run.get("best_step") is None or settings.get("normal_from") is None or settings.get("lambda_normal") is None:
        return None
    return max(0, run["best_step"] - settings["normal_from"]) if settings["lambda_normal"] > 0 else 0


def prior_section(runs: list[dict]) -> list[str]:
    """The runs' geometry errors grouped by the normal-prior steps of the model each kept: a run keeps
    its best check, so whether that model had the prior at all depends on when it plateaued."""
    rows = [(prior_steps(r), r) for r in runs if r.get("normal_err_deg") is not None]
    rows = [(n, r) for n, r in rows if n is not None]
    if not rows:
        return []
    body = []
    for lo, hi in PRIOR_BINS:
        rs = [r for n, r in rows if n >= lo and (hi is None or n <= hi)]
        if rs:
            normal = spread([r["normal_err_deg"] for r in rs])
            body.append(f"| {lo:,} | " if lo == hi else f"| {lo:,}-{hi:,} | " if hi else f"| over {lo - 1:,} | ")
            body[-1] += (f"{len(rs)} | {len({r['scene'] for r in rs})} | {fmt_spread(normal, '.1f')} | "
                         f"{normal['min']:.1f}-{normal['max']:.1f} | "
                         f"{fmt_spread(spread([r.get('depth_abs_err') for r in rs]), '.4f')} |")
    return ["", "## Geometry against the normal prior's steps in the kept model", "",
            "Every run with geometry errors, grouped by how many steps of the normal-consistency loss the model it "
            "kept had trained with (its best check's step past `normal_from`). A run keeps its best validation "
            "check, so a run that plateaus before the loss starts, or whose checks under it never beat the last "
            "one before it, keeps a model without it (`normal_settle` keeps only a model with that many steps).", "",
            "| normal-prior steps | runs | scenes | normal err (deg) | range | depth err (m) |",
            "|---|---|---|---|---|---|"] + body


def main_machine(runs: list[dict]) -> str:
    """The report's main kind of machine: the one most of its recipe seeds trained on. Every
    table and chart times the runs of that kind, or a scene's own where it has none there."""
    return one_machine([r for r in runs if is_seed(r["variant"])])[0]


def summarize(runs: list[dict], refs: dict, curves: list[dict] = ()) -> list[dict]:
    scenes = sorted({r["scene"] for r in runs if is_seed(r["variant"])})
    main_kind = main_machine(runs)
    out = []
    for scene in scenes:
        rs = [r for r in runs if r["scene"] == scene and is_seed(r["variant"])]
        kind, timed = one_machine(rs, main_kind, among=runs)  # every time below: these runs only
        compact, default = refs.get((scene, "compact")), refs.get((scene, "default"))
        s = {"scene": scene, "seeds": len(rs), "psnr": spread([r["psnr"] for r in rs]),
             "num_gaussians": spread([r["num_gaussians"] for r in rs]),
             "timed_on": {"machine": kind, "runs": len(timed)},
             "train_seconds": spread([r["train_seconds"] for r in timed]),
             "compact": None if compact is None else {k: compact.get(k) for k in
                                                      ("psnr", "num_gaussians", "train_seconds", "device")},
             "default": None if default is None else {k: default.get(k) for k in
                                                      ("psnr", "num_gaussians", "train_seconds", "device")}}
        if compact:
            s["goal"] = {"psnr_at_least_compact": s["psnr"]["mean"] >= compact["psnr"],
                         "count_at_most_compact": s["num_gaussians"]["mean"] <= compact["num_gaussians"],
                         "every_run_within_10_min": all((r["train_seconds"] or 1e9) <= TIME_GOAL_S for r in timed)}
            s["time_to_compact_psnr_s"] = [time_to(r["curve"], compact["psnr"]) for r in timed]
        if scene in SCENE_GOALS:
            level, seconds = SCENE_GOALS[scene]
            s["goal"] = {f"psnr_at_least_{level:g}": s["psnr"]["mean"] >= level,
                         f"every_run_within_{seconds / 60:g}_min": all((r["train_seconds"] or 1e9) <= seconds
                                                                      for r in timed)}
        if default:
            s["time_to_default_psnr_s"] = [time_to(r["curve"], default["psnr"]) for r in timed]
        s["psnr_at_10_min"] = spread([psnr_at(r["curve"], TIME_GOAL_S) for r in timed])
        s["equal_time"] = equal_time(scene, timed, list(curves), kind, among=runs)
        s["time_to_level_s"] = {f"{level:g}": spread([time_to(r["curve"], level) for r in timed])
                                for level in PSNR_LEVELS}
        out.append(s)
    return out


def run_label(r: dict) -> str:
    """A chart legend's name of an auto run: the recipe's seed, or the ablation's variant."""
    if r.get("label"):
        return r["label"]
    name = f"auto, seed {r['seed']}" if is_seed(r["variant"]) else r["variant"]
    return f"{name} ({r['num_gaussians']:,} surfels)"


def chart(scene: str, runs: list[dict], refs: dict, path: Path, curves: list[dict] = (),
          main_kind: str | None = None) -> None:
    """The scene's test PSNR against training time: its auto runs and reference curves, timed on
    `main_kind` of machine (the report's) where the scene has runs there."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    markers = "ov^<>pP*hX"
    # a time axis draws one kind of machine: the report's main kind where the scene has runs on it
    everything = [*runs, *curves]
    kind, timed = one_machine([r for r in runs if r["scene"] == scene], main_kind, among=everything)
    for i, r in enumerate(r for r in runs if r["scene"] == scene):
        c = r["curve"]
        if r not in timed:
            ax.axhline(r.get("psnr") or c[-1]["psnr"], ls=":", color=f"C{i}",
                       label=f"{run_label(r)}, {'final' if r.get('psnr') else 'last scored'}, on "
                             f"{machine_kind(r, everything)}: time not comparable")
            continue
        ax.plot([p["elapsed_s"] / 60 for p in c], [p["psnr"] for p in c], "-", marker=markers[i % len(markers)],
                ms=3, color=f"C{i}", label=run_label(r))
    for c in (c for c in curves if c["scene"] == scene):
        marker, color = REFERENCE_STYLE[c["variant"]]
        pts = c["curve"]
        if machine_kind(c, everything) != kind:
            ax.axhline(pts[-1]["psnr"], ls=":", color=color,
                       label=f"{c['variant']}, last scored, on {machine_kind(c, everything)}: time not comparable")
            continue
        reached = "to the end" if c["finished"] else f"to step {c['last_step']:,} (stopped)"
        ax.plot([p["elapsed_s"] / 60 for p in pts], [p["psnr"] for p in pts], "--", marker=marker, ms=3, color=color,
                label=f"{c['variant']}, test curve {reached} ({c['num_surfels_then'] or 0:,} surfels then)")
    here = {r.get("device") or "cpu" for r in runs if r["scene"] == scene}
    for variant, (marker, color) in REFERENCE_STYLE.items():
        ref = refs.get((scene, variant))
        if not ref:
            continue
        device = ref.get("device") or "cpu"
        if device not in here:  # a time axis compares one kind of machine: its PSNR only
            ax.axhline(ref["psnr"], ls=":", color=color,
                       label=f"{variant}, final ({ref['num_gaussians']:,} surfels) on {device}: time not comparable")
        elif ref.get("train_seconds"):
            ax.plot([ref["train_seconds"] / 60], [ref["psnr"]], marker, color=color, ms=8,
                    label=f"{variant}, final ({ref['num_gaussians']:,} surfels; {device}, earlier code)")
    ax.set_xscale("log")
    ax.set_xlabel("training time (min, log scale; test scoring left out)")
    ax.set_ylabel("test PSNR (dB), held-out views")
    ax.set_title(f"{scene}: test PSNR against training time on {kind}", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def timed_note(s: dict) -> str:
    """A scene summary's note where its times leave out seeds trained on another kind of machine."""
    timed = s["timed_on"]
    return "" if timed["runs"] == s["seeds"] else f" ({timed['runs']} of {s['seeds']} runs: {timed['machine']})"


def fmt(x, spec=".2f", none="-"):
    return none if x is None else format(x, spec)


def fmt_spread(x: dict, spec: str = ".2f") -> str:
    """A spread() as "mean ± std" ("-" when it has no values; one value: no spread)."""
    if not x["n"]:
        return "-"
    return f"{x['mean']:{spec}}" if x["n"] == 1 else f"{x['mean']:{spec}} ± {x['std']:{spec}}"


def surfels_cell(r: dict) -> str:
    """A run's count, and the count its compaction started from where it compacted itself."""
    before = r.get("compacted_from")
    return fmt(r["num_gaussians"], ",") + (f" (of {before:,})" if before else "")


def compaction_lines(rows: list[dict], runs: list[dict]) -> list[str]:
    """The README's table of finished models compacted afterwards (benchmarks/analysis/compaction.py).
    A run folder trained again since holds another model than the one compacted: the last column
    says so, so that the row is not read as the compaction of the model the other tables score."""
    losses = sorted({c["max_loss_db"] for r in rows for c in r["compacted"]})
    now = {f"{r['scene']}/{r['variant']}": r for r in runs}
    lines = ["", "## Compaction of finished models", "",
             "Each model compacted afterwards (`benchmarks/analysis/compaction.py`): the surfels of least blending "
             "weight over the training views removed, as many as cost at most the given validation PSNR (the "
             "run's own validation views); the test views score it. Cells: surfels kept (share), test PSNR change "
             "(dB). The recipe has compacted itself at its end since these measurements.", "",
             "| run | surfels | test PSNR | " + " | ".join(f"max {x:g} dB" for x in losses) + " | the folder now |",
             "|---|---|---|" + "---|" * len(losses) + "---|"]
    for r in rows:
        by = {c["max_loss_db"]: c for c in r["compacted"]}
        cells = [f"{by[x]['after']:,} ({by[x]['after'] / r['surfels']:.0%}), {by[x]['test_psnr'] - r['test_psnr']:+.3f}"
                 if x in by else "-" for x in losses]
        current = now.get("/".join(Path(r["run"]).parts[-2:]))
        folder = ("gone" if current is None else "this model" if current["num_gaussians"] == r["surfels"]
                  else f"trained again since ({fmt(current['num_gaussians'], ',')} surfels)")
        lines.append(f"| {r['run']} | {r['surfels']:,} | {r['test_psnr']:.2f} | " + " | ".join(cells)
                     + f" | {folder} |")
    return lines


def gallery_lines(gallery: dict) -> list[str]:
    """The README's pointer to gallery.png (benchmarks/analysis/render_gallery.py's record)."""
    views = "; ".join(f"{label}: " + ", ".join(f"{v['name']} {v['psnr']:.2f} dB" for v in run["views"])
                      for label, run in gallery["runs"].items())
    return ["", "## Test views beside their photos", "",
            f"`gallery.png` (`benchmarks/analysis/render_gallery.py` at {gallery['code_revision'][:10]}): each test "
            f"view's photo, the run's render and their difference (x3). {views}."]


def readme(summary: list[dict], runs: list[dict], record: dict, unfinished: list[dict], ablated: list[dict],
           curves: list[dict] = (), compaction: list[dict] = (), gallery: dict | None = None) -> str:
    title = ("The auto recipe against the default and the compact variant" if any(s["compact"] for s in summary)
             else "The auto recipe")
    lines = [f"# {title}", "",
             "Generated by `benchmarks/analysis/auto_recipe.py` from the runs' metrics.json and test_curve.jsonl "
             "and the reference results; do not edit by hand.", "",
             f"Report written at code revision `{record['code_revision']}` on {record['machine']['processor']} "
             f"({record['machine']['cpu_count']} cores). Each run records its own machine and code revision in "
             "results.json.", "",
             "## Per scene (auto: mean ± sample std over seeds)", "",
             "Every time (train s, the time to reach a PSNR, the PSNR at 10 min, the goals on time) counts only "
             "seeds trained on one kind of machine: the kind most of the report's seeds trained on, where a scene "
             "has seeds there. A row that leaves seeds out of its times names the kind and how many it holds.", "",
             "| scene | seeds | auto test PSNR (dB) | auto surfels | auto train s | compact PSNR | compact surfels | "
             "default PSNR | default surfels | goal: PSNR >= compact | count <= compact | each run <= 10 min |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in summary:
        p, n, t = s["psnr"], s["num_gaussians"], s["train_seconds"]
        c, d, g = s["compact"] or {}, s["default"] or {}, s.get("goal") or {}
        yes = lambda k: "-" if k not in g else ("yes" if g[k] else "**no**")  # noqa: E731
        lines.append(f"| {s['scene']} | {s['seeds']} | {fmt(p['mean'])} ± {fmt(p['std'])} | "
                     f"{fmt(n['mean'], ',.0f')} ± {fmt(n['std'], ',.0f')} | {fmt(t['mean'], '.0f')} ± "
                     f"{fmt(t['std'], '.0f')}{timed_note(s)} | {fmt(c.get('psnr'))} | "
                     f"{fmt(c.get('num_gaussians'), ',')} | "
                     f"{fmt(d.get('psnr'))} | {fmt(d.get('num_gaussians'), ',')} | {yes('psnr_at_least_compact')} | "
                     f"{yes('count_at_most_compact')} | {yes('every_run_within_10_min')} |")
    own = [s for s in summary if s["scene"] in SCENE_GOALS]
    if own:
        lines += ["", "## Scenes with goals of their own", "", "| scene | seeds | goal | met |", "|---|---|---|---|"]
        lines += [f"| {s['scene']} | {s['seeds']} | {k.replace('_', ' ')} | {'yes' if v else '**no**'} |"
                  for s in own for k, v in s["goal"].items()]
    lines += ["", "## Time to reach a test PSNR (auto: mean over the seeds that reached it, min s)", "",
              "| scene | test PSNR at 10 min | " + " | ".join(f"{level:g} dB" for level in PSNR_LEVELS) + " |",
              "|---|---|" + "---|" * len(PSNR_LEVELS)]
    for s in summary:
        cells = []
        for level in PSNR_LEVELS:
            t = s["time_to_level_s"][f"{level:g}"]
            cells.append("never" if not t["n"] else f"{t['mean'] / 60:.1f} ({t['n']} of {s['timed_on']['runs']})")
        lines.append(f"| {s['scene']}{timed_note(s)} | {fmt(s['psnr_at_10_min']['mean'])} | " + " | ".join(cells)
                     + " |")
    if curves:
        lines += ["", "## Equal training time: test PSNR (dB) after 2, 5 and 10 min", "",
                  "The reference variants trained with a test curve on the same machine as the auto runs "
                  "(`default_curve`, `compact_curve`, `mcmc_full`); '-' where a curve stopped before that time. "
                  "Highest load: the largest 1-minute load average recorded at the curve's points; a curve trained "
                  "alone reads about the machine's core count, and more means something ran beside it, so its "
                  "times from then on are longer than the run alone would take.", "",
                  "| scene | variant | " + " | ".join(f"{t / 60:g} min" for t in EQUAL_TIMES_S)
                  + " | curve reaches (step) | highest load | code |",
                  "|---|---|" + "---|" * len(EQUAL_TIMES_S) + "---|---|---|"]
        for s in summary:
            for variant, at in s.get("equal_time", {}).items():
                c = next((c for c in curves if c["scene"] == s["scene"] and c["variant"] == variant), None)
                cells = [fmt(v["mean"] if isinstance(v, dict) else v) for v in at.values()]
                reach = ("stops itself" if c is None else
                         "end" if c["finished"] else f"{c['last_step']:,}")
                code = "per run" if c is None else ", ".join(r[:10] for r in c["code_revisions"])
                loads = [p["load_average"][0] for p in (c or {}).get("curve", []) if p.get("load_average")]
                load = "per run" if c is None else fmt(max(loads) if loads else None)
                name = f"auto (mean of {s['seeds']})" if c is None else variant
                lines.append(f"| {s['scene']} | {name} | " + " | ".join(cells) + f" | {reach} | {load} | {code} |")
    if ablated:
        lines += ["", "## Ablations (each against the same scene's seed-0 run of the recipe, or of its previous "
                  "version, whichever it differs from in fewer settings)", "",
                  "| scene | variant | against | differs in | test PSNR | change (dB) | normal err (deg) | against's "
                  "normal err | surfels | count x | train s | change (s) | same code |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        by = {(r["scene"], r["variant"]): r for r in runs}
        normal = lambda scene, variant: fmt(by.get((scene, variant), {}).get("normal_err_deg"), ".1f")  # noqa: E731
        lines += [f"| {a['scene']} | {a['variant']} | {a.get('against', 'auto')} | "
                  f"{differs_cell(a)} | {fmt(a['psnr'])} | {a['delta_psnr_db']:+.2f} | "
                  f"{normal(a['scene'], a['variant'])} | {normal(a['scene'], a.get('against', 'auto'))} | "
                  f"{a['num_gaussians']:,} | {a['count_ratio']:.2f} | {a['train_seconds']:.0f} | "
                  f"{a['delta_seconds']:+.0f} | {'yes' if a['same_code'] else 'no'} |" for a in ablated]
    seeded = seeded_ablations(runs)
    if seeded:
        lines += ["", "## Ablations over seeds or segments (mean ± sample std; the same scene's recipe seeds beside "
                  "them)", "",
                  "| scene | variant | seeds | test PSNR | recipe's PSNR (seeds) | change (dB) | LPIPS | normal err "
                  "(deg) | recipe's normal err | surfels | recipe's surfels | train s | recipe's train s |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        lines += [f"| {a['scene']} | {a['variant']} | {a['seeds']} | {fmt_spread(a['psnr'])} | "
                  f"{fmt_spread(a['recipe_psnr'])} ({a['recipe_seeds']}) | "
                  f"{a['psnr']['mean'] - a['recipe_psnr']['mean']:+.2f} | {fmt_spread(a['lpips'], '.3f')} | "
                  f"{fmt_spread(a['normal_err_deg'], '.1f')} | {fmt_spread(a['recipe_normal_err_deg'], '.1f')} | "
                  f"{fmt_spread(a['num_gaussians'], ',.0f')} | {fmt_spread(a['recipe_num_gaussians'], ',.0f')} | "
                  f"{fmt_spread(a['train_seconds'], '.0f')} | {fmt_spread(a['recipe_train_seconds'], '.0f')} |"
                  for a in seeded]
    lines += prior_section(runs)
    cc = any(r.get("psnr_cc") is not None for r in runs)  # the metric is newer than some runs
    heads = ["scene", "variant", "seed", "test PSNR"] + ["colour-corrected PSNR"] * cc + [
        "L1", "SSIM", "LPIPS", "depth err (m)", "normal err (deg)", "train PSNR", "surfels", "train s", "steps",
        "kept step", "machine", "load at the end", "code", "why it stopped"]
    lines += ["", "## Every run", "", "| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for r in runs:
        load = (r.get("machine") or {}).get("load_average")
        lines.append(f"| {r['scene']} | {r['variant']} | {r['seed']} | {fmt(r['psnr'])} | "
                     + (f"{fmt(r.get('psnr_cc'))} | " if cc else "") + f"{fmt(r['l1'], '.4f')} | "
                     f"{fmt(r['ssim'], '.3f')} | {fmt(r.get('lpips'), '.3f')} | "
                     f"{fmt(r.get('depth_abs_err'), '.4f')} | {fmt(r.get('normal_err_deg'), '.1f')} | "
                     f"{fmt(r['train_psnr'])} | {surfels_cell(r)} | "
                     f"{fmt(r['train_seconds'], '.0f')} | {r['steps']} | {r['best_step']} | {machine_kind(r, runs)} | "
                     f"{'-' if not load else ', '.join(f'{x:.1f}' for x in load)} | "
                     f"{(r.get('code_revision') or '-')[:10]} | {r['stop_reason'] or '-'} |")
    if compaction:
        lines += compaction_lines(compaction, runs)
    if gallery:
        lines += gallery_lines(gallery)
    if unfinished:
        lines += ["", "## Interrupted runs (not the recipe's result: no stop, no evaluation)", "",
                  "| scene | variant | last scored step | test PSNR then | surfels then | train s then |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {u['scene']} | {u['variant']} | {u['last_scored_step']} | {fmt(u['psnr_then'])} | "
                  f"{fmt(u['num_surfels_then'], ',')} | {fmt(u['train_seconds_then'], '.0f')} |" for u in unfinished]
    lines += ["", "LPIPS (VGG) and the depth and normal errors are over the test views; the geometry errors are "
              "against the procedural scene's ray-cast depth and normals, the model carried into the scene's frame by "
              "its SfM's similarity onto the exact cameras (so they include the SfM's own pose error); '-' where the "
              "run was not evaluated so.", "",
              "Training seconds leave out the test scoring (every 500 steps) and include the validation checks "
              "the recipe needs. The reference rows' seconds were measured at earlier code revisions, some on other "
              "hosts and under other loads: read them as recorded, not as a same-machine comparison.", ""]
    return "\n".join(lines)


def readme_from_results(out: Path = RESULTS / "auto_recipe") -> str:
    """OUT/README.md's text rendered from the committed OUT/results.json (no run folders)."""
    res = json.loads((out / "results.json").read_text())
    return readme(res["summary"], res["runs"], res["report"], res.get("unfinished", []), res.get("ablations", []),
                  res.get("reference_curves", []), res.get("compaction", []), res.get("gallery"))


def check(out: Path = RESULTS / "auto_recipe", readme_path: Path | None = None) -> str:
    """'' when the README is what OUT/results.json gives, else a unified diff (committed -> generated)."""
    return text_diff(readme_path or out / "README.md", readme_from_results(out))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, default=ROOT / "runs" / "table1_greenhouse")
    ap.add_argument("--reference", type=Path, default=RESULTS / "table1_greenhouse" / "results.json")
    ap.add_argument("--out", type=Path, default=RESULTS / "auto_recipe")
    ap.add_argument("--check", action="store_true",
                    help="write nothing: exit 1 with a diff if OUT/README.md differs from OUT/results.json's")
    ap.add_argument("--readme-only", action="store_true",
                    help="rewrite OUT/README.md from the committed OUT/results.json (no run folders), after a change "
                         "to what the README shows")
    args = ap.parse_args(argv)
    if args.check:
        return report(args.out / "README.md", check(args.out), "what auto_recipe.py renders from results.json")
    if args.readme_only:
        with atomic_write(args.out / "README.md", "w") as fh:
            fh.write(readme_from_results(args.out))
        print(f"wrote {args.out}/README.md")
        return 0
    sys.path.insert(0, str(ROOT / "benchmarks"))  # record.py
    from record import machine_record

    from ghsplat_jax.train.config import TrainConfig  # loads JAX: not for --check

    defaults = flat(TrainConfig().to_dict())
    runs, unfinished = auto_runs(args.runs, defaults), unfinished_runs(args.runs)
    # A carried record's settings predate the settings added since: it trained with their defaults.
    carried = [dict(r, settings=defaults | (r.get("settings") or {}),
                    host=r.get("host") or host_label(r.get("machine")))
               for r in carried_runs(args.out / "results.json", runs)]
    runs = sorted(runs + carried, key=lambda r: (r["scene"], r["variant"]))
    if not runs and not unfinished:
        print(f"no auto runs under {args.runs}", file=sys.stderr)
        return 1
    curves = reference_curves(args.runs)
    curves = sorted(curves + carried_runs(args.out / "results.json", curves, "reference_curves"),
                    key=lambda c: (c["scene"], c["variant"]))
    refs = reference_rows(args.reference)
    summary = summarize(runs, refs, curves)
    record = {"machine": machine_record(start_backend=False), "code_revision": code_revision()}
    scenes = sorted({r["scene"] for r in runs + unfinished})
    for scene in scenes:
        interrupted = [dict(u, label=f"{u['variant']}, interrupted at step {u['last_scored_step']} "
                                     f"({u['num_surfels_then'] or 0:,} surfels)") for u in unfinished]
        chart(scene, runs + interrupted, refs, args.out / f"psnr_vs_time_{scene}.png", curves, main_machine(runs))
    ablated = ablations(runs)
    compacted = args.out / "compaction.json"  # benchmarks/analysis/compaction.py's records
    compaction = [r for r in json.loads(compacted.read_text())["runs"] if r["compacted"]] if compacted.is_file() else []
    gallery_path = args.out / "gallery.json"  # benchmarks/analysis/render_gallery.py's record
    gallery = json.loads(gallery_path.read_text()) if gallery_path.is_file() else None
    write_json(args.out / "results.json", {"report": record, "summary": summary, "runs": runs,
                                           "ablations": ablated, "unfinished": unfinished,
                                           "reference_curves": curves, "compaction": compaction, "gallery": gallery})
    with atomic_write(args.out / "README.md", "w") as fh:
        fh.write(readme(summary, runs, record, unfinished, ablated, curves, compaction, gallery))
    print(f"wrote {args.out}/results.json, README.md and {len(scenes)} charts")
    return 0


if __name__ == "__main__":
    sys.exit(main())
