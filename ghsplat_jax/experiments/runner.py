"""Experiment runner: scenes x config variants from a TOML file, finished runs skipped, every
metrics.json collected into one table (markdown + CSV), a Table-1 report and charts.

Experiment file layout (see experiments/*.toml):

    name = "quick_cpu"
    output = "runs/quick_cpu"      # relative to the current folder unless absolute
    [train]                        # TrainConfig overrides for every run
    steps = 300
    [[scenes]]
    name = "fern"
    data = "llff_fern"             # a folder, or a name under the shared datasets root
    train = { downscale = 8.0 }    # per-scene overrides
    [[variants]]                   # optional; one "default" variant when absent
    name = "budget"
    train = { strategy = "budget", max_surfels = 20000 }
    [[variants]]                   # a capped strategy at a fraction of another variant's final count:
    name = "mcmc_20"               # max_surfels = round(0.2 x the scene's `default` run's num_gaussians),
    count_fraction = 0.2           # resolved when it runs (that run goes first; an error if it has not
    count_of = "default"           # finished; its row in results.json if its folder is gone);
                                   # count_of defaults to "default"
    train = { strategy = "mcmc" }
    reports = ["compactness"]      # extra reports (experiments/compactness.py) beside results / table1 / charts
    [presets.quick]                # `--preset quick`; the file itself is the "full" preset
    train = { steps = 300 }        # merged over [train]; `scenes` / `variants` here replace the lists
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import traceback
from pathlib import Path

from ghsplat_jax.eval.evaluate import train_and_evaluate
from ghsplat_jax.host_memory import release_compiled_programs
from ghsplat_jax.train.config import ConfigError, TrainConfig, apply_overrides
from ghsplat_jax.train.run_dir import has_checkpoint, is_evaluated

log = logging.getLogger("ghsplat.run")

FINISHED = "finished"  # a report row's status; a stopped run's reads "stopped at step N of M"

_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclasses.dataclass(frozen=True)
class PlannedRun:
    scene: str
    variant: str
    config: TrainConfig
    out_dir: Path
    count_fraction: float | None = None  # max_surfels from this fraction of the count_of run's final count
    count_of: str = "default"

    @property
    def finished(self) -> bool:
        return is_evaluated(self.out_dir)

    @property
    def state(self) -> str:
        """finished, interrupted (a checkpoint to resume from) or todo."""
        return "finished" if self.finished else ("interrupted" if has_checkpoint(self.out_dir) else "todo")


@dataclasses.dataclass(frozen=True)
class Experiment:
    name: str
    description: str
    output: Path
    runs: list[PlannedRun]
    source: Path
    results: Path  # where the reports go (the file's `results`, else `output`)
    preset: str = "full"
    kind: str = "train"  # "train" (scenes x variants) or a study that commands/run.py dispatches
    spec: dict = dataclasses.field(default_factory=dict)  # the file with its preset applied (for studies)
    reports: tuple[str, ...] = ()  # extra reports of REPORTS to write


def _table(value, what: str, source) -> dict:
    if not isinstance(value, dict):
        raise ConfigError(f"{source}: {what} must be a table, got {value!r}")
    return value


def _name(entry: dict, kind: str, i: int, source) -> str:
    name = _table(entry, f"{kind}[{i}]", source).get("name")
    if not isinstance(name, str) or not _NAME.match(name):
        raise ConfigError(f"{source}: {kind}[{i}] needs a 'name' of letters, digits, '_', '-' or '.', got {name!r}")
    unknown = set(entry) - ({"name", "data", "train", "segment"} if kind == "scenes" else
                            {"name", "train", "count_fraction", "count_of"})
    if unknown:
        raise ConfigError(f"{source}: unknown keys {sorted(unknown)} in {kind[:-1]} {name!r}")
    return name


_KEYS = {"name", "description", "output", "results", "kind", "prepare", "cases", "train", "scenes", "variants",
         "reports", "sfm_recorded", "seeds"}
KINDS = ("train", "stability")


def _apply_preset(spec: dict, preset: str, path) -> dict:
    """The spec with `[presets.PRESET]` laid over it: `train` merged key by key, every other key
    replaced; the preset's runs and reports go to their own folders (OUTPUT_PRESET, RESULTS/PRESET)."""
    presets = _table(spec.pop("presets", {}), "[presets]", path)
    if preset == "full":
        return spec
    if preset not in presets:
        known = ", ".join(["full", *sorted(presets)])
        raise ConfigError(f"{path}: no preset {preset!r} (this file has: {known})")
    over = _table(presets[preset], f"[presets.{preset}]", path)
    unknown = set(over) - _KEYS
    if unknown:
        raise ConfigError(f"{path}: unknown keys {sorted(unknown)} in [presets.{preset}]")
    name = spec.get("name", Path(path).stem)
    out = dict(spec, **over)
    out["train"] = {**_table(spec.get("train", {}), "[train]", path), **_table(over.get("train", {}),
                                                                             f"[presets.{preset}] train", path)}
    if "output" not in over:
        out["output"] = f"{spec.get('output', Path('runs') / name)}_{preset}"
    if "results" not in over and "results" in spec:
        out["results"] = str(Path(spec["results"]) / preset)
    return out


