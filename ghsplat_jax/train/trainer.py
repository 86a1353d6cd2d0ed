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
import signal
import threading
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.train import checkpoint as ckpt
from ghsplat_jax.train import densify, optim
from ghsplat_jax.train.config import TrainConfig, save_config
from ghsplat_jax.train.run_dir import (CHECKPOINT_NAME, CONFIG_NAME, PLY_NAME, STATS_NAME, load_run_checkpoint,
                                       load_training_data, peak_rss_mb)
from ghsplat_jax.train.state import TrainState, grow, initial_surfels, new_state, pad_params, random_init_box
from ghsplat_jax.train.step import make_train_step

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
    """Power-of-two pair capacity with 25% headroom (few buckets: few recompiles)."""
    return 1 << max(12, math.ceil(math.log2(max(pairs, 1) * 1.25)))


def stack_views(views):
    sizes = {(v.camera.width, v.camera.height) for v in views}
    if len(sizes) != 1:
        raise ValueError(f"training views must share one image size, got {sorted(sizes)}")
    (w, h), = sizes
    images = jnp.asarray(np.stack([np.asarray(v.image, np.float32) for v in views]))
    Ks = jnp.asarray(np.stack([np.asarray(v.camera.K, np.float32) for v in views]))
    w2cs = jnp.asarray(np.stack([np.asarray(v.camera.world_to_cam, np.float32) for v in views]))
    return images, Ks, w2cs, w, h


def step_raster_config(config: TrainConfig, pair_capacity: int):
    """The run's rendering settings as the training step uses them: a static pair buffer whose
    overflow is reported (and redone), and only the outputs the losses read."""
    normal_loss = config.lambda_normal > 0
    return dataclasses.replace(config.raster, pair_capacity=pair_capacity, on_overflow="report",
                               median=config.raster.median and normal_loss and config.depth_ratio > 0,
                               distortion=config.raster.distortion and config.lambda_dist > 0)


