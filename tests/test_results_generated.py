"""Every generated results README is what its script makes from the committed results files: each
generator re-runs on the committed files and its text must equal the committed README, so a
number edited by hand (or a results file changed without regenerating) fails here.

Generators checked (each renders from committed files only, no run folders):
- benchmarks/analysis/table1_readme.py -> benchmarks/results/table1_greenhouse/README.md
- benchmarks/analysis/auto_recipe.py   -> benchmarks/results/auto_recipe/README.md,
  benchmarks/results/auto_recipe/real/README.md and .../table1_384/README.md (each from its results.json)
- benchmarks/robustness/sfm_crosscheck.py -> benchmarks/results/sfm_crosscheck/README.md (from its results.json)
- benchmarks/analysis/exposure.py      -> benchmarks/results/exposure_real/README.md (from its results.json)
- benchmarks/analysis/ablation_readme.py -> benchmarks/results/raster_ablation/auto_cpu/README.md

The first two import no JAX; sfm_crosscheck's module does (its table helper): a few seconds.
"""

from __future__ import annotations

import importlib.util
import re
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def _module(rel: str):
    path = ROOT / rel
    sys.path.insert(0, str(path.parent.parent))  # benchmarks/: record.py, for the scripts that import it
    try:
        spec = importlib.util.spec_from_file_location(path.stem + "_under_test", path)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(path.parent.parent))
    return mod


@pytest.fixture(scope="module")
def table1():
    return _module("benchmarks/analysis/table1_readme.py")


@pytest.fixture(scope="module")
def auto_recipe():
    return _module("benchmarks/analysis/auto_recipe.py")


def test_table1_readme_is_generated(table1):
    diff = table1.check(RESULTS / "table1_greenhouse" / "README.md")
    assert not diff, "table1_greenhouse/README.md differs from benchmarks/analysis/table1_readme.py's:\n" + diff


def test_auto_recipe_readme_is_generated(auto_recipe):
    diff = auto_recipe.check(RESULTS / "auto_recipe")
    assert not diff, "auto_recipe/README.md differs from its results.json:\n" + diff


@pytest.mark.parametrize("folder", ["real", "table1_384"])
def test_auto_recipe_subfolder_readme_is_generated(auto_recipe, folder):
    out = RESULTS / "auto_recipe" / folder
    if not (out / "results.json").is_file():
        pytest.skip(f"no auto_recipe/{folder} results committed")
    diff = auto_recipe.check(out)
    assert not diff, f"auto_recipe/{folder}/README.md differs from its results.json:\n" + diff


def test_exposure_readme_is_generated():
    out = RESULTS / "exposure_real"
    if not (out / "results.json").is_file():
        pytest.skip("no exposure_real results committed")
    diff = _module("benchmarks/analysis/exposure.py").check(out)
    assert not diff, "exposure_real/README.md differs from its results.json:\n" + diff


@pytest.fixture(scope="module")
def ablation():
    return _module("benchmarks/analysis/ablation_readme.py")


def test_ablation_readme_is_generated(ablation):
    readme = RESULTS / "raster_ablation" / "auto_cpu" / "README.md"
    diff = ablation.check(readme)
    assert not diff, "raster_ablation/auto_cpu/README.md differs from what its script generates:\n" + diff