def load_experiment(path, output: str | os.PathLike | None = None, overrides: dict | None = None,
                    preset: str = "full", results: str | os.PathLike | None = None) -> Experiment:
    """Parse and validate an experiment file into planned runs (nothing is trained).
    `output` moves the runs and, unless `results` is given, the reports too."""
    import tomllib

    path = Path(path)
    try:
        spec = tomllib.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read experiment ({exc.strerror})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    unknown = set(spec) - _KEYS - {"presets"}
    if unknown:
        raise ConfigError(f"{path}: unknown experiment keys {sorted(unknown)}")
    spec = _apply_preset(spec, preset, path)
    name = spec.get("name", path.stem)
    for key in ("name", "description", "output", "results", "kind", "sfm_recorded"):
        if not isinstance(spec.get(key, ""), str):
            raise ConfigError(f"{path}: '{key}' must be a string, got {spec[key]!r}")
    kind = spec.get("kind", "train")
    if kind not in KINDS:
        raise ConfigError(f"{path}: kind must be one of {KINDS}, got {kind!r}")
    scenes = spec.get("scenes", [] if kind != "train" else None)
    if not isinstance(scenes, list) or (kind == "train" and not scenes):
        raise ConfigError(f"{path}: an experiment needs at least one [[scenes]] entry")
    variants = spec.get("variants") or [{"name": "default"}]
    if not isinstance(variants, list):
        raise ConfigError(f"{path}: 'variants' must be an array of tables ([[variants]])")
    base = apply_overrides(TrainConfig(), _table(spec.get("train", {}), "[train]", path), f"{path} [train]")
    out_root = Path(output or spec.get("output") or Path("runs") / name)
    runs = []
    seen = set()
    for i, scene in enumerate(scenes):
        sname = _name(scene, "scenes", i, path)
        if "data" not in scene:
            raise ConfigError(f"{path}: scene {sname!r} has no 'data'")
        for j, variant in enumerate(variants):
            vname = _name(variant, "variants", j, path)
            if (sname, vname) in seen:
                raise ConfigError(f"{path}: run {sname}/{vname} appears twice")
            seen.add((sname, vname))
            where = f"{path} scene {sname!r} variant {vname!r}"
            scene_train = _table(scene.get("train", {}), f"scene {sname!r} train", path)
            cfg = apply_overrides(base, dict(scene_train, data=scene["data"]), where)
            cfg = apply_overrides(cfg, _table(variant.get("train", {}), f"variant {vname!r} train", path), where)
            if overrides:
                cfg = apply_overrides(cfg, overrides, "command line")
            fraction, of = _count_fraction(variant, vname, variants, cfg, path)
            runs.append(PlannedRun(sname, vname, cfg, out_root / sname / vname, fraction, of))
    report_root = Path(results or output or spec.get("results") or out_root)
    reports = spec.get("reports", [])
    if not isinstance(reports, list) or any(r not in REPORTS for r in reports):
        raise ConfigError(f"{path}: 'reports' must be a list of {sorted(REPORTS)}, got {reports!r}")
    return Experiment(name, spec.get("description", ""), out_root, runs, path, report_root, preset, kind, spec,
                      tuple(reports))


REPORTS = ("compactness",)


