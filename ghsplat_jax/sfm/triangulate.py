"""Points from known cameras: SIFT features of the views, matched pair by pair, triangulated with
the cameras held fixed (pycolmap's point triangulator). For a dataset that has exact cameras
but no SfM points (a rendered or a calibrated capture): training starts from points on the
surfaces the photos show rather than from random points in a box.

    points, colors, info = triangulate_known_cameras(dataset.train, work_dir)

The views' own pixels and pinhole cameras are used (the loaded, undistorted size), so the
cameras and the images always agree. `work_dir` receives images/, database.db and the
triangulated model (sparse/), kept for inspection.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path

import numpy as np

from ghsplat_jax.data.splits import subsample
from ghsplat_jax.sfm.diagnose import verified_pair_count

log = logging.getLogger("ghsplat.sfm")


class TriangulationError(RuntimeError):
    """The points could not be triangulated; the message names the folder and the problem."""


@dataclasses.dataclass
class TriangulateOptions:
    max_size: int | None = 1600  # longest image side for SIFT (None: full size)
    max_features: int = 8192  # SIFT features per image
    sift_peak_threshold: float = 0.02 / 3  # a third of COLMAP's: more features on smooth rendered or plant photos
    max_views: int = 200  # exhaustive matching is quadratic: views beyond this are subsampled evenly
    max_reprojection_px: float = 4.0  # points seen further than this from any observation are dropped
    num_threads: int = -1
    seed: int = 0


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise TriangulationError("triangulating points needs pycolmap (pip install pycolmap)") from None
    missing = [n for n in ("extract_features", "match_exhaustive", "triangulate_points", "Database", "Reconstruction")
               if not hasattr(pycolmap, n)]
    if missing:
        raise TriangulationError(f"pycolmap {getattr(pycolmap, '__version__', '?')} lacks {', '.join(missing)}: "
                                 "triangulating points needs pycolmap >= 3.10")
    return pycolmap


def _write_images(views, folder: Path) -> list[str]:
    """The views' pixels as 8-bit PNGs named by index (a view's name may hold folders)."""
    from ghsplat_jax.data.images import write_image

    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, v in enumerate(views):
        name = f"{i:05d}.png"
        write_image(folder / name, np.clip(np.asarray(v.image, np.float32), 0.0, 1.0))
        names.append(name)
    return names


def _set(obj, name: str, value) -> None:
    """Set an option where this pycolmap has it (option names move between versions)."""
    if hasattr(obj, name):
        setattr(obj, name, value)


def _extract_and_match(pycolmap, database: Path, images: Path, names: list[str], options: TriangulateOptions) -> None:
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    kwargs = dict(image_names=names, camera_mode=pycolmap.CameraMode.PER_IMAGE, reader_options=reader)
    if hasattr(pycolmap, "FeatureExtractionOptions"):  # pycolmap >= 3.12
        extraction = pycolmap.FeatureExtractionOptions()
        _set(extraction, "max_image_size", options.max_size or -1)
        _set(extraction, "num_threads", options.num_threads)
        extraction.sift.max_num_features = options.max_features
        _set(extraction.sift, "peak_threshold", options.sift_peak_threshold)
        kwargs["extraction_options"] = extraction
    else:
        sift = pycolmap.SiftExtractionOptions()
        _set(sift, "max_image_size", options.max_size or -1)
        _set(sift, "max_num_features", options.max_features)
        _set(sift, "peak_threshold", options.sift_peak_threshold)
        _set(sift, "num_threads", options.num_threads)
        kwargs["sift_options"] = sift
    if hasattr(pycolmap, "Device"):
        kwargs["device"] = pycolmap.Device.cpu
    pycolmap.extract_features(database, images, **kwargs)
    match_kwargs = {"device": pycolmap.Device.cpu} if hasattr(pycolmap, "Device") else {}
    if hasattr(pycolmap, "TwoViewGeometryOptions"):
        verification = pycolmap.TwoViewGeometryOptions()
        _set(verification.ransac, "random_seed", options.seed)
        match_kwargs["verification_options"] = verification
    pycolmap.match_exhaustive(database, **match_kwargs)


def _open_database(pycolmap, database: Path):
    """pycolmap >= 3.12 opens with Database.open, older versions with the constructor."""
    if hasattr(pycolmap.Database, "open"):
        return pycolmap.Database.open(str(database))
    return pycolmap.Database(str(database))


def _known_model(pycolmap, database: Path, views, names: list[str]):
    """A reconstruction of the database's cameras and images (their ids) with the views'
    intrinsics and poses and the database's keypoints."""
    by_name = dict(zip(names, views))
    db = _open_database(pycolmap, database)
    try:
        images = list(db.read_all_images())
        keypoints = {im.image_id: np.asarray(db.read_keypoints(im.image_id))[:, :2] for im in images}
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
    finally:
        db.close()
    if len(images) < 2:
        raise TriangulationError(f"{database}: features of {len(images)} image(s) only; two or more are needed")
    rec = pycolmap.Reconstruction()
    frames = hasattr(rec, "add_image_with_trivial_frame")  # pycolmap >= 3.12: rigs and frames
    for im in images:
        view = by_name[im.name]
        K = np.asarray(view.camera.K, np.float64)
        cam = cameras[im.camera_id]
        camera = pycolmap.Camera(model="PINHOLE", width=int(view.camera.width), height=int(view.camera.height),
                                 params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=cam.camera_id)
        w2c = np.asarray(view.camera.world_to_cam, np.float64)
        pose = pycolmap.Rigid3d(w2c[:3, :4])
        image = pycolmap.Image(name=im.name, keypoints=keypoints[im.image_id], camera_id=cam.camera_id,
                               image_id=im.image_id)
        if frames:
            rec.add_camera_with_trivial_rig(camera)
            rec.add_image_with_trivial_frame(image, pose)
        else:
            rec.add_camera(camera)
            image.cam_from_world = pose
            rec.add_image(image)
            rec.register_image(im.image_id)
    return rec