def test_ablation_judges_each_variant_against_the_seed_noise(ablation):
    """Beyond noise means past 2*sqrt(2) seed sds from the default, on the preset's scene only; a
    variant of the experiment without a row is listed as not yet run, with its command."""
    data = ablation.load()
    scene = data["preset"]["scenes"][0]["name"]
    row = dict(split="test", ssim=0.9, lpips=0.2, depth_abs_err=0.03, normal_err_deg=20.0, num_gaussians=20000,
               steps=8000, train_seconds=600.0, step_seconds=0.07, host="h", code_revision="c" * 40)
    seeds = [dict(row, scene=scene, variant=v, psnr=p) for v, p in
             (("auto", 28.0), ("auto_seed1", 28.2), ("auto_seed2", 28.4))]  # sd 0.2: beyond noise past 0.57 dB
    data["table1"] = seeds + [dict(row, scene="other", variant="auto_seed1", psnr=20.0)]
    data["timing"] = None
    names = list(data["variants"])
    data["rows"] = [dict(row, scene=scene, variant="default", psnr=28.0),
                    dict(row, scene=scene, variant=names[1], psnr=27.0),
                    dict(row, scene=scene, variant=names[2], psnr=28.5),
                    dict(row, scene="other", variant=names[3], psnr=35.0)]
    text = ablation.render(data)
    assert "0.57 dB" in text and "Runs: 3 of" in text
    assert f"| {names[1]} | " in text and "| -1.00 | worse |" in text and "| +0.50 | no |" in text
    assert f"| {names[3]} | " not in text and f"`{names[3]}`" in text.split("## Not yet run")[1]
    assert "## Speed against accuracy" not in text  # no interleaved times yet: no front is drawn from logged ones
    # re-timed interleaved: the speed column is relative to the default, and the front and the
    # costly and the noticeable variants are named
    data["timing"] = {"steps_timed": 8, "scenes": {scene: {"default": {"seconds_per_step": 0.1},
                                                           names[1]: {"seconds_per_step": 0.3},
                                                           names[2]: {"seconds_per_step": 0.1}}}}
    text = ablation.render(data)
    assert "| 0.300 | 3.00x |" in text and "| 0.100 | 1.00x |" in text
    assert f"On the front of interleaved step time against test PSNR: `{names[2]}`." in text
    assert f"More than 10% slower a step than the default: `{names[1]}` (3.00x, -1.00 dB)." in text
    assert f"Beyond the noise (0.57 dB) in PSNR: `{names[1]}` (-1.00 dB)." in text
    assert f"not told apart from the default by this single-seed run: `{names[2]}`." in text
    assert "medians, at code not recorded;" in text  # a timing from before the revision was recorded
    data["timing"]["code_revision"] = "0123456789abcdef" * 2 + "01234567+dirty"  # code_revision(): 40 hex digits
    assert "medians, at code `0123456+dirty`;" in ablation.render(data)


def test_sfm_crosscheck_readme_is_generated():
    mod = _module("benchmarks/robustness/sfm_crosscheck.py")
    diff = mod.check()
    assert not diff, "sfm_crosscheck/README.md differs from its results.json:\n" + diff


def test_sfm_repeat_summary_counts_an_ok_model_beyond_the_bounds():
    """The goal check reads only the multithreaded repeats of the summary's revision, and an ok
    model with one view 2.1 degrees off is beyond the bounds."""
    mod = _module("benchmarks/robustness/sfm_crosscheck.py")
    row = dict(variant="after", status="ok", centre_error_max_pct=0.5, rotation_error_max_deg=1.0,
               cross_check_dropped=[], git_revision="new")
    rows = [dict(row, case="row3_x0-mt#1"), dict(row, case="row3_x0-mt#2", rotation_error_max_deg=2.1),
            dict(row, case="row1_x0-mt#1", status="folded"), dict(row, case="row1_x0-mt#2"),
            dict(row, case="row2_x0-mt#1", rotation_error_max_deg=9.0, git_revision="old"),
            dict(row, case="row2_x0", rotation_error_max_deg=9.0)]
    text = mod.repeat_summary(rows, "new")
    assert "**1 ok model(s) beyond the bounds**" in text and "1 of 2 segments ok in every repeat" in text
    assert "row2_x0" not in text and "| row3_x0 | 2 | 2 | - | 0.5 | 2.1 | row3_x0-mt#2 | 0 |" in text
    assert mod.repeat_summary(rows, "other") == ""


def _edit_a_number(text: str, old: str, new: str) -> str:
    assert old in text, f"{old!r} not in the README any more; pick another number for this test"
    return text.replace(old, new, 1)


