"""Structure from motion with pycolmap (CPU, offline), then greenhouse alignment and undistortion.

Stages: frame selection (video input) -> SIFT extraction -> matching (exhaustive,
sequential or spatial) -> pair filtering against self-similar rows (disambiguate.py) ->
mapping (incremental or global/GLOMAP) -> fold diagnostics (folds.py) -> alignment ->
undistortion. Output layout (the one 3DGS/2DGS tools expect):

    OUT/images/            undistorted images (PINHOLE), ready for training
    OUT/sparse/0/          COLMAP binary model of those images, aligned
    OUT/distorted/         database.db (all verified pairs), database_filtered.db (the pairs
                           the mapper used) and the aligned model before undistortion
    OUT/frames/            selected frames (video input only)
    OUT/sfm_report.json    counts, unregistered images, errors, alignment, timings

Only SIFT and classical pair generators are used: learned features and
vocabulary-tree loop detection download models and abort offline.
"""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
import time
from pathlib import Path

import numpy as np

from ghsplat_jax.io_utils import atomic_path, code_revision, replace_path, write_json
from ghsplat_jax.sfm import crosscheck, diagnose, folds
from ghsplat_jax.sfm import disambiguate as dis
from ghsplat_jax.sfm import frames as frames_mod
from ghsplat_jax.sfm.align import AlignOptions, estimate_alignment
from ghsplat_jax.sfm.matchgraph import (
    MatchGraph,
    ModelPoses,
    keep_pairs,
    model_poses,
    read_match_graph,
)
from ghsplat_jax.sfm.report import failure_advice, match_graph_stats, reconstruction_stats
from ghsplat_jax.sfm.second_estimate import ADVICE as SECOND_ESTIMATE_ADVICE
from ghsplat_jax.sfm.second_estimate import SecondEstimateOptions, map_globally
from ghsplat_jax.sfm.second_estimate import check as check_second_estimate

MATCHERS = ("exhaustive", "sequential", "spatial")
MAPPERS = ("incremental", "global")
CAPTURE_ORDERS = ("name", "none")
FOLD_CAPTURE_TIP = folds.FOLD_ADVICE[2]
CAMERA_MODES = ("per-folder", "single", "per-image", "auto")
# Models the undistorter turns into PINHOLE (fisheye models included).
CAMERA_MODELS = (
    "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
    "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE", "FOV",
)


class SfmError(RuntimeError):
    """Bad input or an unusable pipeline setting; the message names the file and the problem."""


# A model of fewer views maps nothing of the row (a map that registers from fewer inliers can
# keep a lone initial pair): the order filter's relaxed pass is redone, and `auto` keeps its
# first model rather than such a second one.
MIN_MODEL_VIEWS = 3
MIN_TRIM_CHAIN_FRACTION = 0.75  # trim_at_seams: share of the kept views one chain segment must hold


