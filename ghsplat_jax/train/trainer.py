"""The training loop: one jitted step per view, densification rounds, pair-capacity and pool
growth, rollback of non-finite steps, stats, progress and checkpoints.

    result = train(config, out_dir)           # or train(config, out_dir, dataset=ds)
    result.surfels                            # the live surfels (host arrays)
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import signal
import threading
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.data.exposure import exposure_warning, flagged_training_photos
from ghsplat_jax.data.tracks import pose_disagreement
from ghsplat_jax.host_memory import IN_RUN_MAP_SHARE, MAPS_CHECK_EVERY, release_compiled_programs, reuse_freed_memory
from ghsplat_jax.io_utils import code_revision, device_name, host_label, machine_info
from ghsplat_jax.raster.render import capacity_bucket
from ghsplat_jax.train import checkpoint as ckpt
from ghsplat_jax.train import exposure as exposure_mod
from ghsplat_jax.train import optim
from ghsplat_jax.train import pose as pose_mod
from ghsplat_jax.train.carve import subject_points
from ghsplat_jax.train.config import TrainConfig, save_config
from ghsplat_jax.train.resolution import (
    box_downscale,
    crop_stack,
    factor_at,
    scale_intrinsics,
    spectrum_schedule,
)
from ghsplat_jax.train.run_dir import (
    CHECKPOINT_NAME,
    CONFIG_NAME,
    EXPOSURE_NAME,
    PLY_NAME,
    POSE_NAME,
    STATS_NAME,
    TEST_CURVE_NAME,
    load_run_checkpoint,
    load_training_data,
    peak_rss_mb,
)
from ghsplat_jax.train.state import (
    TrainState,
    compiles_cost_more_than_slots,
    initial_surfels,
    needs_random_init,
    new_state,
    pad_params,
    random_init_box,
)
from ghsplat_jax.train.step_builder import make_train_step
from ghsplat_jax.train.stopping import PlateauRule
from ghsplat_jax.train.strategies import StrategyContext, last_reset_before, make_strategy  # noqa: F401 (re-export)

log = logging.getLogger("ghsplat.train")


class TrainingDivergedError(RuntimeError):
    """Training kept producing non-finite values after rolling back."""


@dataclasses.dataclass
class TrainResult:
    state: TrainState
    steps: int
    train_seconds: float
    rollbacks: int
    out_dir: Path
    initial_count: int
    strategy_state: dict = dataclasses.field(default_factory=dict)  # the strategy's own state at the end
    finished: bool = False  # the schedule ran out or the stop rule stopped it (not an `until` pause)
    stop: dict | None = None  # the stop rule's state (runs with validation): best step, why it stopped
    pose: dict | None = None  # pose refinement: what pose_corrections.json holds
    exposure: dict | None = None  # exposure compensation: what exposure_corrections.json holds
    held_out: list[str] | None = None  # the validation views' names (runs with validation; [] when the
    #                                    training views were too few to hold any out and the checks read them)

    @property
    def surfels(self):
        return self.state.active_surfels()

    @property
    def num_surfels(self) -> int:
        return int(np.sum(np.asarray(self.state.active)))


def view_order(seed: int, step: int, num_views: int) -> int:
    """The view of `step`: a fresh random permutation every epoch (a function of the step, so a
    resumed run sees the same views)."""
    epoch, i = divmod(step, num_views)
    return int(np.random.default_rng([seed, epoch]).permutation(num_views)[i])


def pair_bucket(pairs: int) -> int:
    """Pair capacity with 25% headroom, in the renderer's buckets (1, 1.25, 1.5, 1.75 x 2^k)."""
    return capacity_bucket(math.ceil(max(pairs, 1) * 1.25))


def regrown_capacity(capacity: int, pairs: int) -> int:
    """The pair capacity after a render that needed `pairs` overflowed `capacity`: at least
    doubled, so a growing count compiles once per doubling, not at every overflow."""
    return max(2 * capacity, pair_bucket(pairs))


def stack_views(views, with_alpha: bool = False):
    """(images (N,H,W,C), Ks, world_to_cams, width, height) of views of one size. `with_alpha`
    and any view with alpha: C = 4, the image's alpha last (1 for a view without alpha)."""
    sizes = {(v.camera.width, v.camera.height) for v in views}
    if len(sizes) != 1:
        raise ValueError(f"training views must share one image size, got {sorted(sizes)}")
    (w, h), = sizes
    with_alpha = with_alpha and any(v.alpha is not None for v in views)

    def pixels(v):
        rgb = np.asarray(v.image, np.float32)
        if not with_alpha:
            return rgb
        alpha = np.ones((h, w), np.float32) if v.alpha is None else np.asarray(v.alpha, np.float32)
        return np.concatenate([rgb, alpha[:, :, None]], axis=2)

    images = jnp.asarray(np.stack([pixels(v) for v in views]))
    Ks = jnp.asarray(np.stack([np.asarray(v.camera.K, np.float32) for v in views]))
    w2cs = jnp.asarray(np.stack([np.asarray(v.camera.world_to_cam, np.float32) for v in views]))
    return images, Ks, w2cs, w, h


