"""Adaptive density control (2DGS defaults) as pure functions on the fixed-capacity state.

Clone, split, prune and opacity reset never change array shapes: new surfels take free
slots found with a cumulative sum, pruned surfels free theirs, so densification compiles
once per pool capacity. The budgeted strategy is the same machinery with the number of
new surfels per round capped by a schedule (a fixed budget, as in Taming-3DGS).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from ghsplat_jax.core.precision import FLOAT32
from ghsplat_jax.core.quaternions import safe_normalize, to_rotation_matrix
from ghsplat_jax.train import optim
from ghsplat_jax.train.state import INACTIVE_LOGIT, TrainState


@dataclasses.dataclass(frozen=True)
class DensifyParams:
    """The static numbers densification needs (hashable: a jit static argument)."""

    grad_threshold: float
    clone_max_scale: float   # percent_dense x extent
    split_scale_div: float
    prune_opacity: float
    prune_world_scale: float  # prune_world_scale x extent
    prune_screen_px: float

    @classmethod
    def from_config(cls, config, scene_extent: float) -> "DensifyParams":
        return cls(
            grad_threshold=float(config.densify_grad_threshold),
            clone_max_scale=float(config.percent_dense * scene_extent),
            split_scale_div=float(config.split_scale_div),
            prune_opacity=float(config.prune_opacity),
            prune_world_scale=float(config.prune_world_scale * scene_extent),
            prune_screen_px=float(config.prune_screen_px),
        )


def accumulate_stats(state: TrainState, probe_grad, radii, visible, width: int, height: int) -> TrainState:
    """Add one view's densification signal: the projected-centre gradient converted from
    pixels to NDC (x W/2, H/2, the 3DGS/2DGS units of the 2e-4 threshold)."""
    g = probe_grad * jnp.array([0.5 * width, 0.5 * height], probe_grad.dtype)
    norm = jnp.sqrt(jnp.sum(g * g, axis=-1))
    vis = visible & state.active & jnp.isfinite(norm)
    return dataclasses.replace(
        state,
        grad_accum=state.grad_accum + jnp.where(vis, norm, 0.0),
        grad_count=state.grad_count + vis.astype(state.grad_count.dtype),
        max_radii=jnp.where(vis, jnp.maximum(state.max_radii, radii.astype(jnp.float32)), state.max_radii),
    )


def mean_grad(state: TrainState) -> jax.Array:
    return state.grad_accum / jnp.maximum(state.grad_count, 1.0)


def count_candidates(state: TrainState, grad_threshold: float) -> jax.Array:
    """Active surfels whose mean gradient reaches the threshold (each needs one new slot)."""
    return jnp.sum(state.active & (mean_grad(state) >= grad_threshold))


TRACE_COUNTS: dict[str, int] = {"densify": 0}  # incremented only while tracing


def densify_and_prune(state: TrainState, key: jax.Array, max_new: jax.Array, prune_big: jax.Array,
                      p: DensifyParams, prune_transparent: jax.Array = True) -> tuple[TrainState, dict]:
    """One densification round: clone small / split large high-gradient surfels (at most
    `max_new` new ones, highest gradient first), then prune transparent (when
    `prune_transparent`) and oversized (when `prune_big`) surfels; resets the statistics.
    Returns the state and counts."""
    TRACE_COUNTS["densify"] += 1
    cap = state.capacity
    params, active = state.params, state.active
    grad = mean_grad(state)
    cand = active & (grad >= p.grad_threshold)
    max_scale = jnp.exp(jnp.max(params.log_scales, axis=-1))

    # Choose at most min(max_new, free slots) candidates, highest gradient first.
    free = ~active
    limit = jnp.minimum(jnp.asarray(max_new, jnp.int32), jnp.sum(free).astype(jnp.int32))
    order = jnp.argsort(jnp.where(cand, -grad, jnp.inf))
    rank = jnp.zeros(cap, jnp.int32).at[order].set(jnp.arange(cap, dtype=jnp.int32))
    chosen = cand & (rank < limit)
    clone = chosen & (max_scale <= p.clone_max_scale)
    split = chosen & ~clone

    # Slot allocation: the k-th chosen surfel's child goes to the k-th free slot.
    free_slots = jnp.nonzero(free, size=cap, fill_value=cap)[0]
    k = jnp.cumsum(chosen) - 1
    dest = jnp.where(chosen, free_slots[jnp.clip(k, 0, cap - 1)], cap)  # cap: dropped by the scatter

    # Split: two children sampled in the parent's tangent plane (N(0, scale) in u, v),
    # scales / 1.6; the first replaces the parent in place, the second takes a new slot.
    q, _ = safe_normalize(params.quats)
    rot = to_rotation_matrix(q)  # (cap,3,3): columns t_u, t_v, normal
    scales = jnp.exp(params.log_scales)
    eps = jax.random.normal(key, (2, cap, 2), params.means.dtype)
    offsets = jnp.einsum("nij,knj->kni", rot[:, :, :2], eps * scales[None], precision=FLOAT32)  # (2,cap,3)
    split_log_scales = params.log_scales - math.log(p.split_scale_div)
    s2 = split[:, None]
    in_place = dataclasses.replace(
        params,
        means=jnp.where(s2, params.means + offsets[0], params.means),
        log_scales=jnp.where(s2, split_log_scales, params.log_scales),
    )
    child = dataclasses.replace(
        params,
        means=jnp.where(s2, params.means + offsets[1], params.means),
        log_scales=jnp.where(s2, split_log_scales, params.log_scales),
    )
    new_params = jax.tree_util.tree_map(lambda a, c: a.at[dest].set(c, mode="drop"), in_place, child)
    born = jnp.zeros(cap, bool).at[dest].set(True, mode="drop")
    active = active | born

    # Prune (children included, as the reference does after densifying).
    opacity = jax.nn.sigmoid(new_params.opacity_logits)
    new_max_scale = jnp.exp(jnp.max(new_params.log_scales, axis=-1))
    radii = jnp.where(born | split, 0.0, state.max_radii)  # new surfels have not been seen yet
    screen_big = (p.prune_screen_px > 0) & (radii > p.prune_screen_px)  # 0 switches the rule off
    big = screen_big | (new_max_scale > p.prune_world_scale)
    prune = active & ((prune_transparent & (opacity < p.prune_opacity)) | (prune_big & big))
    active = active & ~prune
    new_params = dataclasses.replace(
        new_params, opacity_logits=jnp.where(prune, INACTIVE_LOGIT, new_params.opacity_logits))

    # Fresh Adam moments for every new or changed row (the reference's zero-initialised state).
    opt_state = optim.reset_rows(state.opt_state, born | split | prune)
    zeros = jnp.zeros(cap, jnp.float32)
    new_state = dataclasses.replace(state, params=new_params, active=active, opt_state=opt_state, grad_accum=zeros,
                                    grad_count=zeros, max_radii=zeros)
    counts = {
        "candidates": jnp.sum(cand), "cloned": jnp.sum(clone), "split": jnp.sum(split),
        "pruned": jnp.sum(prune), "skipped": jnp.sum(cand) - jnp.sum(chosen),
    }
    return new_state, counts


def reset_opacity(state: TrainState, value: float) -> TrainState:
    """Clamp opacities of live surfels to at most `value` and restart their Adam moments."""
    logit = math.log(value / (1 - value))
    logits = jnp.where(state.active, jnp.minimum(state.params.opacity_logits, logit), state.params.opacity_logits)
    params = dataclasses.replace(state.params, opacity_logits=logits)
    opt_state = optim.reset_rows(state.opt_state, jnp.ones(state.capacity, bool), groups=("opacity_logits",))
    return dataclasses.replace(state, params=params, opt_state=opt_state)


densify_jit = jax.jit(densify_and_prune, static_argnames=("p",))
reset_opacity_jit = jax.jit(reset_opacity, static_argnames=("value",))
count_candidates_jit = jax.jit(count_candidates, static_argnames=("grad_threshold",))


def budget_target(config, schedule: str, step: int, initial_count: int, max_surfels: int) -> int:
    """The budgeted strategy's allowed count at `step` ("linear" or "immediate" `schedule`)."""
    if schedule == "immediate":
        return max_surfels
    span = max(config.densify_until - config.densify_from, 1)
    t = min(max((step - config.densify_from) / span, 0.0), 1.0)
    return int(round(initial_count + (max_surfels - initial_count) * t))