@dataclasses.dataclass
class SfmOptions:
    matching: str = "exhaustive"  # every pair, as the paper does; "sequential" for video
    mapper: str = "incremental"  # or "global" (GLOMAP in pycolmap >= 3.12)
    camera_model: str = "SIMPLE_RADIAL"  # COLMAP model fitted during mapping
    camera_mode: str = "per-folder"  # one shared camera per folder of images
    max_size: int | None = 1600  # longest side for extraction and undistorted output (None: full)
    max_features: int = 8192  # SIFT features per image
    # SIFT's contrast threshold (COLMAP's default, 0.02 / 3). A third of it found 1.4x the features on
    # 480x360 rows of plants and chained more of a hand-held loop (auto: 24-27 of 40 views
    # verified, against 10-15), but on the demo's row plain mapping then registered 31 of 32
    # views at 0.83% RMSE (3.2% max) against 26 at 0.16% (at 0.0067): 5x the error, so not default.
    sift_peak_threshold: float = 0.02 / 3
    sequential_overlap: int = 10  # neighbours matched per frame in sequential matching
    min_registered_fraction: float = 0.9  # below this the run counts as failed
    disambiguate: str = "auto"  # "auto": plain, re-mapped through a pair filter when it looks
    # folded; "order" or "tracks": always filter pairs before mapping; "none": plain pycolmap
    capture_order: str = "name"  # "name": sorted file names are the capture order; "none": unknown
    disambiguate_options: dis.DisambiguateOptions = dataclasses.field(default_factory=dis.DisambiguateOptions)
    fold_options: folds.FoldOptions = dataclasses.field(default_factory=folds.FoldOptions)
    fold_check: bool = True  # a suspected fold sets status "folded" (ghsplat sfm exits 4)
    # Re-localise every registered view with itself left out and deregister those that land
    # elsewhere (crosscheck.py): a row segment's weakly chained first frames came out 2.6% of
    # the extent and 4.5 degrees off in a model that passed every fold check.
    cross_check: bool = True
    cross_check_options: crosscheck.CrossCheckOptions = dataclasses.field(
        default_factory=crosscheck.CrossCheckOptions)
    # Map again with the global mapper from the pairs the model confirms and hold the two against
    # each other view by view (second_estimate.py); where they disagree the model is "inconsistent":
    # multithreaded maps of a row segment bent 1.1-1.2% of the extent and 1.9-2.3 degrees passed
    # every other check. Incremental mapper only.
    second_estimate: bool = True
    second_estimate_options: SecondEstimateOptions = dataclasses.field(default_factory=SecondEstimateOptions)
    select_frames: bool = False  # thin a frame folder like a video (always on for video files)
    frame_options: frames_mod.FrameOptions = dataclasses.field(default_factory=frames_mod.FrameOptions)
    align: str = "greenhouse"  # or "none"
    align_options: AlignOptions = dataclasses.field(default_factory=AlignOptions)
    known_distance_names: tuple[str, str, float] | None = None  # (image a, image b, metres)
    undistort: bool = True  # write OUT/images + OUT/sparse/0 as PINHOLE
    # 1: repeatable (same photos, options and seed give the same model); -1: all cores. With
    # several threads pycolmap numbers images in the order extraction finishes them and maps in
    # a thread-dependent order, and the same 60 photos gave 5-21% centre errors from run to run.
    num_threads: int = 1
    seed: int = 0  # pycolmap RANSAC/mapper seed, for repeatable runs
    progress: bool = True  # tqdm bars

    def validate(self) -> None:
        for name, value, allowed in (
            ("matching", self.matching, MATCHERS), ("mapper", self.mapper, MAPPERS),
            ("camera_mode", self.camera_mode, CAMERA_MODES),
            ("camera_model", self.camera_model, CAMERA_MODELS),
            ("align", self.align, ("greenhouse", "none")),
            ("disambiguate", self.disambiguate, dis.METHODS),
            ("capture_order", self.capture_order, CAPTURE_ORDERS),
        ):
            if value not in allowed:
                raise SfmError(f"{name} must be one of {', '.join(allowed)}; got {value!r}")
        if not 0.0 <= self.min_registered_fraction <= 1.0:
            raise SfmError(f"min_registered_fraction must be in [0, 1], got {self.min_registered_fraction}")
        if not 0.0 < self.sift_peak_threshold < 1.0:
            raise SfmError(f"sift_peak_threshold must be in (0, 1), got {self.sift_peak_threshold}")
        if self.max_size is not None and self.max_size < 32:
            raise SfmError(f"max_size must be at least 32 pixels, got {self.max_size}")
        if self.disambiguate == "order" and self.capture_order == "none":
            raise SfmError("--disambiguate order needs the capture order: use --capture-order name "
                           "(frames named in shooting order) or --disambiguate tracks")
        try:
            self.disambiguate_options.validate()
        except ValueError as exc:
            raise SfmError(str(exc)) from exc


@contextlib.contextmanager
def _timed(timings: dict, name: str, bar=None):
    if bar is not None:
        bar.set_description(f"sfm: {name}")
    start = time.perf_counter()
    yield
    timings[name] = round(time.perf_counter() - start, 3)
    if bar is not None:
        bar.update(1)


def write_model(reconstruction, target: Path) -> None:
    """Write a COLMAP binary model to `target` atomically (temp folder + rename)."""
    with atomic_path(target) as tmp:
        tmp.mkdir()
        reconstruction.write_binary(str(tmp))


# ---------------------------------------------------------------------------- input


