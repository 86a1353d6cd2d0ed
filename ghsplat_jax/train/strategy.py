"""Densification strategies: frozen dataclasses with explicit state and hooks (gsplat's `Strategy`).

The trainer picks a strategy with `make_strategy(config)` (a registry keyed by
`config.strategy`, never an if/else on the name) and calls its hooks:

    strategy.initial_pool(surfels, rng) -> (surfels, capacity)     # before the state exists
    strategy.init_state(initial_count)  -> dict of arrays            # the strategy's own pytree
    strategy.after_step(ctx, state, sstate, it) -> (state, sstate, info)   # after every good step
    strategy.at_end(ctx, state, sstate)  -> (state, sstate, info)    # after the last step
    strategy.meta(sstate) -> dict                                    # JSON facts for the checkpoint

`it` counts completed iterations (the reference's 1-based counter). The strategy state is
saved with every checkpoint and restored on resume. Strategies:

- `default`: the 2DGS adaptive density control (clone / split / prune, opacity reset).
- `budget`: the same with new surfels per round capped by a schedule up to `max_surfels`.
- `mcmc`: 3DGS-MCMC (Kheradmand et al. 2024; gsplat's MCMCStrategy) on 2D surfels: dead
  (low-opacity) surfels are relocated onto live ones sampled by opacity, with the opacity and
  scale of the N copies corrected so their summed footprint matches the original; the count
  grows by `mcmc_grow_rate` per round up to `max_surfels`; noise on positions every step,
  gated by (1 - opacity) and scaled by the means learning rate; L1 opacity and scale
  regularisers in the loss (step.py, weights `lambda_opacity_reg`, `lambda_scale_reg`).

Any strategy can use contribution pruning (`contribution_prune`, run by the base hooks when the
config's `contrib_prune_*` fields say so): surfels whose blending weight summed over the
training views (in pixels) is below a threshold are removed.

A new strategy subclasses `Strategy`, overrides `refine` (and the other hooks it needs), and
registers itself with `@register("name")`; the config then accepts that name.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.core.precision import FLOAT32
from ghsplat_jax.core.quaternions import safe_normalize, to_rotation_matrix
from ghsplat_jax.train import densify, optim
from ghsplat_jax.train.state import INACTIVE_LOGIT, TrainState, fit_pool, grow, growth_bucket, render_params

log = logging.getLogger("ghsplat.train")

REGISTRY: dict[str, type["Strategy"]] = {}


def register(name: str):
    """Class decorator: make a Strategy subclass selectable as `strategy = name`."""
    def deco(cls):
        cls.name = name
        REGISTRY[name] = cls
        return cls
    return deco


def strategy_names() -> tuple[str, ...]:
    return tuple(REGISTRY)


def strategy_class(name: str) -> type["Strategy"]:
    """The registered class of `name`; ValueError naming the known ones otherwise."""
    if name not in REGISTRY:
        raise ValueError(f"strategy must be one of {strategy_names()}, got {name!r}")
    return REGISTRY[name]


def make_strategy(config) -> "Strategy":
    return strategy_class(config.strategy)(config)


@dataclasses.dataclass
class StrategyContext:
    """What the hooks may read of a run (host side; the session keeps it up to date)."""

    extent: float            # scene extent (the unit of positional settings)
    Ks: jax.Array            # (V,3,3) training intrinsics
    w2cs: jax.Array          # (V,4,4) training world-to-camera
    width: int
    height: int
    pair_capacity: int       # the training render's pair buffer (hooks that render may grow it)
    means_lr: Callable[[int], float]  # the means learning rate of a step
    raster: object           # the run's RasterConfig
    render_fn: Callable | None = None


@dataclasses.dataclass(frozen=True)
class Strategy:
    """Base strategy: no densification at all (a fixed set of surfels); hooks run contribution
    pruning when the config asks for it. Subclasses override `refine` and friends."""

    config: object  # the resolved TrainConfig
    name: ClassVar[str] = ""
    caps_count: ClassVar[bool] = False  # True: max_surfels is a hard cap (experiments may set it from a fraction)
    # Loss regulariser weights used when the config leaves them at -1 ("the strategy's default").
    loss_defaults: ClassVar[dict] = {"lambda_opacity_reg": 0.0, "lambda_scale_reg": 0.0}

    @classmethod
    def validate(cls, config) -> None:
        """Raise ValueError for settings this strategy cannot use (TrainConfig wraps it in ConfigError)."""

    # -- hooks ----------------------------------------------------------------------------
    def initial_pool(self, init, rng) -> tuple[object, int]:
        """(initial host Surfels, pool capacity)."""
        return init, max(self.config.initial_capacity, 2 * init.num, 1024)

    def init_state(self, initial_count: int) -> dict:
        return {"contrib_pruned": jnp.zeros((), jnp.int32)}

    def after_step(self, ctx: StrategyContext, state: TrainState, sstate: dict, it: int):
        state, sstate, info = self.refine(ctx, state, sstate, it)
        every = self.config.contrib_prune_every
        if every > 0 and it % every == 0 and it < self.config.steps:
            state, sstate, more = self.contribution_pass(ctx, state, sstate)
            info.update(more)
        return state, sstate, info

    def at_end(self, ctx: StrategyContext, state: TrainState, sstate: dict):
        if self.config.contrib_prune_final:
            return self.contribution_pass(ctx, state, sstate)
        return state, sstate, {}

    def refine(self, ctx, state, sstate, it):
        return state, sstate, {}

    def meta(self, sstate: dict) -> dict:
        return {"max_surfels": int(sstate.get("max_surfels", 0)), "strategy": self.name}

    # -- the reusable pruning pass --------------------------------------------------------
    def contribution_pass(self, ctx, state, sstate):
        c = self.config
        weight = accumulated_weights(ctx, state, c.contrib_prune_views, c.seed)
        state, n = contribution_prune(state, weight, jnp.float32(c.contrib_prune_threshold))
        n = int(n)
        sstate = dict(sstate, contrib_pruned=sstate["contrib_pruned"] + n)
        log.info("contribution pruning: %d surfels under %.3g px of blending weight removed", n,
                 c.contrib_prune_threshold)
        return state, sstate, {"contrib_pruned": n}


# ----------------------------------------------------------------------------- default / budget

@register("default")
@dataclasses.dataclass(frozen=True)
class DefaultStrategy(Strategy):
    """2DGS adaptive density control; the pool grows (one recompile per bucket) when needed."""

    def max_new(self, ctx, state, sstate, it: int, n_active: int) -> tuple[TrainState, int]:
        """(state, how many surfels this round may add)."""
        return self._ensure_capacity(ctx, state, n_active), state.capacity

    def refine(self, ctx, state, sstate, it):
        c = self.config
        info = {}
        if it >= c.densify_until:
            if it % c.densify_every == 0:  # the count no longer grows: drop the spare slots (checked
                state = self._fit_pool(state)  # each round, so a rolled-back step or a resume cannot skip it)
            return state, sstate, info
        white_bg = _white(c)
        if it > c.densify_from and it % c.densify_every == 0:
            n_active = int(jnp.sum(state.active))
            state, max_new = self.max_new(ctx, state, sstate, it, n_active)
            key = jax.random.fold_in(jax.random.PRNGKey(c.seed), it)
            prune_big = it > c.opacity_reset_every
            # Opacities just reset to 0.01 are below the prune threshold: give them time to recover.
            last = last_reset_before(c, it)
            prune_transparent = last is None or it - last >= c.reset_recovery_steps
            state, counts = densify.densify_jit(state, key, jnp.int32(max_new), jnp.bool_(prune_big),
                                                p=densify.DensifyParams.from_config(c, ctx.extent),
                                                prune_transparent=jnp.bool_(prune_transparent))
            info.update({k: int(v) for k, v in counts.items()})
        if is_opacity_reset(c, it):
            state = densify.reset_opacity_jit(state, value=c.opacity_reset_value)
            info["opacity_reset"] = True
        return state, sstate, info

    def _ensure_capacity(self, ctx, state, n_active: int) -> TrainState:
        """Grow the pool (a recompile per bucket) when the candidates would not fit."""
        c = self.config
        need = n_active + int(densify.count_candidates_jit(state, grad_threshold=float(c.densify_grad_threshold)))
        cap = state.capacity
        if need <= cap * (1.0 - c.capacity_headroom):
            return state
        # On a CPU pools take the pair buffer's buckets (1, 1.25, 1.5 or 1.75 x 2^k): one compile
        # each, and a pool at most 1.25x what it must hold, where doubling left up to half of the
        # per-surfel work (projection, SH, Adam) to spare slots. Accelerators double (state.py).
        new_cap = growth_bucket(math.ceil(need / (1.0 - c.capacity_headroom)))
        log.info("surfel pool %d -> %d slots", cap, new_cap)
        return grow(state, new_cap)

    @staticmethod
    def _fit_pool(state: TrainState) -> TrainState:
        """The pool fitted to the live surfels (a recompile when it shrinks)."""
        fitted = fit_pool(state)
        if fitted.capacity < state.capacity:
            log.info("densification over: surfel pool %d -> %d slots for %d surfels", state.capacity,
                     fitted.capacity, fitted.num_active())
        return fitted


def _capped_pool(config, init, rng) -> tuple[object, int]:
    """Initial surfels subsampled to the cap (max_surfels, 0: 5x the initial count); pool = cap."""
    cap = config.max_surfels or 5 * init.num
    if init.num > cap:
        init = init.take(np.sort(rng.choice(init.num, cap, replace=False)))
    return init, cap


@register("budget")
@dataclasses.dataclass(frozen=True)
class BudgetStrategy(DefaultStrategy):
    """2DGS densification with the count capped by a schedule (densify.budget_target)."""

    caps_count: ClassVar[bool] = True

    def initial_pool(self, init, rng):
        return _capped_pool(self.config, init, rng)

    def init_state(self, initial_count: int) -> dict:
        cap = self.config.max_surfels or 5 * initial_count
        return dict(super().init_state(initial_count), initial_count=jnp.int32(min(initial_count, cap)),
                    max_surfels=jnp.int32(cap))

    def max_new(self, ctx, state, sstate, it, n_active):
        target = densify.budget_target(self.config, it, int(sstate["initial_count"]), int(sstate["max_surfels"]))
        return state, max(target - n_active, 0)


# ----------------------------------------------------------------------------------- mcmc

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


def relocate(state: TrainState, key: jax.Array, targets: jax.Array, min_opacity: float) -> tuple[TrainState, dict]:
    """Fill the slots `targets` (dead or free) with copies of live surfels sampled in proportion
    to their opacity; sources and copies get the corrected opacity and scales and fresh Adam
    moments. Only target rows change position; no shapes change."""
    cap = state.capacity
    p = state.params
    op = jax.nn.sigmoid(p.opacity_logits)
    alive = state.active & (op > min_opacity) & ~targets
    any_alive = jnp.any(alive)
    targets = targets & any_alive
    src = jnp.where(targets, sample_in_proportion(key, jnp.where(alive, op, 0.0)), jnp.arange(cap))
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


def mcmc_round(state: TrainState, key: jax.Array, cap: jax.Array, min_opacity: float, grow_rate: float):
    """One MCMC refinement: relocate dead surfels, then grow by grow_rate up to `cap` live ones."""
    op = jax.nn.sigmoid(state.params.opacity_logits)
    dead = state.active & (op <= min_opacity)
    k1, k2 = jax.random.split(key)
    state, r = relocate(state, k1, dead, min_opacity)
    n = jnp.sum(state.active).astype(jnp.int32)
    target = jnp.minimum(cap, jnp.floor(n.astype(jnp.float32) * (1.0 + grow_rate)).astype(jnp.int32))
    free = ~state.active
    add = free & (jnp.cumsum(free) <= jnp.maximum(target - n, 0))
    state, a = relocate(state, k2, add, min_opacity)
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


@register("mcmc")
@dataclasses.dataclass(frozen=True)
class MCMCStrategy(Strategy):
    """3DGS-MCMC on 2D surfels: a fixed pool of max_surfels slots, relocation of dead surfels and
    growth up to the cap every densify_every steps in [densify_from, densify_until), position noise
    every step; no clone/split and no opacity reset."""

    loss_defaults: ClassVar[dict] = {"lambda_opacity_reg": 0.01, "lambda_scale_reg": 0.01}
    caps_count: ClassVar[bool] = True

    @classmethod
    def validate(cls, config) -> None:
        if not 0 < config.mcmc_min_opacity < 1:
            raise ValueError(f"mcmc_min_opacity must be in (0, 1), got {config.mcmc_min_opacity}")
        if config.mcmc_grow_rate < 0:
            raise ValueError(f"mcmc_grow_rate must be >= 0, got {config.mcmc_grow_rate}")
        if config.mcmc_noise_lr < 0:
            raise ValueError(f"mcmc_noise_lr must be >= 0, got {config.mcmc_noise_lr}")

    def initial_pool(self, init, rng):
        return _capped_pool(self.config, init, rng)

    def init_state(self, initial_count: int) -> dict:
        cap = self.config.max_surfels or 5 * initial_count
        return dict(super().init_state(initial_count), max_surfels=jnp.int32(cap),
                    relocated=jnp.zeros((), jnp.int32), added=jnp.zeros((), jnp.int32))

    def refine(self, ctx, state, sstate, it):
        c = self.config
        info = {}
        if c.densify_from < it < c.densify_until and it % c.densify_every == 0:
            key = jax.random.fold_in(jax.random.PRNGKey(c.seed), it)
            state, counts = mcmc_round_jit(state, key, sstate["max_surfels"], min_opacity=float(c.mcmc_min_opacity),
                                           grow_rate=float(c.mcmc_grow_rate))
            counts = {k: int(v) for k, v in counts.items()}
            sstate = dict(sstate, relocated=sstate["relocated"] + counts["relocated"],
                          added=sstate["added"] + counts["added"])
            info.update(counts)
        if c.mcmc_noise_lr > 0:
            key = jax.random.fold_in(jax.random.PRNGKey(c.seed + 1), it)
            state = mcmc_noise_jit(state, key, jnp.float32(c.mcmc_noise_lr * ctx.means_lr(it - 1)))
        return state, sstate, info


# ------------------------------------------------------------------- contribution pruning

def _view_weights(params, active, K, w2c, probe_cfg, width: int, height: int, render_fn):
    """(cap,) blending weight of each surfel summed over the pixels of one view, and the overflow:
    the gradient of the red channel's sum with respect to a constant added to every surfel's
    red DC coefficient (colour 0.5 everywhere, so the clamp at 0 never cuts the gradient)."""
    from ghsplat_jax.core.camera import Camera
    from ghsplat_jax.core.sh import C0

    cam = Camera(K, w2c, width, height)
    p = render_params(params, active, w2c)
    p = dataclasses.replace(p, sh_dc=jnp.zeros_like(p.sh_dc), sh_rest=jnp.zeros_like(p.sh_rest))

    def red(z):
        q = dataclasses.replace(p, sh_dc=p.sh_dc.at[:, 0].add(z))
        out = render_fn(q, cam, probe_cfg)
        return jnp.sum(out.rgb[..., 0]), out.stats.overflow

    g, overflow = jax.grad(red, has_aux=True)(jnp.zeros(active.shape[0], jnp.float32))
    return jnp.where(active, g / C0, 0.0), overflow


_view_weights_jit = jax.jit(_view_weights, static_argnames=("probe_cfg", "width", "height", "render_fn"))


def accumulated_weights(ctx: StrategyContext, state: TrainState, max_views: int = 0, seed: int = 0) -> jax.Array:
    """(cap,) blending weight summed over the training views (all, or `max_views` chosen with
    `seed`), in pixels; grows ctx.pair_capacity and redoes a view whose pair buffer overflowed."""
    render_fn = ctx.render_fn
    if render_fn is None:
        from ghsplat_jax.raster.render import render as render_fn
    nv = ctx.Ks.shape[0]
    views = np.arange(nv)
    if 0 < max_views < nv:
        views = np.sort(np.random.default_rng(seed).choice(nv, max_views, replace=False))
    total = jnp.zeros(state.capacity, jnp.float32)
    for v in views:
        while True:
            cfg = dataclasses.replace(ctx.raster, pair_capacity=ctx.pair_capacity, on_overflow="report",
                                      median=False, distortion=False)
            w, overflow = _view_weights_jit(state.params, state.active, ctx.Ks[v], ctx.w2cs[v], cfg, ctx.width,
                                            ctx.height, render_fn)
            if int(overflow) <= 0:
                break
            ctx.pair_capacity *= 2
        total = total + w
    return total


@jax.jit
def contribution_prune(state: TrainState, weight: jax.Array, threshold: jax.Array) -> tuple[TrainState, jax.Array]:
    """Free the slots of live surfels whose accumulated weight is under `threshold`."""
    prune = state.active & (weight < threshold)
    params = dataclasses.replace(state.params,
                                 opacity_logits=jnp.where(prune, INACTIVE_LOGIT, state.params.opacity_logits))
    new = dataclasses.replace(state, params=params, active=state.active & ~prune,
                              opt_state=optim.reset_rows(state.opt_state, prune))
    return new, jnp.sum(prune)


# ----------------------------------------------------------------------------- helpers

def _white(c) -> bool:
    return all(b == 1.0 for b in c.raster.background)


def is_opacity_reset(c, it: int) -> bool:
    """Whether the round after step `it` resets opacities: every `opacity_reset_every` steps before
    densify_until, and at densify_from on white backgrounds (2DGS); but not within
    `reset_recovery_steps` of the run's last step, which would end on nearly transparent surfels
    (2DGS resets at step 3000 of a 3000-step run: on the demo row that run ended at 8.2 dB test PSNR)."""
    if c.opacity_reset_every <= 0 or it >= c.densify_until or c.steps - it < c.reset_recovery_steps:
        return False
    return it % c.opacity_reset_every == 0 or (_white(c) and it == c.densify_from)


def last_reset_before(c, it: int) -> int | None:
    """The iteration of the last opacity reset before `it` (None when there was none)."""
    if c.opacity_reset_every <= 0:
        return None
    k = (min(it - 1, c.densify_until - 1)) // c.opacity_reset_every
    candidates = [k * c.opacity_reset_every, (k - 1) * c.opacity_reset_every, c.densify_from]
    return max((r for r in candidates if 0 < r < it and is_opacity_reset(c, r)), default=None)


def loss_weight(config, name: str) -> float:
    """A regulariser weight of the config, or the strategy's default where it is -1."""
    v = getattr(config, name)
    return float(strategy_class(config.strategy).loss_defaults[name] if v < 0 else v)