def _count_fraction(variant: dict, vname: str, variants: list, cfg: TrainConfig, path) -> tuple[float | None, str]:
    """The variant's validated (count_fraction, count_of)."""
    from ghsplat_jax.train.strategies import strategy_class

    of = variant.get("count_of", "default")
    if "count_fraction" not in variant:
        if "count_of" in variant:
            raise ConfigError(f"{path}: variant {vname!r} has count_of but no count_fraction")
        return None, of
    f = variant["count_fraction"]
    if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f:
        raise ConfigError(f"{path}: variant {vname!r}: count_fraction must be a number > 0, got {f!r}")
    if not strategy_class(cfg.strategy.name).caps_count:
        raise ConfigError(f"{path}: variant {vname!r}: count_fraction needs a strategy that caps the count "
                          f"(max_surfels), not {cfg.strategy.name!r}")
    ref = [v for v in variants if isinstance(v, dict) and v.get("name") == of]
    if not ref or of == vname:
        raise ConfigError(f"{path}: variant {vname!r}: count_of names {of!r}, which is not another variant of the file")
    if "count_fraction" in ref[0]:
        raise ConfigError(f"{path}: variant {vname!r}: count_of {of!r} has a count_fraction itself")
    return float(f), str(of)


def resolve_count(run: PlannedRun, runs: list[PlannedRun], reported: dict | None = None) -> PlannedRun:
    """`run` with max_surfels = round(count_fraction x the final count of the same scene's
    count_of run); ConfigError when that run has not finished. `reported`: {(scene, variant):
    final count} from the experiment's last report, used when the reference's run folder is gone
    (a long experiment's runs folder lost between sessions; collect() keeps its row too)."""
    from ghsplat_jax.train.run_dir import METRICS_NAME, read_metrics

    if run.count_fraction is None:
        return run
    ref = next((r for r in runs if r.scene == run.scene and r.variant == run.count_of), None)
    count = (read_metrics(ref.out_dir) or {}).get("num_gaussians") if ref is not None else None
    lost = ref is not None and not ref.out_dir.exists()  # a folder without metrics is a run not finished
    if not count and lost and (reported or {}).get((run.scene, run.count_of)):
        count = reported[(run.scene, run.count_of)]
        log.warning("%s/%s: the folder of %s/%s (%s) is gone; its final count %d is taken from the experiment's "
                    "report", run.scene, run.variant, run.scene, run.count_of, ref.out_dir, count)
    if not count:
        where = ref.out_dir / METRICS_NAME if ref is not None else f"{run.scene}/{run.count_of}"
        raise ConfigError(f"{run.scene}/{run.variant}: count_fraction = {run.count_fraction} of variant "
                          f"{run.count_of!r}, which has not finished ({where} missing); run "
                          f"{run.scene}/{run.count_of} first")
    cap = max(1, int(round(run.count_fraction * int(count))))
    return dataclasses.replace(run, config=run.config.replace(**{"strategy.max_surfels": cap}))


def run_one(run: PlannedRun, all_runs: list[PlannedRun] | None = None, reported: dict | None = None,
            until: int | None = None) -> str | None:
    """Train and evaluate one planned run: skipped when finished, resumed from its checkpoint
    when interrupted. Returns None, or the error text (one broken scene must not stop the set).
    The executors (local, Ray) both call this, so a run behaves the same wherever it runs.
    `all_runs` and `reported`: where a count_fraction run finds its reference (resolve_count).
    `until`: train to that step, checkpoint and stop (the reports mark the run as stopped)."""
    if run.finished:
        log.info("%s/%s: finished, skipped", run.scene, run.variant)
        return None
    release_compiled_programs()  # many runs in one process: see host_memory
    try:
        run = resolve_count(run, all_runs or [], reported)
        log.info("%s/%s: training into %s (strategy %s%s)", run.scene, run.variant, run.out_dir,
                 run.config.strategy.name,
                 f", max_surfels {run.config.strategy.max_surfels}" if run.count_fraction else "")
        kw = {} if until is None else {"until": int(until)}  # train_and_evaluate's own default otherwise
        resume = has_checkpoint(run.out_dir)
        dataset = None if resume else triangulated_data(run)
        if dataset is not None:
            kw["dataset"] = dataset
        train_and_evaluate(run.config, run.out_dir, resume=resume, **kw)
    except KeyboardInterrupt:
        raise
    except Exception as exc:
        msg = f"{type(exc).__name__}: {exc}"
        log.error("%s/%s failed: %s", run.scene, run.variant, msg)
        log.debug(traceback.format_exc())
        return msg
    return None