def step_raster_config(config: TrainConfig, pair_capacity: int, step: int | None = None):
    """The run's rendering settings as the training step uses them: a static pair buffer whose
    overflow is reported (and redone), and only the outputs the losses read at `step` (None: every
    term on). A geometry term weighs zero before its start step (as in 2DGS), so until then its
    outputs are not computed at all; the step compiles once more when each term starts."""
    started = lambda start: step is None or step >= start
    normal_loss = config.lambda_normal > 0 and started(config.normal_from)
    return dataclasses.replace(config.raster, pair_capacity=pair_capacity, on_overflow="report",
                               median=config.raster.median and normal_loss and config.depth_ratio > 0,
                               depth_normal=config.raster.depth_normal and normal_loss,
                               distortion=config.raster.distortion and config.lambda_dist > 0
                               and started(config.dist_from))


def _jsonable(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        v = np.asarray(v).item() if np.ndim(v) == 0 else v
        if isinstance(v, float) and not math.isfinite(v):
            v = None  # stats.jsonl stays valid JSON; NaNs never reach disk
        out[k] = v
    return out


# Fewer training views than this draw a warning: in the stability study (benchmarks/results/
# stability/) 10 views of a row stayed within 1 dB of all 30, 5 views lost 2.8 dB.
FEW_TRAIN_VIEWS = 10


MIN_HELD_OUT, MIN_LEFT_TO_TRAIN = 2, 8  # a validation split smaller, or leaving fewer, holds nothing out


def hold_out(views: list, every: int) -> tuple[list, list]:
    """(training views, validation views): every `every`-th view from the middle of the first
    stride on (so it does not line up with a test split that takes every n-th from the first),
    and none when fewer than MIN_HELD_OUT would be held out or fewer than MIN_LEFT_TO_TRAIN would
    train."""
    picked = set(range(every // 2, len(views), every))
    if len(picked) < MIN_HELD_OUT or len(views) - len(picked) < MIN_LEFT_TO_TRAIN:
        return list(views), []
    return [v for i, v in enumerate(views) if i not in picked], [v for i, v in enumerate(views) if i in picked]


def finite_points(points) -> int:
    """How many of a dataset's points (None: none) are finite."""
    return 0 if points is None else int(np.sum(np.all(np.isfinite(points), axis=1)))


def warn_about_inputs(config: TrainConfig, dataset, carved: int | None = None) -> list[str]:
    """Warn (and return the messages) where the inputs predict a poor model that training itself
    cannot notice: random initialisation for want of SfM points (`carved`: that many of them kept
    inside the subject's silhouettes), too few training views, cameras that disagree with the SfM
    points they observed (data/tracks.py), or photos exposed unlike the rest (data/exposure.py)."""
    messages = [m for m in (pose_disagreement(dataset, config.data),
                            exposure_warning(dataset, config.data, config.exposure_compensation)) if m]
    points = finite_points(dataset.points)
    if needs_random_init(points, config):
        start = (f"{carved} random points inside the subject's silhouettes" if carved else
                 f"{config.init_random_points} random points in the camera box")
        messages.append(
            f"{config.data}: {points} SfM points (init_min_points is {config.init_min_points}), so the surfels start "
            f"at {start}; expect lower accuracy and slower steps than from SfM points (run `ghsplat sfm` and train "
            "on its model)")
    if len(dataset.train) < FEW_TRAIN_VIEWS:
        messages.append(
            f"{config.data}: only {len(dataset.train)} training views (fewer than {FEW_TRAIN_VIEWS}); novel views "
            f"will be poorly constrained and the model will fit its training views much better than new ones")
    for m in messages:
        log.warning("%s", m)
    return messages


class TrainingSession:
    """Mutable loop state of one run (host side)."""

    def __init__(self, config: TrainConfig, out_dir: Path, dataset, resume: bool, render_fn=None):
        self.config, self.out = config, out_dir
        self.ds = dataset
        train_views, self.val_views = hold_out(dataset.train, config.val_hold_every) if config.val_every else (
            dataset.train, [])
        if config.val_every and not self.val_views:
            log.warning("%s: too few training views (%d) to hold some out for validation; the stop rule reads the "
                        "training views' PSNR instead, so it stops when they are learnt and cannot see over-fitting",
                        config.data, len(dataset.train))
            self.val_views = list(dataset.train)
        self.held_out = [v.name for v in self.val_views if v not in train_views]
        self.view_names = [v.name for v in train_views]
        self.images, self.Ks, self.w2cs, self.width, self.height = stack_views(
            train_views, with_alpha=config.normal_loss_alpha_mask and config.lambda_normal > 0)
        # Full resolution by res_until, and for the last two thirds of a short run at least.
        until = min(config.res_until, config.steps // 3)
        self.schedule = (spectrum_schedule(np.asarray(self.images), until, config.res_energy, config.res_min_side)
                         if config.res_schedule == "spectrum" else [(0, 1)])
        if len(self.schedule) > 1:
            log.info("resolution schedule: %s", ", ".join(f"1/{f} from step {s}" for s, f in self.schedule))
        self.levels: dict[int, tuple] = {1: (self.images, self.Ks, self.width, self.height)}
        self.crops = None  # the full-resolution windows (crop_tiles > 1), made at first use
        self.rule = PlateauRule.from_config(config, full_resolution_from=self.schedule[-1][0])
        self.stop_state = PlateauRule.initial()
        self.best = None  # (state, strategy state) of the best validation check
        self.val_pair_capacity = 0  # the checks' pair buffer (0: start from the step's)
        self.val_pairs: tuple[int, int] | None = None  # (most pairs a held-out view needed, live count then)
        self.factor: int | None = None  # the scale the last update trained at
        self.extent = float(dataset.scene_extent)
        if not (math.isfinite(self.extent) and self.extent > 0):
            raise ValueError(f"dataset {config.data}: scene extent {self.extent} is not a positive number")
        self.optimizers, self.step_fn = make_train_step(config, render_fn)
        self.means_lr = optim.means_schedule(config, self.extent)
        self.strategy = make_strategy(config)  # the trainer calls its hooks, whatever it is
        self.render_fn = render_fn
        self.changed = False  # the last step's hooks may have changed the count
        self.rollbacks = 0
        self.consecutive = 0  # non-finite steps in a row
        self.prior_seconds = 0.0
        self.prior_peak_rss_mb = 0.0  # training processes before a resume
        self.epoch_pairs, self.epoch_steps = 0, 0  # the most pairs a view needed, over steps since the last refit
        path = out_dir / CHECKPOINT_NAME
        if resume and path.exists():
            self.restore(path)
        else:
            if resume:
                log.warning("%s: no checkpoint to resume from; starting a new run", path)
            self._fresh()

    # -- set-up -----------------------------------------------------------------------------
    def _fresh(self):
        c = self.config
        rng = np.random.default_rng(c.seed)
        box = random_init_box([v.camera for v in self.ds.train], self.ds.scene_center, 0.5 * self.extent)
        points, colors = self.ds.points, self.ds.point_colors
        carved = None
        if c.init_carve and needs_random_init(finite_points(points), c):
            carved = subject_points(self.ds.train, *box, c.init_random_points, rng)
        if carved is not None:
            points, colors = carved
            log.info("%s: %d initial points inside the subject's silhouettes (a plain background in the views)",
                     c.data, len(points))
        init = initial_surfels(points, colors, *box, self.extent, c, rng)
        warn_about_inputs(c, self.ds, carved=None if carved is None else len(carved[0]))
        init, cap = self.strategy.initial_pool(init, rng)
        self.initial_count = init.num
        self.sstate = self.strategy.init_state(init.num)
        params, active = pad_params(init, cap)
        self.state = new_state(params, active, self.optimizers, self._fresh_pose(), self._fresh_exposure())
        self.pair_capacity = c.raster.pair_capacity or self._measure_pairs()

    def _fresh_pose(self):
        """Zero pose corrections, one per training view (None without pose refinement)."""
        return pose_mod.init_pose(len(self.view_names), self.extent) if self.config.pose_refine else None

    def _fresh_exposure(self):
        """No exposure corrections, one per training view (None without exposure compensation)."""
        return exposure_mod.init_exposure(len(self.view_names)) if self.config.exposure_compensation else None

    def _measure_pairs(self) -> int:
        """Size the pair buffer from an eager render of the first view at the first step's scale
        (automatic capacity): sized at full resolution, a run starting at 1/4 scale kept a buffer
        16x its need for an epoch and then compiled the step again to shrink it."""
        from ghsplat_jax.core.camera import Camera
        from ghsplat_jax.raster.render import render
        from ghsplat_jax.train.state import render_params

        _, Ks, width, height = self.level(0)
        cam = Camera(Ks[0], self.w2cs[0], width, height)
        s = self.state
        rcfg = dataclasses.replace(self.config.raster, pair_capacity=None)
        out = render(render_params(s.params, s.active, cam.world_to_cam), cam, rcfg)
        return pair_bucket(2 * int(out.stats.num_pairs))

    def restore(self, path: Path):
        self.state, meta = load_run_checkpoint(path, self.optimizers)
        self.pair_capacity = int(meta["pair_capacity"])
        self.rollbacks = int(meta.get("rollbacks", 0))
        self.stop_state = meta.get("stop_rule") or PlateauRule.initial()
        self.prior_seconds = float(meta.get("train_seconds", 0.0))
        self.prior_peak_rss_mb = float(meta.get("peak_rss_mb", 0.0))
        self.initial_count = int(meta["initial_count"])
        template = self.strategy.init_state(self.initial_count)
        saved = ckpt.load_aux(path, template)
        if saved is None:  # a checkpoint from before strategies kept state: theirs is a function of the config
            log.info("%s: no strategy state saved; rebuilt from the config", path)
        self.sstate = template if saved is None else saved
        c = self.config
        for field, setting, on, fresh in (("pose", "pose_refine", c.pose_refine, self._fresh_pose),
                                          ("exposure", "exposure_compensation", c.exposure_compensation,
                                           self._fresh_exposure)):
            saved = getattr(self.state, field)
            if (saved is not None) != on or (saved is not None and saved.num_views != len(self.view_names)):
                log.warning("%s: the checkpoint's %s corrections (%s) do not fit this run's %s = %s and %d training "
                            "views; %s", path, field, saved.num_views if saved is not None else "none", setting, on,
                            len(self.view_names), "starting them from zero" if on else "dropping them")
                self.state = dataclasses.replace(self.state, **{field: fresh()})
        log.info("resumed from %s at step %d", path, int(self.state.step))

    def save(self, seconds: float):
        s = self.state
        extra = dict(step=int(s.step), capacity=s.capacity, sh_degree=s.params.sh_degree,
                     pair_capacity=self.pair_capacity, rollbacks=self.rollbacks, train_seconds=seconds,
                     initial_count=self.initial_count, peak_rss_mb=max(peak_rss_mb(), self.prior_peak_rss_mb),
                     config=self.config.to_dict(), stop_rule=self.stop_state,
                     pose_views=s.pose.num_views if s.pose is not None else 0,
                     exposure_views=s.exposure.num_views if s.exposure is not None else 0)
        extra.update(self.strategy.meta(self.sstate))
        ckpt.save_checkpoint(self.out / CHECKPOINT_NAME, s, extra, aux=self.sstate)
        from ghsplat_jax.io_utils import write_json

        if s.pose is not None:
            write_json(self.out / POSE_NAME, self.pose_report())
        if s.exposure is not None:
            write_json(self.out / EXPOSURE_NAME, self.exposure_report())

    def pose_report(self) -> dict | None:
        """pose_corrections.json: the scene extent, each training view's correction, a summary."""
        if self.state.pose is None:
            return None
        rows = pose_mod.corrections_report(self.state.pose, self.view_names)
        return {"scene_extent": self.extent, "step": int(self.state.step),
                "summary": pose_mod.corrections_summary(rows), "views": rows}

    def exposure_report(self) -> dict | None:
        """exposure_corrections.json: each training view's gains and offsets, a summary."""
        if self.state.exposure is None:
            return None
        rows = exposure_mod.corrections_report(self.state.exposure, self.view_names)
        return {"step": int(self.state.step), "summary": exposure_mod.corrections_summary(rows), "views": rows}

    def means_lr_at(self, step: int) -> float:
        """The scheduled means learning rate of training step `step` (before the stop rule's annealing)."""
        return self.means_lr(self.strategy.schedule_step(self.sstate, step))

    def context(self) -> StrategyContext:
        return StrategyContext(extent=self.extent, Ks=self.Ks, w2cs=self.w2cs, width=self.width, height=self.height,
                               pair_capacity=self.pair_capacity, means_lr=self.means_lr_at, raster=self.config.raster,
                               render_fn=self.render_fn,
                               validate=(lambda state: self.validate(state)["psnr"]) if self.config.val_every else None,
                               train_copy=self.train_copy)

    def _hook(self, name: str, *args) -> dict:
        """Call a strategy hook on the current state; keep what it returns."""
        ctx = self.context()
        self.state, self.sstate, info = getattr(self.strategy, name)(ctx, self.state, self.sstate, *args)
        self.pair_capacity = max(self.pair_capacity, ctx.pair_capacity)
        self.changed = bool(info)
        return info

    def finish(self) -> dict:
        if self.best is not None and self.best[0] is not self.state:
            log.info("the model of the best validation check (step %d, %.2f dB) is the result",
                     self.stop_state["best_step"], self.stop_state["best_psnr"])
            self.state, self.sstate = self.best
        return self._hook("at_end")

    # -- resolution and validation ------------------------------------------------------------
    def level(self, step: int) -> tuple:
        """(images, Ks, width, height) of the scale `step` trains at."""
        f = factor_at(self.schedule, step)
        if f not in self.levels:
            images = box_downscale(np.asarray(self.images), f)
            self.levels[f] = (jnp.asarray(images), jnp.asarray(scale_intrinsics(np.asarray(self.Ks), f)),
                              images.shape[2], images.shape[1])
        return self.levels[f]

    def view_at(self, step: int) -> tuple:
        """(view index, image, K, width, height) that `step` trains on: a whole view at the
        step's scale, or at full resolution with crop_tiles > 1 one window of a view (every
        window of every view once an epoch)."""
        c, n = self.config, self.images.shape[0]
        images, Ks, width, height = self.level(step)
        tiles = c.crop_tiles ** 2 if factor_at(self.schedule, step) == 1 else 1
        if tiles == 1:
            v = view_order(c.seed, step, n)
            return v, images[v], Ks[v], width, height
        if self.crops is None:
            crops, crop_Ks, w, h = crop_stack(np.asarray(images), np.asarray(Ks), c.crop_tiles)
            self.crops = (jnp.asarray(crops), jnp.asarray(crop_Ks), w, h)
        crops, crop_Ks, w, h = self.crops
        item = view_order(c.seed, step, n * tiles)
        return item // tiles, crops[item], crop_Ks[item], w, h

    def validate(self, state: TrainState | None = None) -> dict:
        """The held-out views' mean PSNR (and L1) of the current model (or of `state`), at full
        resolution."""
        from ghsplat_jax.raster.render import render
        from ghsplat_jax.train.losses import l1, psnr
        from ghsplat_jax.train.state import render_params

        lean = dataclasses.replace(self.config.raster, median=False, distortion=False, depth_normal=False)
        s, psnrs, l1s = self.state if state is None else state, [], []
        # The checks keep a pair buffer of their own: while training runs at reduced resolution its
        # buffer shrinks to fit, and a shared one would see-saw between the two sizes, compiling the
        # step and the check's render again at every check.
        capacity, most = self.val_pair_capacity or self.pair_capacity, 0
        for v in self.val_views:
            while True:
                rcfg = dataclasses.replace(lean, pair_capacity=capacity, on_overflow="report")
                out = render(render_params(s.params, s.active, v.camera.world_to_cam), v.camera, rcfg)
                if int(out.stats.overflow) <= 0:
                    break
                capacity = regrown_capacity(capacity, int(out.stats.num_pairs))
            most = max(most, int(out.stats.num_pairs))
            target = jnp.asarray(v.image)
            psnrs.append(float(psnr(out.rgb, target)))
            l1s.append(float(l1(out.rgb, target)))
        self.val_pair_capacity = capacity
        if state is None:
            self.val_pairs = (most, s.num_active())
        return {"psnr": float(np.mean(psnrs)), "l1": float(np.mean(l1s)), "num_views": len(psnrs)}

    def check(self, step: int) -> dict:
        """A validation check after `step` steps: the strategy's hook, then the stop rule, whose
        anneal or stop a strategy may turn into growth (on_plateau: the plateau judge)."""
        # "early": a check the stop rule does not count (up to stop_after or full resolution, whichever
        # is later); the strategy's count rule does not judge by it either.
        val = self.validate() | {"early": step <= self.rule.stop_after}
        self.sstate, info = self.strategy.on_validation(self.context(), self.state, self.sstate, step, val)
        before = self.stop_state
        self.stop_state, action = self.rule.update(before, step, val["psnr"])
        if action in ("anneal", "stop"):
            self.sstate, grows, more = self.strategy.on_plateau(self.context(), self.state, self.sstate, step,
                                                                 self.stop_state["best_psnr"])
            info = info | more
            if grows:  # the model grows instead: the rule waits for a plateau of the larger model
                self.stop_state = self.rule.held(before, self.stop_state)
                action = "grow"
        if self.stop_state["best_step"] == step:  # also when the same check ends the run
            self.best = (self.state, self.sstate)
        if action == "anneal":
            log.info("step %d: validation PSNR flat for %d checks (best %.2f dB at step %d); means learning rate x %g",
                     step, self.rule.patience, self.stop_state["best_psnr"], self.stop_state["best_step"],
                     self.rule.anneal)
        return {"val_psnr": val["psnr"], "val_l1": val["l1"], "stop_action": action} | info

    @property
    def stopped(self) -> bool:
        return self.stop_state.get("stopped_at") is not None

    # -- one iteration ------------------------------------------------------------------
    def update(self, state: TrainState, step: int) -> tuple[int, TrainState, dict]:
        """(view, `state` after training step `step` (0-based) on its view, the step's metrics).
        A render that dropped pairs grows the buffer and is redone (one compile per bucket)."""
        v, image, K, width, height = self.view_at(step)
        self._presize_for_scale(step, state)
        while True:
            rcfg = step_raster_config(self.config, self.pair_capacity, step)
            lr = jnp.float32(self.means_lr_at(step) * self.stop_state["lr_scale"])
            per_view = state.pose is not None or state.exposure is not None
            view = {"view": jnp.int32(v)} if per_view else {}
            new, m = self.step_fn(state, image, K, self.w2cs[v], lr, rcfg, width, height, **view)
            m = jax.device_get(m)
            if int(m["overflow"]) <= 0:
                return v, new, {k: np.asarray(val).item() for k, val in m.items()} | {"means_lr": float(lr)}
            self.pair_capacity = regrown_capacity(self.pair_capacity, int(m["num_pairs"]))
            log.info("step %d: %d tile-surfel pairs overflowed; pair capacity -> %d", step, int(m["overflow"]),
                     self.pair_capacity)

    def _presize_for_scale(self, step: int, state: TrainState) -> None:
        """At a switch to a finer training scale, grow an automatic pair buffer to what the last
        check's full-resolution renders predict for it (pairs scale with the pixels and the live
        count): the step compiles for the new image size anyway, where growing by overflows
        compiled it once or twice more (384x288: 10-24 s each)."""
        f, previous = factor_at(self.schedule, step), self.factor
        self.factor = f
        if previous is None or f >= previous or self.val_pairs is None or self.config.raster.pair_capacity:
            return
        pairs, count = self.val_pairs
        tiles = self.config.crop_tiles ** 2 if f == 1 else 1  # windows of a view, each a tiles-th of it
        need = pair_bucket(pairs * state.num_active() / max(count, 1) / (f * f * tiles))
        if need > self.pair_capacity:
            log.info("step %d: training at 1/%d scale from here; pair capacity %d -> %d (the last check's pairs)",
                     step, f, self.pair_capacity, need)
            self.pair_capacity = need

    def train_copy(self, state: TrainState, start: int, steps: int) -> TrainState:
        """`state` trained on the views and learning rates of steps start..start+steps-1, as the run
        trains them, without strategy rounds, checks or logs: a counterfactual a strategy may judge
        by. A non-finite step is skipped."""
        for step in range(start, start + steps):
            _, new, m = self.update(state, step)
            state = new if m["finite"] else state
        return state

    def step(self, step: int, before_round=None) -> dict:
        """Run training step `step` (0-based), handling pair overflow and non-finite results.
        `before_round()` is called after the update and before the strategy's round of this step
        (which may reset every opacity), as 3DGS evaluates its test views."""
        c = self.config
        v, new, m = self.update(self.state, step)
        self.changed = False
        if not m["finite"]:
            self.rollbacks += 1
            self.consecutive += 1
            log.warning("step %d (view %d): non-finite loss or parameters; rolled back to the last good state "
                        "(%d in a row, %d in total)", step, v, self.consecutive, self.rollbacks)
            if self.consecutive >= c.max_consecutive_rollbacks or self.rollbacks >= c.max_total_rollbacks:
                raise TrainingDivergedError(
                    f"training diverged: {self.consecutive} consecutive and {self.rollbacks} total non-finite steps "
                    f"(last at step {step}); try lower learning rates or loss weights (lambda_dist, lambda_normal)")
            self.state = dataclasses.replace(self.state, step=self.state.step + 1)  # skip this view
            m["rolled_back"] = True
            if before_round is not None:
                before_round()
            return m
        self.consecutive = 0
        self.state = new
        self._refit_pairs(int(m["num_pairs"]))
        if before_round is not None:
            before_round()
        m.update(self._hook("after_step", step + 1))
        return m

    def _refit_pairs(self, pairs: int) -> None:
        """After each epoch of steps, shrink an automatically sized pair buffer to the bucket of
        the most pairs a view needed, when that is at most half of it. Binning and the compositor's
        set-up work per slot of the buffer, and a run from random points starts with several
        times the pairs it settles at (lego kept a 2M-pair buffer for 290-460k pairs). Growth on
        overflow doubles, so the factor of two keeps the buffer from see-sawing; each change
        compiles the step once more, which is why an accelerator keeps its buffer
        (`compiles_cost_more_than_slots`). A capacity set in the config is left as it grows."""
        self.epoch_pairs, self.epoch_steps = max(self.epoch_pairs, pairs), self.epoch_steps + 1
        if self.epoch_steps < self.images.shape[0]:
            return
        fit = pair_bucket(self.epoch_pairs)
        if (self.config.raster.pair_capacity is None and not compiles_cost_more_than_slots()
                and 2 * fit <= self.pair_capacity):
            log.info("at most %d tile-surfel pairs per view over the last epoch; pair capacity %d -> %d",
                     self.epoch_pairs, self.pair_capacity, fit)
            self.pair_capacity = fit
        self.epoch_pairs, self.epoch_steps = 0, 0


def _sync(fh) -> None:
    """Put every logged step on disk before a checkpoint is written: a resume keeps the log's
    lines up to the checkpoint's step, so a log that lagged its checkpoint (lines still in the
    buffer when the process was killed) would lose those steps for good."""
    fh.flush()
    os.fsync(fh.fileno())


def _truncate_stats(path: Path, last_step: int) -> None:
    from ghsplat_jax.io_utils import atomic_write

    if not path.is_file():
        return
    keep = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line)["step"] <= last_step:
                keep.append(line)
        except (ValueError, KeyError, TypeError):
            continue  # a line cut short by a crash
    with atomic_write(path, "w") as fh:
        fh.write("".join(x + "\n" for x in keep))


def _write_curve_point(curve, test_eval, session, step: int, seconds, num: int, revision: str, host: str) -> float:
    """Evaluate the test views now and append the point to the test curve; returns its seconds.
    Each point names its code revision, its kind of machine and the load then: a curve resumed
    later (another revision, host or load) is a time axis only as far as its points agree."""
    t = time.perf_counter()
    point = test_eval(session.state.params, session.state.active, session.pair_capacity)
    spent = time.perf_counter() - t
    record = dict(step=step, elapsed_s=round(seconds() - spent, 3), num_surfels=num, eval_seconds=round(spent, 3),
                  code_revision=revision, host=host, load_average=[round(x, 2) for x in os.getloadavg()])
    curve.write(json.dumps(_jsonable(record | point), allow_nan=False) + "\n")
    curve.flush()
    log.info("step %d: test PSNR %.2f dB over %d views (%.1f s to evaluate)", step, point["psnr"], point["num_views"],
             spent)
    return spent


@contextlib.contextmanager
def _terminate_as_interrupt():
    """Treat SIGTERM (a job scheduler's or `kill`'s stop) like Ctrl-C while training, so it also
    saves a checkpoint; background jobs started by a shell ignore SIGINT, so kill is their way."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def with_flagged_exposure(config: TrainConfig, dataset) -> TrainConfig:
    """`config` with exposure compensation on where `exposure_compensation_when_flagged` asks for
    it and the exposure check flags a training photo (data/exposure.py); as it was otherwise. The
    check is a function of the data, so a resumed run decides the same."""
    if config.exposure_compensation or not config.exposure_compensation_when_flagged:
        return config
    flagged = flagged_training_photos(dataset)
    if not flagged:
        return config
    log.info("%s: exposure compensation on: training photo(s) %s exposed unlike the rest", config.data,
             ", ".join(flagged))
    return dataclasses.replace(config, exposure_compensation=True)


def train(config: TrainConfig, out_dir, dataset=None, resume: bool = False, render_fn=None,
          until: int | None = None, test_eval=None) -> TrainResult:
    """Train (or resume) a run into `out_dir`; see the module docstring. Ctrl-C (or SIGTERM)
    saves a checkpoint and raises KeyboardInterrupt. `until`: stop after that step with a
    checkpoint (no point_cloud.ply), to be resumed later. `test_eval(params, active,
    pair_capacity) -> dict`: the test views' metrics, written to test_curve.jsonl every
    `config.test_curve_every` steps (eval/evaluate.py: test_curve_metrics), its time left out of
    the training seconds. Sets the process's host memory policy
    (`host_memory.reuse_freed_memory`), as the `ghsplat` command does."""
    from tqdm.auto import tqdm

    reuse_freed_memory()
    config = config.resolved()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dataset = dataset if dataset is not None else load_training_data(config)
    config = with_flagged_exposure(config, dataset)
    session = TrainingSession(config, out, dataset, resume, render_fn)
    save_config(config, out / CONFIG_NAME)
    start = int(session.state.step)
    t0 = time.perf_counter()
    paused = 0.0  # seconds spent on the test curve, which are not training time
    seconds = lambda: session.prior_seconds + time.perf_counter() - t0 - paused  # noqa: E731
    num = int(jnp.sum(session.state.active))
    bar = tqdm(total=config.steps, initial=start, disable=not config.progress, desc="train", dynamic_ncols=True)
    if start:
        _truncate_stats(out / STATS_NAME, start)  # drop steps after the checkpoint: they are redone
    stats = open(out / STATS_NAME, "a" if start else "w")
    curve = None
    if test_eval is not None and config.test_curve_every:
        if start:
            _truncate_stats(out / TEST_CURVE_NAME, start)
        curve = open(out / TEST_CURVE_NAME, "a" if start else "w")
    logs = [stats] if curve is None else [stats, curve]  # synced before each checkpoint, closed at the end
    last_t, last_step = time.perf_counter(), start
    step = start
    stop = config.steps if until is None else min(until, config.steps)

    revision = code_revision() if curve is not None else ""
    host = host_label(machine_info(start_backend=False) | {"device": device_name()}) if curve is not None else ""

    def curve_point():  # inside session.step(step): the model before the step's strategy round
        nonlocal paused, last_t
        spent = _write_curve_point(curve, test_eval, session, step + 1, seconds, num, revision, host)
        paused += spent  # the test curve's time is not training time,
        last_t += spent  # nor does the steps-per-second rate count it

    with _terminate_as_interrupt():
        try:
            while step < stop and not session.stopped:
                due = curve is not None and (step + 1) % config.test_curve_every == 0
                m = session.step(step, before_round=curve_point if due else None)
                step += 1
                if session.changed:
                    num = int(jnp.sum(session.state.active))
                if config.val_every and step % config.val_every == 0 and not m.get("rolled_back"):
                    m.update(session.check(step))
                    if session.stopped:
                        log.info("step %d: stopped: %s; best validation PSNR %.2f dB at step %d", step,
                                 session.stop_state["reason"], session.stop_state["best_psnr"],
                                 session.stop_state["best_step"])
                now = time.perf_counter()
                rate = (step - last_step) / max(now - last_t, 1e-9)
                record = dict(step=step, num_surfels=num, capacity=session.state.capacity,
                              pair_capacity=session.pair_capacity, elapsed_s=round(seconds(), 3), steps_per_s=rate)
                record.update(m)
                stats.write(json.dumps(_jsonable(record), allow_nan=False) + "\n")
                bar.update(1)
                if step % 10 == 0 or step == config.steps:
                    stats.flush()
                    bar.set_postfix(loss=f"{m['loss']:.4f}", psnr=f"{m['psnr']:.2f}", n=num, its=f"{rate:.2f}")
                    last_t, last_step = now, step
                if step % MAPS_CHECK_EVERY == 0:
                    release_compiled_programs(IN_RUN_MAP_SHARE)  # a long run's compiles: see host_memory
                if config.checkpoint_every and step % config.checkpoint_every == 0:
                    for fh in logs:
                        _sync(fh)
                    session.save(seconds())
        except KeyboardInterrupt:
            for fh in logs:
                _sync(fh)
            session.save(seconds())
            log.warning("interrupted at step %d; checkpoint saved to %s (continue with --resume)",
                        int(session.state.step), out / CHECKPOINT_NAME)
            raise
        finally:
            for fh in logs:
                fh.close()
            bar.close()
    if session.stopped:
        step = max(step, int(session.stop_state["stopped_at"]))  # a resumed stopped run ran them before
    finished = step >= config.steps or session.stopped
    if finished:
        end_info = session.finish()  # e.g. a final contribution-pruning pass, before the PLY and checkpoint
        if end_info:
            log.info("end of training: %s", end_info)
    total = seconds()
    session.save(total)
    pose = session.pose_report()
    if pose is not None and finished:
        pose["summary"]["warnings"] = pose_mod.warn_large(pose["views"])
    exposure = session.exposure_report()
    if exposure is not None and finished:
        exposure["summary"]["matched"] = exposure_mod.describe_large(exposure["views"])
    result = TrainResult(session.state, step, total, session.rollbacks, out, session.initial_count,
                         jax.device_get(session.sstate), finished, session.stop_state if config.val_every else None,
                         pose, exposure, session.held_out if config.val_every else None)
    if finished:
        from ghsplat_jax.data.ply import save_ply

        save_ply(result.surfels, out / PLY_NAME)
    return result
