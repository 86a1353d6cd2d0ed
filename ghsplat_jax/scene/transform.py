"""Similarity transforms of surfels: rescale, rigid motion and mirror, SH included.

All functions are pure and work on host (numpy) copies: x_new = M (s x) + t with M
orthogonal. Positions, tangent frames, log-scales and SH bands 1-3 move together, so a
transformed scene seen from the correspondingly transformed camera renders the same.
"""

from __future__ import annotations

import numpy as np

from ghsplat_jax.core import quaternions
from ghsplat_jax.core.sh_rotation import transform_sh_rest
from ghsplat_jax.core.surfels import Surfels


def rotation_from_euler(degrees_xyz) -> np.ndarray:
    """R = Rz @ Ry @ Rx (extrinsic x, then y, then z), angles in degrees."""
    return quaternions.from_euler_xyz(degrees_xyz, degrees=True)


def yaw_matrix(yaw_deg: float) -> np.ndarray:
    return rotation_from_euler([0.0, 0.0, yaw_deg])


def mirror_matrix(axis: str = "y") -> np.ndarray:
    """Reflection that negates one world axis ('x', 'y' or 'z')."""
    if axis not in ("x", "y", "z"):
        raise ValueError(f"mirror axis must be x, y or z, got {axis!r}")
    M = np.eye(3)
    M["xyz".index(axis), "xyz".index(axis)] = -1.0
    return M


def similarity(s: Surfels, scale: float = 1.0, M=None, t=None) -> Surfels:
    """x_new = M (scale x) + t for orthogonal M (a rotation, or a reflection with det -1).

    Rotation: q_new = q_M * q. Reflection: the reflected tangent frame (M t_u, M t_v, M n)
    is left-handed; swapping the tangent roles gives the proper frame (M t_v, M t_u, M n)
    of the same surfel, so the two scales swap too. SH bands are refitted for M either way.
    """
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"scale must be a positive finite number, got {scale}")
    s = s.to_numpy()
    M = np.eye(3) if M is None else np.asarray(M, np.float64)
    t = np.zeros(3) if t is None else np.asarray(t, np.float64)
    if M.shape != (3, 3) or not np.allclose(M @ M.T, np.eye(3), atol=1e-5):
        raise ValueError("similarity needs an orthogonal 3x3 matrix (rotation or reflection)")
    det = np.linalg.det(M)
    f32 = lambda a: np.ascontiguousarray(a, np.float32)
    means = (s.means.astype(np.float64) * scale) @ M.T + t
    log_scales = s.log_scales + np.float32(np.log(scale))
    if det > 0:
        qm = quaternions.from_rotation_matrix(M[None])[0]
        quats = quaternions.multiply_np(np.broadcast_to(qm, s.quats.shape), s.quats.astype(np.float64))
    else:
        frames = M @ quaternions.to_rotation_matrix_np(s.quats.astype(np.float64))  # columns t_u, t_v, n
        frames = frames[..., [1, 0, 2]]
        norm = np.linalg.norm(s.quats.astype(np.float64), axis=-1, keepdims=True)
        quats = quaternions.from_rotation_matrix(frames) * norm  # keep the stored (unnormalised) magnitude
        log_scales = log_scales[:, ::-1]
    sh_rest = s.sh_rest if not s.sh_rest.shape[1] or np.allclose(M, np.eye(3), atol=1e-12) else \
        transform_sh_rest(s.sh_rest, M)
    return Surfels(means=f32(means), quats=f32(quats), log_scales=f32(log_scales),
                   opacity_logits=f32(s.opacity_logits), sh_dc=f32(s.sh_dc), sh_rest=f32(sh_rest))


def rigid_transform(s: Surfels, R, t=None) -> Surfels:
    """Rotate by R (det +1) and translate by t."""
    R = np.asarray(R, np.float64)
    if np.linalg.det(R) < 0:
        raise ValueError("rigid_transform got a reflection (det -1); use mirror or similarity")
    return similarity(s, 1.0, R, t)


def rescale(s: Surfels, factor: float, center=None) -> Surfels:
    """Uniform scale about `center` (default the origin): positions x s, log-scales + log s."""
    center = np.zeros(3) if center is None else np.asarray(center, np.float64)
    return similarity(similarity(s, 1.0, None, -center), factor, None, center)


def mirror(s: Surfels, axis: str = "y", origin=None) -> Surfels:
    """Reflect across the plane through `origin` normal to `axis`."""
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    M = mirror_matrix(axis)
    return similarity(s, 1.0, M, origin - M @ origin)


def scale_from_length(measured: float, true: float) -> float:
    """Factor that makes a length measured in the reconstruction equal its true length."""
    if not (measured > 0 and true > 0 and np.isfinite(measured) and np.isfinite(true)):
        raise ValueError(f"lengths must be positive and finite, got measured={measured}, true={true}")
    return float(true / measured)


def scale_from_segments(measured_here: float, measured_reference: float,
                        reference_scale: float = 1.0) -> float:
    """Scale for a segment so a feature (e.g. the row width) matches an already-scaled reference.

    The paper rescales segments to a common scale by the ratio of one row width between
    segments: s = reference_scale * measured_reference / measured_here.
    """
    return reference_scale * scale_from_length(measured_here, measured_reference)


def transform_camera(world_to_cam, scale: float = 1.0, M=None, t=None) -> np.ndarray:
    """world_to_cam of the camera that sees similarity(s, scale, M, t) as the old one saw s.

    For a reflection the camera x axis is negated to keep a proper rotation: the image is
    then the left-right mirror of the original (exactly, for a centred principal point).
    """
    M = np.eye(3) if M is None else np.asarray(M, np.float64)
    t = np.zeros(3) if t is None else np.asarray(t, np.float64)
    w2c = np.asarray(world_to_cam, np.float64)
    R, c = w2c[:3, :3], -w2c[:3, :3].T @ w2c[:3, 3]
    R_new = R @ M.T
    if np.linalg.det(M) < 0:
        R_new = np.diag([-1.0, 1.0, 1.0]) @ R_new
    c_new = M @ (scale * c) + t
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R_new, -R_new @ c_new
    return out
