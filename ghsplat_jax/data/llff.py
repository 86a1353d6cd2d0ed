"""LLFF `poses_bounds.npy`: N x 17 rows of a 3x5 [R | t | hwf] camera-to-world and near/far.

The rotation columns are the camera's [down, right, back] axes in world coordinates;
OpenCV wants [right, down, forward] = [col 1, col 0, -col 2]. hwf (height, width,
focal) refers to the full-resolution images/ folder, which LLFF scenes often ship only
as images_4/ or images_8/ (different file names, same sorted order). The world frame
is COLMAP's, so sparse/0/points3D gives the initial points. Like NeRF and 3DGS we use
a centred pinhole and ignore the lens distortion of the COLMAP camera.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ghsplat_jax.data.colmap import model_file, read_points
from ghsplat_jax.data.errors import DatasetError
from ghsplat_jax.data.frames import Frame, SceneSpec, check_camera, choose_folder, invert_rigid, pinhole_K, rigid
from ghsplat_jax.data.images import list_images


def load_poses_bounds(path: Path) -> np.ndarray:
    try:
        with open(path, "rb") as fh:
            # The .npy header's shape is checked against the file size before numpy
            # allocates anything from it.
            fmt = np.lib.format
            version = fmt.read_magic(fh)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f"unsupported .npy version {version}")
            # numpy reads the header's declared length in one go: check it against the file first
            (length,) = struct.unpack("<H" if version == (1, 0) else "<I", fh.read(2 if version == (1, 0) else 4))
            if length > 10_000 or length > path.stat().st_size:
                raise ValueError(f"header of {length} bytes")
            fh.seek(-(2 if version == (1, 0) else 4), 1)
            read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, _, dtype = read_header(fh)
            available = path.stat().st_size - fh.tell()
    except Exception as exc:  # numpy's header parser raises value, syntax and tokenizer errors alike
        raise DatasetError(f"{path}: cannot read LLFF poses ({type(exc).__name__}: {exc})") from None
    if len(shape) != 2 or shape[1] != 17 or shape[0] == 0:
        raise DatasetError(f"{path}: expected an N x 17 array of LLFF poses, got shape {shape}")
    if dtype.kind not in "fiu" or dtype.hasobject:
        raise DatasetError(f"{path}: LLFF poses must be numbers, got dtype {dtype}")
    if available < shape[0] * shape[1] * dtype.itemsize:
        raise DatasetError(f"{path}: truncated, {available} bytes for a {shape[0]} x 17 {dtype} array")
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise DatasetError(f"{path}: cannot read LLFF poses ({exc})") from None
    return data.astype(np.float64)


def llff_to_opencv(pose: np.ndarray, where: str) -> np.ndarray:
    """world_to_cam (4,4) from one 3x5 LLFF pose."""
    R = pose[:, :3]
    R_cv = np.stack([R[:, 1], R[:, 0], -R[:, 2]], axis=1)
    return invert_rigid(rigid(R_cv, pose[:, 3], where))


def read_llff(root: Path, downscale: float) -> SceneSpec:
    path = root / "poses_bounds.npy"
    poses = load_poses_bounds(path)[:, :15].reshape(-1, 3, 5)
    folder, factor = choose_folder(root / "images", downscale)
    files = list_images(folder)
    if len(files) != len(poses):
        raise DatasetError(f"{folder}: {len(files)} images, but {path} has {len(poses)} poses")
    frames = []
    for i, (pose, file) in enumerate(zip(poses, files)):
        height, width, focal = pose[:, 4]
        where = f"{path} (pose {i})"
        if not (np.isfinite(height) and np.isfinite(width)):
            raise DatasetError(f"{where}: non-finite image size {width} x {height}")
        K = pinhole_K(focal, focal, width / 2, height / 2)
        check_camera(K, int(round(width)), int(round(height)), None, where)
        frames.append(Frame(
            name=file.name,
            sources=[(file, float(factor))],
            K=K,
            world_to_cam=llff_to_opencv(pose, where),
            width=int(round(width)),
            height=int(round(height)),
        ))
    points_path = None
    for model in (root / "sparse" / "0", root / "sparse"):
        points_path = points_path or model_file(model, "points3D")
    points, colors = read_points(points_path) if points_path else (np.zeros((0, 3), np.float32), None)
    return SceneSpec("llff", frames, points, colors, None, path)
