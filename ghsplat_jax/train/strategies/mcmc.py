"""3DGS-MCMC (Kheradmand et al. 2024; gsplat's MCMCStrategy) on 2D surfels: dead (low-opacity)
surfels are relocated onto live ones sampled by opacity, with the opacity and scale of the N
copies corrected so their summed footprint matches the original; the count grows by
`grow_rate` per round up to `max_surfels`; noise on positions every step, gated by
(1 - opacity) and scaled by the means learning rate; L1 opacity and scale regularisers in the
loss (step.py, weights `lambda_opacity_reg`, `lambda_scale_reg`)."""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.core.precision import FLOAT32
from ghsplat_jax.core.quaternions import safe_normalize, to_rotation_matrix
from ghsplat_jax.train import optim
from ghsplat_jax.train.state import TrainState
from ghsplat_jax.train.strategies.base import Strategy, StrategySettings, grow_pool, register
from ghsplat_jax.train.strategies.default import capped_start, count_cap


def relocation_integral(opacity: jax.Array, n: jax.Array, nodes: int = 24) -> jax.Array:
    """I(o, N) = integral_0^o (1 - (1 - t)^N) / t dt, the closed form of the 3DGS-MCMC sum
    sum_{i=1..N} sum_{k<i} C(i-1, k) (-1)^k o^(k+1) / (k+1) (hockey-stick identity), evaluated by
    Gauss-Legendre quadrature (the alternating binomial sum loses float32 precision for large N)."""
    x, w = np.polynomial.legendre.leggauss(nodes)
    t = 0.5 * opacity[..., None] * (jnp.asarray(x, jnp.float32) + 1.0)  # (..., nodes) in (0, o)
    f = (1.0 - jnp.power(1.0 - t, n[..., None].astype(jnp.float32))) / jnp.maximum(t, 1e-12)
    return 0.5 * opacity * jnp.sum(f * jnp.asarray(w, jnp.float32), axis=-1)


def relocation_values(opacity: jax.Array, log_scales: jax.Array, n: jax.Array):
    """Opacity and log scales of each of N copies of a surfel so that the N copies, stacked,
    cover the surfel plane like the original (2D adaptation of 3DGS-MCMC's Eq. 9):
    o' = 1 - (1 - o)^(1/N), and the area integral of 1 - (1 - o' G')^N, which is
    2 pi s_u' s_v' I(o', N) for a 2D Gaussian G' with scales s', equals 2 pi s_u s_v o:
    both scales times sqrt(o / I(o', N)). N = 1 leaves a surfel unchanged."""
    n = jnp.maximum(n, 1)
    new_op = 1.0 - jnp.power(1.0 - opacity, 1.0 / n.astype(jnp.float32))
    new_op = jnp.clip(new_op, 1e-6, 1.0 - 1e-6)
    integral = relocation_integral(new_op, n)
    coeff = jnp.sqrt(jnp.maximum(opacity, 1e-12) / jnp.maximum(integral, 1e-12))
    return new_op, log_scales + jnp.log(coeff)[..., None]


def sample_in_proportion(key: jax.Array, weights: jax.Array) -> jax.Array:
    """len(weights) indices drawn with replacement in proportion to the non-negative weights, by
    inverse CDF: O(n log n). (jax.random.categorical with shape (n,) draws an (n, n) Gumbel
    table: 400M numbers and 30 s per MCMC round at 20k slots.) All-zero weights give index 0."""
    n = weights.shape[0]
    cdf = jnp.cumsum(weights)
    u = jax.random.uniform(key, (n,), weights.dtype) * cdf[-1]
    idx = jnp.searchsorted(cdf, u, side="right")  # the first i with cdf[i] > u: never a zero weight
    positive = weights > 0
    last = jnp.where(jnp.any(positive), n - 1 - jnp.argmax(positive[::-1]), 0)  # u rounded up to the total
    return jnp.where(idx < n, idx, last).astype(jnp.int32)


