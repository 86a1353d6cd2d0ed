"""The Surfels pytree: a set of 2D Gaussian surfels (the 2DGS parameterisation)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Surfels:
    """N 2D Gaussian surfels; all fields are raw (pre-activation) parameters.

    means (N,3) world positions; quats (N,4) w-x-y-z, not necessarily normalised;
    log_scales (N,2) tangent-plane scales; opacity_logits (N,) pre-sigmoid;
    sh_dc (N,3) and sh_rest (N,K,3) with K = (degree+1)^2 - 1 (3DGS real-SH basis).

    Args:
        means: (N,3) world positions.
        quats: (N,4) rotations as w-x-y-z quaternions, not necessarily normalised.
        log_scales: (N,2) log of the two tangent-plane scales.
        opacity_logits: (N,) opacities before the sigmoid.
        sh_dc: (N,3) degree-0 spherical-harmonic colour coefficients.
        sh_rest: (N,K,3) higher-order coefficients, K = (degree+1)^2 - 1 (0, 3, 8 or 15).

    Returns:
        A frozen pytree of device arrays as a rule (host NumPy arrays after `to_numpy` or
        `load_ply`); `num`, `sh_degree` and `opacity` are derived from the fields.
    """

    means: jax.Array | np.ndarray
    quats: jax.Array | np.ndarray
    log_scales: jax.Array | np.ndarray
    opacity_logits: jax.Array | np.ndarray
    sh_dc: jax.Array | np.ndarray
    sh_rest: jax.Array | np.ndarray

    @property
    def num(self) -> int:
        return self.means.shape[-2]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_rest(self.sh_rest.shape[-2])

    @property
    def opacity(self) -> jax.Array:
        return jax.nn.sigmoid(self.opacity_logits)

    def to_numpy(self) -> "Surfels":
        return jax.tree_util.tree_map(np.asarray, self)

    def take(self, index) -> "Surfels":
        """Select surfels by an index array or boolean mask (host or device)."""
        return jax.tree_util.tree_map(lambda a: a[index], self)


def sh_degree_from_rest(num_rest: int) -> int:
    degree = int(round(np.sqrt(num_rest + 1))) - 1
    if (degree + 1) ** 2 - 1 != num_rest or not 0 <= degree <= 3:
        raise ValueError(f"{num_rest} higher-order SH coefficients do not form a degree 0-3 basis")
    return degree


def make_surfels(means, quats=None, log_scales=None, opacity_logits=None, sh_dc=None,
                 sh_rest=None, sh_degree: int = 0) -> Surfels:
    """Build Surfels with sensible defaults for the fields that are left out.

    Args:
        means: (N,3) world positions.
        quats: (N,4) w-x-y-z quaternions; default the identity rotation.
        log_scales: (N,2) log tangent-plane scales; default log(0.01) (1 cm surfels).
        opacity_logits: (N,) pre-sigmoid opacities; default 0 (opacity 0.5).
        sh_dc: (N,3) degree-0 colour coefficients; default 0 (mid grey).
        sh_rest: (N,K,3) higher-order coefficients; default zeros of `sh_degree`'s K.
        sh_degree: the SH degree (0-3) that sizes the default `sh_rest`.

    Returns:
        Surfels with float32 device-array fields.
    """
    means = jnp.asarray(means, jnp.float32)
    n = means.shape[0]
    k = (sh_degree + 1) ** 2 - 1
    default = lambda x, fill: jnp.asarray(fill if x is None else x, jnp.float32)
    return Surfels(
        means=means,
        quats=default(quats, jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (n, 1))),
        log_scales=default(log_scales, jnp.full((n, 2), np.log(0.01))),
        opacity_logits=default(opacity_logits, jnp.zeros((n,))),
        sh_dc=default(sh_dc, jnp.zeros((n, 3))),
        sh_rest=default(sh_rest, jnp.zeros((n, k, 3))),
    )


def concatenate(parts: list[Surfels]) -> Surfels:
    """Join sets of surfels into one, in order.

    Args:
        parts: Surfels of one SH degree.

    Returns:
        Surfels holding every part's surfels, the first part's first.

    Raises:
        ValueError: when the parts have different SH degrees.
    """
    degrees = {p.sh_degree for p in parts}
    if len(degrees) > 1:
        raise ValueError(f"cannot concatenate surfels of different SH degrees {sorted(degrees)}")
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a, axis=0), *parts)
