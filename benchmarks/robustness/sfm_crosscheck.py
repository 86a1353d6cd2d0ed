"""The SfM checks against the generator's exact cameras: greenhouse row segments (Table 1's
capture) and orbits round one plant, each mapped twice, with the earlier checks (fixed 30-degree
rotation-chain bound, no cross-check) and with the current ones.

    python benchmarks/robustness/sfm_crosscheck.py --cases row3_x0 row3_x1 orbit72 --work runs/sfm_crosscheck

Cases: rowR_xE (R in 0-3, E in x0/x1; 60 views of 384x288 round that end of row R of the
default four-row greenhouse, half the row: experiments/table1_greenhouse.toml [prepare]),
orbitN (N views of 384x288 round the single plant of benchmarks/configs/orbit_plant.toml,
mapped with --align none), walkN (N views of 384x288 of a hand-held walk round the whole of row 0:
a long video-like walk), a "-mt" suffix maps with every CPU thread (--threads -1), and a
"#k" suffix names a repeat (the multithreaded mapper differs from run to run).
Photos are rendered once into WORK/case/photos and kept. Every run is `run_sfm` as
`ghsplat sfm --max-size 384` runs it; the model is scored with compare_model_dirs, and the
cross-check's flagged views with their true errors in the earlier model. Appends to
benchmarks/results/sfm_crosscheck/results.json (one entry per case and variant, latest
kept) and rewrites README.md's table. `--check` runs nothing: it renders README.md from the
committed results.json and exits 1 with a diff when they differ.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py
from readme_check import report, text_diff  # noqa: E402
from record import ROOT, machine_record  # noqa: E402

from ghsplat_jax.experiments.report import markdown_table  # noqa: E402
from ghsplat_jax.io_utils import atomic_write, code_revision, write_json  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "sfm_crosscheck"
ORBIT_CONFIG = ROOT / "benchmarks" / "configs" / "orbit_plant.toml"
WIDTH, HEIGHT = 384, 288


def render(case: str, photos: Path) -> float:
    """Photos and exact cameras of `case` into `photos` (skipped when there); seconds taken."""
    from ghsplat_jax.synth import capture, config, dataset, scene

    if (photos / "sparse" / "0").is_dir():
        return 0.0
    start = time.perf_counter()
    base = _base(case)
    if m := re.fullmatch(r"row(\d)_(x[01])", base):
        world = scene.generate_scene(config.SceneConfig())
        cams = capture.capture_path(world, "handheld", 60, row=int(m[1]), width=WIDTH, height=HEIGHT,
                                    seed=world.config.seed,
                                    config=capture.PathConfig(end=m[2], segment_fraction=0.5))
    elif m := re.fullmatch(r"orbit(\d+)", base):
        world = scene.generate_scene(config.load_config(ORBIT_CONFIG))
        cams = capture.capture_path(world, "orbit", int(m[1]), width=WIDTH, height=HEIGHT, seed=world.config.seed)
    elif m := re.fullmatch(r"walk(\d+)", base):
        world = scene.generate_scene(config.SceneConfig())
        cams = capture.capture_path(world, "handheld", int(m[1]), row=0, width=WIDTH, height=HEIGHT,
                                    seed=world.config.seed)
    else:
        raise SystemExit(f"unknown case {case!r} (rowR_xE, orbitN or walkN, optional -mt)")
    dataset.write_dataset(world, cams, photos, meshes=False, overwrite=True, progress=False)
    return time.perf_counter() - start


def _base(case: str) -> str:
    """The capture a case maps: its name without the -mt and #k suffixes."""
    return case.split("#")[0].removesuffix("-mt")


def per_view_errors(model: Path, truth: Path) -> dict[str, tuple[float, float]]:
    """{name: (centre error % of the extent, rotation error deg)} after a similarity alignment."""
    from ghsplat_jax.sfm.align import camera_centres
    from ghsplat_jax.sfm.evaluate import model_dir_w2c, umeyama

    est, ref = model_dir_w2c(model), model_dir_w2c(truth)
    names = sorted(set(est) & set(ref))
    e, r = np.stack([est[n] for n in names]), np.stack([ref[n] for n in names])
    ec, rc = camera_centres(e), camera_centres(r)
    scale, rot, t = umeyama(ec, rc)
    err = np.linalg.norm(scale * ec @ rot.T + t - rc, axis=1)
    extent = 2.0 * float(np.max(np.linalg.norm(rc - rc.mean(0), axis=1)))
    rel = np.einsum("nij,nkj->nik", e[:, :3, :3] @ rot.T, r[:, :3, :3])
    deg = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)))
    return {n: (100 * float(a) / extent, float(b)) for n, a, b in zip(names, err, deg)}