def triangulated_data(run: PlannedRun):
    """The run's dataset with points triangulated from its cameras (sfm/triangulate.py, into
    RUN/triangulated.ply) when it has fewer SfM points than init_min_points, else as read (training
    takes it rather than reading it again); None when it cannot be read here: training then reads
    it and reports the problem itself."""
    from ghsplat_jax.sfm.triangulate import with_triangulated_points
    from ghsplat_jax.train.run_dir import load_training_data

    try:
        dataset = load_training_data(run.config)
    except (ValueError, OSError) as exc:
        log.debug("%s/%s: data not read before training (%s)", run.scene, run.variant, exc)
        return None
    return with_triangulated_points(dataset, run.config.init_min_points, run.out_dir)


def _run_locally(runs: list[PlannedRun], stop_on_error: bool, all_runs=None, reported=None,
                 until: int | None = None) -> list[tuple[str, str]]:
    failed = []
    for r in runs:
        msg = run_one(r, all_runs, reported, until) if until is not None else run_one(r, all_runs, reported)
        if msg is not None:
            failed.append((f"{r.scene}/{r.variant}", msg))
            if stop_on_error:
                break
    return failed


def run_experiment(exp: Experiment, only: set[str] | None = None, stop_on_error: bool = False,
                   evaluate_only: bool = False, executor: str = "local", ray_options: dict | None = None,
                   exclude: set[str] = frozenset(), until: int | None = None, retrain: bool = False) -> dict:
    """Train every unfinished run (resuming interrupted ones), then write the reports.
    executor: "local" (one run after another in this process) or "ray" (one Ray task per run,
    see experiments/ray_executor.py; `ray_options` are its keyword arguments).
    `until`: every run trains to that step, checkpoints and stops; the reports mark it stopped.
    A run whose folder is gone but whose finished row the experiment's results.json holds is not
    trained again (hours of work already reported) unless `retrain`.
    Returns {"rows": [...], "failed": [(run, message)], "reports": [paths]}."""
    from ghsplat_jax.experiments.report import RESULTS_NAME

    if until is not None and until < 1:
        raise ValueError(f"until must be a step >= 1, got {until}")
    results = Path(exp.results) / RESULTS_NAME
    earlier = earlier_rows(results)
    selected = [r for r in exp.runs if r.scene not in exclude
                and (not only or r.scene in only or f"{r.scene}/{r.variant}" in only)]
    todo = [] if evaluate_only else [r for r in selected if not r.finished]
    for r in selected:
        if r.finished:
            log.info("%s/%s: finished, skipped", r.scene, r.variant)
    if not retrain:
        skipped = [r for r in todo if is_reported(earlier.get((r.scene, r.variant))) and not has_checkpoint(r.out_dir)]
        for r in skipped:
            row = earlier[(r.scene, r.variant)]
            log.info("%s/%s: no metrics.json or checkpoint in %s, but %s reports it finished (PSNR %s, %s steps); "
                     "not trained again (--retrain trains it again)", r.scene, r.variant, r.out_dir, results,
                     row.get("psnr"), row.get("steps"))
        todo = [r for r in todo if r not in skipped]
    if executor not in ("local", "ray"):
        raise ValueError(f"unknown executor {executor!r} (local or ray)")
    # Two waves: runs with a count_fraction need their reference's final count.
    reported = {key: row["num_gaussians"] for key, row in earlier.items() if row.get("num_gaussians")}
    failed = []
    for wave in ([r for r in todo if r.count_fraction is None], [r for r in todo if r.count_fraction is not None]):
        if not wave or (failed and stop_on_error):
            continue
        if executor == "local":
            failed += _run_locally(wave, stop_on_error, exp.runs, reported, until)
        else:
            import functools

            from ghsplat_jax.experiments.ray_executor import run_on_ray

            extra = {} if until is None else {"until": int(until)}
            failed += run_on_ray(wave, functools.partial(run_one, all_runs=exp.runs, reported=reported, **extra),
                                 stop_on_error=stop_on_error, **(ray_options or {}))
    rows, reports = collect(exp)
    return {"rows": rows, "failed": failed, "reports": reports}


