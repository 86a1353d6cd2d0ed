"""Pose refinement: a learnable correction per training view, applied to its world_to_cam inside
the training step (`TrainConfig.pose_refine`).

A correction is a 6-vector (omega, tau): omega an so(3) rotation (radians), tau a translation in
units of the scene extent, so one learning rate serves every scene size. It acts in the camera's
frame, on the left of the view's pose:

    world_to_cam' = [exp(omega) | tau * extent] @ world_to_cam

which turns the camera by |omega| about its own centre and moves that centre by |tau| x extent
(the rotation is orthonormal, so the shift keeps its length in the world). Each view has its own
Adam moments and count (optax `scale_by_adam`, one row per view), updated only on the steps that
train that view: a view that is not drawn keeps its correction (no momentum drift between visits).
"""

from __future__ import annotations

import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ghsplat_jax.core.precision import FLOAT32
from ghsplat_jax.train.optim import adam_row_step

log = logging.getLogger("ghsplat.train")

# A correction beyond either of these draws a warning naming the view: the SfM pose was likely bad.
LARGE_ROTATION_DEG = 0.5
LARGE_TRANSLATION = 0.01  # fraction of the scene extent


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PoseState:
    delta: jax.Array      # (V, 6) per training view: so(3) rotation (rad), translation (x extent)
    adam: optax.ScaleByAdamState  # per view: count (V,), mu and nu (V, 6)
    extent: jax.Array     # () the scene extent, metres per unit of translation

    @property
    def num_views(self) -> int:
        return self.delta.shape[0]


def pose_adam() -> optax.GradientTransformation:
    """Adam's moment estimates without a rate: `update_view` scales rotation and translation apart."""
    return optax.scale_by_adam(eps=1e-8)


def init_pose(num_views: int, extent: float) -> PoseState:
    """Zero corrections (every pose as given) and fresh moments."""
    delta = jnp.zeros((num_views, 6), jnp.float32)
    adam = jax.vmap(pose_adam().init)(delta)
    return PoseState(delta=delta, adam=adam, extent=jnp.asarray(extent, jnp.float32))


def so3_exp(omega: jax.Array) -> jax.Array:
    """(3, 3) rotation of the axis-angle vector `omega` (Rodrigues). Near zero the series: sin(t)/t
    and (1 - cos t)/t^2 are 0/0 there, and the "double where" keeps the unused branch's gradient
    finite (jaxlie)."""
    theta2 = jnp.sum(omega * omega)
    small = theta2 < 1e-8
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / jnp.where(small, 1.0, theta2))
    x, y, z = omega[0], omega[1], omega[2]
    zero = jnp.zeros_like(x)
    k = jnp.stack([jnp.stack([zero, -z, y]), jnp.stack([z, zero, -x]), jnp.stack([-y, x, zero])])
    return jnp.eye(3, dtype=omega.dtype) + a * k + b * jnp.matmul(k, k, precision=FLOAT32)


def correct(world_to_cam: jax.Array, delta: jax.Array, extent) -> jax.Array:
    """world_to_cam with the correction `delta` (6,) applied on the camera's side; a zero
    correction returns it exactly."""
    R = so3_exp(delta[:3])
    top = jnp.concatenate([R, (delta[3:] * extent)[:, None]], axis=1)
    return jnp.concatenate([jnp.matmul(top, world_to_cam, precision=FLOAT32), world_to_cam[3:]], axis=0)


def update_view(pose: PoseState, view, grad: jax.Array, lr_rot: float, lr_trans: float, on) -> PoseState:
    """One Adam step of view `view`'s correction from its gradient `grad` (6,); other views are
    untouched. `on` (bool): False leaves everything as it was (before pose_refine_from)."""
    rate = jnp.array([lr_rot] * 3 + [lr_trans] * 3, jnp.float32)
    delta, adam = adam_row_step(pose_adam(), pose.delta, pose.adam, view, grad, rate, on)
    return dataclasses.replace(pose, delta=delta, adam=adam)


# ----------------------------------------------------------------------------- host side

def correction_matrix(delta, extent: float) -> np.ndarray:
    """(4, 4) float64 matrix of one correction (NumPy), to left-multiply a world_to_cam."""
    delta = np.asarray(delta, np.float64)
    w = delta[:3]
    t = float(np.linalg.norm(w))
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    a, b = (1.0, 0.5) if t < 1e-8 else (np.sin(t) / t, (1 - np.cos(t)) / t ** 2)
    out = np.eye(4)
    out[:3, :3] = np.eye(3) + a * k + b * k @ k
    out[:3, 3] = delta[3:] * extent
    return out


def refined_world_to_cam(world_to_cam, delta, extent: float) -> np.ndarray:
    return correction_matrix(delta, extent) @ np.asarray(world_to_cam, np.float64)


def corrections_report(pose: PoseState, names: list[str]) -> list[dict]:
    """Per view: its name, the correction's rotation (degrees) and its centre's shift (metres and
    % of the scene extent), and the raw 6-vector (`correction_matrix` makes it a matrix)."""
    delta = np.asarray(pose.delta, np.float64)
    extent = float(pose.extent)
    rows = []
    for name, d in zip(names, delta):
        shift = float(np.linalg.norm(d[3:]))
        rows.append(dict(name=name, rotation_deg=float(np.degrees(np.linalg.norm(d[:3]))),
                         translation_m=shift * extent, translation_pct_extent=100.0 * shift, delta=d.tolist()))
    return rows


def is_large(row: dict) -> bool:
    return row["rotation_deg"] > LARGE_ROTATION_DEG or row["translation_pct_extent"] > 100 * LARGE_TRANSLATION


def corrections_summary(rows: list[dict]) -> dict:
    """metrics.json's `pose_refinement`: the largest and median correction, and the large ones."""
    if not rows:
        return {"num_views": 0}
    rot = [r["rotation_deg"] for r in rows]
    pct = [r["translation_pct_extent"] for r in rows]
    return {"num_views": len(rows), "max_rotation_deg": max(rot), "median_rotation_deg": float(np.median(rot)),
            "max_translation_pct_extent": max(pct), "median_translation_pct_extent": float(np.median(pct)),
            "max_translation_m": max(r["translation_m"] for r in rows),
            "large_views": [r["name"] for r in rows if is_large(r)]}


def warn_large(rows: list[dict]) -> list[str]:
    """Log (and return) a warning for every view whose correction is large."""
    messages = [f"view {r['name']}: pose refinement moved it by {r['rotation_deg']:.2f} deg and "
                f"{r['translation_m']:.4g} m ({r['translation_pct_extent']:.2f}% of the scene extent); its SfM pose "
                "was likely off (re-register it, or drop it if the render still disagrees with the photo)"
                for r in rows if is_large(r)]
    for m in messages:
        log.warning("%s", m)
    return messages


def refine_views(views: list, rows: list[dict], extent: float) -> list:
    """`views` with the cameras of those named in `rows` at their refined poses (others as given)."""
    from ghsplat_jax.core.camera import Camera

    by_name = {r["name"]: r["delta"] for r in rows}
    out = []
    for v in views:
        if v.name in by_name:
            c = v.camera
            w2c = refined_world_to_cam(c.world_to_cam, by_name[v.name], extent).astype(np.float32)
            v = dataclasses.replace(v, camera=Camera(np.asarray(c.K), w2c, c.width, c.height))
        out.append(v)
    return out
