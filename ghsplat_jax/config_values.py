"""Config values read from TOML, checked against the type of their defaults: one checker for the
training config and the scene generator's."""

from __future__ import annotations

import math
import os


def coerce(value, default, where: str, error: type[Exception] = ValueError, ranges: bool = False):
    """`value` as the type of `default`, else `error` naming `where`.

    bool; int (a whole float such as 3.0 counts); float; str (paths too); and tuples: a list of the
    same length whose items are checked like the default's first. With `ranges`, a 2-tuple default
    is a [min, max] range instead, where a single number means a fixed value.
    """
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise error(f"{where} must be true or false, got {value!r}")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise error(f"{where} must be an integer, got {value!r}")
        return int(value)
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise error(f"{where} must be a number, got {value!r}")
        if not math.isfinite(value):  # TOML spells nan and inf; neither is a setting
            raise error(f"{where} must be a finite number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, (str, os.PathLike)):
            raise error(f"{where} must be a string, got {value!r}")
        return str(value)
    if isinstance(default, tuple) and ranges and len(default) == 2:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value, value]
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise error(f"{where} must be a [min, max] pair, got {value!r}")
        out = tuple(coerce(v, default[0], where, error) for v in value)
        if out[0] > out[1]:
            raise error(f"{where} must have min <= max, got {value!r}")
        return out
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)) or len(value) != len(default):
            raise error(f"{where} must be a list of {len(default)} numbers, got {value!r}")
        return tuple(coerce(v, default[0], where, error) for v in value)
    raise TypeError(f"unsupported config field type at {where}")
