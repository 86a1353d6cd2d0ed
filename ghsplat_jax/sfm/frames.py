"""Keyframe selection for video input: sharp frames with enough baseline between them.

A video (any file cv2.VideoCapture reads) or a folder of frames captured at a fixed rate
(the paper used 12.5 fps) holds far more frames than SfM needs, many of them blurred.
Each frame gets a sharpness score (variance of the Laplacian) and a displacement from
its predecessor (median Lucas-Kanade optical flow of tracked corners, as a fraction of
the image diagonal). `select_frames` then walks the sequence: once the accumulated
displacement since the last keyframe reaches `min_baseline`, it keeps the sharpest of
the next few frames (at most `window`, within twice the baseline), skipping blurred ones.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import numpy as np

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm", ".webp"}
VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".mts"}


@dataclasses.dataclass(frozen=True)
class FrameOptions:
    min_baseline: float = 0.05  # accumulated flow between keyframes, fraction of the diagonal
    window: int = 5  # choose the sharpest among this many frames once the baseline is reached
    blur_fraction: float = 0.3  # frames sharper than this times the median are eligible
    analysis_width: int = 320  # frames are scored at this width (speed)
    max_frames: int | None = None  # keep at most this many keyframes (evenly thinned)


def list_images(folder: Path) -> list[str]:
    """Image files under `folder` (recursively), as sorted relative POSIX paths."""
    return sorted(
        p.relative_to(folder).as_posix()
        for p in folder.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
    )


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


# ---------------------------------------------------------------------------- scoring


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian: low for blurred frames."""
    import cv2

    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def flow_displacement(prev: np.ndarray, gray: np.ndarray) -> float:
    """Median optical-flow displacement prev -> gray as a fraction of the diagonal.

    Returns inf when too few corners can be tracked (a cut or a very fast move): such a
    frame starts a new keyframe rather than being skipped.
    """
    import cv2

    corners = cv2.goodFeaturesToTrack(prev, maxCorners=300, qualityLevel=0.01, minDistance=7)
    if corners is None or len(corners) < 10:
        return float("inf")
    moved, status, _ = cv2.calcOpticalFlowPyrLK(prev, gray, corners, None)
    ok = status.ravel() == 1
    if ok.sum() < 10:
        return float("inf")
    step = np.linalg.norm((moved - corners).reshape(-1, 2)[ok], axis=1)
    return float(np.median(step) / np.hypot(*prev.shape))


def select_frames(
    sharp: np.ndarray, step: np.ndarray, options: FrameOptions = FrameOptions()
) -> list[int]:
    """Indices of keyframes from per-frame sharpness and displacement from the previous frame.

    Once the displacement accumulated since the last keyframe reaches `min_baseline`,
    the sharpest eligible frame among the next `window` frames is kept, looking no
    further than twice the baseline (fast motion keeps every frame it needs). When all
    of those are blurred, the first sharp frame a little further on is kept, failing
    that the least blurred candidate.
    """
    sharp, step = np.asarray(sharp, float), np.asarray(step, float)
    n = len(sharp)
    if n == 0:
        return []
    eligible = sharp >= options.blur_fraction * np.median(sharp)

    def choose(candidates: np.ndarray) -> int:
        good = candidates[eligible[candidates]]
        if len(good):
            return int(good[np.argmax(sharp[good])])
        later = np.arange(candidates[-1] + 1, min(n, candidates[0] + 4 * options.window))
        later = later[eligible[later]]
        return int(later[0]) if len(later) else int(candidates[np.argmax(sharp[candidates])])

    keys = [choose(np.arange(min(n, options.window)))]
    travelled, i = 0.0, keys[0] + 1
    while i < n:
        travelled += step[i]
        if travelled >= options.min_baseline:
            reach = travelled + np.cumsum(step[i + 1 : i + options.window])
            extra = int(np.sum(reach <= 2 * options.min_baseline))  # contiguous: steps >= 0
            keys.append(choose(np.arange(i, i + 1 + extra)))
            travelled, i = 0.0, keys[-1]
        i += 1
    if options.max_frames is not None and len(keys) > options.max_frames:
        keep = np.linspace(0, len(keys) - 1, options.max_frames).round().astype(int)
        keys = [keys[k] for k in keep]
    return keys


# ---------------------------------------------------------------------------- reading


def _small_gray(frame: np.ndarray, width: int) -> np.ndarray:
    import cv2

    gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    if gray.shape[1] > width:
        gray = cv2.resize(gray, (width, round(gray.shape[0] * width / gray.shape[1])),
                          interpolation=cv2.INTER_AREA)
    return gray


def iter_frames(source: Path) -> Iterator[np.ndarray]:
    """BGR frames of a video file or an image folder, in order."""
    import cv2

    if source.is_dir():
        for name in list_images(source):
            frame = cv2.imread(str(source / name), cv2.IMREAD_COLOR)
            if frame is None:
                raise ValueError(f"{source / name}: cannot read this image")
            yield frame
        return
    cap = cv2.VideoCapture(str(source))
    if not cap.isOpened():
        raise ValueError(f"{source}: cannot open as a video (unknown format or codec)")
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            yield frame
    finally:
        cap.release()


def score_frames(source: Path, options: FrameOptions = FrameOptions(), progress=None):
    """(sharpness, displacement) per frame of `source`."""
    sharp, step, prev = [], [], None
    for frame in iter_frames(source):
        gray = _small_gray(frame, options.analysis_width)
        sharp.append(sharpness(gray))
        step.append(0.0 if prev is None else flow_displacement(prev, gray))
        prev = gray
        if progress is not None:
            progress.update(1)
    if not sharp:
        raise ValueError(f"{source}: no frames found")
    return np.array(sharp), np.array(step)


def write_video_frames(source: Path, keep: list[int], out_dir: Path) -> list[str]:
    """Decode `source` again and write the kept frames as JPEGs; returns their names."""
    import cv2

    from ghsplat_jax.io_utils import atomic_write

    out_dir.mkdir(parents=True, exist_ok=True)
    wanted, names = set(keep), []
    for index, frame in enumerate(iter_frames(source)):
        if index in wanted:
            name = f"frame_{index:06d}.jpg"
            ok, data = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, 95])
            if not ok:
                raise RuntimeError(f"cannot encode frame {index} of {source}")
            with atomic_write(out_dir / name) as fh:
                fh.write(data.tobytes())
            names.append(name)
    return names