def resolve_input(
    images: Path, out: Path, options: SfmOptions, timings: dict
) -> tuple[Path, list[str], dict]:
    """(image root, image names in capture order, frame-selection report)."""
    images = Path(images)
    if not images.exists():
        raise SfmError(f"--images {images}: no such file or folder")
    if images.is_dir():
        if out.resolve().is_relative_to(images.resolve()):
            raise SfmError(f"--out {out} lies inside --images {images}: choose another folder")
        names = frames_mod.list_images(images)
        if not names:
            suffixes = ", ".join(sorted(frames_mod.IMAGE_SUFFIXES))
            raise SfmError(f"--images {images}: no image files ({suffixes})")
        if not options.select_frames:
            return images, names, {}
    elif not frames_mod.is_video(images):
        raise SfmError(
            f"--images {images}: not a folder of images or a video file "
            f"({', '.join(sorted(frames_mod.VIDEO_SUFFIXES))})"
        )

    from tqdm import tqdm

    start = time.perf_counter()
    try:
        with tqdm(desc="scoring frames", unit="frame", disable=not options.progress) as bar:
            sharp, step = frames_mod.score_frames(images, options.frame_options, bar)
    except ValueError as exc:
        raise SfmError(str(exc)) from exc
    keep = frames_mod.select_frames(sharp, step, options.frame_options)
    if images.is_dir():
        root, selected = images, [names[i] for i in keep]
    else:
        root = out / "frames"
        shutil.rmtree(root, ignore_errors=True)
        selected = frames_mod.write_video_frames(images, keep, root)
    timings["frame_selection"] = round(time.perf_counter() - start, 3)
    info = {
        "num_frames": int(len(sharp)),
        "num_selected": len(selected),
        "selected_indices": [int(i) for i in keep],
        "min_baseline": options.frame_options.min_baseline,
        "median_sharpness": float(np.median(sharp)),
    }
    return root, selected, info


# ---------------------------------------------------------------------------- pycolmap stages


def extract(database: Path, root: Path, names: list[str], options: SfmOptions) -> list[str]:
    """SIFT features of `names` into `database`; returns the names pycolmap could not read."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.type = pycolmap.FeatureExtractorType.SIFT
    extraction.max_image_size = options.max_size or -1
    extraction.num_threads = options.num_threads
    extraction.sift.max_num_features = options.max_features
    extraction.sift.peak_threshold = options.sift_peak_threshold
    mode = getattr(pycolmap.CameraMode, options.camera_mode.replace("-", "_").upper())
    pycolmap.extract_features(
        database, root, image_names=names, camera_mode=mode, reader_options=reader,
        extraction_options=extraction, device=pycolmap.Device.cpu,
    )
    db = pycolmap.Database.open(str(database))
    try:
        read = {image.name for image in db.read_all_images()}
    finally:
        db.close()
    return [name for name in names if name not in read]


def match(database: Path, options: SfmOptions) -> None:
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = options.seed
    common = dict(matching_options=matching, verification_options=verification,
                  device=pycolmap.Device.cpu)
    if options.matching == "exhaustive":
        pycolmap.match_exhaustive(database, **common)
    elif options.matching == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = options.sequential_overlap
        pairing.quadratic_overlap = True
        pairing.loop_detection = False  # needs a vocabulary tree (a download): never offline
        pycolmap.match_sequential(database, pairing_options=pairing, **common)
    else:
        db = pycolmap.Database.open(str(database))
        try:
            priors = db.num_pose_priors()
        finally:
            db.close()
        if priors == 0:
            raise SfmError(
                f"--matching spatial needs position priors (EXIF GPS), and none of the images in "
                f"{database} has one: use --matching exhaustive or sequential"
            )
        pycolmap.match_spatial(database, **common)


def map_images(database: Path, root: Path, models_dir: Path, options: SfmOptions, filtered: bool = False) -> dict:
    """All reconstructions the mapper produced, {index: Reconstruction}. `filtered`: the
    database holds only the order filter's trusted and verified pairs, so the incremental
    mapper registers views from fewer inliers (DisambiguateOptions.min_pose_inliers)."""
    import pycolmap

    pycolmap.set_random_seed(options.seed)
    shutil.rmtree(models_dir, ignore_errors=True)
    models_dir.mkdir(parents=True)
    if options.mapper == "incremental":
        pipeline = pycolmap.IncrementalPipelineOptions()
        pipeline.num_threads = options.num_threads
        pipeline.random_seed = options.seed
        if filtered:
            pipeline.mapper.abs_pose_min_num_inliers = options.disambiguate_options.min_pose_inliers
            pipeline.mapper.abs_pose_min_inlier_ratio = options.disambiguate_options.min_pose_inlier_ratio
        return pycolmap.incremental_mapping(database, root, models_dir, options=pipeline)
    if not hasattr(pycolmap, "global_mapping"):
        raise SfmError(
            f"--mapper global needs pycolmap >= 3.12 (GLOMAP built in); this is pycolmap "
            f"{pycolmap.__version__}: use --mapper incremental"
        )
    return map_globally(database, root, models_dir, options.num_threads, options.seed)


def cameras_and_points(reconstruction) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Registered image names in name (capture) order, their world_to_cam (N,4,4), points (M,3)."""
    images = sorted(
        (reconstruction.images[i] for i in reconstruction.reg_image_ids()), key=lambda im: im.name
    )
    w2c = np.tile(np.eye(4), (len(images), 1, 1))
    for k, image in enumerate(images):
        w2c[k, :3] = image.cam_from_world().matrix()
    points = np.array([p.xyz for p in reconstruction.points3D.values()]).reshape(-1, 3)
    return [im.name for im in images], w2c, points


