"""Densification strategies, one module each, every one a settings dataclass (the config's
`[strategy]` table) and a class of hooks that the trainer calls (base.py says which):

- `default` (default.py): the 2DGS adaptive density control (clone / split / prune, opacity reset).
- `budget` (default.py): the same with new surfels per round capped by a schedule up to `max_surfels`.
- `mcmc` (mcmc.py): 3DGS-MCMC on 2D surfels, a fixed cap.
- `auto` (auto.py): MCMC refinement whose count grows where the error is until the held-out
  views stop paying for it, and a finished model compacted to what they need
  (train/compaction.py); the `auto` recipe's strategy.

Any strategy can prune by contribution (base.py: `contribution_prune`).
"""

from ghsplat_jax.train.strategies.auto import AutoSettings, AutoStrategy  # noqa: E402 (after mcmc, which it extends)
from ghsplat_jax.train.strategies.base import (
                                               REGISTRY,
                                               Strategy,
                                               StrategyContext,
                                               StrategySettings,
                                               accumulated_weights,
                                               contribution_prune,
                                               is_opacity_reset,
                                               last_reset_before,
                                               loss_weight,
                                               make_strategy,
                                               register,
                                               settings_from,
                                               strategy_class,
                                               strategy_names,
)
from ghsplat_jax.train.strategies.default import BudgetSettings, BudgetStrategy, DefaultSettings, DefaultStrategy
from ghsplat_jax.train.strategies.mcmc import (
                                               MCMCSettings,
                                               MCMCStrategy,
                                               relocate,
                                               relocation_integral,
                                               relocation_values,
                                               sample_in_proportion,
)

__all__ = ["REGISTRY", "AutoSettings", "AutoStrategy", "BudgetSettings", "BudgetStrategy", "DefaultSettings",
           "DefaultStrategy", "MCMCSettings", "MCMCStrategy", "Strategy", "StrategyContext", "StrategySettings",
           "accumulated_weights", "contribution_prune", "is_opacity_reset", "last_reset_before", "loss_weight",
           "make_strategy", "register", "relocate", "relocation_integral", "relocation_values", "sample_in_proportion",
           "settings_from", "strategy_class",
           "strategy_names"]