def triangulate_known_cameras(views, work_dir, options: TriangulateOptions | None = None):
    """(points (M,3) float32, colours (M,3) float32 in [0, 1], info) triangulated from `views`
    (data.dataset.View: pixels and an exact pinhole camera each) with the cameras held fixed.
    info: views used, registered, matched pairs, points, mean track length and reprojection
    error. Raises TriangulationError with the folder and the problem."""
    pycolmap = _pycolmap()
    options = options or TriangulateOptions()
    views = subsample(list(views), options.max_views)
    if len(views) < 2:
        raise TriangulationError(f"{work_dir}: {len(views)} view(s); triangulation needs two or more")
    work = Path(work_dir)
    shutil.rmtree(work, ignore_errors=True)
    images, database, model = work / "images", work / "database.db", work / "sparse"
    names = _write_images(views, images)
    model.mkdir(parents=True)
    try:
        if hasattr(pycolmap, "set_random_seed"):
            pycolmap.set_random_seed(options.seed)
        _extract_and_match(pycolmap, database, images, names, options)
        rec = _known_model(pycolmap, database, views, names)
        pipeline = pycolmap.IncrementalPipelineOptions()
        _set(pipeline, "num_threads", options.num_threads)
        _set(pipeline.mapper if hasattr(pipeline, "mapper") else pipeline, "filter_max_reproj_error",
             options.max_reprojection_px)
        out = pycolmap.triangulate_points(rec, database, images, model, options=pipeline)
    except TriangulationError:
        raise
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError with its own text
        raise TriangulationError(f"{work}: pycolmap {pycolmap.__version__} could not triangulate: "
                                 f"{type(exc).__name__}: {exc}") from None
    out = out if out is not None else rec
    pts = list(out.points3D.values())
    err = np.array([p.error for p in pts], np.float64)
    keep = err <= options.max_reprojection_px
    points = np.array([p.xyz for p in pts], np.float32).reshape(-1, 3)[keep]
    colors = (np.array([p.color for p in pts], np.float32).reshape(-1, 3) / 255.0)[keep]
    tracks = np.array([p.track.length() for p in pts], np.float64)[keep]
    finite = np.isfinite(points).all(axis=1)
    points, colors, tracks = points[finite], colors[finite], tracks[finite]
    db = _open_database(pycolmap, database)
    try:
        pairs = verified_pair_count(db)
    finally:
        db.close()
    info = {"views": len(views), "verified_pairs": pairs, "points": int(len(points)),
            "mean_track_length": float(tracks.mean()) if len(tracks) else None,
            "mean_reprojection_px": float(err[keep].mean()) if keep.any() else None,
            "pycolmap": pycolmap.__version__, "folder": str(work)}
    return points, colors, info


