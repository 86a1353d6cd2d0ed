"""A strategy that sizes its own model: MCMC's relocation and regularisers, growth drawn to where
the error is, and a count that stops growing when the held-out views stop paying for it.

Every refinement round (each `densify_every` steps from `densify_from`) relocates dead surfels
and, while the model grows, adds `grow_rate` of the live count. New surfels copy live ones drawn
in proportion to opacity x their mean projected-centre gradient since the last round: the
gradient says where the image error pulls on the model (FastGS and Taming 3DGS grow where the
error is; as a sampling weight, not a threshold, it does not depend on the image size as the
2DGS gradient threshold does).

Growth stops by a rate-distortion rule. The validation checks (the trainer renders views held
out of training) are read at full resolution only. Once the count has grown by half a doubling
(x1.41) since the reference check, the gain in validation PSNR since that check is divided by
the growth in doublings; when a doubling buys less than `min_gain_db`, the count is frozen for
the rest of the run (relocation and noise go on), else the check becomes the new reference.
Two things keep one noisy check from deciding: the span of half a doubling (between consecutive
checks the count grows 20-30%, and a 0.2 dB dip then reads as a dB per doubling), and the better
of the last two checks standing for "now" (a check right after a growth round dips while the
new surfels settle). `max_surfels` is a safety ceiling only (0: one surfel per pixel of a
training image x `ceiling_per_pixel`).

At the end (after the stop rule has restored its best check's model), compaction removes the
surfels that carry least blending weight over the training views, as many as cost at most
`compact_max_loss_db` of validation PSNR (train/compaction.py): growth judged on a converging
model overshoots, and a quarter or more of a finished model adds next to nothing to any view.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import ClassVar

import jax
import jax.numpy as jnp

from ghsplat_jax.train import densify
from ghsplat_jax.train.compaction import compact_model
from ghsplat_jax.train.state import TrainState, fit_pool, grow, growth_bucket
from ghsplat_jax.train.strategies.base import accumulated_weights, register
from ghsplat_jax.train.strategies.mcmc import MCMCSettings, MCMCStrategy, mcmc_round

log = logging.getLogger("ghsplat.train")

GROWTH_WEIGHTS = ("error", "opacity")


@dataclasses.dataclass(frozen=True)
class AutoSettings(MCMCSettings):
    """The self-sizing strategy (`recipe = "auto"` uses it).

    Args:
        min_gain_db: stop growing when a doubling of the count gains less validation PSNR than
            this (dB), measured between consecutive validation checks.
        grow_rate: while growing, each refinement round adds this fraction of the live count.
        growth_weight: "error" draws new surfels by opacity x mean projected-centre gradient,
            "opacity" by opacity alone (3DGS-MCMC).
        max_surfels: a safety ceiling on the count (0: `ceiling_per_pixel` x the pixels of one
            training image); the validation rule is meant to stop growth well before it.
        ceiling_per_pixel: the ceiling when max_surfels is 0.
        compact: at the end, remove the surfels of least blending weight over the training views
            that validation can spare (needs a validation split: val_every > 0).
        compact_max_loss_db: the validation PSNR compaction may cost (dB).
        compact_at_freeze: compact also when the count stops growing (the surfels that are left
            train on, the freed slots stay empty), so the rest of the run steps with fewer.
        min_opacity, noise_lr: as MCMCSettings.
    """

    grow_rate: float = 0.1
    min_gain_db: float = 0.5
    growth_weight: str = "error"
    ceiling_per_pixel: float = 2.0
    compact: bool = True
    compact_max_loss_db: float = 0.05
    compact_at_freeze: bool = False

    def validate(self) -> None:
        super().validate()
        if self.min_gain_db < 0:
            raise ValueError(f"min_gain_db must be >= 0, got {self.min_gain_db}")
        if not self.grow_rate > 0:
            raise ValueError(f"grow_rate must be positive, got {self.grow_rate}")
        if self.growth_weight not in GROWTH_WEIGHTS:
            raise ValueError(f"growth_weight must be one of {GROWTH_WEIGHTS}, got {self.growth_weight!r}")
        if not self.ceiling_per_pixel > 0:
            raise ValueError(f"ceiling_per_pixel must be positive, got {self.ceiling_per_pixel}")
        if not self.compact_max_loss_db >= 0:
            raise ValueError(f"compact_max_loss_db must be >= 0, got {self.compact_max_loss_db}")


def growth_weights(state: TrainState, kind: str) -> jax.Array:
    """Sampling weight of each slot as a source of new surfels (see the module docstring)."""
    op = jax.nn.sigmoid(state.params.opacity_logits)
    if kind == "opacity":
        return op
    g = densify.mean_grad(state)
    seen = state.active & (state.grad_count > 0)
    mean = jnp.sum(jnp.where(seen, g, 0.0)) / jnp.maximum(jnp.sum(seen), 1)
    # Surfels no view saw since the last round keep the average pull (they are not known to be fitted).
    g = jnp.where(seen, g, mean)
    return op * g / jnp.maximum(mean, 1e-12)


def auto_round(state: TrainState, key: jax.Array, cap: jax.Array, min_opacity: float, grow_rate: float,
               kind: str):
    """Relocate the dead, grow by grow_rate up to `cap`, then restart the gradient statistics."""
    state, counts = mcmc_round(state, key, cap, min_opacity, grow_rate, growth_weights(state, kind))
    zeros = jnp.zeros_like(state.grad_accum)
    return dataclasses.replace(state, grad_accum=zeros, grad_count=zeros), counts


auto_round_jit = jax.jit(auto_round, static_argnames=("min_opacity", "grow_rate", "kind"))


MIN_SPAN_DOUBLINGS = 0.5  # the growth between two checks the rule compares (see the module docstring)


def gain_per_doubling(prev: tuple[int, float], now: tuple[int, float],
                      min_span: float = MIN_SPAN_DOUBLINGS) -> float | None:
    """Validation PSNR gained per doubling of the count between two (count, psnr) checks; None
    when the count grew by less than `min_span` doublings, too little to judge its worth."""
    doublings = math.log2(max(now[0], 1) / max(prev[0], 1))
    if doublings < min_span:
        return None
    return (now[1] - prev[1]) / doublings


@register("auto", AutoSettings)
@dataclasses.dataclass(frozen=True)
class AutoStrategy(MCMCStrategy):
    """See the module docstring: MCMC refinement with error-drawn growth and a count that stops
    growing when validation says a doubling is worth less than `min_gain_db`."""

    caps_count: ClassVar[bool] = False

    def initial_pool(self, init, rng):
        return init, growth_bucket(max(math.ceil(1.25 * init.num), 1024))

    def init_state(self, initial_count: int) -> dict:
        base = super(MCMCStrategy, self).init_state(initial_count)
        return dict(base, max_surfels=jnp.int32(self.settings.max_surfels), growing=jnp.int32(1),
                    relocated=jnp.zeros((), jnp.int32), added=jnp.zeros((), jnp.int32),
                    checked_count=jnp.int32(0), checked_psnr=jnp.float32(0.0), last_psnr=jnp.float32(-jnp.inf),
                    frozen_at=jnp.int32(0), compacted_from=jnp.int32(0), compacted_to=jnp.int32(0),
                    compact_val_before=jnp.float32(0.0), compact_val_after=jnp.float32(0.0),
                    compact_due=jnp.int32(0), freeze_compacted_from=jnp.int32(0), freeze_compacted_to=jnp.int32(0))

    def ceiling(self, ctx, sstate) -> int:
        s = self.settings
        return int(sstate["max_surfels"]) or int(s.ceiling_per_pixel * ctx.width * ctx.height)

    def refine(self, ctx, state, sstate, it):
        c, s = self.config, self.settings
        info = {}
        if int(sstate["compact_due"]) and ctx.validate is not None:
            state, rec = self.compact(ctx, state, f"step {it}, the count frozen")
            sstate = dict(sstate, compact_due=jnp.int32(0), freeze_compacted_from=jnp.int32(rec["before"]),
                          freeze_compacted_to=jnp.int32(rec["after"]))
            info["compacted"] = rec["before"] - rec["after"]
        if it > c.densify_from and it % c.densify_every == 0:
            n = state.num_active()
            growing = bool(sstate["growing"])
            cap = min(math.floor(n * (1 + s.grow_rate)), self.ceiling(ctx, sstate)) if growing else n
            if cap > state.capacity:
                # Doubling: each new pool compiles the step (and the validation renders) again, and a
                # count that grows 10% a round would cross a 1.25x bucket every other round.
                new_cap = growth_bucket(max(2 * state.capacity, math.ceil(cap / (1.0 - c.capacity_headroom))))
                log.info("surfel pool %d -> %d slots", state.capacity, new_cap)
                state = grow(state, new_cap)
            elif not growing and (fitted := fit_pool(state)) is not state:
                log.info("the count is final: surfel pool %d -> %d slots", state.capacity, fitted.capacity)
                state = fitted
            key = jax.random.fold_in(jax.random.PRNGKey(c.seed), it)
            state, counts = auto_round_jit(state, key, jnp.int32(cap), min_opacity=float(s.min_opacity),
                                           grow_rate=float(s.grow_rate) if growing else 0.0, kind=s.growth_weight)
            sstate = self.count_round(sstate, counts, info)
        return self.add_noise(ctx, state, it), sstate, info

    def on_validation(self, ctx, state, sstate, it, val):
        if not bool(sstate["growing"]) or val.get("train_scale", 1) != 1:
            return sstate, {}  # at reduced resolution the held-out views cannot judge the count
        psnr = float(val["psnr"])
        now = (state.num_active(), max(psnr, float(sstate["last_psnr"])))
        sstate = dict(sstate, last_psnr=jnp.float32(psnr))
        ref = (int(sstate["checked_count"]), float(sstate["checked_psnr"]))
        gain = gain_per_doubling(ref, now) if ref[0] else None
        at_ceiling = now[0] >= self.ceiling(ctx, sstate)
        if gain is None and ref[0] and not at_ceiling:
            return sstate, {}  # the count has not grown enough since the reference check to judge it
        sstate = dict(sstate, checked_count=jnp.int32(now[0]), checked_psnr=jnp.float32(now[1]))
        if (gain is not None and gain < self.settings.min_gain_db) or at_ceiling:
            why = (f"the ceiling of {self.ceiling(ctx, sstate)}" if at_ceiling else
                   f"{gain:.2f} dB of validation PSNR per doubling (under {self.settings.min_gain_db})")
            log.info("step %d: the count stops growing at %d surfels: %s", it, now[0], why)
            sstate = dict(sstate, growing=jnp.int32(0), frozen_at=jnp.int32(it),
                          compact_due=jnp.int32(int(self.settings.compact_at_freeze)))
            return sstate, {"growth_stopped": now[0]}
        return sstate, {}

    def at_end(self, ctx, state, sstate):
        state, sstate, info = super().at_end(ctx, state, sstate)
        s = self.settings
        if not s.compact or ctx.validate is None:
            return state, sstate, info
        state, rec = self.compact(ctx, state, "the end")
        sstate = dict(sstate, compacted_from=jnp.int32(rec["before"]), compacted_to=jnp.int32(rec["after"]),
                      compact_val_before=jnp.float32(rec["val_psnr_before"]),
                      compact_val_after=jnp.float32(rec["val_psnr_after"]))
        return state, sstate, info | {"compacted": rec["before"] - rec["after"]}

    def compact(self, ctx, state, when: str):
        """compact_model on the training views' blending weights, logged."""
        state, rec = compact_model(state, accumulated_weights(ctx, state), ctx.validate,
                                   self.settings.compact_max_loss_db)
        log.info("compaction at %s: %d -> %d surfels (the least blending weight over the training views); "
                 "validation PSNR %.2f -> %.2f dB (%d checks)", when, rec["before"], rec["after"],
                 rec["val_psnr_before"], rec["val_psnr_after"], rec["validations"])
        return state, rec

    def meta(self, sstate: dict) -> dict:
        return super().meta(sstate) | {"growing": bool(sstate["growing"]), "frozen_at": int(sstate["frozen_at"])}

    def report(self, sstate: dict) -> dict:
        if not int(sstate.get("compacted_from", 0)):
            return {}
        record = {"before": int(sstate["compacted_from"]), "after": int(sstate["compacted_to"]),
                  "val_psnr_before": round(float(sstate["compact_val_before"]), 4),
                  "val_psnr_after": round(float(sstate["compact_val_after"]), 4),
                  "max_loss_db": self.settings.compact_max_loss_db}
        if int(sstate.get("freeze_compacted_from", 0)):
            record["at_freeze"] = {"step": int(sstate["frozen_at"]), "before": int(sstate["freeze_compacted_from"]),
                                   "after": int(sstate["freeze_compacted_to"])}
        return {"compaction": record}
