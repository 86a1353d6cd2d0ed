"""What every reader produces: per-image camera records before any pixel is read.

A `Frame` describes one image at the resolution its intrinsics refer to ("full"
resolution), plus the files that may hold it, best first: a pre-downscaled copy in
a sibling folder such as `images_4/` (stored at full/4) before the original.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ghsplat_jax.data.errors import DatasetError


@dataclass
class Frame:
    name: str  # stable identifier (file name relative to its image folder or the root)
    sources: list[tuple[Path, float]]  # (file, factor it is stored at relative to full), best first
    K: np.ndarray  # (3,3) float64 at full resolution; pixel centres at +0.5
    world_to_cam: np.ndarray  # (4,4) float64, OpenCV axes
    width: int  # full resolution
    height: int
    dist: np.ndarray | None = None  # OpenCV-order distortion coefficients, None for pinhole


@dataclass
class SceneSpec:
    format: str  # "colmap" | "transforms" | "llff"
    frames: list[Frame]
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    point_colors: np.ndarray | None = None
    split: list[str] | None = None  # "train"/"test" per frame where the dataset defines one
    source: Path | None = None  # the file or folder the cameras came from (for messages)


_SUFFIX = re.compile(r"_(\d+)$")


def downscaled_folders(folder: Path) -> dict[int, Path]:
    """{factor: folder} for `folder` itself (factor 1, if it exists) and siblings `folder_N`."""
    found = {1: folder} if folder.is_dir() else {}
    parent = folder.parent
    if parent.is_dir():
        for sibling in parent.iterdir():
            if sibling.name.startswith(folder.name + "_") and sibling.is_dir():
                m = _SUFFIX.search(sibling.name[len(folder.name):])
                if m and m.start() == 0 and int(m.group(1)) > 0:
                    found[int(m.group(1))] = sibling
    return found


def usable_factors(folders: dict[int, Path], downscale: float) -> list[int]:
    """Factors not above `downscale` (we filter down, never up), largest (cheapest) first."""
    return sorted((k for k in folders if k <= downscale + 1e-9), reverse=True)


def image_sources(folder: Path, relative: str, downscale: float) -> list[tuple[Path, float]]:
    """Candidate files for image `relative` inside `folder` or its downscaled siblings."""
    folders = downscaled_folders(folder)
    if folders and not usable_factors(folders, downscale):
        choose_folder(folder, downscale)  # raises, naming the folders there are
    factors = usable_factors(folders, downscale) or [1]
    return [(folders.get(k, folder) / relative, float(k)) for k in factors]


def choose_folder(folder: Path, downscale: float) -> tuple[Path, int]:
    """The single folder to read for `downscale` (for layouts whose file names differ per folder)."""
    folders = downscaled_folders(folder)
    if not folders:
        raise DatasetError(f"{folder.parent}: no image folder ({folder.name}/ or {folder.name}_N/)")
    factors = usable_factors(folders, downscale)
    if not factors:
        available = ", ".join(f"{folders[k].name}/ (downscale {k})" for k in sorted(folders))
        raise DatasetError(
            f"{folder.parent}: downscale {downscale:g} needs {folder.name}/ or {folder.name}_N/ with "
            f"N <= {downscale:g}, but only {available} exist; pass downscale={min(folders)} or more"
        )
    return folders[factors[0]], factors[0]


MAX_IMAGE_SIDE = 100_000  # pixels; larger sizes in a camera file are corruption, not photos


def check_camera(K: np.ndarray, width, height, dist, where: str) -> None:
    """A clear error for intrinsics no image can have: a bad size, a non-positive or
    non-finite focal length, a non-finite principal point or distortion."""
    if not all(isinstance(v, (int, np.integer)) and 0 < v <= MAX_IMAGE_SIDE for v in (width, height)):
        raise DatasetError(f"{where}: image size {width!r} x {height!r} is not 1..{MAX_IMAGE_SIDE} pixels")
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise DatasetError(f"{where}: intrinsics need finite values and positive focal lengths, got "
                           f"fx={K[0, 0]!r} fy={K[1, 1]!r} cx={K[0, 2]!r} cy={K[1, 2]!r}")
    if dist is not None and not np.all(np.isfinite(dist)):
        raise DatasetError(f"{where}: non-finite distortion coefficients {np.asarray(dist).tolist()}")


def check_points(points: np.ndarray, where: str) -> np.ndarray:
    """The SfM points, refused when any is NaN or Inf (they seed the surfels)."""
    bad = np.count_nonzero(~np.all(np.isfinite(points), axis=1)) if len(points) else 0
    if bad:
        raise DatasetError(f"{where}: {bad} of {len(points)} points have non-finite coordinates")
    return points


def pinhole_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], np.float64)


def rigid(R: np.ndarray, t: np.ndarray, where: str) -> np.ndarray:
    """4x4 [R|t] with R snapped to the nearest rotation; a clear error if R is not one."""
    R = np.asarray(R, np.float64)
    t = np.asarray(t, np.float64)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise DatasetError(f"{where}: pose has non-finite values")
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise DatasetError(f"{where}: pose rotation is not a rotation matrix (scaled or mirrored pose?)")
    u, _, vt = np.linalg.svd(R)  # remove text-rounding noise
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = t
    return out


def invert_rigid(m: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    out = np.eye(4)
    R, t = m[:3, :3], m[:3, 3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out