def run(case: str, photos: Path, out: Path, variant: str) -> dict:
    import pycolmap

    from ghsplat_jax.sfm.evaluate import compare_model_dirs
    from ghsplat_jax.sfm.folds import FoldOptions
    from ghsplat_jax.sfm.pipeline import SfmOptions, run_sfm

    options = SfmOptions(max_size=max(WIDTH, HEIGHT), progress=False,
                         num_threads=-1 if case.split("#")[0].endswith("-mt") else 1,
                         align="none" if case.startswith("orbit") else "greenhouse")
    if variant == "before":  # the fixed 30-degree drift bound and no cross-check
        options = dataclasses.replace(options, cross_check=False, fold_options=FoldOptions(drift_sigmas=0.0))
    pycolmap.logging.minloglevel = 2
    shutil.rmtree(out, ignore_errors=True)
    report = run_sfm(photos / "images", out, options)
    model = out / "sparse" / "0"
    acc = compare_model_dirs(model, photos / "sparse" / "0") if model.is_dir() else None
    chain = (report.get("fold_diagnostics") or {}).get("rotation_chain") or {}
    check = report.get("cross_check") or {}
    dis = report.get("disambiguation") or {}
    second = report.get("second_estimate") or {}
    return {
        "case": case, "variant": variant, "status": report["status"],
        "registered": report.get("num_registered"), "views": report["num_images"],
        "centre_error_max_pct": None if acc is None else round(100 * acc["centre_error_max_rel"], 3),
        "centre_error_rmse_pct": None if acc is None else round(100 * acc["centre_error_rmse"] / acc["extent"], 3),
        "rotation_error_max_deg": None if acc is None else round(acc["rotation_error_max_deg"], 3),
        "mapping_used": dis.get("used", dis.get("method")),
        "fold_reasons": (report.get("fold_diagnostics") or {}).get("reasons", []),
        "drift_deg": chain.get("max_drift_deg"), "drift_bound_deg": chain.get("drift_bound_deg", 30.0),
        "link_error_median_deg": chain.get("link_error_median_deg"),
        "cross_check_dropped": check.get("dropped", []),
        "cross_check_rounds": check.get("rounds", []),
        "cross_check_largest_kept": [check.get("largest_centre_rel"), check.get("largest_rotation_deg")],
        "cross_check_s": (report.get("timings_s") or {}).get("cross_check"),
        **second_estimate_fields(second),
        "second_estimate_s": (report.get("timings_s") or {}).get("second_estimate"),
        "sfm_s": report["timings_s"]["total"],
    }


def second_estimate_fields(second: dict) -> dict:
    """A results row's record of the global mapper's second estimate (second_estimate.py)."""
    return {"second_estimate": second.get("verdict", "-"),
            "second_estimate_disagree": [v["name"] for v in second.get("disagree", [])],
            "second_estimate_largest": [second.get("largest_centre_rel"), second.get("largest_rotation_deg")]}


def _truth_error(reconstruction, truth: Path) -> list[float] | None:
    """[largest centre error % of the extent, largest rotation error deg] of a pycolmap model's
    views against the exact cameras in `truth` (None without a model or 3 views in common)."""
    from ghsplat_jax.sfm.evaluate import compare_poses, model_dir_w2c, model_w2c

    if reconstruction is None:
        return None
    est, ref = model_w2c(reconstruction), model_dir_w2c(truth)
    names = sorted(set(est) & set(ref))
    if len(names) < 3:
        return None
    acc = compare_poses(np.stack([est[n] for n in names]), np.stack([ref[n] for n in names]))
    return [round(100 * acc["centre_error_max_rel"], 3), round(acc["rotation_error_max_deg"], 3)]


