"""COLMAP sparse models (binary and text): cameras, registered images, 3D points.

A small numpy/struct parser rather than pycolmap: it needs no compiled dependency
(lent GPU images may lack pycolmap), reads the cameras/points of incomplete models
(LLFF scenes ship cameras.bin + points3D.bin without images.bin), skips the 2D
keypoints we never use, and reports a truncated file by name. The tests cross-check
it against pycolmap.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ghsplat_jax.core.quaternions import to_rotation_matrix_np
from ghsplat_jax.data.errors import DatasetError
from ghsplat_jax.data.frames import Frame, SceneSpec, check_camera, check_points, image_sources, pinhole_K, rigid

# model id -> (name, number of parameters), from colmap/src/colmap/sensor/models.h
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_IDS = {name: i for i, (name, _) in CAMERA_MODELS.items()}


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    id: int
    qvec: np.ndarray  # w, x, y, z (world -> camera)
    tvec: np.ndarray
    camera_id: int
    name: str


class _Reader:
    """Sequential little-endian reads that name the file when it ends early."""

    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def read(self, fmt: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise DatasetError(f"{self.path}: truncated COLMAP binary file (ends at byte {len(self.data)})")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def skip(self, size: int):
        if self.pos + size > len(self.data):
            raise DatasetError(f"{self.path}: truncated COLMAP binary file (ends at byte {len(self.data)})")
        self.pos += size

    def string(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise DatasetError(f"{self.path}: truncated COLMAP binary file (unterminated image name)")
        out = self.data[self.pos : end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return out


def _text_lines(path: Path):
    """(line number, stripped line) of a COLMAP text file, comments dropped, blank lines kept."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        for number, line in enumerate(fh, 1):
            line = line.strip()
            if not line.startswith("#"):
                yield number, line


def _bad_line(path: Path, number: int, what: str) -> DatasetError:
    return DatasetError(f"{path}:{number}: malformed COLMAP text ({what})")


def read_cameras(path: Path) -> dict[int, ColmapCamera]:
    cameras = {}
    if path.suffix == ".bin":
        r = _Reader(path)
        (count,) = r.read("Q")
        for _ in range(count):
            cam_id, model_id, width, height = r.read("iiQQ")
            if model_id not in CAMERA_MODELS:
                raise DatasetError(f"{path}: camera {cam_id} has unknown model id {model_id}")
            name, n = CAMERA_MODELS[model_id]
            cameras[cam_id] = ColmapCamera(cam_id, name, width, height, np.array(r.read("d" * n)))
        return cameras
    for number, line in _text_lines(path):
        if not line:
            continue
        parts = line.split()
        try:
            cam_id, model, width, height = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = np.array([float(v) for v in parts[4:]])
        except (IndexError, ValueError) as exc:
            raise _bad_line(path, number, str(exc)) from None
        if model not in MODEL_IDS:
            raise _bad_line(path, number, f"unknown camera model {model}")
        if len(params) != CAMERA_MODELS[MODEL_IDS[model]][1]:
            raise _bad_line(path, number, f"{model} takes {CAMERA_MODELS[MODEL_IDS[model]][1]} parameters")
        cameras[cam_id] = ColmapCamera(cam_id, model, width, height, params)
    return cameras


def read_images(path: Path) -> dict[int, ColmapImage]:
    images = {}
    if path.suffix == ".bin":
        r = _Reader(path)
        (count,) = r.read("Q")
        for _ in range(count):
            values = r.read("i7di")
            name = r.string()
            (num_points2d,) = r.read("Q")
            r.skip(24 * num_points2d)  # x, y (double) and point3D id (int64) per keypoint
            image_id, qvec, tvec, cam_id = values[0], values[1:5], values[5:8], values[8]
            images[image_id] = ColmapImage(image_id, np.array(qvec), np.array(tvec), cam_id, name)
        return images
    lines = _text_lines(path)
    for number, line in lines:
        if not line:
            continue
        parts = line.split(maxsplit=9)
        try:
            image_id, cam_id, name = int(parts[0]), int(parts[8]), parts[9]
            qvec = np.array([float(v) for v in parts[1:5]])
            tvec = np.array([float(v) for v in parts[5:8]])
        except (IndexError, ValueError) as exc:
            raise _bad_line(path, number, str(exc)) from None
        images[image_id] = ColmapImage(image_id, qvec, tvec, cam_id, name)
        next(lines, None)  # the keypoint line that follows every image line (may be blank)
    return images


