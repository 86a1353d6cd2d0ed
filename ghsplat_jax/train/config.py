"""Every training hyperparameter in one dataclass (2DGS defaults), TOML overrides and saving.

A field's comment says what it does; experiment files (experiments/*.toml) and
`ghsplat train --config` override fields by name, and the resolved config is saved with
the run as config.toml so a run can be reproduced or resumed.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

from ghsplat_jax.config_values import coerce
from ghsplat_jax.raster.config import RasterConfig

# The densification strategies (train/strategy.py registers them; a registered class adds its name).
STRATEGIES = ("default", "budget", "mcmc")
# Flat names that earlier configs (and experiment files) used for fields of the raster section.
RASTER_ALIASES = {"near": "near", "far": "far", "background": "background", "tile_size": "tile_size",
                  "chunk_size": "chunk_size", "batch_chunks": "batch_chunks", "raster_backward": "backward",
                  "pair_capacity": "pair_capacity"}


class ConfigError(ValueError):
    """A config file or override that cannot be applied; the message names the file and key."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    # --- data ---------------------------------------------------------------------------
    data: str = ""                      # dataset folder (absolute, or relative to the datasets root)
    downscale: float = 1.0              # image downscale factor applied by the dataset reader
    test_every: int = 8                 # every n-th image is a test view unless the dataset has a split
    max_views: int = 0                  # cap on the number of images read (0: all)
    seed: int = 0                       # view order, initialisation and split noise
    pose_noise: float = 0.0             # robustness studies: move each training camera by this fraction of
                                        # the scene extent (seeded by `seed`; test views keep true poses)

    # --- schedule -------------------------------------------------------------------------
    steps: int = 30_000                 # optimisation steps, one view per step (2DGS: 30k)
    sh_degree: int = 3                  # final spherical-harmonics degree
    sh_increase_every: int = 1000       # one more SH band every this many steps
    # Short runs: scale every step-based setting by steps / 30000. A smoke test, not the method:
    # densification then starts before the images are fitted (step 17 of 1000) and, measured on
    # fern at 504x378, the count grew 13x in 100 steps at 12 dB. For short accuracy numbers stop
    # the real schedule early instead (ghsplat train --until N, then ghsplat eval).
    scale_schedule: bool = False

    # --- Adam (optax), one learning rate per parameter group -----------------------------
    lr_means_init: float = 1.6e-4       # x scene extent at step 0
    lr_means_final: float = 1.6e-6      # x scene extent after lr_means_steps (exponential decay)
    # Steps the means' rate takes to decay (2DGS position_lr_max_steps: 30000 however long the run is,
    # so a short run keeps the rate the real schedule has at its steps); 0: the run's own length.
    lr_means_steps: int = 30_000
    lr_sh_dc: float = 2.5e-3            # base colour
    lr_sh_rest: float = 2.5e-3 / 20     # higher SH bands
    lr_opacity: float = 0.05            # opacity logits
    lr_scales: float = 5e-3             # log scales
    lr_quats: float = 1e-3              # rotation quaternions
    adam_eps: float = 1e-15             # 2DGS uses 1e-15 (tiny gradients of far surfels still move)

    # --- loss -----------------------------------------------------------------------------
    lambda_dssim: float = 0.2           # loss = (1 - l) L1 + l (1 - SSIM) + ...
    lambda_dist: float = 0.0            # depth distortion weight (2DGS: 0 unbounded, 1000 DTU, 10-100 TnT)
    dist_from: int = 3000               # distortion loss active from this step
    lambda_normal: float = 0.05         # rendered normal vs depth-derived normal consistency
    normal_from: int = 7000             # normal loss active from this step
    depth_ratio: float = 0.0            # depth for the normal prior: 0 expected, 1 median (2DGS bounded: 1)
    # Images with alpha (RGBA, as NeRF-synthetic): the normal loss counts only where the image is
    # covered. Off is the 2DGS loss everywhere, which on lego grew opaque white sheets in the empty
    # background after densification ended (test PSNR 33.3 dB at step 15,000, 32.2 at 20,000).
    normal_loss_alpha_mask: bool = True

    # --- initialisation -------------------------------------------------------------------
    init_opacity: float = 0.1           # initial opacity of every surfel
    init_random_points: int = 100_000   # random points in the scene box when the dataset has none
    init_min_points: int = 100          # fewer dataset points than this: initialise randomly instead
    init_max_points: int = 0            # subsample dataset points to at most this many (0: all)
    init_scale_max: float = 0.0         # clamp of the initial scale as a fraction of the extent (0: none)
    random_init_scale: float = 0.5      # random points: multiple of the nearest-neighbour scale (see random_init.py)

    # --- densification (2DGS defaults) ---------------------------------------------------
    strategy: str = "default"           # "default" (2DGS), "budget" (capped count), "mcmc" (3DGS-MCMC, fixed cap);
    #                                     see train/strategy.py (the classes, their state and hooks)
    densify_from: int = 500             # first densification step
    densify_until: int = 15_000         # no densification (or pruning) after this step
    densify_every: int = 100            # densify and prune every this many steps
    densify_grad_threshold: float = 2e-4  # accumulated mean NDC gradient of projected centres
    percent_dense: float = 0.01         # clone if max scale <= this x extent, else split
    split_scale_div: float = 1.6        # split children scales = parent / this (0.8 N, N = 2)
    prune_opacity: float = 0.05         # prune surfels less opaque than this
    prune_world_scale: float = 0.1      # prune surfels larger than this x extent (after first reset)
    # Prune surfels whose screen radius exceeded this many pixels (after the first reset); 0 = off.
    # Off by default: the 2DGS/3DGS code zeroes its tracked radii just before this check, so the
    # 20 px rule it names never fires there, and applied literally it wrecks small-image runs.
    prune_screen_px: float = 0.0
    opacity_reset_every: int = 3000     # clamp opacities to opacity_reset_value every this many steps
    opacity_reset_value: float = 0.01   # opacity after a reset
    reset_recovery_steps: int = 100     # no opacity pruning this soon after a reset (2DGS: the reset at 3000
    #                                     is followed by densification at 3100; short runs need the same gap)

    # --- budgeted strategy ------------------------------------------------------------------
    max_surfels: int = 0                # "budget": the hard cap on the count (0: 5x the initial count)
    budget_schedule: str = "linear"     # "linear" growth from the initial count to the cap by densify_until,
    #                                     or "immediate" (the cap is available from densify_from)

    # --- MCMC strategy (3DGS-MCMC; refinement every densify_every steps in [densify_from, densify_until)) ---
    mcmc_min_opacity: float = 0.005     # "dead" below this opacity: relocated onto live surfels sampled by opacity
    mcmc_grow_rate: float = 0.05        # each round grows the live count by this fraction, up to max_surfels
    mcmc_noise_lr: float = 5e5          # position noise = this x the means learning rate x in-plane covariance
    lambda_opacity_reg: float = -1.0    # L1 on opacities (mean over live surfels); -1: the strategy's default
    #                                     (mcmc 0.01, others 0)
    lambda_scale_reg: float = -1.0      # L1 on scales (mean of exp(log_scales)); -1: the strategy's default (same)

    # --- contribution pruning (any strategy) -------------------------------------------------
    # Remove surfels whose blending weight summed over the training views (alpha x transmittance,
    # in pixels) is under contrib_prune_threshold: every contrib_prune_every steps (0: never; scaled
    # by scale_schedule) and/or once after the last step (contrib_prune_final).
    contrib_prune_every: int = 0
    contrib_prune_final: bool = False
    contrib_prune_threshold: float = 1.0  # pixels' worth of weight over all the views counted
    contrib_prune_views: int = 0        # training views to count (0: all; else a seeded subset)

    # --- fixed-capacity pool ------------------------------------------------------------
    initial_capacity: int = 0           # surfel slots at the start (0: 2x the initial count)
    capacity_headroom: float = 0.05     # grow the pool when fewer free slots than this fraction remain

    # --- rasterizer: the run's one set of rendering settings ----------------------------------
    # Saved as the [raster] table of config.toml; training, eval, render, export previews, the
    # simulator and the viewer all read it from there. `background` is also the colour RGBA
    # images are composited on; `pair_capacity` the initial pair buffer (None: sized from a first
    # render, and shrunk after an epoch that needs under half of it). The flat names near, far,
    # background, tile_size, chunk_size, batch_chunks, raster_backward and pair_capacity are
    # accepted as aliases of these fields.
    raster: RasterConfig = RasterConfig()

    # --- bookkeeping ----------------------------------------------------------------------
    checkpoint_every: int = 1000        # write a checkpoint every this many steps (and on Ctrl-C)
    step_threads: int = 0               # threads that walk the compositor's loops in a training step (a part of
    #                                     the tiles each, `train/parted_step.py`); 0: 2 for the carried compositor
    #                                     on a CPU with 2 or more cores, else 1 (one program)
    max_consecutive_rollbacks: int = 10 # stop with an error after this many non-finite steps in a row
    max_total_rollbacks: int = 100      # ... or this many over the run
    progress: bool = True               # tqdm progress bar
    eval_max_train_views: int = 0       # evaluate at most this many training views (0: all)
    save_test_renders: bool = True      # write rgb/depth/normal images of the test views
    # Evaluate the test views every this many steps while training (0: off), into test_curve.jsonl:
    # the test PSNR against training time. Only `ghsplat train` and experiment runs, which know the
    # test views, do it; its time is left out of the run's training seconds. A point shows the model
    # before that step's densification round, as 3DGS evaluates (not just after an opacity reset).
    test_curve_every: int = 0

    def __post_init__(self):
        from ghsplat_jax.train.strategy import strategy_class

        try:
            strategy_class(self.strategy).validate(self)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if self.max_surfels < 0:
            raise ConfigError(f"max_surfels must be >= 0 (0: 5x the initial count), got {self.max_surfels}")
        for name in ("lambda_opacity_reg", "lambda_scale_reg"):
            if getattr(self, name) < 0 and getattr(self, name) != -1:
                raise ConfigError(f"{name} must be >= 0, or -1 for the strategy's default, got {getattr(self, name)}")
        if self.contrib_prune_every < 0 or self.contrib_prune_views < 0 or self.contrib_prune_threshold < 0:
            raise ConfigError("contrib_prune_every, contrib_prune_views and contrib_prune_threshold must be >= 0, got "
                              f"{self.contrib_prune_every}, {self.contrib_prune_views}, {self.contrib_prune_threshold}")
        if self.budget_schedule not in ("linear", "immediate"):
            raise ConfigError(f"budget_schedule must be 'linear' or 'immediate', got {self.budget_schedule!r}")
        if self.steps < 0:
            raise ConfigError(f"steps must be >= 0, got {self.steps}")
        if self.step_threads < 0:
            raise ConfigError(f"step_threads must be >= 0 (0: automatic), got {self.step_threads}")
        if self.test_curve_every < 0:
            raise ConfigError(f"test_curve_every must be >= 0 (0: off), got {self.test_curve_every}")
        if self.densify_every < 1:
            raise ConfigError(f"densify_every must be >= 1 (refinement rounds run every this many steps; set "
                              f"densify_until = 0 to turn densification off), got {self.densify_every}")
        if self.lr_means_steps < 0:
            raise ConfigError(f"lr_means_steps must be >= 0, got {self.lr_means_steps}")
        if not 0 <= self.sh_degree <= 3:
            raise ConfigError(f"sh_degree must be 0-3, got {self.sh_degree}")
        if self.downscale <= 0:
            raise ConfigError(f"downscale must be positive, got {self.downscale}")
        if not self.pose_noise >= 0:
            raise ConfigError(f"pose_noise must be >= 0 (a fraction of the scene extent), got {self.pose_noise}")
        if not self.random_init_scale > 0:
            raise ConfigError(f"random_init_scale must be positive, got {self.random_init_scale}")
        if not isinstance(self.raster, RasterConfig):
            raise ConfigError(f"raster must be a RasterConfig, got {type(self.raster).__name__}")

    def resolved(self) -> "TrainConfig":
        """With scale_schedule, the step-based settings scaled by steps / 30000 (the 2DGS
        schedule's shape on a shorter run); the result has scale_schedule off."""
        if not self.scale_schedule:
            return self
        f = self.steps / 30_000

        def s(v: int, lo: int = 1) -> int:
            return max(int(round(v * f)), lo)

        return dataclasses.replace(
            self, scale_schedule=False, sh_increase_every=s(self.sh_increase_every),
            lr_means_steps=s(self.lr_means_steps) if self.lr_means_steps else 0,
            dist_from=s(self.dist_from, 0), normal_from=s(self.normal_from, 0), densify_from=s(self.densify_from, 0),
            densify_until=s(self.densify_until), densify_every=s(self.densify_every, 10),
            opacity_reset_every=s(self.opacity_reset_every, 100),
            contrib_prune_every=s(self.contrib_prune_every) if self.contrib_prune_every else 0)

    def replace(self, **changes) -> "TrainConfig":
        return apply_overrides(self, changes)

    def to_dict(self) -> dict:
        """Plain values with the raster section as a nested table (None fields left out: TOML has no null)."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}


def _plain(v):
    if isinstance(v, RasterConfig):
        return {f.name: _plain(getattr(v, f.name)) for f in dataclasses.fields(v) if getattr(v, f.name) is not None}
    return list(v) if isinstance(v, tuple) else v


def apply_overrides(config: TrainConfig, overrides: dict, source: str = "overrides") -> TrainConfig:
    """A copy of `config` with fields replaced; unknown names or wrong types name `source`.
    Raster fields come as a `raster` table, as dotted `raster.NAME` keys or by their aliases."""
    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    changes, raster = {}, {}
    for key, value in overrides.items():
        if key == "raster":
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: option 'raster' must be a table of rasterizer settings, got {value!r}")
            raster.update(value)
            continue
        if key.startswith("raster."):
            raster[key.removeprefix("raster.")] = value
            continue
        if key in RASTER_ALIASES:
            raster[RASTER_ALIASES[key]] = None if key == "pair_capacity" and value == 0 else value
            continue
        if key not in fields:
            close = [n for n in fields if key.split("_")[0] in n][:5]
            hint = f" (did you mean one of {close}?)" if close else ""
            raise ConfigError(f"{source}: unknown training option {key!r}{hint}")
        default = getattr(TrainConfig, key, None)
        changes[key] = coerce(value, default, f"{source}: option {key!r}", ConfigError)
    if raster:
        changes["raster"] = _raster_overrides(config.raster, raster, source)
    try:
        return dataclasses.replace(config, **changes)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _raster_overrides(base: RasterConfig, values: dict, source: str) -> RasterConfig:
    fields = {f.name for f in dataclasses.fields(RasterConfig)}
    changes = {}
    for key, value in values.items():
        if key not in fields:
            raise ConfigError(f"{source}: unknown rasterizer option 'raster.{key}' (one of {sorted(fields)})")
        default = getattr(RasterConfig, key)
        where = f"{source}: option 'raster.{key}'"
        if default is None:  # optional integers (pair_capacity, sh_degree)
            changes[key] = None if value is None else coerce(value, 0, where, ConfigError)
        else:
            changes[key] = coerce(value, default, where, ConfigError)
    try:
        return dataclasses.replace(base, **changes)
    except ValueError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def load_config(path: str | os.PathLike, base: TrainConfig | None = None) -> TrainConfig:
    """Read a TOML (or JSON) file of overrides; a [train] table is used when present."""
    return apply_overrides(base or TrainConfig(), load_config_table(path), str(path))


def load_config_table(path: str | os.PathLike) -> dict:
    """The table of a TOML (or JSON) config file (its [train] table when it has one)."""
    import tomllib

    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config ({exc.strerror})") from None
    try:
        table = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: not valid {'JSON' if path.suffix == '.json' else 'TOML'}: {exc}") from None
    if "train" in table and isinstance(table["train"], dict):
        table = table["train"]
    return table


def settings_missing_from(path: str | os.PathLike) -> list[str]:
    """The settings a saved config file leaves out (`raster.NAME` for rasterizer ones): a file
    written before they existed, whose run would now take their defaults."""
    saved = TrainConfig().to_dict()
    table = load_config_table(path)
    missing = [k for k in saved if k != "raster" and k not in table]
    raster = table.get("raster", {})
    return missing + [f"raster.{k}" for k in saved["raster"] if k not in raster]


def save_config(config: TrainConfig, path: str | os.PathLike) -> Path:
    import tomli_w

    from ghsplat_jax.io_utils import atomic_write

    with atomic_write(path, "w") as fh:
        fh.write("# resolved training config (ghsplat train); pass with --config to reproduce\n")
        fh.write(tomli_w.dumps(config.to_dict()))
    return Path(path)
