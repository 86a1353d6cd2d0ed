"""`ghsplat run experiments/NAME.toml`: train a set of runs (scenes x variants), skip finished
ones, and collect their metrics into one table, a Table-1 report and charts. A file with
`kind = "stability"` runs the stability study instead (ghsplat_jax/experiments/stability.py)."""

from __future__ import annotations

import argparse
import logging
import sys

HELP = "run an experiment file: scenes x config variants, then tables and charts"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("experiment", help="experiment TOML file (see experiments/)")
    p.add_argument("--preset", default="full",
                   help="a [presets.NAME] table of the file laid over it, e.g. quick (default: full, the file itself)")
    p.add_argument("--output", help="folder for the runs and reports (default: the file's `output`)")
    p.add_argument("--results", help="folder for the reports (default: the file's `results`, else the runs' folder)")
    p.add_argument("--only", action="append", default=[], metavar="SCENE[/VARIANT]", help="run only these")
    p.add_argument("--steps", type=int, help="override the step count of every run")
    p.add_argument("--list", action="store_true", help="list the planned runs and their state, train nothing")
    p.add_argument("--report-only", action="store_true",
                   help="only collect finished runs into the reports (and a missing segments report, once every "
                        "segment exists)")
    p.add_argument("--prepare-only", action="store_true",
                   help="only make the data of a file with [prepare] (photos and SfM), e.g. to train elsewhere")
    p.add_argument("--stop-on-error", action="store_true", help="stop at the first failed run")
    p.add_argument("--stop-at", type=int, metavar="N",
                   help="train every run to step N, checkpoint and stop (a later run without it resumes there); "
                        "the reports mark such a run 'stopped at step N of M' rather than leaving it out")
    p.add_argument("--retrain", action="store_true",
                   help="train again a run whose folder is gone although the experiment's results.json reports it "
                        "finished. Without it such a run is skipped and its reported row kept: a lost runs folder "
                        "must not cost hours of training to reproduce numbers already reported (the log names each "
                        "run skipped so)")
    g = p.add_argument_group("executor")
    g.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local: one run after another here (default); ray: one Ray task per run "
                        '(pip install -e ".[ray]")')
    g.add_argument("--address", metavar="ADDR",
                   help="Ray cluster to use: 'auto' (this machine's cluster), 'ray://HEAD:10001' (remote "
                        "head); default: start a local Ray instance")
    g.add_argument("--cpus-per-run", type=float, help="Ray: CPUs each run reserves (default 1)")
    g.add_argument("--gpus-per-run", type=float,
                   help="Ray: GPUs each run reserves (default 1 when the cluster has GPUs, else 0)")