def read_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (M,3) float32, rgb (M,3) float32 in [0, 1])."""
    xyz, rgb = [], []
    if path.suffix == ".bin":
        r = _Reader(path)
        (count,) = r.read("Q")
        for _ in range(count):
            values = r.read("Q3d3BdQ")
            xyz.append(values[1:4])
            rgb.append(values[4:7])
            r.skip(8 * values[8])  # track: (image id, keypoint index) int32 pairs
    else:
        for number, line in _text_lines(path):
            if not line:
                continue
            parts = line.split(maxsplit=8)
            if len(parts) < 8:
                raise _bad_line(path, number, "a point needs POINT3D_ID X Y Z R G B ERROR")
            try:
                xyz.append([float(v) for v in parts[1:4]])
                rgb.append([int(v) for v in parts[4:7]])
            except (IndexError, ValueError) as exc:
                raise _bad_line(path, number, str(exc)) from None
    with np.errstate(over="ignore"):  # doubles beyond float32 become Inf and are refused below
        xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    rgb = np.asarray(rgb, np.float32).reshape(-1, 3) / 255.0
    if len(rgb) and not (rgb.min() >= 0 and rgb.max() <= 1):
        raise DatasetError(f"{path}: point colours outside 0..255")
    return check_points(xyz, str(path)), rgb


def model_file(folder: Path, stem: str) -> Path | None:
    """folder/stem.bin, else folder/stem.txt, else None (binary wins, as in COLMAP tools)."""
    for suffix in (".bin", ".txt"):
        if (folder / (stem + suffix)).is_file():
            return folder / (stem + suffix)
    return None


def is_model(folder: Path) -> bool:
    return folder.is_dir() and all(model_file(folder, s) is not None for s in ("cameras", "images"))


def find_model(root: Path, anywhere: bool = True) -> Path | None:
    """The sparse model folder of a dataset: sparse/0, sparse or the root itself, then
    (if `anywhere`) other sub-folders such as colmap_ground_truth/ or colmap/sparse/0."""
    folders = [root / "sparse" / "0", root / "sparse", root]
    if anywhere and root.is_dir():
        children = sorted(p for p in root.iterdir() if p.is_dir())
        folders += sorted((root / "sparse").glob("*")) if (root / "sparse").is_dir() else []
        folders += children + [c / "sparse" / "0" for c in children] + [c / "0" for c in children]
    return next((folder for folder in folders if is_model(folder)), None)


def intrinsics(camera: ColmapCamera, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(K, OpenCV-order distortion or None) of a COLMAP camera; COLMAP's pixel centres are at +0.5 too."""
    p = camera.params
    if camera.model == "SIMPLE_PINHOLE":
        return pinhole_K(p[0], p[0], p[1], p[2]), None
    if camera.model == "PINHOLE":
        return pinhole_K(p[0], p[1], p[2], p[3]), None
    if camera.model == "SIMPLE_RADIAL":
        return pinhole_K(p[0], p[0], p[1], p[2]), np.array([p[3], 0.0, 0.0, 0.0])
    if camera.model == "RADIAL":
        return pinhole_K(p[0], p[0], p[1], p[2]), np.array([p[3], p[4], 0.0, 0.0])
    if camera.model == "OPENCV":
        return pinhole_K(*p[:4]), np.array(p[4:8])
    if camera.model == "FULL_OPENCV":  # COLMAP: k1 k2 p1 p2 k3 k4 k5 k6, OpenCV's rational order too
        return pinhole_K(*p[:4]), np.array(p[4:12])
    raise DatasetError(
        f"{where}: camera {camera.id} uses the {camera.model} model, which is not supported "
        "(PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV are); "
        "undistort the images first with `colmap image_undistorter`"
    )


def image_folder(root: Path, model: Path) -> Path:
    """`images/` beside the model (or at the dataset root); the root itself as a last resort."""
    for base in (root, model.parent, model.parent.parent):
        if (base / "images").is_dir() or any(p.is_dir() for p in base.glob("images_*")):
            return base / "images"
    return root


def read_colmap(root: Path, downscale: float, model: Path | None = None) -> SceneSpec:
    """A COLMAP dataset: registered images sorted by name, points3D if present."""
    model = model or find_model(root)
    if model is None:
        usual = (root / "sparse" / "0", root / "sparse", root)
        partial = [f for f in usual if model_file(f, "cameras") or model_file(f, "images")]
        if partial:  # e.g. an LLFF scene's sparse/0 without images.bin: say what is missing
            model = partial[0]
        else:
            raise DatasetError(f"{root}: no COLMAP model (cameras.bin/.txt and images.bin/.txt) found")
    cameras_path, images_path = model_file(model, "cameras"), model_file(model, "images")
    if cameras_path is None or images_path is None:
        missing = "cameras" if cameras_path is None else "images"
        raise DatasetError(f"{model}: incomplete COLMAP model, {missing}.bin / {missing}.txt is missing")
    cameras = read_cameras(cameras_path)
    images = read_images(images_path)
    if not images:
        raise DatasetError(f"{images_path}: COLMAP model has zero registered images")
    folder = image_folder(root, model)
    frames = []
    for image in sorted(images.values(), key=lambda im: im.name):
        where = f"{images_path} (image {image.id} {image.name!r})"
        camera = cameras.get(image.camera_id)
        if camera is None:
            raise DatasetError(f"{where}: refers to camera {image.camera_id}, absent from {cameras_path}")
        if not (np.all(np.isfinite(image.qvec)) and np.linalg.norm(image.qvec) > 1e-6):
            raise DatasetError(f"{where}: rotation quaternion {image.qvec.tolist()} is not a rotation")
        K, dist = intrinsics(camera, str(cameras_path))
        check_camera(K, camera.width, camera.height, dist, f"{cameras_path} (camera {camera.id})")
        frames.append(Frame(
            name=image.name,
            sources=image_sources(folder, image.name, downscale),
            K=K,
            world_to_cam=rigid(to_rotation_matrix_np(image.qvec), image.tvec, where),
            width=camera.width,
            height=camera.height,
            dist=dist,
        ))
    points_path = model_file(model, "points3D")
    points, colors = read_points(points_path) if points_path else (np.zeros((0, 3), np.float32), None)
    return SceneSpec("colmap", frames, points, colors, None, images_path)
