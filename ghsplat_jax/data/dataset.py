"""`load_dataset`: detect the layout, read cameras, split, then read, undistort and scale images.

Images stay float32 numpy on the host (never jax arrays): a full-size scene can be
larger than the accelerator wants, and the trainer decides what to move.
"""

from __future__ import annotations

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ghsplat_jax.core.camera import Camera
from ghsplat_jax.data.errors import DatasetError
from ghsplat_jax.data.frames import Frame, SceneSpec
from ghsplat_jax.data.splits import split_indices, subsample

FORMATS = ("colmap", "transforms", "llff")


@dataclass(eq=False)
class View:
    """One image and its undistorted pinhole camera (K for the loaded size)."""

    name: str
    camera: Camera
    image: np.ndarray  # (H,W,3) float32 in [0, 1], RGBA composited on the dataset background
    alpha: np.ndarray | None = None  # (H,W) float32 coverage of RGBA images, else None
    image_path: Path | None = None  # the file the pixels came from

    def __repr__(self) -> str:
        alpha = "" if self.alpha is None else ", alpha"
        return f"View({self.name!r}, {self.camera.width}x{self.camera.height}{alpha})"


@dataclass(eq=False)
class Dataset:
    """Train and test views of one scene, its SfM points and its size (see `load_dataset`)."""

    root: Path
    format: str  # "colmap" | "transforms" | "llff"
    train: list[View]
    test: list[View]
    points: np.ndarray  # (M,3) float32 SfM points; (0,3) when the dataset has none
    point_colors: np.ndarray | None  # (M,3) float32 in [0, 1], or None
    scene_extent: float  # 1.1 x the largest distance of a training camera centre from their mean
    scene_center: np.ndarray  # (3,) float32 mean of the training camera centres
    downscale: float = 1.0  # relative to the resolution the dataset's cameras refer to
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    split: str = "every"  # the rule that made train/test: "dataset", "every" or "all"
    test_every: int = 8
    source: Path | None = field(default=None, repr=False)  # the camera file read

    @property
    def views(self) -> list[View]:
        return self.train + self.test

    def __repr__(self) -> str:
        size = f"{self.train[0].camera.width}x{self.train[0].camera.height}" if self.train else "-"
        return (
            f"Dataset({str(self.root)!r}, format={self.format!r}, train={len(self.train)}, "
            f"test={len(self.test)}, size={size}, points={len(self.points)}, extent={self.scene_extent:.3g})"
        )


def detect_format(root: Path) -> str:
    """"colmap", "transforms" or "llff", by the files present.

    A COLMAP model in the usual places (sparse/0, sparse, the root) wins, as in 3DGS;
    then transforms.json, then poses_bounds.npy (LLFF scenes often carry an incomplete
    sparse/0 for their points), then a model in any other sub-folder.
    """
    from ghsplat_jax.data.colmap import find_model
    from ghsplat_jax.data.nerf import transforms_files

    root = Path(root)
    if not root.is_dir():
        problem = "not a folder" if root.exists() else "dataset folder not found"
        raise DatasetError(f"{root}: {problem}")
    if find_model(root, anywhere=False) is not None:
        return "colmap"
    if transforms_files(root):
        return "transforms"
    if (root / "poses_bounds.npy").is_file():
        return "llff"
    if find_model(root) is not None:
        return "colmap"
    raise DatasetError(
        f"{root}: unknown dataset layout; expected a COLMAP model (sparse/0/ with cameras and "
        "images .bin or .txt), transforms.json / transforms_train.json + transforms_test.json, "
        "or LLFF poses_bounds.npy"
    )


def read_scene(root: Path, format: str, downscale: float) -> SceneSpec:
    if format == "colmap":
        from ghsplat_jax.data.colmap import read_colmap

        return read_colmap(root, downscale)
    if format == "transforms":
        from ghsplat_jax.data.nerf import read_transforms

        return read_transforms(root, downscale)
    if format == "llff":
        from ghsplat_jax.data.llff import read_llff

        return read_llff(root, downscale)
    raise DatasetError(f"unknown dataset format {format!r}; choose auto or one of {', '.join(FORMATS)}")


