"""The jit-compiled training step: render -> loss -> gradients -> Adam, plus the
densification statistics from the gradient of the projected centres."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from ghsplat_jax.core.camera import Camera
from ghsplat_jax.train import exposure as exposure_mod
from ghsplat_jax.train import losses, optim
from ghsplat_jax.train import pose as pose_mod
from ghsplat_jax.train.densify import accumulate_stats
from ghsplat_jax.train.state import TrainState, render_params


@dataclasses.dataclass(frozen=True)
class LossWeights:
    """Static loss settings (hashable)."""

    lambda_dssim: float
    lambda_dist: float
    dist_from: int
    lambda_normal: float
    normal_from: int
    depth_ratio: float
    sh_degree: int
    sh_increase_every: int
    opacity_reg: float = 0.0  # L1 regularisers (3DGS-MCMC); the strategy's default where the config says -1
    scale_reg: float = 0.0
    exposure_reg: float = 0.0  # x the L1 norm of a view's exposure correction (with exposure compensation)

    @classmethod
    def from_config(cls, c) -> "LossWeights":
        from ghsplat_jax.train.strategies import loss_weight

        return cls(c.lambda_dssim, c.lambda_dist, c.dist_from, c.lambda_normal, c.normal_from,
                   c.depth_ratio, c.sh_degree, c.sh_increase_every, loss_weight(c, "lambda_opacity_reg"),
                   loss_weight(c, "lambda_scale_reg"), c.exposure_reg)


def sh_band_mask(step: jax.Array, w: LossWeights, num_rest: int) -> jax.Array:
    """(K,) 1 for the higher SH coefficients of bands already switched on at `step`: the
    degree grows by one every sh_increase_every steps without changing shapes (no recompile)."""
    degree = jnp.minimum(step // max(w.sh_increase_every, 1), w.sh_degree)
    band = jnp.floor(jnp.sqrt(jnp.arange(1, num_rest + 1, dtype=jnp.float32)) + 1e-6)
    return (band <= degree).astype(jnp.float32)


def step_surfels(params, active, camera: Camera, step, w: LossWeights):
    """The surfels a step renders: the live ones, with the SH bands not yet switched on zeroed."""
    p = render_params(params, active, camera.world_to_cam)
    mask = sh_band_mask(step, w, p.sh_rest.shape[1])
    return dataclasses.replace(p, sh_rest=p.sh_rest * mask[None, :, None])


def image_loss(out, image, camera: Camera, step, w: LossWeights, raster_cfg, tone=None):
    """The loss of a render against `image` (H,W,3), or (H,W,4) with the image's alpha, which
    masks the normal loss; and the step's metrics. `tone` (6,): the view's exposure correction,
    applied to the render's colour (None: the render as it is)."""
    image, coverage = (image, None) if image.shape[-1] == 3 else (image[..., :3], image[..., 3])
    rgb = out.rgb if tone is None else exposure_mod.apply(out.rgb, tone)
    l1 = losses.l1(rgb, image)
    ssim = losses.ssim(rgb, image)
    loss = (1.0 - w.lambda_dssim) * l1 + w.lambda_dssim * (1.0 - ssim)
    if tone is not None:
        loss = loss + w.exposure_reg * exposure_mod.penalty(tone)
    dist = jnp.mean(out.distortion)
    # A geometry term is computed only while the render computes what it reads
    # (`trainer.step_raster_config` switches it on at its start step).
    if w.lambda_dist > 0 and raster_cfg.distortion:
        loss = loss + jnp.where(step >= w.dist_from, w.lambda_dist, 0.0) * dist
    normal_loss = jnp.zeros(())
    if w.lambda_normal > 0 and raster_cfg.depth_normal:
        depth = out.depth if w.depth_ratio == 0 else (
            (1 - w.depth_ratio) * out.depth + w.depth_ratio * out.median_depth)
        dn = losses.depth_to_normal(depth, camera.K, camera.world_to_cam)
        normal_loss = losses.normal_consistency(out.normal, dn, out.alpha, coverage)
        loss = loss + jnp.where(step >= w.normal_from, w.lambda_normal, 0.0) * normal_loss
    aux = dict(l1=l1, ssim=ssim, psnr=losses.psnr(rgb, image), distortion=dist, normal=normal_loss,
               visible=out.visible, radii=out.radii, num_pairs=out.stats.num_pairs,
               overflow=out.stats.overflow)
    return loss, aux


def regularisers(params, active, w: LossWeights):
    """The L1 regularisers on opacity and scale (3DGS-MCMC), averaged over the live surfels."""
    live = active.astype(jnp.float32)
    n = jnp.maximum(jnp.sum(live), 1.0)
    return (w.opacity_reg * jnp.sum(jax.nn.sigmoid(params.opacity_logits) * live) / n
            + w.scale_reg * jnp.sum(jnp.exp(params.log_scales) * live[:, None]) / n)


def _loss(params, probe, active, image, camera: Camera, step, w: LossWeights, raster_cfg, render_fn, tone=None):
    out = render_fn(step_surfels(params, active, camera, step, w), camera, raster_cfg, means2d_probe=probe)
    loss, aux = image_loss(out, image, camera, step, w, raster_cfg, tone)
    if w.opacity_reg > 0 or w.scale_reg > 0:
        loss = loss + regularisers(params, active, w)
    return loss, aux


def _all_finite(tree, active) -> jax.Array:
    """Whether every live row of every leaf is finite: one fused sum per leaf (a sum of finite
    parameters this small cannot overflow float32, and any inf or NaN makes it non-finite)."""
    def leaf_ok(a):
        return jnp.isfinite(jnp.sum(jnp.where(active.reshape((-1,) + (1,) * (a.ndim - 1)), a, 0.0)))
    return jnp.all(jnp.stack([leaf_ok(a) for a in jax.tree_util.tree_leaves(tree)]))