def test_table1_check_fails_on_a_hand_edited_number(table1, tmp_path):
    """A copy of the committed README with one number changed: --check exits 1 and shows the line."""
    readme = tmp_path / "README.md"
    committed = (RESULTS / "table1_greenhouse" / "README.md").read_text()
    gain = re.search(r"\| row2_x1 \| [\d.]+ \| (\+[\d.]+) \|", committed).group(1)
    readme.write_text(_edit_a_number(committed, f"| {gain} |", "| +0.99 |"))
    diff = table1.check(readme)
    assert "+0.99" in diff and gain in diff
    assert table1.main(["--check", "--readme", str(readme)]) == 1
    readme.write_text(committed)
    assert table1.main(["--check", "--readme", str(readme)]) == 0


def test_table1_check_fails_when_a_results_file_changes(table1, tmp_path):
    """The README follows the results: a changed PSNR in results.json makes the committed one stale."""
    results = tmp_path / "results"
    shutil.copytree(RESULTS / "table1_greenhouse", results / "table1_greenhouse")
    shutil.copy(RESULTS / "fusion_profile_step.json", results / "fusion_profile_step.json")
    for sub in ("real", "table1_384"):  # the real captures' rows, and the rows at the photos' own size
        if (RESULTS / "auto_recipe" / sub).is_dir():
            shutil.copytree(RESULTS / "auto_recipe" / sub, results / "auto_recipe" / sub)
    shutil.copy(RESULTS / "auto_recipe" / "results.json", results / "auto_recipe" / "results.json")  # its runs' steps
    assert table1.check(results / "table1_greenhouse" / "README.md", results) == ""
    path = results / "table1_greenhouse" / "results.json"
    path.write_text(path.read_text().replace("31.485863276890345", "31.0", 1))  # row0_x1 compact
    diff = table1.check(results / "table1_greenhouse" / "README.md", results)
    assert "31.49" in diff and "31.00" in diff


def test_auto_recipe_check_fails_on_a_hand_edited_number(auto_recipe, tmp_path):
    shutil.copy(RESULTS / "auto_recipe" / "results.json", tmp_path / "results.json")
    committed = (RESULTS / "auto_recipe" / "README.md").read_text()
    row = next(line for line in committed.splitlines() if line.startswith("| row") and " auto" in line)
    psnr = row.split(" | ")[3]
    (tmp_path / "README.md").write_text(committed.replace(row, row.replace(f" {psnr} ", " 99.99 ", 1), 1))
    assert "99.99" in auto_recipe.check(tmp_path)
    assert auto_recipe.main(["--check", "--out", str(tmp_path)]) == 1


def test_spearman_exact_permutation_p_value(table1):
    rho, p = table1.spearman([1, 2, 3, 4], [1, 2, 3, 4])
    assert rho == pytest.approx(1.0) and p == pytest.approx(2 / 24)  # the two perfect orderings of 4! = 24
    rho, p = table1.spearman([1, 2, 3, 4, 5], [2, 1, 4, 3, 5])
    assert rho == pytest.approx(0.8)
    scipy_stats = pytest.importorskip("scipy.stats")
    a, b = [3.1, 0.2, 5.5, 1.4, 2.2, 4.0, 0.9], [0.5, 0.1, 0.7, 1.2, 0.3, 0.9, 0.2]
    rho, p = table1.spearman(a, b)
    assert rho == pytest.approx(scipy_stats.spearmanr(a, b).statistic)
    assert p == pytest.approx(scipy_stats.permutation_test(
        (b,), lambda y: scipy_stats.spearmanr(a, y).statistic, permutation_type="pairings",
        alternative="two-sided", n_resamples=10**6).pvalue, abs=1e-9)


