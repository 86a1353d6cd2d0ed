"""The one config-value checker that the training and scene-generator configs share."""

import pytest

from ghsplat_jax.config_values import coerce
from ghsplat_jax.synth.config import config_from_dict
from ghsplat_jax.train.config import ConfigError, TrainConfig


def test_scalars_follow_the_default_type():
    assert coerce(3.0, 0, "n") == 3 and type(coerce(3.0, 0, "n")) is int
    assert coerce(2, 0.5, "x") == 2.0 and coerce(True, False, "b") is True
    for value, default in [(2.5, 0), (True, 0), ("1", 1.0), (1, "s"), (1, True)]:
        with pytest.raises(ValueError, match="field"):
            coerce(value, default, "field")


def test_tuples_are_vectors_or_ranges():
    assert coerce([1, 0, 0], (0.0, 0.0, 0.0), "bg") == (1.0, 0.0, 0.0)
    assert coerce([1, 2], (0.0, 0.0), "r", ranges=True) == (1.0, 2.0)
    assert coerce(3, (0, 0), "r", ranges=True) == (3, 3)  # one number: a fixed value
    with pytest.raises(ValueError, match="min <= max"):
        coerce([2, 1], (0.0, 0.0), "r", ranges=True)
    with pytest.raises(ConfigError, match="list of 3"):
        coerce([1, 2], (0.0, 0.0, 0.0), "bg", ConfigError)


def test_both_configs_use_it():
    with pytest.raises(ConfigError, match="'steps' must be an integer"):
        TrainConfig().replace(steps=1.5)
    assert TrainConfig().replace(steps=300.0).steps == 300
    with pytest.raises(ValueError, match="layout.rows must be an integer"):
        config_from_dict({"layout": {"rows": "two"}})
