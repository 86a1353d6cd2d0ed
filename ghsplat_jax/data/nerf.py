"""NeRF `transforms.json`: Blender-synthetic (camera_angle_x, train/test files) and instant-ngp.

Poses are camera-to-world in OpenGL axes (x right, y up, z backward); we flip y and z
to OpenCV and invert. instant-ngp intrinsics (fl_x, fl_y, cx, cy, k1, k2, k3, p1, p2)
may also appear per frame, overriding the top-level ones. Frames whose image file is
missing are skipped with one warning naming them.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np

from ghsplat_jax.data.errors import DatasetError, DatasetWarning
from ghsplat_jax.data.frames import Frame, SceneSpec, check_camera, image_sources, invert_rigid, pinhole_K, rigid
from ghsplat_jax.data.images import IMAGE_EXTENSIONS, image_size

_GL_TO_CV = np.diag([1.0, -1.0, -1.0])
_FISHEYE = {"OPENCV_FISHEYE", "EQUIRECTANGULAR", "FISHEYE"}


def transforms_files(root: Path) -> dict[str, Path]:
    """{"train": ..., "test": ...} for Blender-style split files, else {"all": transforms.json}."""
    train, test = root / "transforms_train.json", root / "transforms_test.json"
    if train.is_file() and test.is_file():
        return {"train": train, "test": test}
    if (root / "transforms.json").is_file():
        return {"all": root / "transforms.json"}
    if train.is_file():
        return {"all": train}
    return {}


def _load_json(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: cannot parse transforms file ({exc})") from None
    except RecursionError:  # "[[[[..." nested deeper than the parser's stack
        raise DatasetError(f"{path}: cannot parse transforms file (nested too deeply)") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise DatasetError(f"{path}: not a transforms file (no 'frames' list)")
    return meta


def _resolve(folder: Path, file_path: str) -> Path:
    """The image a frame names; NeRF-synthetic file paths lack the extension."""
    path = folder / file_path
    if path.suffix.lower() in IMAGE_EXTENSIONS or path.is_file():
        return path
    for ext in IMAGE_EXTENSIONS + tuple(e.upper() for e in IMAGE_EXTENSIONS):
        candidate = path.with_name(path.name + ext)
        if candidate.is_file():
            return candidate
    return path.with_name(path.name + ".png")


def _sources(root: Path, path: Path, downscale: float) -> list[tuple[Path, float]]:
    # images/0001.jpg may have a copy in images_4/0001.jpg; files straight in root have none
    rel = path.relative_to(root) if path.is_relative_to(root) else Path(path.name)
    if len(rel.parts) < 2:
        return [(path, 1.0)]
    return image_sources(root / rel.parts[0], Path(*rel.parts[1:]).as_posix(), downscale)


def _frame(root: Path, json_path: Path, meta: dict, index: int, raw: dict, downscale: float) -> Frame | str:
    """A Frame, or the image path (a str) when its file is missing."""
    where = f"{json_path} (frame {index})"
    if not isinstance(raw, dict) or "file_path" not in raw or "transform_matrix" not in raw:
        raise DatasetError(f"{where}: a frame needs 'file_path' and 'transform_matrix'")
    if not isinstance(raw["file_path"], str) or "\0" in raw["file_path"]:
        raise DatasetError(f"{where}: file_path must be a path string, got {raw['file_path']!r}")
    try:
        path = _resolve(json_path.parent, raw["file_path"])
        name = path.relative_to(root).as_posix() if path.is_relative_to(root) else path.name
        sources = _sources(root, path, downscale)
        existing = [(p, k) for p, k in sources if p.is_file()]
    except OSError as exc:  # e.g. a name too long for the file system
        raise DatasetError(f"{where}: bad file_path {raw['file_path'][:80]!r} ({exc.strerror})") from None
    if not existing:
        return name

    def get(key, default=None):
        return raw.get(key, meta.get(key, default))

    try:
        if get("w") is not None and get("h") is not None:
            width, height = int(get("w")), int(get("h"))
        else:  # Blender files give no size: read it from the image header
            w, h = image_size(existing[0][0])
            width, height = round(w * existing[0][1]), round(h * existing[0][1])
        if get("fl_x") is not None:
            fx = float(get("fl_x"))
        elif get("camera_angle_x") is not None:
            fx = 0.5 * width / math.tan(0.5 * float(get("camera_angle_x")))
        else:
            raise DatasetError(f"{where}: no focal length (fl_x or camera_angle_x)")
        if get("fl_y") is not None:
            fy = float(get("fl_y"))
        elif get("camera_angle_y") is not None and get("fl_x") is None:
            fy = 0.5 * height / math.tan(0.5 * float(get("camera_angle_y")))
        else:
            fy = fx
        K = pinhole_K(fx, fy, float(get("cx", width / 2)), float(get("cy", height / 2)))
        dist = np.array([float(get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")])
        c2w = np.asarray(raw["transform_matrix"], np.float64)
        model = str(get("camera_model", "")).upper()
        fisheye = get("is_fisheye") or model in _FISHEYE or float(get("k4", 0.0))
    except (TypeError, ValueError, ArithmeticError) as exc:  # ArithmeticError: a zero angle, an Inf size
        raise DatasetError(f"{where}: bad camera value ({exc})") from None
    if fisheye:
        raise DatasetError(f"{where}: fisheye cameras are not supported")
    if c2w.shape not in ((4, 4), (3, 4)):
        raise DatasetError(f"{where}: transform_matrix must be 4x4 or 3x4, got {c2w.shape}")
    check_camera(K, width, height, dist, where)
    c2w_cv = rigid(c2w[:3, :3] @ _GL_TO_CV, c2w[:3, 3], where)
    return Frame(name, sources, K, invert_rigid(c2w_cv), width, height, dist if dist.any() else None)


def read_transforms(root: Path, downscale: float) -> SceneSpec:
    files = transforms_files(root)
    if not files:
        raise DatasetError(f"{root}: no transforms.json or transforms_train.json")
    frames, split, missing = [], [], []
    for part, json_path in files.items():
        meta = _load_json(json_path)
        for index, raw in enumerate(meta["frames"]):
            frame = _frame(root, json_path, meta, index, raw, downscale)
            if isinstance(frame, str):
                missing.append(frame)
                continue
            frames.append(frame)
            split.append(part)
    where = ", ".join(p.name for p in files.values())
    if missing:
        warnings.warn(
            f"{root}: skipping {len(missing)} frame(s) of {where} whose image is missing: "
            + ", ".join(missing),
            DatasetWarning,
            stacklevel=4,  # the caller of load_dataset
        )
    if not frames:
        raise DatasetError(f"{root}: none of the frames in {where} has an image file")
    predefined = split if "train" in files else None
    return SceneSpec("transforms", frames, split=predefined, source=next(iter(files.values())))