def test_compact_seeds_are_judged_against_the_default_by_their_spread(table1):
    def row(scene, variant, psnr, rev="a" * 40):
        return {"scene": scene, "variant": variant, "psnr": psnr, "num_gaussians": 30000, "train_seconds": 2600.0,
                "code_revision": rev}

    rows = [row("s1", "default", 28.0), row("s1", "compact", 28.9), row("s1", "compact_seed1", 28.7, "b" * 40),
            row("s1", "compact_seed2", 28.8, "b" * 40),
            row("s2", "default", 28.0), row("s2", "compact", 28.5), row("s2", "compact_seed1", 27.9),  # one seed below
            row("s3", "default", 28.0), row("s3", "compact", 29.0),  # one seed: no row
            row("s4", "compact_curve", 29.0), row("s4", "compact_seedx", 29.0),  # neither is a seed
            row("s5", "default", 28.0), row("s5", "compact", 29.0, None), row("s5", "compact_seed1", 29.0)]
    rows[2]["lpips"], rows[3]["lpips"] = 0.14, 0.12  # the seed-0 run predates LPIPS
    text = "\n".join(table1.compact_seeds_section(rows))
    assert ("| s1 | 3 and 1 | 28.80 ± 0.10 | 28.00 | +0.80 ± 0.10 | +0.70 | yes | 30,000 ± 0 | 2,600 ± 0 | "
            "aaaaaaa, bbbbbbb |" in text)
    # The same seeds' metrics, each over the seeds that record it.
    assert "| s1 | 3 | 28.80 ± 0.10 | - | 0.130 ± 0.014 (2 of 3 seeds) | - | - | 30,000 ± 0 |" in text
    assert "| s2 | 2 and 1 | 28.20 ± 0.42 | 28.00 | +0.20 ± 0.42 | -0.10 | no |" in text
    assert "| s3 |" not in text and "| s4 |" not in text and "| aaaaaaa, 1 not recorded |" in text  # s5's
    assert table1.compact_seeds_section(rows[7:11]) == []

    # With the default's own seeds: the difference of the means, both spreads combined, and the worst
    # compact seed against the best default seed (a default seed still training is not one).
    rows += [row("s6", "default", 28.0), row("s6", "default_seed1", 28.2), row("s6", "default_seed2", None),
             row("s6", "compact", 28.9), row("s6", "compact_seed1", 29.1)]
    text = "\n".join(table1.compact_seeds_section(rows))
    assert "| s6 | 2 and 2 | 29.00 ± 0.14 | 28.10 ± 0.14 | +0.90 ± 0.20 | +0.70 | yes |" in text
    rows[-4]["psnr"] = 28.95  # a default seed above a compact one: inside the spread
    assert "| 28.48 ± 0.67 | +0.52 ± 0.69 | -0.05 | no |" in "\n".join(table1.compact_seeds_section(rows))


def test_default_seeds_carry_the_metrics_the_protocol_rows_lack(table1):
    """The default over seeds: only segments with two finished seeds, and a metric the seed-0 run
    lacks is averaged over the seeds that record it, with their count named."""
    def row(scene, variant, psnr, lpips=None):
        return {"scene": scene, "variant": variant, "psnr": psnr, "ssim": 0.9, "lpips": lpips,
                "depth_abs_err": None if lpips is None else 0.03, "normal_err_deg": None if lpips is None else 20.0,
                "num_gaussians": 150000, "train_seconds": 7000.0, "code_revision": None if lpips is None else "c" * 40}

    rows = [row("s1", "default", 28.6), row("s1", "default_seed1", 28.8, 0.15), row("s1", "default_seed2", 28.7, 0.17),
            row("s2", "default", 28.0), row("s2", "default_seed1", None),  # still training
            row("s3", "default_curve", 28.0, 0.2), row("s3", "default_seedx", 28.0, 0.2)]  # neither is a seed
    text = "\n".join(table1.default_seeds_section(rows))
    assert ("| s1 | 3 | 28.70 ± 0.10 | 0.900 ± 0.000 | 0.160 ± 0.014 (2 of 3 seeds) | 0.0300 ± 0.0000 (2 of 3 seeds) "
            "| 20.0 ± 0.0 (2 of 3 seeds) | 150,000 ± 0 |" in text)
    assert "| s2 |" not in text and "| s3 |" not in text and "Code revisions: ccccccc, 1 not recorded." in text
    assert table1.default_seeds_section(rows[3:]) == []
    assert "the machine's as much as the method's" in text  # no conditions recorded: the seconds may be shared
    alone = {f"s1/{v}": {"text": "alone", "alone": True} for v in ("default", "default_seed1", "default_seed2")}
    text = "\n".join(table1.default_seeds_section(rows, alone))
    assert "(s1/default: alone; s1/default_seed1: alone; s1/default_seed2: alone)." in text
    assert "machine's" not in text