def align(reconstruction, options: SfmOptions) -> dict:
    """Apply the greenhouse alignment to `reconstruction` in place; returns its report."""
    import pycolmap

    names, w2c, points = cameras_and_points(reconstruction)
    align_options = options.align_options
    if options.known_distance_names is not None:
        a, b, metres = options.known_distance_names
        missing = [n for n in (a, b) if n not in names]
        if missing:
            raise SfmError(f"--known-distance: image(s) {', '.join(missing)} not registered")
        align_options = dataclasses.replace(
            align_options, known_distance=(names.index(a), names.index(b), float(metres))
        )
    try:
        alignment = estimate_alignment(w2c, points, align_options)
    except ValueError as exc:
        raise SfmError(f"greenhouse alignment: {exc}") from exc
    reconstruction.transform(
        pycolmap.Sim3d(alignment.scale, pycolmap.Rotation3d(alignment.rotation), alignment.translation)
    )
    return {"method": "greenhouse", **alignment.to_json()}


def undistort(model_dir: Path, root: Path, out: Path, options: SfmOptions) -> None:
    """OUT/images + OUT/sparse/0 as PINHOLE from the distorted model."""
    import pycolmap

    tmp = out / ".undistort.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    undistort_options = pycolmap.UndistortCameraOptions()
    undistort_options.max_image_size = options.max_size or -1
    pycolmap.undistort_images(
        tmp, model_dir, root, undistort_options=undistort_options,
        num_threads=options.num_threads,
    )
    replace_path(tmp / "images", out / "images")
    replace_path(tmp / "sparse", out / "sparse" / "0")
    shutil.rmtree(tmp, ignore_errors=True)  # stereo/ and scripts are for COLMAP's MVS


def map_chain(database: Path, root: Path, graph: MatchGraph, options: SfmOptions,
              verify: bool = False) -> list[ModelPoses]:
    """The chain: segments mapped from the trusted neighbour pairs alone (largest first, none
    a subset of another). It cannot fold (no look-alike pair between distant frames reaches
    it); it may break where neighbours share too little, hence segments. The fold check reads
    it as COLMAP maps it. `verify`: the order filter's chain, which registers views from fewer
    inliers and is cut at links that disagree with their own matches (longer segments verify
    more pairs, but cut into smaller pieces they hid a fold from the fold check)."""
    distorted = database.parent
    chain_db = distorted / "chain.db"
    opts = options.disambiguate_options
    keep_pairs(database, chain_db, graph, dis.sequential_pairs(graph, opts))
    models = map_images(chain_db, root, distorted / "chain_models", options, filtered=verify)
    shutil.rmtree(distorted / "chain_models", ignore_errors=True)
    chain_db.unlink(missing_ok=True)
    segments = [model_poses(r, graph) for r in models.values()]
    return dis.cut_links(graph, segments, opts) if verify else dis.distinct_segments(segments)