def write_points_ply(path, points: np.ndarray, colors: np.ndarray | None = None) -> Path:
    """A binary little-endian PLY of points (x, y, z float32) and 8-bit colours, atomically."""
    from ghsplat_jax.io_utils import atomic_write

    path = Path(path)
    points = np.asarray(points, np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(len(points), dtype=fields)
    v["x"], v["y"], v["z"] = points.T
    if colors is not None:
        rgb = np.clip(np.round(np.asarray(colors, np.float32) * 255.0), 0, 255).astype(np.uint8)
        v["red"], v["green"], v["blue"] = rgb.T
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {n}\n" for n, t in fields)
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n{props}end_header\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.tobytes())
    return path


def read_points_ply(path) -> tuple[np.ndarray, np.ndarray | None]:
    """(points, colours in [0, 1] or None) of a PLY `write_points_ply` wrote (any vertex PLY
    with x, y, z; red, green, blue when present)."""
    from ghsplat_jax.data.ply import read_vertices

    v = read_vertices(path)
    names = v.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise TriangulationError(f"{path}: no x, y, z vertex properties")
    points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    colors = (np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.float32) / 255.0
              if {"red", "green", "blue"} <= set(names) else None)
    return points, colors


TRIANGULATED_NAME = "triangulated.ply"  # RUN/triangulated.ply: the points a run started from
TRIANGULATION_DIR = "triangulation"  # RUN/triangulation/: images, database and model of that step


def _finite_count(points) -> int:
    return 0 if points is None else int(np.sum(np.all(np.isfinite(np.asarray(points).reshape(-1, 3)), axis=1)))


def with_triangulated_points(dataset, min_points: int, run_dir, options: TriangulateOptions | None = None):
    """`dataset` with points triangulated from its training cameras when it has fewer than
    `min_points` (the run's init_min_points) finite SfM points, else `dataset` itself. The points
    go to RUN_DIR/triangulated.ply (reused when present: a restarted run does not match again).
    When triangulation fails or gives fewer than `min_points`, the dataset is returned as it is
    (training then starts from random points, with the trainer's warning) after a warning here
    that says why."""
    have = _finite_count(dataset.points)
    if have >= min_points:
        return dataset
    run_dir = Path(run_dir)
    ply = run_dir / TRIANGULATED_NAME
    if ply.is_file():
        points, colors = read_points_ply(ply)
        log.info("%s: %d SfM points; using the %d points triangulated earlier from its cameras (%s)", dataset.root,
                 have, len(points), ply)
    else:
        log.info("%s: %d SfM points (init_min_points is %d): triangulating points from its %d known training "
                 "cameras (SIFT, exhaustive matching, cameras held fixed) into %s", dataset.root, have, min_points,
                 len(dataset.train), run_dir / TRIANGULATION_DIR)
        try:
            points, colors, info = triangulate_known_cameras(dataset.train, run_dir / TRIANGULATION_DIR, options)
        except TriangulationError as exc:
            log.warning("%s: no points from its cameras (%s); training starts from random points", dataset.root, exc)
            return dataset
        log.info("%s: triangulated %d points from %d views (%s verified pairs, mean track %s, mean reprojection "
                 "error %s px)", dataset.root, info["points"], info["views"], info["verified_pairs"],
                 _fmt(info["mean_track_length"]), _fmt(info["mean_reprojection_px"]))
        if len(points):
            write_points_ply(ply, points, colors)
    if len(points) < min_points:
        log.warning("%s: triangulation from the known cameras gave only %d points (fewer than init_min_points %d), "
                    "too few to start from: training starts from random points. Textureless or blurred photos, or "
                    "views that overlap little, give few matches: run `ghsplat sfm` on the photos or lower "
                    "init_min_points", dataset.root, len(points), min_points)
        return dataset
    log.info("%s: training starts from the %d triangulated points (%s)", dataset.root, len(points), ply)
    return dataclasses.replace(dataset, points=np.asarray(points, np.float32), point_colors=colors)


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.2f}"