def recheck(case: str, work: Path) -> dict:
    """The second estimate applied to the `after` model an earlier run left in WORK/case (its
    database and its aligned model: the same views and tracks), as a results row: that map's own
    status (its sfm_report.json) and errors against the truth, the verdict, the status the current
    checks would give, and how far the second estimate, and the global mapper given every verified
    pair, lie from the truth. Everything about the map is read from its folder, never from a
    results row, which may describe a later map of the same case."""
    import json

    import pycolmap

    from ghsplat_jax.sfm import second_estimate
    from ghsplat_jax.sfm.pipeline import SfmOptions, map_images

    run_dir = work / case / "sfm_after"
    photos = work / _base(case) / "photos"
    database, scratch = run_dir / "distorted" / "database.db", run_dir / "distorted" / "second_estimate"
    mapped = json.loads((run_dir / "sfm_report.json").read_text())
    truth = photos / "sparse" / "0"
    pycolmap.logging.minloglevel = 2
    model = pycolmap.Reconstruction(str(run_dir / "sparse" / "0"))
    centre_error, rotation_error = _truth_error(model, truth)
    start = time.perf_counter()
    second, estimate = second_estimate.estimate_and_compare(database, photos / "images", model, scratch)
    seconds = time.perf_counter() - start
    every_pair = map_images(database, photos / "images", scratch / "every_pair", SfmOptions(mapper="global"))
    every_pair = max(every_pair.values(), key=lambda m: m.num_reg_images(), default=None)
    # maps written before sfm_report.json recorded the code revision have it "unrecorded"
    row = {"case": case, "variant": "recheck", "registered": mapped.get("num_registered"),
           "views": mapped["num_images"], "centre_error_max_pct": centre_error,
           "rotation_error_max_deg": rotation_error,
           "cross_check_dropped": (mapped.get("cross_check") or {}).get("dropped", []),
           "mapped_status": mapped["status"], "mapped_revision": mapped["versions"].get("ghsplat_jax", "unrecorded"),
           "status": "inconsistent" if mapped["status"] == "ok" and second["verdict"] == "disagree"
           else mapped["status"], **second_estimate_fields(second),
           "second_estimate_true_error": _truth_error(estimate, truth),
           "global_every_pair_true_error": _truth_error(every_pair, truth),
           "second_estimate_s": round(seconds, 3)}
    shutil.rmtree(scratch, ignore_errors=True)
    return row


REPEAT = re.compile(r"(row\d_x[01])-mt#\d+")
CENTRE_GOAL_PCT, ROTATION_GOAL_DEG = 1.0, 2.0  # no "ok" model beyond these (largest view error)


def latest_revision(rows: list[dict], variant: str) -> str | None:
    """The code revision of the multithreaded repeats of `variant` appended last (None without any)."""
    picked = [r.get("git_revision") for r in rows if r["variant"] == variant and REPEAT.fullmatch(r["case"])]
    return picked[-1] if picked else None


def repeat_summary(rows: list[dict], revision: str | None, variant: str = "after") -> str:
    """The goal check over the multithreaded repeats of the row segments checked at `revision`
    (the checks of that code only): per segment, how many ended "ok" and the largest errors of
    those that did; '' when there are none. `variant` "recheck": the earlier models held against
    the second estimate offline."""
    picked = [r for r in rows if r["variant"] == variant and REPEAT.fullmatch(r["case"])
              and r.get("git_revision") == revision]
    if not picked:
        return ""
    table, segments_ok, over = [], 0, 0
    for segment in sorted({REPEAT.fullmatch(r["case"])[1] for r in picked}):
        runs = [r for r in picked if REPEAT.fullmatch(r["case"])[1] == segment]
        ok = [r for r in runs if r["status"] == "ok"]
        beyond = [r for r in ok if r["centre_error_max_pct"] > CENTRE_GOAL_PCT
                  or r["rotation_error_max_deg"] > ROTATION_GOAL_DEG]
        segments_ok += len(ok) == len(runs)
        over += len(beyond)
        others = sorted({r["status"] for r in runs} - {"ok"})
        table.append({"segment": segment, "repeats": len(runs), "ok": len(ok),
                      "other": ", ".join(others) or "-",
                      "centre": max((r["centre_error_max_pct"] for r in ok), default=None),
                      "rotation": max((r["rotation_error_max_deg"] for r in ok), default=None),
                      "beyond": ", ".join(r["case"] for r in beyond) or "-",
                      "dropped": sum(len(r["cross_check_dropped"]) for r in runs),
                      "inconsistent": ", ".join(r["case"] for r in runs if r["status"] == "inconsistent") or "-"})
    cols = ("segment", "repeats", "ok", "other", "centre", "rotation", "beyond", "dropped", "inconsistent")
    heads = ("segment", "repeats (-mt)", "ended ok", "other statuses", "largest centre error of an ok model, % extent",
             "largest rotation error of an ok model, deg", f"ok beyond {CENTRE_GOAL_PCT}% or {ROTATION_GOAL_DEG} deg",
             "views the cross-check dropped (all repeats)", "called inconsistent by the second estimate")
    verdict = (f"**{over} ok model(s) beyond the bounds** (goal: none)" if over else
               f"no ok model beyond {CENTRE_GOAL_PCT}% of the extent or {ROTATION_GOAL_DEG} degrees (goal met)")
    segments_any = sum(row["ok"] > 0 for row in table)
    title, lead = {
        "after": (f"Multithreaded repeats: the goal check at {revision[:10]}",
                  "Every row segment mapped with all CPU threads (`--threads -1`), whose mapper differs from run "
                  "to run, with the current checks."),
        "recheck": (f"The earlier repeats held against the second estimate: the goal check at {revision[:10]}",
                    "The multithreaded models of an earlier revision (each row's `mapped_revision`), each held "
                    "offline against the global mapper's estimate from the pairs it confirms "
                    "(`--recheck`); a model the two place differently is `inconsistent`."),
    }[variant]
    return (f"## {title}\n\n{lead} Goal: no model called ok with a view beyond {CENTRE_GOAL_PCT}% of the extent "
            f"or {ROTATION_GOAL_DEG} degrees, and at least 7 of the 8 segments still ok. Result: {verdict}; "
            f"{segments_ok} of {len(table)} segments ok in every repeat, {segments_any} in at least one.\n\n"
            + markdown_table(table, cols, heads) + "\n" + _estimates_against_truth(picked))