def filter_pairs(database: Path, root: Path, graph: MatchGraph, method: str, options: SfmOptions,
                 relaxed: bool = False, chain: list[ModelPoses] | None = None) -> tuple[Path, dict, dict, set[int]]:
    """(database to map from, disambiguation report, {pair kept: the matches the mapper sees},
    views the order filter's chain placed) for `method` (order, tracks). `relaxed`: the order
    filter's chain registers from fewer inliers and is cut at disagreeing links; otherwise it
    is COLMAP's chain, `chain` when the fold check has mapped it already."""
    opts = options.disambiguate_options
    narrowed, placed = None, set()
    if method == "tracks":
        keep, info = dis.track_filter(graph, opts)
    else:  # "order": trust the neighbour pairs, verify the others (match by match) against the chain
        if relaxed or chain is None:
            chain = map_chain(database, root, graph, options, verify=relaxed)
        keep, info, narrowed = dis.order_filter(graph, chain, opts)
        placed = set().union(*(set(s.world_to_cam) for s in chain))
    filtered = database.parent / "database_filtered.db"
    info["num_pairs_removed"] = keep_pairs(database, filtered, graph, keep, narrowed)
    return filtered, info, {p: (narrowed or {}).get(p, graph.pairs[p]) for p in keep}, placed


@dataclasses.dataclass
class Mapped:
    """What one mapping pass produced."""
    models: dict                 # {index: Reconstruction}
    best: object | None          # the largest, or None
    disambiguation: dict         # the pair filter's report
    diagnostics: dict | None     # folds.diagnose of `best`
    graph: MatchGraph            # every verified pair (before any filter), by capture order


def _fold_options(options: SfmOptions) -> folds.FoldOptions:
    """The fold checks' options; a loop capture is cyclic for them as for the pair filter."""
    return dataclasses.replace(options.fold_options, cyclic=options.disambiguate_options.cyclic)


def map_and_check(database: Path, root: Path, graph: MatchGraph, method: str, options: SfmOptions,
                  models_dir: Path, chain: list[ModelPoses] | None) -> Mapped:
    """Filter pairs with `method` (none, order, tracks), map, and run the fold diagnostics.
    The order filter first registers views from fewer inliers, in its chain and in its map;
    when the fold check flags that model, or it has under MIN_MODEL_VIEWS views, the filter
    and the map run again at COLMAP's thresholds (the filter as it was before)."""
    relaxed = method == "order"
    mapped = _map_once(database, root, graph, method, options, models_dir, chain, relaxed)
    if relaxed and (mapped.best is None or mapped.best.num_reg_images() < MIN_MODEL_VIEWS
                    or mapped.diagnostics["fold_suspected"]):
        # It placed more of every hand-held loop, but on a video-rate walk it let in views that
        # bent the map (4.4%, flagged), round one row end its map came out 21.8% off (flagged;
        # its 60-view chain was within 1.4%), and where nothing chains it keeps a lone initial pair.
        first = {"min_pose_inliers": options.disambiguate_options.min_pose_inliers,
                 "num_registered": 0 if mapped.best is None else mapped.best.num_reg_images(),
                 "reasons": [] if mapped.best is None else mapped.diagnostics["reasons"]}
        mapped = _map_once(database, root, graph, method, options, models_dir, chain, relaxed=False)
        mapped.disambiguation["first_mapping"] = first
    return mapped


def _map_once(database: Path, root: Path, graph: MatchGraph, method: str, options: SfmOptions,
              models_dir: Path, chain: list[ModelPoses] | None, relaxed: bool) -> Mapped:
    mapped_graph, mapping_db, info, placed = graph, database, {"method": "none"}, set()
    if method != "none":
        mapping_db, info, mapped_pairs, placed = filter_pairs(database, root, graph, method, options, relaxed, chain)
        mapped_graph = dataclasses.replace(graph, pairs=mapped_pairs)
    models = map_images(mapping_db, root, models_dir, options, filtered=relaxed)
    best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
    diagnostics = None
    if best is not None:
        def diagnose(model):
            return folds.diagnose(graph, mapped_graph, model_poses(model, graph), model, _fold_options(options),
                                  capture_order=options.capture_order == "name", num_models=len(models),
                                  chain=chain, reached=placed)

        diagnostics = diagnose(best)
        # --disambiguate none stays plain pycolmap: the fold check only flags its model.
        if diagnostics["fold_suspected"] and options.capture_order == "name" and options.disambiguate != "none":
            trimmed = trim_at_seams(best, graph, diagnostics, options, diagnose)
            if trimmed is not None:
                models = {k: trimmed[0] if m is best else m for k, m in models.items()}
                best, diagnostics = trimmed
    return Mapped(models, best, info, diagnostics, graph)