def scene_bounds(centers: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre, radius) as in 3DGS/2DGS getNerfppNorm: mean of the camera centres, 1.1 x max distance."""
    center = centers.mean(axis=0)
    radius = 1.1 * float(np.linalg.norm(centers - center, axis=1).max())
    # A single camera (or all at one spot) gives 0, which would zero every
    # extent-scaled learning rate; fall back to unit scale.
    return center.astype(np.float32), radius if radius > 1e-6 else 1.0


class _Undistorters:
    """Remap tables shared by every view of one camera, built once across threads."""

    def __init__(self):
        self._cache, self._lock = {}, threading.Lock()

    def get(self, K: np.ndarray, dist: np.ndarray, width: int, height: int):
        from ghsplat_jax.data.distortion import make_undistorter

        key = (K.tobytes(), np.asarray(dist, np.float64).tobytes(), width, height)
        with self._lock:
            if key not in self._cache:
                self._cache[key] = make_undistorter(K, dist, width, height)
            return self._cache[key]


def _size_matches(w: int, h: int, frame: Frame, factor: float) -> bool:
    if factor == 1:
        return (w, h) == (frame.width, frame.height)
    # downscaled copies are floor-, round- or ceil-sized depending on the tool
    return abs(w - frame.width / factor) < 1 and abs(h - frame.height / factor) < 1


def _read_source(frame: Frame, where: str):
    from ghsplat_jax.data.images import read_image

    problems = []
    for path, factor in frame.sources:
        if not path.is_file():
            problems.append(f"{path} not found")
            continue
        rgb, alpha = read_image(path)
        h, w = rgb.shape[:2]
        if _size_matches(w, h, frame, factor):
            return path, factor, rgb, alpha
        expected = f"{frame.width / factor:g}x{frame.height / factor:g}"
        problems.append(f"{path} is {w}x{h} but its camera says {expected}")
    what = "image not found" if all(p.endswith("not found") for p in problems) else "image size mismatch"
    raise DatasetError(f"{where}: {what} for {frame.name!r}: {'; '.join(problems)}")


def load_view(frame: Frame, downscale: float, background, undistorters: _Undistorters, where: str) -> View:
    from ghsplat_jax.data.distortion import has_distortion
    from ghsplat_jax.data.images import composite, resize_area

    path, factor, rgb, alpha = _read_source(frame, where)
    h, w = rgb.shape[:2]
    # Our pixel-centre convention makes a resize an exact scaling of K: K' = diag(s, s, 1) K.
    K = np.diag([w / frame.width, h / frame.height, 1.0]) @ frame.K
    if has_distortion(frame.dist):
        undistort = undistorters.get(K, frame.dist, w, h)
        stacked = rgb if alpha is None else np.concatenate([rgb, alpha[:, :, None]], axis=2)
        stacked = undistort(stacked)  # premultiplied colour and alpha interpolate alike
        rgb, alpha = (stacked, None) if alpha is None else (stacked[:, :, :3], stacked[:, :, 3])
        K = undistort.new_K
    if abs(downscale - factor) < 1e-9:
        width, height = w, h
    else:
        width = max(1, round(frame.width / downscale))
        height = max(1, round(frame.height / downscale))
    rgb = resize_area(rgb, width, height)
    if alpha is not None:
        alpha = np.clip(resize_area(alpha, width, height), 0.0, 1.0).astype(np.float32)
    K = np.diag([width / w, height / h, 1.0]) @ K
    image = np.ascontiguousarray(composite(rgb, alpha, background))
    camera = Camera(K.astype(np.float32), frame.world_to_cam.astype(np.float32), width, height)
    return View(frame.name, camera, image, alpha, path)


def load_dataset(
    root,
    downscale: float = 1,
    background=(1.0, 1.0, 1.0),
    split: str = "auto",
    test_every: int = 8,
    max_views: int | None = None,
    format: str = "auto",
    num_threads: int | None = None,
) -> Dataset:
    """Read a COLMAP, NeRF transforms.json or LLFF dataset into undistorted pinhole views.

    root: the dataset folder. downscale: images at 1/downscale of the resolution the
    cameras refer to (a pre-downscaled images_N/ folder is used when it fits, else
    area filtering). background: colour RGBA images are composited on. split: "auto"
    (the dataset's own train/test, else every `test_every`-th image in sorted file order
    is a test view), "every", "dataset" or "all" (no test views). max_views: keep at most
    this many views per split, evenly spaced, chosen before any pixel is read.
    format: "auto" (detected from the files) or one of "colmap", "transforms", "llff".
    """
    root = Path(root).expanduser()
    try:
        downscale = float(downscale)
        background = np.asarray(background, np.float64).ravel()
    except (TypeError, ValueError):
        raise DatasetError("downscale must be a number and background 1 or 3 numbers") from None
    if not (math.isfinite(downscale) and downscale > 0):
        raise DatasetError(f"downscale must be a positive number, got {downscale!r}")
    if background.size not in (1, 3):
        raise DatasetError(f"background must be 1 or 3 numbers (RGB in [0, 1]), got {background.tolist()}")
    background = tuple(float(c) for c in np.broadcast_to(background, (3,)))
    format = detect_format(root) if format == "auto" else format
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found")
    spec = read_scene(root, format, downscale)
    names = [f.name for f in spec.frames]
    train_idx, test_idx, rule = split_indices(names, spec.split, split, test_every)
    # The extent sets learning rates: take it from the whole training split, so that
    # max_views does not change it.
    centers = np.array([_center(spec.frames[i]) for i in (train_idx or test_idx)]).reshape(-1, 3)
    center, extent = scene_bounds(centers) if len(centers) else (np.zeros(3, np.float32), 1.0)
    train_idx, test_idx = subsample(train_idx, max_views), subsample(test_idx, max_views)

    where = str(spec.source or root)
    undistorters = _Undistorters()
    chosen = train_idx + test_idx
    threads = num_threads or min(8, os.cpu_count() or 1, max(1, len(chosen)))

    def load(i: int) -> View:
        return load_view(spec.frames[i], downscale, background, undistorters, where)

    if threads > 1:  # decoding and cv2 release the GIL
        with ThreadPoolExecutor(threads) as pool:
            views = list(pool.map(load, chosen))
    else:
        views = [load(i) for i in chosen]
    train, test = views[: len(train_idx)], views[len(train_idx) :]
    return Dataset(
        root=root,
        format=format,
        train=train,
        test=test,
        points=np.asarray(spec.points, np.float32).reshape(-1, 3),
        point_colors=None if spec.point_colors is None else np.asarray(spec.point_colors, np.float32),
        scene_extent=extent,
        scene_center=center,
        downscale=downscale,
        background=background,
        split=rule,
        test_every=test_every,
        source=spec.source,
    )


def _center(frame: Frame) -> np.ndarray:
    R, t = frame.world_to_cam[:3, :3], frame.world_to_cam[:3, 3]
    return -R.T @ t
