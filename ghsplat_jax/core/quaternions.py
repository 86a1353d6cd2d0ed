"""Rotations: the one quaternion / matrix module of the package.

Quaternions are w-x-y-z (scalar first), the order of the Surfels pytree, the PLY `rot_*`
properties, COLMAP and viser. Message formats that use x-y-z-w (ROS geometry_msgs, scipy)
convert at their boundary with `wxyz_to_xyzw` / `xyzw_to_wxyz`, by name.

Each operation has one formula, written once over an array namespace: `jnp` for the
differentiable float32 code (rasterizer, training) and float64 NumPy (`*_np`) for host-side
edits, file formats and the simulator. (The float64 reference renderer keeps its own copy
on purpose: it is the independent oracle the rasterizer is tested against.)
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

_TINY = 1e-12


# -------------------------------------------------------------------- one formula each

def _matrix_rows(w, x, y, z):
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]


def _matrix(q, xp):
    rows = _matrix_rows(q[..., 0], q[..., 1], q[..., 2], q[..., 3])
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def _multiply(a, b, xp):
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return xp.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


# -------------------------------------------------------------------- jnp (float32, traced)

def _unit_parts(parts):
    """The components of q / |q| and whether q is valid (identity where not), with finite
    gradients for zero inputs (the double `where`)."""
    sq = sum(p * p for p in parts)
    valid = (sq > _TINY) & jnp.isfinite(sq)
    norm = jnp.sqrt(jnp.where(valid, sq, 1.0))
    return [jnp.where(valid, p, 1.0 if i == 0 else 0.0) / norm for i, p in enumerate(parts)], valid


def safe_normalize(q: jnp.ndarray, axis: int = -1) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(q / |q|, is_valid). Zero or non-finite q gives identity and is_valid False."""
    q = jnp.moveaxis(q, axis, -1)
    unit, valid = _unit_parts([q[..., i] for i in range(q.shape[-1])])
    return jnp.moveaxis(jnp.stack(unit, axis=-1), -1, axis), valid


def rotation_planes(q: jnp.ndarray) -> tuple[list[list[jnp.ndarray]], jnp.ndarray]:
    """The rotation matrices of q (..., 4), normalised as `safe_normalize` does, as (...) planes
    R[i][j], and whether each q was valid. For code written on planes (`raster.project`): on
    XLA:CPU every slice of a (..., 3, 3) array becomes a full-size pad in the gradient."""
    unit, valid = _unit_parts(list(jnp.moveaxis(q, -1, 0)))  # rows: a row's gradient is a cheap pad on XLA:CPU
    return _matrix_rows(*unit), valid


def to_rotation_matrix(q: jnp.ndarray) -> jnp.ndarray:
    """Rotation matrices (...,3,3) of unit quaternions (...,4) w-x-y-z."""
    return _matrix(q, jnp)


def multiply(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Hamilton product a * b (w-x-y-z): the rotation b, then a."""
    return _multiply(a, b, jnp)


# -------------------------------------------------------------------- NumPy float64 (host)

def to_rotation_matrix_np(q) -> np.ndarray:
    """Rotation matrices (...,3,3) of quaternions (...,4) w-x-y-z, normalised here (files
    round them); float64."""
    q = np.asarray(q, np.float64)
    return _matrix(q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), _TINY), np)


def multiply_np(a, b) -> np.ndarray:
    """Hamilton product a * b (w-x-y-z), float64."""
    return _multiply(np.asarray(a, np.float64), np.asarray(b, np.float64), np)


def from_rotation_matrix(R) -> np.ndarray:
    """Unit quaternions w-x-y-z (w >= 0) of rotation matrices (...,3,3), as float64 numpy.

    Shepperd's method, vectorised: each matrix uses the best-conditioned of four formulas.
    """
    R = np.asarray(R, np.float64)
    m = R.reshape(-1, 3, 3)
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    candidates = np.stack([
        [1 + m00 + m11 + m22, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]],
        [m[:, 2, 1] - m[:, 1, 2], 1 + m00 - m11 - m22, m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]],
        [m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0], 1 - m00 + m11 - m22, m[:, 1, 2] + m[:, 2, 1]],
        [m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1], 1 - m00 - m11 + m22],
    ]).transpose(2, 0, 1)                                         # (n, case, wxyz)
    case = np.argmax(np.stack([m00 + m11 + m22, m00, m11, m22], 1), axis=1)
    q = candidates[np.arange(len(m)), case]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


def from_euler_xyz(angles, degrees: bool = False) -> np.ndarray:
    """R = Rz(c) Ry(b) Rx(a) of angles (a, b, c): fixed axes x, then y, then z (the URDF
    roll-pitch-yaw convention); float64."""
    a, b, c = np.radians(angles) if degrees else np.asarray(angles, np.float64)
    half = lambda axis, t: np.array([np.cos(t / 2)] + [np.sin(t / 2) * (i == axis) for i in range(3)])  # noqa: E731
    return to_rotation_matrix_np(multiply_np(half(2, c), multiply_np(half(1, b), half(0, a))))


# -------------------------------------------------------------------- order at boundaries

def wxyz_to_xyzw(q) -> np.ndarray:
    """Scalar-last order (ROS geometry_msgs/Quaternion, scipy) of w-x-y-z quaternions."""
    return np.asarray(q, np.float64)[..., [1, 2, 3, 0]]


def xyzw_to_wxyz(q) -> np.ndarray:
    """Scalar-first order (this package) of x-y-z-w quaternions."""
    return np.asarray(q, np.float64)[..., [3, 0, 1, 2]]
