"""LLFF `poses_bounds.npy`: N x 17 rows of a 3x5 [R | t | hwf] camera-to-world and near/far.

The rotation columns are the camera's [down, right, back] axes in world coordinates;
OpenCV wants [right, down, forward] = [col 1, col 0, -col 2]. hwf (height, width,
focal) refers to the full-resolution images/ folder, which LLFF scenes often ship only
as images_4/ or images_8/ (different file names, same sorted order). The world frame
is COLMAP's, so sparse/0/points3D gives the initial points. Like NeRF and 3DGS we use
a centred pinhole and ignore the lens distortion of the COLMAP camera.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ghsplat_jax.data.colmap import model_file, read_points
from ghsplat_jax.data.errors import DatasetError
from ghsplat_jax.data.frames import Frame, SceneSpec, choose_folder, invert_rigid, pinhole_K, rigid
from ghsplat_jax.data.images import list_images


def load_poses_bounds(path: Path) -> np.ndarray:
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise DatasetError(f"{path}: cannot read LLFF poses ({exc})") from None
    if data.ndim != 2 or data.shape[1] != 17 or len(data) == 0:
        raise DatasetError(f"{path}: expected an N x 17 array of LLFF poses, got shape {data.shape}")
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
        frames.append(Frame(
            name=file.name,
            sources=[(file, float(factor))],
            K=pinhole_K(focal, focal, width / 2, height / 2),
            world_to_cam=llff_to_opencv(pose, f"{path} (pose {i})"),
            width=int(round(width)),
            height=int(round(height)),
        ))
    points_path = None
    for model in (root / "sparse" / "0", root / "sparse"):
        points_path = points_path or model_file(model, "points3D")
    points, colors = read_points(points_path) if points_path else (np.zeros((0, 3), np.float32), None)
    return SceneSpec("llff", frames, points, colors, None, path)
