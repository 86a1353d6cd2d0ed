"""Quaternions in w-x-y-z order, NaN-safe where they may be zero."""

from __future__ import annotations

import jax.numpy as jnp

_TINY = 1e-12


def safe_normalize(q: jnp.ndarray, axis: int = -1) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(q / |q|, is_valid). Zero or non-finite q gives identity and is_valid False.

    The double `where` keeps gradients finite for zero inputs.
    """
    sq = jnp.sum(q * q, axis=axis, keepdims=True)
    valid = (sq > _TINY) & jnp.isfinite(sq)
    identity = jnp.zeros_like(q).at[..., 0].set(1.0)
    safe_q = jnp.where(valid, q, identity)
    safe_sq = jnp.where(valid, sq, 1.0)
    return safe_q / jnp.sqrt(safe_sq), valid[..., 0]


def to_rotation_matrix(q: jnp.ndarray) -> jnp.ndarray:
    """Rotation matrices (...,3,3) of unit quaternions (...,4) w-x-y-z."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def from_rotation_matrix(R) -> "np.ndarray":
    """Unit quaternions w-x-y-z (w >= 0) of rotation matrices (...,3,3), as float64 numpy.

    Shepperd's method, vectorised: each matrix uses the best-conditioned of four formulas.
    """
    import numpy as np

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


def multiply(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Hamilton product a * b (w-x-y-z)."""
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return jnp.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)