def trim_at_seams(model, graph: MatchGraph, diagnostics: dict, options: SfmOptions, diagnose):
    """(trimmed copy, its diagnostics) of a flagged model cut at its seams (consecutive views
    whose neighbour pair it contradicts) down to its largest piece, when that piece has at
    least MIN_MODEL_VIEWS views, is larger than any other, passes every fold check and lies
    mostly in one chain segment; else None. A fold that maps the first frames of a walk onto
    later ones leaves such a seam: round one greenhouse row end, cutting four views off a map
    21.8% off left 56 views within 0.22%; on a video-rate walk, 55 of 59 within 0.27%."""
    import pycolmap

    pieces = folds.seam_pieces(graph, model_poses(model, graph), _fold_options(options))
    if len(pieces) < 2 or len(pieces[0]) < MIN_MODEL_VIEWS or len(pieces[0]) == len(pieces[1]):
        return None
    keep = {graph.names[k] for k in pieces[0]}
    trimmed = pycolmap.Reconstruction(model)
    dropped = _deregister(trimmed, lambda name: name not in keep)
    checked = diagnose(trimmed)
    # Passing the checks is not enough: a plain model of five identical plants, 44.6% off, had
    # a single contradicted pair, and the 35 views past it passed every check, placed by two
    # short chain segments. So most of the piece must lie in one chain segment (neighbour
    # pairs alone, which cannot fold) that agrees with it.
    segments = checked.get("chain_consistency", {}).get("segments", [])
    covered = max((s["num_images"] for s in segments), default=0)
    if checked["fold_suspected"] or covered < MIN_TRIM_CHAIN_FRACTION * trimmed.num_reg_images():
        return None
    checked["trimmed_at_seams"] = {"dropped": dropped, "reasons_before": diagnostics["reasons"]}
    return trimmed, checked


def reconstruct(database: Path, root: Path, names: list[str], options: SfmOptions, distorted: Path,
                timings: dict, bar=None) -> Mapped:
    """Mapping with options.disambiguate. "auto": map every verified pair (plain pycolmap) and
    keep that model unless the fold check flags it (or nothing registers); then map again
    through the order filter (the tracks filter without a capture order) and keep that."""
    graph = read_match_graph(database, names)
    models_dir = distorted / "models"
    chain = None
    if options.capture_order == "name" and options.fold_check:
        with _timed(timings, "chain"):
            chain = map_chain(database, root, graph, options)
    first = "none" if options.disambiguate == "auto" else options.disambiguate
    with _timed(timings, "mapping", bar):
        result = map_and_check(database, root, graph, first, options, models_dir, chain)
    if options.disambiguate != "auto":
        return result
    flagged = result.best is None or result.diagnostics["fold_suspected"]
    cut = None if result.best is None else result.diagnostics.get("trimmed_at_seams")  # a trimmed model is clean
    first_pass = {"num_registered": 0, "fold_suspected": None, "reasons": []}
    if result.best is not None:
        first_pass = {"num_registered": result.best.num_reg_images(), "fold_suspected": flagged or cut is not None,
                      "reasons": cut["reasons_before"] if cut else result.diagnostics["reasons"]}
        if cut:
            first_pass["trimmed_at_seams"] = cut["dropped"]
    summary = {"method": "auto", "first_pass": first_pass}
    if not flagged and cut is None:
        result.disambiguation = {**summary, "used": "none"}
        return result
    # A flagged first model, or one that passed only once trimmed at its seams: the filter may
    # place more views.
    fallback = "order" if options.capture_order == "name" else "tracks"
    with _timed(timings, "disambiguation"):
        second = map_and_check(database, root, graph, fallback, options, distorted / "models_filtered", chain)
    shutil.rmtree(distorted / "models_filtered", ignore_errors=True)
    def views(mapped: Mapped) -> int:
        return 0 if mapped.best is None else mapped.best.num_reg_images()

    if views(second) < MIN_MODEL_VIEWS or (cut is not None and (second.diagnostics["fold_suspected"]
                                                                or views(second) <= views(result))):
        # nothing better: keep the first model (flagged, or trimmed and clean)
        result.disambiguation = {**summary, "used": "none", "fallback": second.disambiguation}
        return result
    second.disambiguation = {**summary, "used": fallback, "fallback": second.disambiguation}
    return second