def main(args) -> int:
    from ghsplat_jax.experiments.runner import load_experiment, run_experiment
    from ghsplat_jax.experiments.segments import prepare_segments
    from ghsplat_jax.train.config import ConfigError

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    overrides = {"steps": args.steps} if args.steps is not None else None
    try:
        exp = load_experiment(args.experiment, args.output, overrides, args.preset, args.results)
    except ConfigError as exc:
        print(f"ghsplat run: {exc}", file=sys.stderr)
        return 2
    if exp.kind == "stability":
        if args.prepare_only:  # the study makes its rows inside its cases
            print(f"ghsplat run: {exp.source}: --prepare-only applies to [prepare] segments, not a stability study",
                  file=sys.stderr)
            return 2
        if args.stop_at is not None or args.retrain:
            print(f"ghsplat run: {exp.source}: --stop-at and --retrain apply to scenes x variants, not a stability "
                  "study", file=sys.stderr)
            return 2
        return _run_stability(exp, args)
    if args.list:
        from ghsplat_jax.experiments.report import RESULTS_NAME
        from ghsplat_jax.experiments.runner import earlier_rows, is_reported

        earlier = earlier_rows(exp.results / RESULTS_NAME)
        for r in exp.runs:
            state = r.state
            if state == "todo" and is_reported(earlier.get((r.scene, r.variant))):
                state = "reported (its folder is gone; --retrain trains it again)"
            print(f"{r.scene}/{r.variant}: {state}  {r.out_dir}  (data={r.config.data}, steps={r.config.steps}, "
                  f"strategy={r.config.strategy.name})")
        return 0
    if args.executor != "ray" and (args.address or args.cpus_per_run or args.gpus_per_run):
        print("ghsplat run: --address, --cpus-per-run and --gpus-per-run need --executor ray", file=sys.stderr)
        return 2
    ray_options = {"address": args.address, "cpus_per_run": args.cpus_per_run, "gpus_per_run": args.gpus_per_run}
    if args.executor == "ray":
        try:
            import ray  # noqa: F401
        except ImportError:
            print('ghsplat run: --executor ray needs Ray: pip install -e ".[ray]"', file=sys.stderr)
            return 2
    if args.stop_at is not None and args.stop_at < 1:
        print(f"ghsplat run: --stop-at must be a step >= 1, got {args.stop_at}", file=sys.stderr)
        return 2
    if args.report_only and args.prepare_only:
        print("ghsplat run: --report-only and --prepare-only exclude each other", file=sys.stderr)
        return 2
    try:
        only_scenes = {name.split("/")[0] for name in args.only} or None
        prepared = prepare_segments(exp, only_scenes, make=not args.report_only)  # {scene: why its data is unfit}
        unusable = {} if args.report_only else prepared  # a report lists every run that trained
    except ConfigError as exc:
        print(f"ghsplat run: {exc}", file=sys.stderr)
        return 2
    if args.prepare_only:
        if not exp.spec.get("prepare"):
            print(f"{exp.source}: no [prepare] table, so no data to make")
            return 0
        for scene, msg in unusable.items():
            print(f"ghsplat run: {scene}: {msg}", file=sys.stderr)
        print(f"data made; report: {exp.results / 'segments.md'}")
        return 1 if unusable else 0
    result = run_experiment(exp, set(args.only) or None, args.stop_on_error, evaluate_only=args.report_only,
                            executor=args.executor, ray_options=ray_options, exclude=set(unusable),
                            until=args.stop_at, retrain=args.retrain)
    result["failed"] = list(unusable.items()) + result["failed"]
    for run, msg in result["failed"]:
        print(f"ghsplat run: {run} failed: {msg}", file=sys.stderr)
    stopped = [r for r in result["rows"] if r.get("status", "finished") != "finished"]
    listed = ", ".join(f"{r['scene']}/{r['variant']}: {r['status']}" for r in stopped)
    print(f"{len(result['rows']) - len(stopped)} finished runs"
          + (f", {len(stopped)} not finished ({listed})" if stopped else "")
          + "; reports: " + ", ".join(str(p) for p in result["reports"]))
    return 1 if result["failed"] else 0


def _run_stability(exp, args) -> int:
    """kind = "stability": the cases of experiments/stability.toml (ghsplat_jax/experiments/stability.py)."""
    from ghsplat_jax.experiments.stability import StudyError, check_cases, run_study

    try:
        cases = check_cases(exp.spec.get("cases"))
    except StudyError as exc:
        print(f"ghsplat run: {exp.source}: {exc}", file=sys.stderr)
        return 2
    if args.list:
        for c in cases:
            print(f"{c['family']}/{c['name']}")
        return 0
    if args.steps is not None:
        exp.spec.setdefault("train", {})["steps"] = args.steps
    try:
        result = run_study(exp, set(args.only) or None)
    except StudyError as exc:
        print(f"ghsplat run: {exp.source}: {exc}", file=sys.stderr)
        return 2
    for name, msg in result["failed"]:
        print(f"ghsplat run: case {name} could not run: {msg}", file=sys.stderr)
    print(f"{len(result['rows'])} rows; reports: " + ", ".join(str(p) for p in result["reports"]))
    return 1 if result["failed"] else 0