def test_default_against_compact_names_each_metric_the_compact_loses(table1):
    """Beyond PSNR: a segment enters only where both variants' seeds record every metric, and the
    verdict names each metric whose compact mean is higher (worse), segment by segment."""
    def row(scene, variant, lpips, depth, normal):
        return {"scene": scene, "variant": variant, "lpips": lpips, "depth_abs_err": depth, "normal_err_deg": normal}

    defaults = [row("s1", "default", None, None, None), row("s1", "default_seed1", 0.11, 0.024, 24.0),
                row("s2", "default_seed1", 0.15, 0.030, 22.0), row("s3", "default_seed1", 0.15, 0.030, 22.0)]
    compacts = [row("s1", "compact_seed1", 0.13, 0.020, 20.0), row("s1", "compact_seed2", 0.15, 0.022, 19.0),
                row("s2", "compact_seed1", 0.14, 0.031, 18.0), row("s3", "compact", None, None, None)]
    text = "\n".join(table1.quality_against_compact(defaults, compacts))
    assert ("| s1 | 0.110 (1) | 0.140 ± 0.014 (2) | 0.0240 (1) | 0.0210 ± 0.0014 (2) | 24.0 (1) | 19.5 ± 0.7 (2) |"
            in text)
    assert "| s3 |" not in text  # its compact seed records none of them
    assert "worse on s1 (LPIPS) and s2 (depth error)" in text
    better = row("s2", "compact_seed1", 0.14, 0.029, 18.0)
    assert "as good or better" in "\n".join(table1.quality_against_compact(defaults[2:3], [better]))
    assert table1.quality_against_compact(defaults, compacts[3:]) == []


def test_table1_seed_table_times_one_kind_of_machine(table1):
    """A segment whose seeds trained on two kinds of machine: its PSNR over every seed, its
    training seconds over the table's main kind only, with the kind named."""
    amd, intel = "AMD EPYC x2, cpu", "Intel Xeon x2, cpu"  # the runs' host, as results.json names it
    row = dict(variant="auto", ssim=0.9, lpips=0.2, depth_abs_err=0.04, normal_err_deg=30.0, num_gaussians=20000)
    rows = [dict(row, scene="a", psnr=28.0, train_seconds=600.0, host=amd),
            dict(row, scene="a", variant="auto_seed1", psnr=28.4, train_seconds=1300.0, host=intel),
            dict(row, scene="b", psnr=27.0, train_seconds=500.0, host=amd)]
    text = "\n".join(table1.seed_table(rows, "segment"))
    assert "| a | 2 | 28.20 ± 0.28 |" in text and "| 600 (1 of 2 runs: AMD EPYC x2, cpu) |" in text
    assert "| b | 1 | 27.00 |" in text and text.rstrip().endswith("| 500 |")


def test_table1_names_as_unrecorded_only_the_table_rows_without_a_training_psnr(table1):
    """The evaluation note and the table agree: the segments it says lack a training-view PSNR are
    those whose default or compact row shows "not recorded" (extra seeds have no column there)."""
    text = table1.render(table1.load())
    in_table = {line.split(" | ")[0].lstrip("| ") for line in text.splitlines()
                if line.startswith("| row") and line.rstrip().endswith("| not recorded |")}
    note = re.search(r"The training-view PSNR of (.+?) is not recorded", text)
    named = set(re.split(r", | and ", note.group(1))) if note else set()
    assert named == in_table


