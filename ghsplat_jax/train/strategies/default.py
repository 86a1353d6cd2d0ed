"""The 2DGS adaptive density control (clone / split / prune, opacity reset) and its budgeted
variant, whose new surfels per round are capped by a schedule up to `max_surfels`."""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.train import densify
from ghsplat_jax.train.state import TrainState, fit_pool, grow, growth_bucket
from ghsplat_jax.train.strategies.base import (
    Strategy,
    StrategySettings,
    grow_pool,
    is_opacity_reset,
    last_reset_before,
    log,
    register,
    starting_pool,
)


@dataclasses.dataclass(frozen=True)
class DefaultSettings(StrategySettings):
    """The 2DGS adaptive density control. Its schedule and thresholds (densify_from,
    densify_until, densify_every, densify_grad_threshold, percent_dense, prune_*,
    opacity_reset_*) are the config's, shared with every strategy that refines.

    Args: those of StrategySettings (contribution pruning).
    """


@dataclasses.dataclass(frozen=True)
class BudgetSettings(StrategySettings):
    """2DGS densification with the count capped by a schedule.

    Args:
        max_surfels: the hard cap on the count (0: 5x the initial count).
        schedule: "linear" growth of the allowed count from the initial count to the cap by
            densify_until, or "immediate" (the cap is available from densify_from).
    """

    max_surfels: int = 0
    schedule: str = "linear"

    def validate(self) -> None:
        super().validate()
        if self.max_surfels < 0:
            raise ValueError(f"max_surfels must be >= 0 (0: 5x the initial count), got {self.max_surfels}")
        if self.schedule not in ("linear", "immediate"):
            raise ValueError(f"the budget schedule must be 'linear' or 'immediate', got {self.schedule!r}")


@register("default", DefaultSettings)
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


def count_cap(max_surfels: int, initial_count: int) -> int:
    """The cap on the live count of a strategy that caps it: max_surfels, 0 for 5x the initial count."""
    return max_surfels or 5 * initial_count


def capped_start(max_surfels: int, init, rng) -> tuple[object, int]:
    """(initial surfels subsampled to the cap (count_cap), the first pool): the initial count and
    a quarter (starting_pool), at most the cap; the pool grows with the count (grow_pool)."""
    cap = count_cap(max_surfels, init.num)
    if init.num > cap:
        init = init.take(np.sort(rng.choice(init.num, cap, replace=False)))
    return init, min(cap, starting_pool(init.num))


@register("budget", BudgetSettings)
@dataclasses.dataclass(frozen=True)
class BudgetStrategy(DefaultStrategy):
    """2DGS densification with the count capped by a schedule (densify.budget_target). The pool
    grows with the schedule's target, as MCMC's does, rather than holding the cap from step 0."""

    caps_count: ClassVar[bool] = True

    def initial_pool(self, init, rng):
        return capped_start(self.settings.max_surfels, init, rng)

    def init_state(self, initial_count: int) -> dict:
        cap = count_cap(self.settings.max_surfels, initial_count)
        return dict(super().init_state(initial_count), initial_count=jnp.int32(min(initial_count, cap)),
                    max_surfels=jnp.int32(cap))

    def max_new(self, ctx, state, sstate, it, n_active):
        cap = int(sstate["max_surfels"])
        target = densify.budget_target(self.config, self.settings.schedule, it, int(sstate["initial_count"]), cap)
        new = max(target - n_active, 0)
        return grow_pool(state, n_active + new, limit=cap), new


# ----------------------------------------------------------------------------------- mcmc

