"""2DGS training: config, losses, optimiser groups, densification on a fixed-capacity pool,
the jitted step, the training loop and the run folder (run_dir.py).

    from ghsplat_jax.train import TrainConfig, train
    result = train(TrainConfig(data="llff_fern", downscale=8), "runs/fern")
"""

from ghsplat_jax.train.config import ConfigError, TrainConfig, load_config
from ghsplat_jax.train.trainer import TrainingDivergedError, TrainResult, train

__all__ = ["ConfigError", "TrainConfig", "TrainResult", "TrainingDivergedError", "load_config", "train"]