def test_ablation_timing_redraws_its_charts_from_the_times_on_record(tmp_path):
    """--redraw times nothing: the interleaved front and table come from step_timing.json as committed."""
    import json

    folder = RESULTS / "raster_ablation" / "auto_cpu"
    for name in ("results.json", "step_timing.json"):
        shutil.copy(folder / name, tmp_path / name)
    assert _module("benchmarks/speed/ablation_timing.py").main([str(tmp_path), "--redraw"]) == 0
    timed = json.loads((tmp_path / "step_timing.json").read_text())["scenes"]
    front = json.loads((tmp_path / "pareto_interleaved.json").read_text())["scenes"]
    assert {s: {v: p["cost"] for v, p in vs.items()} for s, vs in front.items()} == {
        s: {v: t["seconds_per_step"] for v, t in vs.items()} for s, vs in timed.items()}
    table = (tmp_path / "step_timing.md").read_text()
    assert all(f"| {v} |" in table for vs in timed.values() for v in vs)
    assert (tmp_path / "step_timing.json").read_bytes() == (folder / "step_timing.json").read_bytes()


def test_ablation_timing_pools_its_passes_and_the_readme_shows_each_pass():
    """--passes: each variant's median over every pass's steps, each pass's own median kept, and
    the README's last column the ratio to the default in each pass."""
    timing = _module("benchmarks/speed/ablation_timing.py")
    facts = {"step": 8000, "surfels": 20000, "pool": 32768, "pair_capacity": 1 << 20}

    def row(wall):  # a pass's row as time_sessions makes it: samples of (wall, CPU, pairs, faults)
        return facts | {"seconds_per_step": wall, "samples": [[wall, 2 * wall, 1e5, 0.0]] * 3}

    pooled = timing.pooled_passes([{"default": row(0.10), "tile32": row(0.30)},
                                   {"default": row(0.12), "tile32": row(0.33)}])
    assert pooled["tile32"]["pass_seconds_per_step"] == [0.30, 0.33] and len(pooled["tile32"]["samples"]) == 6
    assert pooled["default"]["seconds_per_step"] == pytest.approx(0.11)  # the median of all six steps
    assert pooled["default"]["cpu_seconds_per_step"] == pytest.approx(0.22) and pooled["default"]["step"] == 8000

    ablation = _module("benchmarks/analysis/ablation_readme.py")
    data = ablation.load()
    scene = data["preset"]["scenes"][0]["name"]
    assert "each pass" not in ablation.render(data)  # the committed timing has one pass
    timed = data["timing"]["scenes"][scene]
    timed["default"] |= {"pass_seconds_per_step": [0.10, 0.12]}
    timed["tile32"] |= {"pass_seconds_per_step": [0.30, 0.33]}
    data["timing"]["passes"] = 2
    lines = ablation.render(data).splitlines()
    head = next(line for line in lines if line.startswith("| variant |"))
    assert head.rstrip().endswith("| vs default, each pass |") and "in each of 2 passes" in "\n".join(lines)
    assert next(line for line in lines if line.startswith("| tile32 |")).rstrip().endswith("| 3.00x, 2.75x |")


def test_auto_recipe_groups_geometry_by_the_kept_models_normal_prior_steps(auto_recipe):
    """The kept model's prior steps: its best check past normal_from (0 before it, or with the loss
    off); runs without a geometry error or a record of the settings are left out."""
    def run(best, normal_err, normal_from=7000, lam=0.05, scene="a"):
        return {"scene": scene, "best_step": best, "normal_err_deg": normal_err, "depth_abs_err": 0.04,
                "settings": {"normal_from": normal_from, "lambda_normal": lam}}

    runs = [run(6500, 34.0), run(7000, 32.0, scene="b"), run(7250, 24.0), run(8500, 19.0), run(9000, 30.0, lam=0.0),
            run(8000, None), {"scene": "a", "best_step": 8000, "normal_err_deg": 20.0}]
    assert [auto_recipe.prior_steps(r) for r in runs[:5]] == [0, 0, 250, 1500, 0]
    text = "\n".join(auto_recipe.prior_section(runs))
    assert "| 0 | 3 | 2 | 32.0 ± 2.0 | 30.0-34.0 |" in text and "| 1-500 | 1 | 1 | 24.0 |" in text
    assert "| over 1,000 | 1 | 1 | 19.0 | 19.0-19.0 |" in text and "501-1,000" not in text
    assert auto_recipe.prior_section(runs[5:]) == []
