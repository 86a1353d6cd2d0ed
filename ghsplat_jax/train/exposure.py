"""Exposure compensation: a learnable gain and offset per colour channel for every training view
(`TrainConfig.exposure_compensation`), applied to that view's render inside the loss.

A phone's auto exposure or white balance makes some photos of a capture brighter or tinted
(`data/exposure.py` finds them before training). Without compensation, the surfels learn such a
photo's brightness as view-dependent colour and show it to new views from its side. With it, the
render a view's photo is compared against is

    rgb' = exp(g) * rgb + b        (per channel: g log gains, b offsets, a 6-vector per view)

so the surfels keep the capture's common exposure: every other render (test and held-out views,
the exported model) is the plain one; evaluation scores a training view under its correction. An L1 penalty on (g, b) in
each view's loss holds the corrections at zero where the photos agree, so the common exposure is
the median photo's. (With a squared penalty, one photo of four made 40% darker let the model and
every other view's gain drift 3% darker: a mean, not a median.) Each view has its own Adam moments, updated on the steps
that train it (as pose refinement's corrections).
"""

from __future__ import annotations

import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ghsplat_jax.train.optim import adam_row_step

log = logging.getLogger("ghsplat.train")

# A training view whose correction moves a mid-grey (0.5) this far from itself (x, any channel) is
# named: the photos compensation matched. A 3x brighter photo (linear light) learnt gains of 1.1 and
# offsets of +0.16 (the aloe's 01.jpg): gain and offset share the change.
LARGE_CHANGE = 1.15


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ExposureState:
    values: jax.Array             # (V, 6) per training view: log gains (r, g, b), offsets (r, g, b)
    adam: optax.ScaleByAdamState  # per view: count (V,), mu and nu (V, 6)

    @property
    def num_views(self) -> int:
        return self.values.shape[0]


def exposure_adam() -> optax.GradientTransformation:
    return optax.scale_by_adam(eps=1e-8)


def init_exposure(num_views: int) -> ExposureState:
    """No correction (every photo as it is) and fresh moments."""
    values = jnp.zeros((num_views, 6), jnp.float32)
    return ExposureState(values=values, adam=jax.vmap(exposure_adam().init)(values))


def apply(rgb: jax.Array, tone: jax.Array) -> jax.Array:
    """A render (..., 3) under one view's correction `tone` (6,); a zero correction returns it exactly."""
    return rgb * jnp.exp(tone[:3]) + tone[3:]


def penalty(tone: jax.Array) -> jax.Array:
    return jnp.sum(jnp.abs(tone))


def update_view(exposure: ExposureState, view, grad: jax.Array, lr: float, on) -> ExposureState:
    """One Adam step of view `view`'s correction from its gradient `grad` (6,); other views are
    untouched. `on` (bool): False leaves everything as it was (before exposure_from)."""
    values, adam = adam_row_step(exposure_adam(), exposure.values, exposure.adam, view, grad, lr, on)
    return dataclasses.replace(exposure, values=values, adam=adam)


# ----------------------------------------------------------------------------- host side

def corrections_report(exposure: ExposureState, names: list[str]) -> list[dict]:
    """Per training view: its name, its gains and offsets per channel (r, g, b)."""
    values = np.asarray(exposure.values, np.float64)
    return [dict(name=name, gain=np.exp(v[:3]).tolist(), offset=v[3:].tolist()) for name, v in zip(names, values)]


def tone_of(row: dict) -> np.ndarray:
    """The 6-vector `apply` takes, from a corrections report's row (gains and offsets)."""
    return np.concatenate([np.log(row["gain"]), row["offset"]]).astype(np.float32)


def mid_grey_change(row: dict) -> list[float]:
    """Per channel, what the correction makes of a mid-grey (0.5), as a ratio to it."""
    return [(0.5 * g + b) / 0.5 for g, b in zip(row["gain"], row["offset"])]


def is_large(row: dict) -> bool:
    return max(abs(np.log(max(c, 1e-6))) for c in mid_grey_change(row)) > np.log(LARGE_CHANGE)


def corrections_summary(rows: list[dict]) -> dict:
    """metrics.json's `exposure_compensation`: the gains' range, the largest offset, the views
    whose correction moves a mid-grey more than LARGE_CHANGE from itself."""
    if not rows:
        return {"num_views": 0}
    gains = np.array([r["gain"] for r in rows])
    offsets = np.abs(np.array([r["offset"] for r in rows]))
    return {"num_views": len(rows), "min_gain": float(gains.min()), "max_gain": float(gains.max()),
            "max_abs_offset": float(offsets.max()), "large_views": [r["name"] for r in rows if is_large(r)]}


def describe_large(rows: list[dict]) -> list[str]:
    """Log (and return) a line for every training view whose correction is large (`is_large`):
    the photos compensation matched (the model keeps the others' exposure)."""
    messages = [f"view {r['name']}: exposure compensation matched it (a mid-grey x "
                f"{', '.join(f'{c:.2f}' for c in mid_grey_change(r))}) with gains "
                f"{', '.join(f'{g:.2f}' for g in r['gain'])} (r, g, b) and offsets "
                f"{', '.join(f'{b:+.3f}' for b in r['offset'])}; the model keeps the other photos' exposure"
                for r in rows if is_large(r)]
    for m in messages:
        log.info("%s", m)
    return messages
