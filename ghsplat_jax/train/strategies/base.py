"""The strategy interface: settings dataclasses, the registry, the hooks' context and the
pieces every strategy may use (contribution pruning, the opacity-reset calendar).

A strategy is two classes: its settings (a frozen dataclass, the `[strategy]` table of a
config: `name` plus the strategy's own fields) and its hooks (gsplat's `Strategy`), which
the trainer calls and never branches on:

    strategy.initial_pool(surfels, rng) -> (surfels, capacity)     # before the state exists
    strategy.init_state(initial_count)  -> dict of arrays            # the strategy's own pytree
    strategy.after_step(ctx, state, sstate, it) -> (state, sstate, info)   # after every good step
    strategy.on_validation(ctx, state, sstate, it, val) -> (sstate, info)  # after a validation check
    strategy.at_end(ctx, state, sstate)  -> (state, sstate, info)    # after the last step
    strategy.meta(sstate) -> dict                                    # JSON facts for the checkpoint

`it` counts completed iterations (the reference's 1-based counter). The strategy state is
saved with every checkpoint and restored on resume.

A new strategy subclasses `StrategySettings` and `Strategy`, and registers the pair with
`@register("name", SettingsClass)`; configs then accept `strategy = "name"` or a
`[strategy]` table with `name = "name"` and the settings' fields.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.train.compaction import free_slots
from ghsplat_jax.train.state import TrainState, grow, growth_bucket, render_params

log = logging.getLogger("ghsplat.train")

REGISTRY: dict[str, type["Strategy"]] = {}


@dataclasses.dataclass(frozen=True)
class StrategySettings:
    """Settings every strategy has: contribution pruning, which removes surfels whose blending
    weight summed over the training views (alpha x transmittance, in pixels) is small.

    Args:
        contrib_prune_every: prune every this many steps (0: never; scaled by scale_schedule).
        contrib_prune_final: prune once more after the last step.
        contrib_prune_threshold: pixels' worth of weight over all the views counted.
        contrib_prune_views: training views to count (0: all; else a seeded subset).
    """

    name: ClassVar[str] = ""
    contrib_prune_every: int = 0
    contrib_prune_final: bool = False
    contrib_prune_threshold: float = 1.0
    contrib_prune_views: int = 0

    def validate(self) -> None:
        """Raise ValueError for settings that cannot work (the config wraps it in ConfigError)."""
        if self.contrib_prune_every < 0 or self.contrib_prune_views < 0 or self.contrib_prune_threshold < 0:
            raise ValueError("contrib_prune_every, contrib_prune_views and contrib_prune_threshold must be >= 0, got "
                             f"{self.contrib_prune_every}, {self.contrib_prune_views}, {self.contrib_prune_threshold}")

    def to_dict(self) -> dict:
        """The `[strategy]` table: the name first, then every field."""
        return {"name": self.name} | dataclasses.asdict(self)


def register(name: str, settings: type[StrategySettings]):
    """Class decorator: make a Strategy subclass selectable as `strategy = name`, with `settings`
    (a StrategySettings subclass of its own) as its `[strategy]` table."""
    def deco(cls):
        cls.name = name
        cls.settings_class = settings
        settings.name = name
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


def settings_from(table: dict | str) -> StrategySettings:
    """The settings of a `[strategy]` table (or a bare name: its defaults); ValueError naming
    an unknown strategy or field."""
    table = {"name": table} if isinstance(table, str) else dict(table)
    name = table.pop("name", None)
    if name is None:
        raise ValueError(f"a [strategy] table needs a name (one of {strategy_names()})")
    cls = strategy_class(name).settings_class
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise ValueError(f"strategy {name!r} has no setting {unknown[0]!r} (its settings: {sorted(fields)})")
    return cls(**table)


def make_strategy(config) -> "Strategy":
    return strategy_class(config.strategy.name)(config)


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
    validate: Callable[[TrainState], float] | None = None  # held-out views' mean PSNR of a state (runs with
                                                           # a validation split; else None)
    train_copy: Callable[[TrainState, int, int], TrainState] | None = None  # (state, start, steps): a state
                                                           # trained on as the run would, hooks left out


def starting_pool(initial_count: int) -> int:
    """The first pool of a strategy whose count grows: the initial surfels and a quarter more, in
    the pool's buckets (growth_bucket); it grows with the count (grow_pool)."""
    return growth_bucket(max(math.ceil(1.25 * initial_count), 1024))