def _estimates_against_truth(rows: list[dict]) -> str:
    """A line on how far the second estimates, and the global mapper given every verified pair,
    lie from the exact cameras ('' for rows without those numbers)."""
    second = [r["second_estimate_true_error"] for r in rows if r.get("second_estimate_true_error")]
    every = [r.get("global_every_pair_true_error") for r in rows if "global_every_pair_true_error" in r]
    if not second:
        return ""
    far = [e for e in every if e is None or e[0] > 5.0]
    return (f"The second estimates themselves lay {min(e[0] for e in second):.2f}-{max(e[0] for e in second):.2f}% "
            f"of the extent and {min(e[1] for e in second):.2f}-{max(e[1] for e in second):.2f} degrees from the "
            f"exact cameras ({len(second)} maps). The global mapper given every verified pair instead ended more "
            f"than 5% of the extent off (or with no model) on {len(far)} of {len(every)}"
            + (f" (up to {max(e[0] for e in far if e):.1f}%)" if any(far) else "") + ".\n\n")


def readme_text(rows: list[dict], revision: str) -> str:
    """README.md's text: the table of `rows` (results.json's) made at code revision `revision`."""
    from ghsplat_jax.sfm.crosscheck import CrossCheckOptions
    from ghsplat_jax.sfm.second_estimate import SecondEstimateOptions

    loo, second = CrossCheckOptions(), SecondEstimateOptions()
    table = []
    for r in rows:
        flagged = r["cross_check_dropped"]
        truth = r.get("flagged_true_errors", {})
        table.append({**r, "flagged": ", ".join(f"{n} ({truth[n][0]:.2f}%, {truth[n][1]:.1f} deg)" if n in truth
                                                else n for n in flagged) or "-",
                      "drift": f"{r['drift_deg']} / {r['drift_bound_deg']}" if r.get("drift_deg") is not None else "-"})
        verdict = r.get("second_estimate", "-")
        if verdict == "disagree":
            verdict += " (" + ", ".join(r["second_estimate_disagree"][:4]) + (", ..." if len(
                r["second_estimate_disagree"]) > 4 else "") + ")"
        table[-1]["second"] = verdict
    cols = ("case", "variant", "status", "registered", "views", "centre_error_max_pct", "rotation_error_max_deg",
            "drift", "flagged", "cross_check_s", "second", "second_estimate_s", "sfm_s")
    heads = ("case", "checks", "status", "registered", "photos", "max centre error % extent", "max rotation error deg",
             "chain drift / bound deg", "cross-check dropped (true error in the earlier model)", "cross-check s",
             "second estimate", "second estimate s", "SfM s")
    return ("# SfM checks against the exact cameras: rotation-chain bound, leave-one-out cross-check, "
            "second estimate\n\n"
            "Made by `benchmarks/robustness/sfm_crosscheck.py` from results.json; do not edit by hand. "
            "`before`: the fixed 30-degree rotation-chain bound and "
            "no cross-check; `after`: the bound scaled with the chain's own link errors and every view "
            f"re-localised with itself left out (views landing more than {100 * loo.max_centre_rel:g}% of the extent "
            f"or {loo.max_rotation_deg:g} degrees away are dropped), then the model held against the global "
            f"mapper's estimate from the pairs it confirms (a view more than {100 * second.max_centre_rel:g}% of "
            f"the extent or {second.max_rotation_deg:g} degrees away makes it `inconsistent`; rows "
            "with a second estimate only). `recheck`: an earlier `after` model held against that estimate "
            "offline. Errors are of the kept views against the generator's exact cameras "
            "(similarity-aligned), % of the extent. Row segments: 60 photos of 384x288 round one end of "
            "a row of the default greenhouse (Table 1's capture); orbitN: N photos round one plant "
            "(`--capture orbit`, `--align none`); walkN: N photos of a hand-held walk round the whole of row 0; "
            "-mt: all CPU threads.\n\n"
            f"results.json last written at revision {revision} (each row records its own `git_revision`); "
            "machine in results.json. What each run shows, and the "
            "models checked offline: NOTES.md.\n\n" + repeat_summary(rows, latest_revision(rows, "after"))
            + repeat_summary(rows, latest_revision(rows, "recheck"), "recheck")
            + "## Every run\n\n" + markdown_table(table, cols, heads))