def relocate(state: TrainState, key: jax.Array, targets: jax.Array, min_opacity: float,
             weights: jax.Array | None = None) -> tuple[TrainState, dict]:
    """Fill the slots `targets` (dead or free) with copies of live surfels sampled in proportion
    to `weights` (default: their opacity); sources and copies get the corrected opacity and
    scales and fresh Adam moments. Only target rows change position; no shapes change."""
    cap = state.capacity
    p = state.params
    op = jax.nn.sigmoid(p.opacity_logits)
    alive = state.active & (op > min_opacity) & ~targets
    any_alive = jnp.any(alive)
    targets = targets & any_alive
    weights = op if weights is None else weights
    src = jnp.where(targets, sample_in_proportion(key, jnp.where(alive, weights, 0.0)), jnp.arange(cap))
    copies = jnp.zeros(cap, jnp.int32).at[src].add(targets.astype(jnp.int32))
    is_src = copies > 0
    new_op, new_ls = relocation_values(op, p.log_scales, copies + 1)
    new_logit = jnp.log(new_op) - jnp.log1p(-new_op)
    upd = dataclasses.replace(p, opacity_logits=jnp.where(is_src, new_logit, p.opacity_logits),
                              log_scales=jnp.where(is_src[:, None], new_ls, p.log_scales))

    def copy_rows(a):
        m = targets.reshape((cap,) + (1,) * (a.ndim - 1))
        return jnp.where(m, a[src], a)

    params = jax.tree_util.tree_map(copy_rows, upd)
    changed = is_src | targets
    opt_state = optim.reset_rows(state.opt_state, changed)
    zero = lambda a: jnp.where(targets, 0.0, a)  # noqa: E731
    new = dataclasses.replace(state, params=params, active=state.active | targets, opt_state=opt_state,
                              grad_accum=zero(state.grad_accum), grad_count=zero(state.grad_count),
                              max_radii=zero(state.max_radii))
    return new, {"filled": jnp.sum(targets), "sources": jnp.sum(is_src)}


def mcmc_round(state: TrainState, key: jax.Array, cap: jax.Array, min_opacity: float, grow_rate: float,
               weights: jax.Array | None = None):
    """One MCMC refinement: relocate dead surfels, then grow by grow_rate up to `cap` live ones;
    copies are drawn in proportion to `weights` (default: opacity)."""
    op = jax.nn.sigmoid(state.params.opacity_logits)
    dead = state.active & (op <= min_opacity)
    k1, k2 = jax.random.split(key)
    state, r = relocate(state, k1, dead, min_opacity, weights)
    n = jnp.sum(state.active).astype(jnp.int32)
    target = jnp.minimum(cap, jnp.floor(n.astype(jnp.float32) * (1.0 + grow_rate)).astype(jnp.int32))
    free = ~state.active
    add = free & (jnp.cumsum(free) <= jnp.maximum(target - n, 0))
    state, a = relocate(state, k2, add, min_opacity, weights)
    return state, {"relocated": r["filled"], "added": a["filled"]}


def mcmc_noise(state: TrainState, key: jax.Array, scale: jax.Array) -> TrainState:
    """Perturb live means by N(0, Sigma) x sigmoid(100 (1 - opacity - 0.995)) x scale, Sigma the
    surfel's in-plane covariance R diag(s_u^2, s_v^2, 0) R^T (a 2D surfel has no normal extent)."""
    p = state.params
    op = jax.nn.sigmoid(p.opacity_logits)
    gate = jax.nn.sigmoid(100.0 * ((1.0 - op) - 0.995))
    q, _ = safe_normalize(p.quats)
    tuv = to_rotation_matrix(q)[:, :, :2]  # (cap,3,2)
    eps = jax.random.normal(key, p.means.shape, p.means.dtype)
    local = jnp.einsum("nji,nj->ni", tuv, eps, precision=FLOAT32) * jnp.exp(2.0 * p.log_scales)
    noise = jnp.einsum("nij,nj->ni", tuv, local, precision=FLOAT32) * (gate * scale)[:, None]
    means = jnp.where(state.active[:, None], p.means + noise, p.means)
    return dataclasses.replace(state, params=dataclasses.replace(p, means=means))


