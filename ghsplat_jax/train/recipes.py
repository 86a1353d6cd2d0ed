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
  decaying over 10k steps instead of 30k; `steps` only a ceiling.
  The normal-consistency loss keeps 2DGS's start (step 7,000); from step 2,000 it cost 0.62-1.18 dB
  of test PSNR on four segments (auto_normal2k). A run keeps its best validation check, and most
  plateau within 1,000 steps of step 7,000, so whether the kept model had the loss at all was
  chance: 20 of the 24 Table 1 runs at 192x144 and all 24 at 384x288 kept one from before it (29-38
  degrees of mean normal error, against 17-24 for runs that kept one with it). So the recipe keeps
  only a model that has had it 1,000 steps (normal_settle): on row0_x0, row2_x0 and row2_x1 at
  192x144 and row0_x0 and row2_x1 at 384x288 (one seed each, against the recipe's three before it)
  the normal error fell from 30-37 to 19-23 degrees and the median depth error by 26-44%, for -0.30
  to +0.26 dB of test PSNR (LPIPS -0.012 to +0.003) and 11-79% more training time (8,750-9,250
  steps, where those runs had stopped at 5,500-8,000; the most at 384x288, where they stopped
  soonest). benchmarks/results/auto_recipe/ and auto_recipe/table1_384/ (READMEs: "Ablations over
  seeds or segments").
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
        # The kept model has had the normal-consistency loss (from step 7,000) for 1,000 steps.
        "normal_settle": 1000,
    },
}