def _deregister(reconstruction, drop) -> list[str]:
    """Deregister (in place) the registered images for which drop(name) holds; their names."""
    dropped = []
    for image_id in list(reconstruction.reg_image_ids()):
        image = reconstruction.images[image_id]
        if drop(image.name):
            reconstruction.deregister_frame(image.frame_id)
            dropped.append(image.name)
    return sorted(dropped)


def drop_spikes(reconstruction, graph: MatchGraph, options: SfmOptions) -> list[str]:
    """Deregister the frames folds.spikes calls mis-registered (in place); their names."""
    bad = {graph.names[k] for k in folds.spikes(model_poses(reconstruction, graph), _fold_options(options))}
    return _deregister(reconstruction, bad.__contains__)


# ---------------------------------------------------------------------------- the run


def run_sfm(images: Path, out: Path, options: SfmOptions = SfmOptions()) -> dict:
    """Run the whole pipeline; writes OUT/sfm_report.json and returns the report.

    report["status"] is "ok", "folded" (the fold diagnostics suspect a row mapped onto
    itself; outputs still written, for inspection only), "inconsistent" (the global mapper's second
    estimate places some views elsewhere: second_estimate.py; also for inspection only), "partial" (fewer than
    min_registered_fraction registered; outputs still written) or "failed" (no reconstruction).
    """
    import pycolmap
    from tqdm import tqdm

    options.validate()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    root, names, frame_info = resolve_input(Path(images), out, options, timings)
    if len(names) < 2:
        raise SfmError(f"--images {images}: need at least 2 images, found {len(names)}")

    distorted = out / "distorted"
    distorted.mkdir(parents=True, exist_ok=True)
    database = distorted / "database.db"
    for stale in (database, database.with_name("database.db-wal"), database.with_name("database.db-shm"),
                  database.with_name("database_filtered.db")):
        stale.unlink(missing_ok=True)
    shutil.rmtree(distorted / "second_estimate", ignore_errors=True)

    report = {
        "input": str(Path(images).resolve()),
        "image_root": str(root.resolve()),
        "options": _options_json(options),
        "versions": {"pycolmap": pycolmap.__version__, "colmap": pycolmap.COLMAP_version,
                     "ghsplat_jax": code_revision()},
        "num_images": len(names),
    }
    if frame_info:
        report["frame_selection"] = frame_info

    stages = 3 + (options.align == "greenhouse") + options.undistort
    with tqdm(total=stages, unit="stage", disable=not options.progress) as bar:
        with _timed(timings, "extraction", bar):
            unreadable = extract(database, root, names, options)
        if unreadable:
            report["unreadable_images"] = unreadable
        if len(unreadable) > len(names) - 2:
            raise SfmError(f"--images {images}: pycolmap could read only {len(names) - len(unreadable)} "
                           f"of {len(names)} images (unreadable: {', '.join(unreadable[:10])})")
        with _timed(timings, "matching", bar):
            match(database, options)
        result = reconstruct(database, root, names, options, distorted, timings, bar)
        models, best = result.models, result.best
        report["disambiguation"] = result.disambiguation
        report["match_graph"] = match_graph_stats(result.graph)
        if best is not None and options.fold_check and options.capture_order == "name":
            report["dropped_spikes"] = drop_spikes(best, result.graph, options)
        if best is not None and options.cross_check:
            with _timed(timings, "cross_check"):
                report["cross_check"] = crosscheck.check_and_drop(best, options.cross_check_options,
                                                                  num_threads=options.num_threads)
        if best is not None and options.second_estimate and options.mapper == "incremental":
            with _timed(timings, "second_estimate"):
                report["second_estimate"] = check_second_estimate(
                    database, root, best, distorted / "second_estimate", options.second_estimate_options, options.seed)
        report.update(_registration(models, best, names))
        refused = best is None or report["registered_fraction"] < options.min_registered_fraction
        if refused or report["unregistered_images"]:
            with _timed(timings, "diagnosis"):
                report["diagnosis"] = diagnose.diagnose_run(
                    database, names, best, refused, ordered=options.capture_order == "name",
                    dropped=_dropped_why(report))
        model_dir = distorted / "sparse" / "0"
        if best is None:  # leave no earlier run's model beside a report that says "failed"
            for stale in (out / "images", out / "sparse" / "0", model_dir):
                shutil.rmtree(stale, ignore_errors=True)
        else:
            report.update(reconstruction_stats(best))
            report["fold_diagnostics"] = result.diagnostics
            report["alignment"] = {"method": "none"}
            if options.align == "greenhouse":
                write_model(best, model_dir)  # kept unaligned should the alignment fail
                with _timed(timings, "alignment", bar):
                    try:
                        report["alignment"] = align(best, options)
                    except SfmError as exc:
                        raise SfmError(f"{exc} (the unaligned model is in {model_dir})") from exc
            write_model(best, model_dir)
            if options.undistort:
                with _timed(timings, "undistortion", bar):
                    undistort(model_dir, root, out, options)
                report["cameras"] = _camera_summary(out / "sparse" / "0")
    shutil.rmtree(distorted / "models", ignore_errors=True)

    folded = options.fold_check and report.get("fold_diagnostics", {}).get("fold_suspected", False)
    if best is None:
        report["status"] = "failed"
    elif folded:
        report["status"] = "folded"
    elif report.get("second_estimate", {}).get("verdict") == "disagree":
        report["status"] = "inconsistent"
    elif report["registered_fraction"] < options.min_registered_fraction:
        report["status"] = "partial"
    else:
        report["status"] = "ok"
    dropped_advice = crosscheck.advice(report.get("cross_check", {}))
    if report["status"] == "folded":
        report["advice"] = folds.FOLD_ADVICE
    elif report["status"] == "inconsistent":
        report["advice"] = SECOND_ESTIMATE_ADVICE
    elif report["status"] != "ok" or report["unregistered_images"]:
        report["advice"] = dropped_advice + failure_advice(options, len(names), report["num_registered"],
                                                           report["match_graph"])
        used = report.get("disambiguation", {}).get("used", "none")
        if used != "none":
            report["advice"].insert(0, f"every pair mapped together looked folded (look-alike plants); "
                                       f"the {used} filter kept only the views it could verify: "
                                       f"{FOLD_CAPTURE_TIP}")
    timings["total"] = round(time.perf_counter() - start, 3)
    report["timings_s"] = timings
    write_json(out / "sfm_report.json", report)
    return report


