"""Real spherical harmonics in the 3DGS basis and sign convention (degrees 0-3)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def _basis_planes(dirs, degree: int) -> list:
    """The SH basis values for unit directions (..., 3), one (...) plane per coefficient."""
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
    return out


def basis(dirs: jax.Array | np.ndarray, degree: int) -> jax.Array:
    """SH basis values (..., (degree+1)^2) for unit directions (..., 3)."""
    return jnp.stack(_basis_planes(dirs, degree), axis=-1)


def evaluate(sh_dc: jnp.ndarray, sh_rest: jnp.ndarray, dirs: jnp.ndarray, degree: int) -> jnp.ndarray:
    """Colour (..., 3) = SH(dirs) + 0.5, clamped at 0; uses the first `degree` bands only."""
    return jnp.maximum(_colour(sh_dc, sh_rest, dirs, degree) + 0.5, 0.0)


# The SH sum with a written-out gradient. On XLA:CPU an einsum over the coefficients runs as
# batched (16) x (16, 3) dots (with a concatenation, 43 ms of a training step's thread time
# at 196k pool slots); the forward written as (...) planes fuses into one loop, but autodiff
# of its 45 slices of sh_rest pads each one back to full size (an order of magnitude worse).
# Here the forward is planes and the coefficients' gradient is one broadcast product.
@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _colour(sh_dc, sh_rest, dirs, degree: int):
    planes = _basis_planes(dirs, degree)
    return jnp.stack([C0 * sh_dc[..., c] + sum(b * sh_rest[..., k, c] for k, b in enumerate(planes[1:]))
                      for c in range(3)], axis=-1)


def _colour_fwd(sh_dc, sh_rest, dirs, degree: int):
    return _colour(sh_dc, sh_rest, dirs, degree), (sh_rest, dirs)


def _colour_bwd(degree: int, residuals, g):
    sh_rest, dirs = residuals
    planes, pull_back = jax.vjp(lambda d: _basis_planes(d, degree), dirs)
    used = len(planes) - 1
    d_planes = [jnp.zeros_like(planes[0])] + [sum(sh_rest[..., k, c] * g[..., c] for c in range(3))
                                              for k in range(used)]
    d_rest = jnp.stack(planes[1:], axis=-1)[..., None] * g[..., None, :] if used else sh_rest[..., :0, :]
    pad = [(0, 0)] * (sh_rest.ndim - 2) + [(0, sh_rest.shape[-2] - used), (0, 0)]
    return C0 * g, jnp.pad(d_rest, pad), pull_back(d_planes)[0]


_colour.defvjp(_colour_fwd, _colour_bwd)


def rgb_to_dc(rgb):
    """The DC coefficient that renders `rgb` with all higher bands zero."""
    return (rgb - 0.5) / C0
