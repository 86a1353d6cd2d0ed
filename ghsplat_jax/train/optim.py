"""Adam with one learning rate (and schedule) per parameter group, as one optax chain per
Surfels field, so densification can reset a group's moments row by row."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from ghsplat_jax.core.surfels import Surfels

GROUPS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


def means_schedule(config, scene_extent: float = 1.0) -> optax.Schedule:
    """lr_means_init x extent decaying exponentially to lr_means_final x extent at step
    lr_means_steps (the run's last step where that is 0), constant after."""
    init = config.lr_means_init * scene_extent
    final = config.lr_means_final * scene_extent
    steps = max(int(config.lr_means_steps or config.steps), 1)
    return optax.exponential_decay(init, transition_steps=steps, decay_rate=final / init, end_value=final)


def learning_rates(config, scene_extent: float = 1.0) -> dict[str, optax.ScalarOrSchedule]:
    return {
        "means": means_schedule(config, scene_extent),
        "quats": config.lr_quats,
        "log_scales": config.lr_scales,
        "opacity_logits": config.lr_opacity,
        "sh_dc": config.lr_sh_dc,
        "sh_rest": config.lr_sh_rest,
    }


def make_optimizers(config) -> dict[str, optax.GradientTransformation]:
    """Adam per group. The means get a unit learning rate here: `update` multiplies their
    step by the scheduled rate (a traced value computed on the host from means_schedule), so
    one compiled step serves every scene extent and run length."""
    lrs = learning_rates(config) | {"means": 1.0}
    return {name: optax.adam(lr, eps=config.adam_eps) for name, lr in lrs.items()}


def init(optimizers: dict, params: Surfels) -> dict:
    return {name: optimizers[name].init(getattr(params, name)) for name in GROUPS}


def update(optimizers: dict, opt_state: dict, grads: Surfels, params: Surfels,
           means_lr=1.0) -> tuple[Surfels, dict]:
    """One Adam step of every group (the means' step scaled by `means_lr`); returns the new
    parameters and optimiser state."""
    new_params, new_state = {}, {}
    for name in GROUPS:
        p = getattr(params, name)
        upd, new_state[name] = optimizers[name].update(getattr(grads, name), opt_state[name], p)
        if name == "means":
            upd = jax.tree_util.tree_map(lambda u: u * means_lr, upd)
        new_params[name] = optax.apply_updates(p, upd)
    return Surfels(**new_params), new_state


def reset_rows(opt_state: dict, rows: jax.Array, groups=GROUPS) -> dict:
    """Zero the Adam moments of the surfel rows where `rows` (cap,) is True, in `groups`."""
    cap = rows.shape[0]

    def zero(leaf):
        if hasattr(leaf, "ndim") and leaf.ndim >= 1 and leaf.shape[0] == cap:
            mask = rows.reshape((cap,) + (1,) * (leaf.ndim - 1))
            return jnp.where(mask, jnp.zeros_like(leaf), leaf)
        return leaf

    return {name: (jax.tree_util.tree_map(zero, s) if name in groups else s) for name, s in opt_state.items()}


def adam_row_step(adam: optax.GradientTransformation, values: jax.Array, moments, row, grad: jax.Array, rate,
                  on) -> tuple[jax.Array, object]:
    """One Adam step of row `row` of per-view `values` (V, D) with its own `moments` (optax state
    with a row per view, as from `jax.vmap(adam.init)`), at `rate` (scalar or (D,)); other rows are
    untouched. `on` (bool): False leaves everything as it was. A view not drawn keeps its values and
    moments (no momentum drift between its visits)."""
    old = jax.tree_util.tree_map(lambda a: a[row], moments)
    step, new = adam.update(grad, old)
    keep = lambda n, o: jnp.where(on, n, o)  # noqa: E731
    moments = jax.tree_util.tree_map(lambda a, n: a.at[row].set(keep(n, a[row])), moments, new)
    return values.at[row].set(keep(values[row] - rate * step, values[row])), moments