def _dropped_why(report: dict) -> dict[str, str]:
    """Images registered, then left out by a check: {name: which check}."""
    why = {name: "mis-registered (a spike off the camera path)" for name in report.get("dropped_spikes", [])}
    for name in report.get("cross_check", {}).get("dropped", []):
        why[name] = "landed elsewhere when re-localised with itself left out (cross-check)"
    return why


def _registration(models: dict, best, names: list[str]) -> dict:
    registered = set() if best is None else {best.images[i].name for i in best.reg_image_ids()}
    return {
        "num_registered": len(registered),
        "registered_fraction": round(len(registered) / len(names), 4),
        "unregistered_images": [n for n in names if n not in registered],
        "num_reconstructions": len(models),
        "reconstruction_sizes": sorted((r.num_reg_images() for r in models.values()), reverse=True),
    }


def _camera_summary(model_dir: Path) -> list[dict]:
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    return [
        {"camera_id": int(cid), "model": cam.model.name, "width": int(cam.width),
         "height": int(cam.height), "params": [float(p) for p in cam.params]}
        for cid, cam in sorted(rec.cameras.items())
    ]


def _options_json(options: SfmOptions) -> dict:
    def plain(value):
        if isinstance(value, np.ndarray):
            return value.tolist()
        if dataclasses.is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, (tuple, list)):
            return [plain(v) for v in value]
        return value

    return plain(options)