def grow_pool(state: TrainState, need: int, limit: float = math.inf) -> TrainState:
    """`state` in a pool that holds `need` surfels: at least doubled when it grows (each new pool
    compiles the step and the validation renders again, and a count growing 5-10% a round would
    cross a 1.25x bucket every other round), but not past the bucket of `limit` (a hard cap on the
    count, which a doubling would overshoot by up to 2x for the rest of the run)."""
    if need <= state.capacity:
        return state
    new_cap = growth_bucket(max(need, min(2 * state.capacity, limit)))
    log.info("surfel pool %d -> %d slots", state.capacity, new_cap)
    return grow(state, new_cap)


@dataclasses.dataclass(frozen=True)
class Strategy:
    """Base strategy: no densification at all (a fixed set of surfels); hooks run contribution
    pruning when the settings ask for it. Subclasses override `refine` and friends."""

    config: object  # the resolved TrainConfig; `config.strategy` holds this strategy's settings
    name: ClassVar[str] = ""
    settings_class: ClassVar[type[StrategySettings]] = StrategySettings
    caps_count: ClassVar[bool] = False  # True: `max_surfels` is a hard cap (experiments may set it from a fraction)
    # Loss regulariser weights used when the config leaves them at -1 ("the strategy's default").
    loss_defaults: ClassVar[dict] = {"lambda_opacity_reg": 0.0, "lambda_scale_reg": 0.0}

    @property
    def settings(self):
        return self.config.strategy

    # -- hooks ----------------------------------------------------------------------------
    def initial_pool(self, init, rng) -> tuple[object, int]:
        """(initial host Surfels, pool capacity)."""
        return init, max(self.config.initial_capacity, 2 * init.num, 1024)

    def init_state(self, initial_count: int) -> dict:
        return {"contrib_pruned": jnp.zeros((), jnp.int32)}

    def after_step(self, ctx: StrategyContext, state: TrainState, sstate: dict, it: int):
        state, sstate, info = self.refine(ctx, state, sstate, it)
        every = self.settings.contrib_prune_every
        if every > 0 and it % every == 0 and it < self.config.steps:
            state, sstate, more = self.contribution_pass(ctx, state, sstate)
            info.update(more)
        return state, sstate, info

    def on_validation(self, ctx: StrategyContext, state: TrainState, sstate: dict, it: int, val: dict):
        """After a validation check (`val`: the held-out views' metrics): (sstate, info)."""
        return sstate, {}

    def schedule_step(self, sstate: dict, step: int) -> int:
        """The step whose means learning rate training step `step` uses (a strategy may rewind
        the schedule: the auto strategy's `rewind_lr`)."""
        return step

    def on_plateau(self, ctx: StrategyContext, state: TrainState, sstate: dict, it: int, best_psnr: float):
        """When the stop rule would anneal or stop (validation flat; `best_psnr` its best so far):
        (sstate, True to grow instead and keep the rule from acting, info)."""
        return sstate, False, {}

    def at_end(self, ctx: StrategyContext, state: TrainState, sstate: dict):
        if self.settings.contrib_prune_final:
            return self.contribution_pass(ctx, state, sstate)
        return state, sstate, {}

    def refine(self, ctx, state, sstate, it):
        return state, sstate, {}

    def meta(self, sstate: dict) -> dict:
        return {"max_surfels": int(sstate.get("max_surfels", 0)), "strategy": self.name}

    def report(self, sstate: dict) -> dict:
        """Facts of the finished run for metrics.json (JSON values; none by default)."""
        return {}

    # -- the reusable pruning pass --------------------------------------------------------
    def contribution_pass(self, ctx, state, sstate):
        s = self.settings
        weight = accumulated_weights(ctx, state, s.contrib_prune_views, self.config.seed)
        state, n = contribution_prune(state, weight, jnp.float32(s.contrib_prune_threshold))
        n = int(n)
        sstate = dict(sstate, contrib_pruned=sstate["contrib_pruned"] + n)
        log.info("contribution pruning: %d surfels under %.3g px of blending weight removed", n,
                 s.contrib_prune_threshold)
        return state, sstate, {"contrib_pruned": n}



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
    return free_slots(state, prune), jnp.sum(prune)


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
    return float(strategy_class(config.strategy.name).loss_defaults[name] if v < 0 else v)
