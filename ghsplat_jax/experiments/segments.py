"""Row segments for experiments, made the way the paper made its Table 1 data: a procedural
greenhouse photographed by a hand-held walk round each end of each row, then structure from
motion on each segment's photos. `ghsplat run` calls `prepare_segments` before training when
the experiment file has a [prepare] table; every scene with a `segment = { row, end }` key is
made here, and its `data` folder is the SfM output the run trains on.

    [prepare]
    greenhouse = { layout = { rows = 4 } }   # synth SceneConfig tables (default: built-in scene)
    views = 60                               # photos per segment
    width = 384
    height = 288
    segment_fraction = 0.5                   # share of the row each walk covers
    sfm = { mapper = "incremental" }         # SfmOptions fields
    [[scenes]]
    name = "row0_x0"
    data = "runs/greenhouse/row0_x0/sfm"     # photos and exact cameras go to the sibling photos/
    segment = { row = 0, end = "x0" }

A segment whose SfM status is not "ok" (folded or too few images registered) is not trained:
training on it would give a confident, wrong asset. Its error names the SfM report.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

from ghsplat_jax.config_values import coerce
from ghsplat_jax.io_utils import atomic_write, host_label, machine_info, write_json
from ghsplat_jax.train.config import ConfigError

log = logging.getLogger("ghsplat.segments")

PREPARE_KEYS = {"greenhouse", "views", "width", "height", "segment_fraction", "sfm"}
SFM_KEYS = {"matching", "mapper", "camera_model", "max_features", "disambiguate", "min_registered_fraction", "seed"}


@dataclasses.dataclass(frozen=True)
class Capture:
    views: int = 60
    width: int = 384
    height: int = 288
    segment_fraction: float = 0.5


@dataclasses.dataclass(frozen=True)
class Segment:
    scene: str
    row: int
    end: str
    sfm_dir: Path

    @property
    def photos_dir(self) -> Path:
        return self.sfm_dir.parent / "photos"


def _segments(spec: dict, source) -> list[Segment]:
    out = []
    for scene in spec.get("scenes", []):
        seg = scene.get("segment")
        if seg is None:
            continue
        where = f"{source}: scene {scene.get('name')!r} segment"
        if not isinstance(seg, dict) or set(seg) != {"row", "end"} or seg["end"] not in ("x0", "x1"):
            raise ConfigError(f"{where} must be {{ row = N, end = \"x0\" | \"x1\" }}, got {seg!r}")
        out.append(Segment(scene["name"], coerce(seg["row"], 0, f"{where} row", ConfigError), seg["end"],
                           Path(scene["data"])))
    return out


def _options(prep: dict, source):
    from ghsplat_jax.sfm.pipeline import SfmError, SfmOptions
    from ghsplat_jax.synth.config import config_from_dict

    unknown = set(prep) - PREPARE_KEYS
    if unknown:
        raise ConfigError(f"{source}: unknown keys {sorted(unknown)} in [prepare]; known: {sorted(PREPARE_KEYS)}")
    defaults = Capture()
    capture = Capture(**{f.name: coerce(prep[f.name], getattr(defaults, f.name), f"{source} [prepare] {f.name}",
                                        ConfigError)
                         for f in dataclasses.fields(Capture) if f.name in prep})
    try:
        greenhouse = config_from_dict(prep.get("greenhouse", {}), f"{source} [prepare] greenhouse")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    sfm = prep.get("sfm", {})
    bad = set(sfm) - SFM_KEYS
    if bad:
        raise ConfigError(f"{source}: unknown keys {sorted(bad)} in [prepare] sfm; known: {sorted(SFM_KEYS)}")
    base = SfmOptions(max_size=max(capture.width, capture.height), progress=False)
    sfm_options = dataclasses.replace(base, **{k: coerce(v, getattr(base, k), f"{source} [prepare] sfm.{k}",
                                                         ConfigError) for k, v in sfm.items()})
    try:
        sfm_options.validate()
    except SfmError as exc:
        raise ConfigError(f"{source} [prepare] sfm: {exc}") from None
    return capture, greenhouse, sfm_options


def _is_done(seg: Segment) -> dict | None:
    report = seg.sfm_dir / "sfm_report.json"
    if report.is_file() and (seg.sfm_dir / "sparse" / "0").is_dir():
        return _with_reference_frame(seg, json.loads(report.read_text()))
    return None


def _with_reference_frame(seg: Segment, report: dict) -> dict:
    """A report written before the accuracy recorded its similarity onto the exact cameras
    (which evaluation needs for depth and normal errors) gets it now, from the same two models."""
    from ghsplat_jax.sfm.evaluate import compare_model_dirs

    acc = report.get("accuracy")
    if not acc or "to_reference" in acc or not (seg.photos_dir / "sparse" / "0").is_dir():
        return report
    fresh = compare_model_dirs(seg.sfm_dir / "sparse" / "0", seg.photos_dir / "sparse" / "0")
    if fresh is None:
        return report
    report = dict(report, accuracy=acc | {k: fresh[k] for k in ("to_reference", "reference")})
    write_json(seg.sfm_dir / "sfm_report.json", report)
    return report


def _make(seg: Segment, world, capture: Capture, sfm_options) -> dict:
    import pycolmap

    from ghsplat_jax.sfm.evaluate import compare_model_dirs
    from ghsplat_jax.sfm.pipeline import run_sfm
    from ghsplat_jax.synth import capture as capture_mod
    from ghsplat_jax.synth import dataset

    start = time.perf_counter()
    cameras = capture_mod.capture_path(
        world, "handheld", capture.views, row=seg.row, width=capture.width, height=capture.height,
        seed=world.config.seed, config=capture_mod.PathConfig(end=seg.end, segment_fraction=capture.segment_fraction))
    dataset.write_dataset(world, cameras, seg.photos_dir, meshes=False, overwrite=True)
    synth_s = time.perf_counter() - start
    pycolmap.logging.minloglevel = 2  # errors only; the report holds the rest
    report = run_sfm(seg.photos_dir / "images", seg.sfm_dir, sfm_options)
    if (seg.sfm_dir / "sparse" / "0").is_dir():
        report["accuracy"] = compare_model_dirs(seg.sfm_dir / "sparse" / "0", seg.photos_dir / "sparse" / "0")
    report["synth_seconds"] = synth_s
    report["machine"] = machine_info()  # the same pycolmap has given different models on different machines
    write_json(seg.sfm_dir / "sfm_report.json", report)
    return report


def _row(seg: Segment, report: dict) -> dict:
    acc = report.get("accuracy") or {}
    return {"segment": seg.scene, "row": seg.row, "end": seg.end, "status": report.get("status"),
            "registered": report.get("num_registered"), "views": report.get("num_images"),
            "reprojection_px": _round(report.get("mean_reprojection_error_px"), 3),
            "centre_error_max_pct_extent": _round(100 * acc["centre_error_max_rel"] if acc else None, 3),
            "rotation_error_max_deg": _round(acc.get("rotation_error_max_deg"), 3),
            "sfm_seconds": _round((report.get("timings_s") or {}).get("total"), 1), "data": str(seg.sfm_dir),
            "pycolmap": (report.get("versions") or {}).get("pycolmap"),  # SfM results differ across installs
            "host": host_label(report.get("machine"))}  # the machine the SfM ran on, not the report's


def _round(value, digits: int):
    return None if value is None else round(float(value), digits)


def prepare_segments(exp, scenes: set[str] | None = None, make: bool = True) -> dict[str, str]:
    """Make every missing segment of the experiment (photos with exact cameras, then SfM), or
    only those of `scenes` (`ghsplat run --only`), write RESULTS/segments.{json,md} and return
    {scene: error} for segments not fit to train. The report is rewritten only when it can list
    every segment, so a partial preparation never drops the rows of segments it left alone.
    `make=False` (`--report-only`) makes nothing: it writes a missing report once every segment
    exists, as a preset trained one segment at a time with `--only` never did."""
    prep = exp.spec.get("prepare")
    if not prep:
        return {}
    if not isinstance(prep, dict):
        raise ConfigError(f"{exp.source}: [prepare] must be a table")
    capture, greenhouse, sfm_options = _options(prep, exp.source)
    world = None
    rows, unusable, made, left = [], {}, False, []
    for seg in _segments(exp.spec, exp.source):
        report = _is_done(seg)
        if report is None and (not make or scenes is not None and seg.scene not in scenes):
            left.append(seg.scene)
            continue
        if report is None:
            if world is None:
                from ghsplat_jax.synth.scene import generate_scene

                world = generate_scene(greenhouse)
                if not 0 <= seg.row < len(world.rows):
                    raise ConfigError(f"{exp.source}: scene {seg.scene!r}: row {seg.row} does not exist "
                                      f"(the greenhouse has {len(world.rows)} rows)")
            log.info("%s: photographing row %d round end %s, then SfM", seg.scene, seg.row, seg.end)
            report = _make(seg, world, capture, sfm_options)
            made = True
        rows.append(_row(seg, report))
        if report.get("status") != "ok":
            unusable[seg.scene] = (f"SfM status {report.get('status')!r} (see {seg.sfm_dir / 'sfm_report.json'}); "
                                   "not trained, since a folded or partial model gives a wrong asset")
    if left:  # a partial report would drop the rows of the segments left alone
        if made:
            log.info("not made (outside --only): %s; %s lists every segment once they exist (--prepare-only)",
                     ", ".join(left), exp.results / "segments.md")
    elif rows and (made or not (exp.results / "segments.json").is_file()):  # keeps the report the runs were made with
        _write_report(rows, exp.results, capture)
    return unusable


def _write_report(rows: list[dict], folder: Path, capture: Capture) -> None:
    from ghsplat_jax.experiments.report import markdown_table

    write_json(folder / "segments.json", {"capture": dataclasses.asdict(capture), "report": {"machine": machine_info()},
                                          "segments": rows})  # each row's host: the machine its SfM ran on
    cols = ("segment", "status", "registered", "views", "reprojection_px", "centre_error_max_pct_extent",
            "rotation_error_max_deg", "sfm_seconds", "host")
    heads = ("segment", "SfM status", "registered", "photos", "reproj. px", "max centre error % extent",
             "max rotation error deg", "SfM s", "SfM machine")
    with atomic_write(folder / "segments.md", "w") as fh:
        fh.write(f"# Row segments: {capture.views} photos of {capture.width}x{capture.height} per segment, SfM "
                 "scored against the generator's exact cameras (similarity-aligned)\n\n"
                 + markdown_table(rows, cols, heads))