def _jsonable(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        v = np.asarray(v).item() if np.ndim(v) == 0 else v
        if isinstance(v, float) and not math.isfinite(v):
            v = None  # stats.jsonl stays valid JSON; NaNs never reach disk
        out[k] = v
    return out


def _white(c: TrainConfig) -> bool:
    return all(b == 1.0 for b in c.raster.background)


def last_reset_before(c: TrainConfig, it: int) -> int | None:
    """The iteration of the last opacity reset before `it` (None when there was none)."""
    resets = []
    if c.opacity_reset_every > 0:
        k = (min(it - 1, c.densify_until - 1)) // c.opacity_reset_every
        if k >= 1:
            resets.append(k * c.opacity_reset_every)
        if _white(c) and c.densify_from < it and c.densify_from < c.densify_until:
            resets.append(c.densify_from)
    return max(resets) if resets else None


class _Session:
    """Mutable loop state of one run (host side)."""

    def __init__(self, config: TrainConfig, out_dir: Path, dataset, resume: bool, render_fn=None):
        self.config, self.out = config, out_dir
        self.ds = dataset
        self.images, self.Ks, self.w2cs, self.width, self.height = stack_views(dataset.train)
        self.extent = float(dataset.scene_extent)
        if not (math.isfinite(self.extent) and self.extent > 0):
            raise ValueError(f"dataset {config.data}: scene extent {self.extent} is not a positive number")
        self.optimizers, self.step_fn = make_train_step(config, render_fn)
        self.means_lr = optim.means_schedule(config, self.extent)
        self.dparams = densify.DensifyParams.from_config(config, self.extent)
        self.densify_fn = densify.densify_jit
        self.reset_fn = densify.reset_opacity_jit
        self.count_fn = densify.count_candidates_jit
        self.render_fn = render_fn
        self.rollbacks = 0
        self.consecutive = 0  # non-finite steps in a row
        self.prior_seconds = 0.0
        self.prior_peak_rss_mb = 0.0  # training processes before a resume
        path = out_dir / CHECKPOINT_NAME
        if resume and path.exists():
            self._restore(path)
        else:
            if resume:
                log.warning("%s: no checkpoint to resume from; starting a new run", path)
            self._fresh()

    # -- set-up -----------------------------------------------------------------------------
    def _fresh(self):
        c = self.config
        rng = np.random.default_rng(c.seed)
        box = random_init_box([v.camera for v in self.ds.train], self.ds.scene_center, 0.5 * self.extent)
        init = initial_surfels(self.ds.points, self.ds.point_colors, *box, self.extent, c, rng)
        if c.strategy == "budget":
            self.max_surfels = c.max_surfels or 5 * init.num
            if init.num > self.max_surfels:
                init = init.take(np.sort(rng.choice(init.num, self.max_surfels, replace=False)))
            cap = self.max_surfels
        else:
            self.max_surfels = 0
            cap = max(c.initial_capacity, 2 * init.num, 1024)
        self.initial_count = init.num
        params, active = pad_params(init, cap)
        self.state = new_state(params, active, self.optimizers)
        self.pair_capacity = c.raster.pair_capacity or self._measure_pairs()

    def _measure_pairs(self) -> int:
        """Size the pair buffer from an eager render of the first view (automatic capacity)."""
        from ghsplat_jax.core.camera import Camera
        from ghsplat_jax.raster.render import render
        from ghsplat_jax.train.state import render_params

        cam = Camera(self.Ks[0], self.w2cs[0], self.width, self.height)
        s = self.state
        rcfg = dataclasses.replace(self.config.raster, pair_capacity=None)
        out = render(render_params(s.params, s.active, cam.world_to_cam), cam, rcfg)
        return pair_bucket(2 * int(out.stats.num_pairs))

    def _restore(self, path: Path):
        self.state, meta = load_run_checkpoint(path, self.optimizers)
        self.pair_capacity = int(meta["pair_capacity"])
        self.rollbacks = int(meta.get("rollbacks", 0))
        self.prior_seconds = float(meta.get("train_seconds", 0.0))
        self.prior_peak_rss_mb = float(meta.get("peak_rss_mb", 0.0))
        self.initial_count = int(meta["initial_count"])
        self.max_surfels = int(meta.get("max_surfels", 0))
        log.info("resumed from %s at step %d", path, int(self.state.step))

    def save(self, seconds: float):
        s = self.state
        extra = dict(step=int(s.step), capacity=s.capacity, sh_degree=s.params.sh_degree,
                     pair_capacity=self.pair_capacity, rollbacks=self.rollbacks, train_seconds=seconds,
                     initial_count=self.initial_count, max_surfels=self.max_surfels,
                     peak_rss_mb=max(peak_rss_mb(), self.prior_peak_rss_mb), config=self.config.to_dict())
        ckpt.save_checkpoint(self.out / CHECKPOINT_NAME, s, extra)

    # -- one iteration ------------------------------------------------------------------
    def step(self, step: int) -> dict:
        """Run training step `step` (0-based), handling pair overflow and non-finite results."""
        c = self.config
        v = view_order(c.seed, step, self.images.shape[0])
        while True:
            rcfg = step_raster_config(c, self.pair_capacity)
            lr = jnp.float32(self.means_lr(step))
            new, m = self.step_fn(self.state, self.images[v], self.Ks[v], self.w2cs[v], lr, rcfg, self.width,
                                  self.height)
            m = jax.device_get(m)
            if int(m["overflow"]) <= 0:
                break
            # The render dropped pairs: discard the step, grow the buffer, redo (one compile per bucket).
            self.pair_capacity = max(2 * self.pair_capacity, pair_bucket(int(m["num_pairs"])))
            log.info("step %d: %d tile-surfel pairs overflowed; pair capacity -> %d", step, int(m["overflow"]),
                     self.pair_capacity)
        m = {k: np.asarray(val).item() for k, val in m.items()}
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
            return m
        self.consecutive = 0
        self.state = new
        m.update(self.densify(step + 1))
        return m

    def densify(self, it: int) -> dict:
        """2DGS schedule, counted in completed iterations `it` (the reference's 1-based counter)."""
        c = self.config
        info = {}
        if it >= c.densify_until:
            return info
        white_bg = _white(c)
        if it > c.densify_from and it % c.densify_every == 0:
            n_active = int(jnp.sum(self.state.active))
            if c.strategy == "budget":
                target = densify.budget_target(c, it, self.initial_count, self.max_surfels)
                max_new = max(target - n_active, 0)
            else:
                self._ensure_capacity(n_active)
                max_new = self.state.capacity
            key = jax.random.fold_in(jax.random.PRNGKey(c.seed), it)
            prune_big = it > c.opacity_reset_every
            # Opacities just reset to 0.01 are below the prune threshold: give them time to recover.
            last = last_reset_before(c, it)
            prune_transparent = last is None or it - last >= c.reset_recovery_steps
            self.state, counts = self.densify_fn(self.state, key, jnp.int32(max_new), jnp.bool_(prune_big),
                                                 p=self.dparams, prune_transparent=jnp.bool_(prune_transparent))
            info.update({k: int(v) for k, v in counts.items()})
        if c.opacity_reset_every > 0 and (it % c.opacity_reset_every == 0 or (white_bg and it == c.densify_from)):
            self.state = self.reset_fn(self.state, value=c.opacity_reset_value)
            info["opacity_reset"] = True
        return info

    def _ensure_capacity(self, n_active: int):
        """Grow the pool (a recompile per bucket) when the candidates would not fit."""
        need = n_active + int(self.count_fn(self.state, grad_threshold=self.dparams.grad_threshold))
        cap = self.state.capacity
        limit = cap * (1.0 - self.config.capacity_headroom)
        if need <= limit:
            return
        new_cap = cap
        while new_cap * (1.0 - self.config.capacity_headroom) < need:
            new_cap *= 2
        log.info("surfel pool %d -> %d slots", cap, new_cap)
        self.state = grow(self.state, new_cap)


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


def train(config: TrainConfig, out_dir, dataset=None, resume: bool = False, render_fn=None,
          until: int | None = None) -> TrainResult:
    """Train (or resume) a run into `out_dir`; see the module docstring. Ctrl-C (or SIGTERM)
    saves a checkpoint and raises KeyboardInterrupt. `until`: stop after that step with a
    checkpoint (no point_cloud.ply), to be resumed later."""
    from tqdm.auto import tqdm

    config = config.resolved()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dataset = dataset if dataset is not None else load_training_data(config)
    session = _Session(config, out, dataset, resume, render_fn)
    save_config(config, out / CONFIG_NAME)
    start = int(session.state.step)
    t0 = time.perf_counter()
    seconds = lambda: session.prior_seconds + time.perf_counter() - t0  # noqa: E731
    num = int(jnp.sum(session.state.active))
    bar = tqdm(total=config.steps, initial=start, disable=not config.progress, desc="train", dynamic_ncols=True)
    if start:
        _truncate_stats(out / STATS_NAME, start)  # drop steps after the checkpoint: they are redone
    stats = open(out / STATS_NAME, "a" if start else "w")
    last_t, last_step = time.perf_counter(), start
    step = start
    stop = config.steps if until is None else min(until, config.steps)
    with _terminate_as_interrupt():
        try:
            while step < stop:
                m = session.step(step)
                step += 1
                if "pruned" in m or "opacity_reset" in m:
                    num = int(jnp.sum(session.state.active))
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
                if config.checkpoint_every and step % config.checkpoint_every == 0:
                    session.save(seconds())
        except KeyboardInterrupt:
            stats.flush()
            session.save(seconds())
            log.warning("interrupted at step %d; checkpoint saved to %s (continue with --resume)", int(session.state.step),
                        out / CHECKPOINT_NAME)
            raise
        finally:
            stats.close()
            bar.close()
    total = seconds()
    session.save(total)
    result = TrainResult(session.state, step, total, session.rollbacks, out, session.initial_count)
    if step >= config.steps:
        from ghsplat_jax.data.ply import save_ply

        save_ply(result.surfels, out / PLY_NAME)
    return result
