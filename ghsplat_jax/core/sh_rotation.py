"""Rotate (or reflect) real spherical-harmonic coefficients, degrees 1-3, in the 3DGS basis.

Each band l spans a (2l+1)-dimensional space that any orthogonal map M of directions
(rotation or reflection) maps to itself. The band matrix D_l is fitted by least squares
on sample directions so that   basis_l(M d) . (D_l c) == basis_l(d) . c   for every d,
which is exactly the invariance a renderer needs: after moving a surfel by M, the colour
seen from the moved direction M d equals the old colour seen from d. Using the basis of
core.sh itself means the 3DGS sign convention (band 1 = -y, z, -x) is handled for free.

Pure numpy (float64) on the host: transforms are edits, not training steps.
"""

from __future__ import annotations

import functools

import numpy as np

from ghsplat_jax.core import sh


@functools.lru_cache(maxsize=1)
def _sample_directions(n: int = 128) -> np.ndarray:
    """Fibonacci-sphere directions: well spread, deterministic, many more than 2l+1 = 7."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5.0 ** 0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _basis64(dirs: np.ndarray, degree: int) -> np.ndarray:
    # core.sh.basis uses jnp (float32 by default); x64 for the fit keeps D_l exact to ~1e-12.
    import jax

    with jax.enable_x64(True):
        return np.asarray(sh.basis(np.asarray(dirs, np.float64), degree), np.float64)


def band_matrices(M, degree: int) -> list[np.ndarray]:
    """[D_1, ..., D_degree]: (2l+1, 2l+1) matrices for the orthogonal 3x3 map M."""
    M = np.asarray(M, np.float64)
    if M.shape != (3, 3) or not np.allclose(M @ M.T, np.eye(3), atol=1e-5):
        raise ValueError(f"SH transform needs an orthogonal 3x3 matrix, got {M.round(6).tolist()}")
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0-3, got {degree}")
    d = _sample_directions()
    b_src = _basis64(d, degree)
    b_dst = _basis64(d @ M.T, degree)
    out = []
    for l in range(1, degree + 1):
        sl = slice(l * l, (l + 1) * (l + 1))
        D, *_ = np.linalg.lstsq(b_dst[:, sl], b_src[:, sl], rcond=None)
        out.append(D)
    return out


def transform_sh_rest(sh_rest, M) -> np.ndarray:
    """Coefficients (N,K,3) re-expressed for directions mapped by M (rotation or reflection)."""
    sh_rest = np.asarray(sh_rest)
    k = sh_rest.shape[-2]
    degree = int(round(np.sqrt(k + 1))) - 1
    if (degree + 1) ** 2 - 1 != k:
        raise ValueError(f"{k} higher-order SH coefficients do not form a degree 0-3 basis")
    out = np.empty_like(sh_rest)
    for l, D in enumerate(band_matrices(M, degree), start=1):
        sl = slice(l * l - 1, (l + 1) * (l + 1) - 1)  # sh_rest has no DC row
        out[..., sl, :] = np.einsum("ij,...jc->...ic", D, sh_rest[..., sl, :].astype(np.float64))
    return out


def rotate_sh_rest(sh_rest, R) -> np.ndarray:
    """Rotate SH coefficients (N,K,3) by the proper rotation R (det +1)."""
    R = np.asarray(R, np.float64)
    if np.linalg.det(R) < 0:
        raise ValueError("rotate_sh_rest got a reflection (det -1); use transform_sh_rest")
    return transform_sh_rest(sh_rest, R)
