"""Real spherical harmonics in the 3DGS basis and sign convention (degrees 0-3)."""

from __future__ import annotations

import jax.numpy as jnp

from ghsplat_jax.core.precision import FLOAT32

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def basis(dirs: jnp.ndarray, degree: int) -> jnp.ndarray:
    """SH basis values (..., (degree+1)^2) for unit directions (..., 3)."""
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    out = [jnp.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return jnp.stack(out, axis=-1)


def evaluate(sh_dc: jnp.ndarray, sh_rest: jnp.ndarray, dirs: jnp.ndarray, degree: int) -> jnp.ndarray:
    """Colour (..., 3) = SH(dirs) + 0.5, clamped at 0; uses the first `degree` bands only."""
    k = (degree + 1) ** 2
    coeffs = jnp.concatenate([sh_dc[..., None, :], sh_rest[..., : k - 1, :]], axis=-2)
    colour = jnp.einsum("...k,...kc->...c", basis(dirs, degree), coeffs, precision=FLOAT32)
    return jnp.maximum(colour + 0.5, 0.0)


def rgb_to_dc(rgb):
    """The DC coefficient that renders `rgb` with all higher bands zero."""
    return (rgb - 0.5) / C0