mcmc_round_jit = jax.jit(mcmc_round, static_argnames=("min_opacity", "grow_rate"))
mcmc_noise_jit = jax.jit(mcmc_noise)


@dataclasses.dataclass(frozen=True)
class MCMCSettings(StrategySettings):
    """3DGS-MCMC (Kheradmand et al. 2024; gsplat's MCMCStrategy) on 2D surfels.

    Args:
        max_surfels: the cap on the live count (0: 5x the initial count); the pool grows with the
            count up to it.
        min_opacity: a surfel is "dead" below this opacity and is relocated onto live surfels
            sampled by opacity.
        grow_rate: each refinement round grows the live count by this fraction, up to the cap.
        noise_lr: position noise = this x the means learning rate x the in-plane covariance.
    """

    max_surfels: int = 0
    min_opacity: float = 0.005
    grow_rate: float = 0.05
    noise_lr: float = 5e5

    def validate(self) -> None:
        super().validate()
        if self.max_surfels < 0:
            raise ValueError(f"max_surfels must be >= 0 (0: 5x the initial count), got {self.max_surfels}")
        if not 0 < self.min_opacity < 1:
            raise ValueError(f"min_opacity must be in (0, 1), got {self.min_opacity}")
        if self.grow_rate < 0:
            raise ValueError(f"grow_rate must be >= 0, got {self.grow_rate}")
        if self.noise_lr < 0:
            raise ValueError(f"noise_lr must be >= 0, got {self.noise_lr}")


@register("mcmc", MCMCSettings)
@dataclasses.dataclass(frozen=True)
class MCMCStrategy(Strategy):
    """3DGS-MCMC on 2D surfels: relocation of dead surfels and growth up to max_surfels every
    densify_every steps in [densify_from, densify_until), position noise every step; no
    clone/split and no opacity reset. The pool grows with the count: held at the cap from the
    start, its free slots cost every step the per-surfel work of live ones (row2_x1 at 155k:
    step 2,000 after 307 s, against 94 s for the same count in a pool at 31k)."""

    loss_defaults: ClassVar[dict] = {"lambda_opacity_reg": 0.01, "lambda_scale_reg": 0.01}
    caps_count: ClassVar[bool] = True

    def initial_pool(self, init, rng):
        return capped_start(self.settings.max_surfels, init, rng)

    def init_state(self, initial_count: int) -> dict:
        cap = count_cap(self.settings.max_surfels, initial_count)
        return dict(super().init_state(initial_count), max_surfels=jnp.int32(cap),
                    relocated=jnp.zeros((), jnp.int32), added=jnp.zeros((), jnp.int32))

    def refine(self, ctx, state, sstate, it):
        c, s = self.config, self.settings
        info = {}
        if c.densify_from < it < c.densify_until and it % c.densify_every == 0:
            cap = int(sstate["max_surfels"])
            need = math.floor(state.num_active() * (1 + s.grow_rate)) + 1  # + 1: the round's float32 target
            state = grow_pool(state, min(need, cap), limit=cap)
            key = jax.random.fold_in(jax.random.PRNGKey(c.seed), it)
            state, counts = mcmc_round_jit(state, key, sstate["max_surfels"], min_opacity=float(s.min_opacity),
                                           grow_rate=float(s.grow_rate))
            sstate = self.count_round(sstate, counts, info)
        return self.add_noise(ctx, state, it), sstate, info

    @staticmethod
    def count_round(sstate: dict, counts: dict, info: dict) -> dict:
        """Add a refinement round's relocated and added counts to the state (and to `info`)."""
        counts = {k: int(v) for k, v in counts.items()}
        info.update(counts)
        return dict(sstate, relocated=sstate["relocated"] + counts["relocated"],
                    added=sstate["added"] + counts["added"])

    def add_noise(self, ctx, state: TrainState, it: int) -> TrainState:
        """The step's position noise (none when noise_lr is 0)."""
        s = self.settings
        if s.noise_lr <= 0:
            return state
        key = jax.random.fold_in(jax.random.PRNGKey(self.config.seed + 1), it)
        return mcmc_noise_jit(state, key, jnp.float32(s.noise_lr * ctx.means_lr(it - 1)))