def readme_from_results(results: Path = RESULTS) -> str:
    """README.md's text rendered from the committed results.json (no run folders)."""
    import json

    res = json.loads((results / "results.json").read_text())
    return readme_text(res["rows"], res["git_revision"])


def check(results: Path = RESULTS) -> str:
    """'' when README.md is what results.json gives, else a unified diff (committed -> generated)."""
    return text_diff(results / "README.md", readme_from_results(results))


def write(rows: list[dict]) -> None:
    revision = code_revision()
    write_json(RESULTS / "results.json", {"machine": machine_record(), "git_revision": revision, "rows": rows})
    with atomic_write(RESULTS / "README.md", "w") as fh:
        fh.write(readme_text(rows, revision))


def main(argv=None) -> int:
    import json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["row3_x0", "row3_x1", "orbit72"])
    ap.add_argument("--variants", nargs="+", default=["before", "after"], choices=["before", "after"])
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "sfm_crosscheck")
    ap.add_argument("--recheck", action="store_true",
                    help="map nothing: hold the `after` models an earlier run left in WORK against the second "
                         "estimate (rows of variant 'recheck')")
    ap.add_argument("--render", action="store_true", help="run nothing: write README.md from results.json")
    ap.add_argument("--check", action="store_true",
                    help="run nothing: exit 1 with a diff if README.md differs from what results.json gives")
    args = ap.parse_args(argv)
    if args.check:
        return report(RESULTS / "README.md", check(), "what results.json gives")
    if args.render:
        with atomic_write(RESULTS / "README.md", "w") as fh:
            fh.write(readme_from_results())
        return 0
    old = RESULTS / "results.json"
    rows = json.loads(old.read_text())["rows"] if old.is_file() else []
    if args.recheck:
        for case in args.cases:
            run_dir = args.work / case / "sfm_after"
            if not (run_dir / "sparse" / "0").is_dir() or not (run_dir / "sfm_report.json").is_file():
                raise SystemExit(f"{case}: no `after` model with its sfm_report.json in {run_dir}")
            row = recheck(case, args.work) | {"git_revision": code_revision()}
            rows = [r for r in rows if (r["case"], r["variant"]) != (case, "recheck")] + [row]
            print({k: row[k] for k in ("case", "mapped_status", "status", "second_estimate", "second_estimate_largest",
                                       "centre_error_max_pct", "rotation_error_max_deg")}, flush=True)
            write(rows)
        return 0
    for case in args.cases:
        photos = args.work / _base(case) / "photos"
        seconds = render(case, photos)
        earlier = args.work / case / "sfm_before" / "sparse" / "0"  # a before model from an earlier invocation
        before_errors = per_view_errors(earlier, photos / "sparse" / "0") if earlier.is_dir() else None
        for variant in args.variants:
            out = args.work / case / f"sfm_{variant}"
            row = run(case, photos, out, variant)
            row["render_s"] = round(seconds, 1)
            row["git_revision"] = code_revision()
            if variant == "before" and (out / "sparse" / "0").is_dir():
                before_errors = per_view_errors(out / "sparse" / "0", photos / "sparse" / "0")
            if before_errors is not None:
                row["flagged_true_errors"] = {n: [round(v, 3) for v in before_errors[n]]
                                              for n in row["cross_check_dropped"] if n in before_errors}
            rows = [r for r in rows if (r["case"], r["variant"]) != (case, variant)] + [row]
            print({k: row[k] for k in ("case", "variant", "status", "registered", "centre_error_max_pct",
                                       "rotation_error_max_deg", "drift_deg", "drift_bound_deg",
                                       "cross_check_dropped", "sfm_s")}, flush=True)
            write(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
