"""Training recipes: named sets of settings that `recipe = NAME` lays under every other
override (a recipe's table, then the config file, then the command line).

- "" (none): the 2DGS defaults, the Table 1 protocol: 30k steps, adaptive density control.
- "auto": a model that sizes itself and a run that stops itself. Growth by the `auto` strategy
  (train/strategies/auto.py) in levels, until a level's validation PSNR per doubling of the count,
  net of the gain a fixed count still makes per step, falls under its threshold; a validation
  split carved from the training views; a stop on a validation plateau (after one annealing of
  the means learning rate), keeping the best check's model, compacted (the surfels validation can
  spare removed: train/compaction.py); images at reduced resolution early, raised by their
  spectrum (DashGaussian); the means' learning rate
  decaying over 10k steps instead of 30k; `steps` only a ceiling. The normal-consistency loss keeps
  2DGS's start (step 7,000), which a run that stops itself often does not reach: from step 2,000
  it cost 1.38 dB of test PSNR on row2_x1 (28.01 against 29.39) for better normals (20 against 34
  degrees mean error; median depth error 3.1 against 4.1 cm). Where geometry comes first (depth
  or LiDAR renders), set normal_from = 2000. Since the run keeps its best check, whether that model
  had the loss at all is chance (most runs plateau within 1,000 steps of step 7,000): normal_settle
  = N keeps only a model that has had it N steps (experiments/table1_greenhouse.toml: auto_settle).
"""

from __future__ import annotations

RECIPES: dict[str, dict] = {
    "auto": {
        "strategy": {"name": "auto"},
        "val_every": 250,
        "stop_patience": 3,
        "stop_min_gain": 0.1,
        "stop_after": 1500,
        "res_schedule": "spectrum",
        "res_until": 2000,
        "densify_from": 300,
        # The means' rate decays 100x by step 10,000, not 30,000: a run that stops itself ends
        # near there, and a position rate still at a third of its start would end it unsettled.
        "lr_means_steps": 10_000,
    },
}
