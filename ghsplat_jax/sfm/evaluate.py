"""Pose accuracy against a reference: similarity (Umeyama) alignment of camera centres."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ghsplat_jax.sfm.align import camera_centres


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, R, t) minimising sum |dst - (scale R src + t)|^2 (Umeyama 1991)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama needs matching (N>=3, 3) arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    u, sigma, vt = np.linalg.svd(xd.T @ xs / len(src))
    d = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2] = -1.0
    rot = u @ np.diag(d) @ vt
    var_s = (xs**2).sum() / len(src)
    scale = float((sigma * d).sum() / var_s)
    return scale, rot, mu_d - scale * rot @ mu_s


def compare_poses(est_w2c: np.ndarray, ref_w2c: np.ndarray) -> dict:
    """Camera-centre and rotation errors of matched cameras after a similarity alignment.

    Centre errors are also given relative to the reference extent (the largest distance
    of a reference centre from their centroid, times two). `to_reference` is the similarity
    itself, x_ref = scale R x_est + t (evaluation carries a model into the reference's frame).
    """
    est_c, ref_c = camera_centres(est_w2c), camera_centres(ref_w2c)
    scale, rot, t = umeyama(est_c, ref_c)
    aligned = scale * est_c @ rot.T + t
    centre_err = np.linalg.norm(aligned - ref_c, axis=1)
    extent = 2.0 * float(np.max(np.linalg.norm(ref_c - ref_c.mean(0), axis=1)))
    # Aligned camera rotation: R_est @ rot^T (world_to_cam of the moved camera).
    rel = np.einsum("nij,nkj->nik", est_w2c[:, :3, :3] @ rot.T, ref_w2c[:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    rot_err = np.degrees(np.arccos(cos))
    return {
        "num_cameras": len(est_c),
        "scale": scale,
        "extent": extent,
        "centre_error_max": float(centre_err.max()),
        "centre_error_mean": float(centre_err.mean()),
        "centre_error_rmse": float(np.sqrt(np.mean(centre_err**2))),
        "centre_error_max_rel": float(centre_err.max() / extent),
        "rotation_error_max_deg": float(rot_err.max()),
        "rotation_error_mean_deg": float(rot_err.mean()),
        "to_reference": {"scale": scale, "rotation": rot.tolist(), "translation": t.tolist()},
    }


def model_w2c(reconstruction) -> dict[str, np.ndarray]:
    """{image name: world_to_cam (4,4)} of the registered images of a pycolmap model."""
    poses = {}
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.images[image_id]
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        poses[image.name] = w2c
    return poses


def compare_models(estimate, reference) -> dict:
    """compare_poses over the images both pycolmap models registered (matched by name)."""
    est, ref = model_w2c(estimate), model_w2c(reference)
    names = sorted(set(est) & set(ref))
    if len(names) < 3:
        raise ValueError(f"only {len(names)} images in common; need at least 3 to compare")
    result = compare_poses(np.stack([est[n] for n in names]), np.stack([ref[n] for n in names]))
    result["missing_from_estimate"] = sorted(set(ref) - set(est))
    return result


def model_dir_w2c(model) -> dict[str, np.ndarray]:
    """{image file name: world_to_cam (4,4)} of a COLMAP model folder (binary or text)."""
    from ghsplat_jax.core.quaternions import to_rotation_matrix_np
    from ghsplat_jax.data import colmap

    poses = {}
    for image in colmap.read_images(colmap.model_file(Path(model), "images")).values():
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = to_rotation_matrix_np(image.qvec), image.tvec
        poses[Path(image.name).name] = w2c
    return poses


def compare_model_dirs(estimate, reference) -> dict | None:
    """compare_poses of two COLMAP model folders over their common images (None below 3),
    e.g. an SfM model against the generator's exact cameras; `reference` is the reference
    folder's path relative to the estimate's."""
    est, ref = model_dir_w2c(estimate), model_dir_w2c(reference)
    names = sorted(set(est) & set(ref))
    if len(names) < 3:
        return None
    result = compare_poses(np.stack([est[n] for n in names]), np.stack([ref[n] for n in names]))
    # Relative to the estimate's model folder where both sit under one tree, so a moved tree keeps the link.
    return result | {"reference": os.path.relpath(Path(reference).resolve(), Path(estimate).resolve())}
