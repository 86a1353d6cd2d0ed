"""Removing surfels: freeing slots, and compaction, the fewest surfels that keep a finished
model's held-out PSNR.

A trained model holds many surfels that add almost nothing to any view. On row2_x1 (the auto
recipe's seed-0 model, 55,296 surfels at 192x144) a quarter of them carry under 0.15 px of
blending weight summed over the 43 training views, over a tenth none at all (outside every view or
behind opaque surfaces), and removing the 30% of least weight left the test PSNR where it was
(29.39 dB; 40% cost 0.29 dB). Compaction ranks the live surfels by that weight and removes the
largest lowest-ranked share whose removal costs at most `max_loss_db` of validation PSNR. The
loss grows with the share removed, so bisection finds it in about ten validation renders of the
held-out views. Nothing is retrained: it only removes.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import jax.numpy as jnp

from ghsplat_jax.train import optim
from ghsplat_jax.train.state import INACTIVE_LOGIT, TrainState, fit_pool

MAX_SHARE = 0.9         # compaction never removes more than this share of the live surfels
SHARE_RESOLUTION = 1 / 256  # bisection stops when the bracket is this share of the count


@jax.jit
def free_slots(state: TrainState, mask: jax.Array) -> TrainState:
    """`state` with the slots in `mask` freed: transparent, inactive, fresh Adam moments."""
    params = dataclasses.replace(state.params,
                                 opacity_logits=jnp.where(mask, INACTIVE_LOGIT, state.params.opacity_logits))
    return dataclasses.replace(state, params=params, active=state.active & ~mask,
                               opt_state=optim.reset_rows(state.opt_state, mask))


@jax.jit
def lowest_mask(active: jax.Array, weight: jax.Array, k: jax.Array) -> jax.Array:
    """(cap,) the k live slots of least weight (ties: lower slot first)."""
    order = jnp.argsort(jnp.where(active, weight, jnp.inf), stable=True)
    rank = jnp.zeros(active.shape[0], jnp.int32).at[order].set(jnp.arange(active.shape[0], dtype=jnp.int32))
    return active & (rank < k)


def largest_safe_count(loss_of: Callable[[int], float], count: int, max_loss_db: float,
                       max_share: float = MAX_SHARE, resolution: float = SHARE_RESOLUTION) -> int:
    """The largest k in [0, max_share x count] with loss_of(k) <= max_loss_db, by bisection on a
    loss that grows with k (within `resolution` x count of it; 0 when even that loses too much)."""
    lo, hi = 0, math.floor(max_share * count)
    if hi <= 0 or loss_of(hi) <= max_loss_db:
        return max(hi, 0)
    step = max(1, math.floor(resolution * count))
    while hi - lo > step:
        mid = (lo + hi) // 2
        if loss_of(mid) <= max_loss_db:
            lo = mid
        else:
            hi = mid
    return lo


def compact_model(state: TrainState, weight: jax.Array, validate: Callable[[TrainState], float],
                  max_loss_db: float) -> tuple[TrainState, dict]:
    """(state without its least-weighted surfels, in the smallest pool that holds the rest; the
    record: counts and validation PSNR before and after). `weight`: (cap,) each slot's blending
    weight over the training views; `validate`: a state's validation PSNR."""
    count = state.num_active()
    before = validate(state)
    psnr_at = {0: before}

    def loss_of(k: int) -> float:
        psnr_at[k] = validate(free_slots(state, lowest_mask(state.active, weight, jnp.int32(k))))
        return before - psnr_at[k]

    k = largest_safe_count(loss_of, count, max_loss_db)  # a count it judged: psnr_at holds it
    if k:
        state = fit_pool(free_slots(state, lowest_mask(state.active, weight, jnp.int32(k))))
    return state, {"before": count, "after": count - k, "val_psnr_before": float(before),
                   "val_psnr_after": float(psnr_at[k]), "max_loss_db": float(max_loss_db),
                   "validations": len(psnr_at)}