@dataclasses.dataclass(frozen=True)
class PoseRates:
    """Static pose-refinement settings (hashable): Adam's rates and the first step that refines."""

    rot: float
    trans: float
    start: int

    @classmethod
    def from_config(cls, c) -> "PoseRates | None":
        return cls(c.pose_lr_rot, c.pose_lr_trans, c.pose_refine_from) if c.pose_refine else None


@dataclasses.dataclass(frozen=True)
class ExposureRates:
    """Static exposure-compensation settings (hashable): Adam's rate and the first step that learns."""

    lr: float
    start: int

    @classmethod
    def from_config(cls, c) -> "ExposureRates | None":
        return cls(c.exposure_lr, c.exposure_from) if c.exposure_compensation else None


def view_corrections(state: TrainState, view):
    """Training view `view`'s pose and exposure corrections (each None where the state has none)."""
    delta = None if state.pose is None else state.pose.delta[view]
    tone = None if state.exposure is None else state.exposure.values[view]
    return delta, tone


def update_view_corrections(state: TrainState, metrics: dict, view, step, delta_grad, tone_grad,
                            pose_rates: PoseRates | None, exposure_rates: ExposureRates | None):
    """One Adam step of training view `view`'s corrections (those the state has) from their
    gradients, taken at step `step`; (new state, metrics with the corrections' sizes)."""
    finite = metrics["finite"]
    if state.pose is not None:
        pose = pose_mod.update_view(state.pose, view, delta_grad, pose_rates.rot, pose_rates.trans,
                                    step >= pose_rates.start)
        d = pose.delta[view]
        finite = finite & jnp.all(jnp.isfinite(d))
        metrics = metrics | dict(pose_deg=jnp.degrees(jnp.linalg.norm(d[:3])), pose_pct=100.0 * jnp.linalg.norm(d[3:]))
        state = dataclasses.replace(state, pose=pose)
    if state.exposure is not None:
        exposure = exposure_mod.update_view(state.exposure, view, tone_grad, exposure_rates.lr,
                                            step >= exposure_rates.start)
        t = exposure.values[view]
        finite = finite & jnp.all(jnp.isfinite(t))
        metrics = metrics | dict(exposure_gain=jnp.exp(jnp.mean(t[:3])))
        state = dataclasses.replace(state, exposure=exposure)
    return state, metrics | dict(finite=finite)


def train_step(state: TrainState, image, K, world_to_cam, means_lr, *, width: int, height: int, optimizers, weights,
               raster_cfg, render_fn, view=None, pose_rates: PoseRates | None = None,
               exposure_rates: ExposureRates | None = None):
    """One step on one view; returns (new state, metrics). Rows of free slots get zero
    gradients; `finite` is False when the loss, a gradient or a live parameter is not finite.
    A state with per-view corrections (`state.pose`, `state.exposure`) also differentiates
    through training view `view`'s and takes one Adam step of them (from their start steps)."""
    probe = jnp.zeros((state.capacity, 2), jnp.float32)
    delta, tone = view_corrections(state, view)

    def loss_of(params, probe, delta, tone):
        w2c = world_to_cam if delta is None else pose_mod.correct(world_to_cam, delta, state.pose.extent)
        return _loss(params, probe, state.active, image, Camera(K, w2c, width, height), state.step, weights,
                     raster_cfg, render_fn, tone)

    grad_fn = jax.value_and_grad(loss_of, argnums=(0, 1, 2, 3), has_aux=True)
    (loss, aux), (grads, probe_grad, delta_grad, tone_grad) = grad_fn(state.params, probe, delta, tone)
    new, metrics = apply_gradients(state, loss, aux, grads, probe_grad, means_lr, optimizers, width, height)
    return update_view_corrections(new, metrics, view, state.step, delta_grad, tone_grad, pose_rates,
                                   exposure_rates)


def apply_gradients(state: TrainState, loss, aux, grads, probe_grad, means_lr, optimizers, width: int, height: int):
    """Adam on the live rows and the densification statistics; (new state, metrics)."""
    act = state.active

    def mask_rows(g):
        return jnp.where(act.reshape((-1,) + (1,) * (g.ndim - 1)), g, 0.0)

    grads = jax.tree_util.tree_map(mask_rows, grads)
    params, opt_state = optim.update(optimizers, state.opt_state, grads, state.params, means_lr)
    new = dataclasses.replace(state, params=params, opt_state=opt_state, step=state.step + 1)
    new = accumulate_stats(new, probe_grad, aux["radii"], aux["visible"], width, height)
    # A non-finite gradient makes its Adam step non-finite (inf / inf or NaN), so the new
    # parameters alone tell whether the step went wrong.
    finite = jnp.isfinite(loss) & _all_finite(params, act)
    metrics = dict(loss=loss, l1=aux["l1"], ssim=aux["ssim"], psnr=aux["psnr"], distortion=aux["distortion"],
                   normal=aux["normal"], num_pairs=aux["num_pairs"], overflow=aux["overflow"], finite=finite)
    return new, metrics


TRACE_COUNTS: dict[str, int] = {"train_step": 0}  # incremented only while tracing: proves no recompiles


@functools.partial(jax.jit, static_argnames=("raster_cfg",))
def render_active(params, active, camera: Camera, raster_cfg):
    """Render the live surfels of a training state (for evaluation inside a run)."""
    from ghsplat_jax.raster.render import render

    return render(render_params(params, active, camera.world_to_cam), camera, raster_cfg)