def earlier_rows(path: Path) -> dict[tuple[str, str], dict]:
    """The rows of the experiment's last report, its results.json at `path`, by (scene, variant)."""
    try:
        rows = json.loads(path.read_text())["rows"] if path.is_file() else []
    except (ValueError, KeyError, TypeError) as exc:
        log.warning("%s: not a results report (%s); earlier rows are not kept", path, exc)
        return {}
    return {(r.get("scene"), r.get("variant")): r for r in rows if isinstance(r, dict)}


def is_reported(row: dict | None) -> bool:
    """A report row of a finished run (rows written before runs had a status are finished)."""
    return bool(row) and row.get("status", FINISHED) == FINISHED


def stopped_row(run: PlannedRun, experiment: str = "") -> dict | None:
    """The report row of a run with a checkpoint but no metrics.json (stopped by --stop-at or
    --until, or interrupted): its step of the planned steps as `status`, and the metrics of
    its checkpoint's evaluation when `ghsplat eval` made one (RUN/snapshots/step_N/), else none.
    None without a (readable) checkpoint."""
    from ghsplat_jax.experiments.report import run_row
    from ghsplat_jax.train.checkpoint import CheckpointError, read_meta
    from ghsplat_jax.train.run_dir import CHECKPOINT_NAME, snapshot_dir

    path = run.out_dir / CHECKPOINT_NAME
    if not path.is_file():
        return None
    try:
        step = int(read_meta(path)["step"])
    except (CheckpointError, KeyError, TypeError, ValueError) as exc:
        log.warning("%s/%s: %s is not a readable checkpoint (%s); the run is left out of the report",
                    run.scene, run.variant, path, exc)
        return None
    row = run_row(snapshot_dir(run.out_dir, step), run.scene, run.variant, experiment) or {
        "experiment": experiment, "scene": run.scene, "variant": run.variant, "split": None, "psnr": None,
        "l1": None, "ssim": None, "num_gaussians": None}
    from ghsplat_jax.train.run_dir import PLY_NAME

    status = (f"trained to step {step}, not evaluated" if (run.out_dir / PLY_NAME).is_file()
              else f"stopped at step {step} of {run.config.steps}")
    return dict(row, steps=step, run_dir=str(run.out_dir), status=status)


def collect(exp: Experiment) -> tuple[list[dict], list[Path]]:
    """Rows of every finished run, and the reports written into the experiment folder. A planned
    run whose folder has no metrics.json (a long experiment's runs folder lost between machines
    or sessions) keeps its row from the last report, with a warning, rather than vanishing."""
    from ghsplat_jax.experiments.charts import write_charts, write_pareto_charts
    from ghsplat_jax.experiments.report import RESULTS_NAME, run_row, write_results, write_table1

    report = Path(exp.results) / RESULTS_NAME
    rows, earlier = [], earlier_rows(report)
    for r in exp.runs:
        row = run_row(r.out_dir, r.scene, r.variant, exp.name)
        if row is not None:
            row = dict(row, status=FINISHED)
        else:
            row = stopped_row(r, exp.name)
            if row is not None:
                log.warning("%s/%s: %s (no metrics.json in %s); reported as stopped", r.scene, r.variant,
                            row["status"], r.out_dir)
        if row is not None:
            contrib = bool(r.config.strategy.contrib_prune_every or r.config.strategy.contrib_prune_final)
            rows.append(dict(row, strategy=r.config.strategy.name, count_fraction=r.count_fraction,
                             count_of=r.count_of if r.count_fraction is not None else None, contrib_prune=contrib))
        elif (r.scene, r.variant) in earlier:
            log.warning("%s/%s: no metrics.json in %s; its row is kept from %s", r.scene, r.variant, r.out_dir, report)
            rows.append({"status": FINISHED} | earlier[(r.scene, r.variant)])
    if not rows:
        return rows, []
    finished = [row for row in rows if row.get("status") == FINISHED]  # charts: only final numbers
    name = exp.name if exp.preset == "full" else f"{exp.name} ({exp.preset} preset)"
    title = f"{name}: {exp.description}" if exp.description else name
    reports = write_results(rows, exp.results, title) + write_table1(rows, exp.results, f"Table 1 ({name})")
    reports += write_charts(finished, exp.results, name) + write_pareto_charts(finished, exp.results, name)
    if "compactness" in exp.reports:
        from ghsplat_jax.experiments.compactness import write_compactness

        reports += write_compactness(finished, exp.results, name)
    return rows, reports
